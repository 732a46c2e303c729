"""The model tests' trained checkpoint: the tiny recipe on the tiny rendered dataset, once
per session (the tests only read it)."""

import pytest

from kpstudy.models.training import train
from tests.helpers.training import TINY


@pytest.fixture(scope="session")
def checkpoint(tiny_dataset, tmp_path_factory):
    path = tmp_path_factory.mktemp("ckpt") / "cnn.pt"
    train(tiny_dataset, path, TINY, progress=False)
    return path
