"""The rasteriser the data_gen tests share, one per test module."""

import pytest

from data_gen.render import Renderer


@pytest.fixture(scope="module")
def renderer():
    r = Renderer(shadow_size=1024)
    yield r
    r.release()
