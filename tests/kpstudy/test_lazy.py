"""kpstudy._lazy: the subpackages' lazy re-exports."""

import pytest


def test_a_re_export_reads_the_modules_own_list_or_refuses():

    from kpstudy._lazy import lazy_exports
    from kpstudy.pose import allocation

    names, getattr_, _ = lazy_exports("kpstudy.pose", {"allocation": None})
    assert names == sorted(allocation.__all__)
    assert getattr_("allocate_tolerances") is allocation.allocate_tolerances
    with pytest.raises(ValueError, match=r"^modules: kpstudy.pose.pnp has no literal __all__"):
        lazy_exports("kpstudy.pose", {"pnp": None})
