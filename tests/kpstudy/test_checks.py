"""The shared argument checks (kpstudy._checks) and the two methods' options, each checked in
one place: a good value passes, each bad kind is refused with a message that starts with
the argument's name."""

from __future__ import annotations

import math

import pytest

from kpstudy import _checks
from kpstudy.certify.allocation_method import AllocationOptions
from kpstudy.certify.hull import POSE_BOUND_KEYWORDS, pose_bound_options
from kpstudy.certify.pose_bound_method import PoseBoundOptions
from kpstudy.study.campaign import Settings, allocation_options


def test_integer_takes_ints_in_range():
    assert _checks.integer(3, "n") == 3
    assert _checks.integer(0, "n", minimum=0) == 0
    assert _checks.integer(12, "n", minimum=0, maximum=12) == 12
    assert _checks.integer(None, "n", minimum=1, optional=True) is None


@pytest.mark.parametrize(
    "value, bounds, message",
    [
        (True, dict(minimum=1), "n: expected a positive integer, got True"),
        (2.0, dict(minimum=1), "n: expected a positive integer, got 2.0"),
        ("2", dict(), "n: expected an integer, got '2'"),
        (None, dict(minimum=0), "n: expected an integer >= 0, got None"),
        (-1, dict(minimum=0), "n: expected an integer >= 0, got -1"),
        (13, dict(minimum=0, maximum=12), "n: expected an integer in [0, 12], got 13"),
        (0, dict(minimum=1, optional=True), "n: expected None or a positive integer, got 0"),
    ],
)
def test_integer_refuses_by_name(value, bounds, message):
    with pytest.raises(ValueError) as refused:
        _checks.integer(value, "n", **bounds)
    assert str(refused.value) == message


def test_seconds_takes_positive_reals_and_refuses_the_rest_by_name():
    assert _checks.seconds(2, "timeout") == 2.0 and _checks.seconds(math.inf, "timeout") == math.inf
    assert _checks.seconds(None, "timeout", optional=True) is None
    for bad in (0, -1.0, math.nan, True, "1", None):
        with pytest.raises(ValueError, match=r"^timeout: expected seconds > 0, got "):
            _checks.seconds(bad, "timeout")
    with pytest.raises(ValueError, match=r"^timeout: expected None or seconds > 0, got 0"):
        _checks.seconds(0, "timeout", optional=True)


def test_choice_takes_a_listed_value_and_names_the_choices_in_order():
    assert _checks.choice("simplex", "input_form", ("box", "simplex")) == "simplex"
    assert _checks.choice("b", "name", iter(["c", "b"])) == "b"  # any iterable, read once
    with pytest.raises(ValueError) as refused:
        _checks.choice("cube", "input_form", {"simplex": 1, "box": 2})
    assert str(refused.value) == "input_form: expected one of simplex, box, got 'cube'"
    with pytest.raises(ValueError, match=r"^n: expected one of 1, 2, got None$"):
        _checks.choice(None, "n", ["1", "2"])


def test_named_puts_a_check_in_the_callers_words():
    with pytest.raises(ValueError, match=r"^where: nodes: expected None or a positive integer"):
        with _checks.named({"max_nodes": "nodes"}, "where: "):
            _checks.integer(0, "max_nodes", minimum=1, optional=True)
    with pytest.raises(ValueError, match=r"^stride: expected"):  # not in names: kept
        with _checks.named({"max_nodes": "nodes"}):
            _checks.integer(0, "stride", minimum=1)
    with pytest.raises(ValueError, match=r"^no colon$"):  # not a check's message: as it is
        with _checks.named({"no colon": "x"}):
            raise ValueError("no colon")


def test_the_pose_bound_options_are_checked_once_for_every_caller():
    assert PoseBoundOptions() == PoseBoundOptions("forward", 10.0, None, 0, 0.0, 0, 1)
    assert PoseBoundOptions(max_nodes=0).max_nodes == 0  # witnesses only
    bad = [
        (dict(stride=2), "stride"),
        (dict(stride=0), "stride"),
        (dict(stride=3.0), "stride"),
        (dict(method="crown"), "method"),
        (dict(timeout=0), "timeout"),
        (dict(max_nodes=-1), "max_nodes"),
        (dict(max_nodes=True), "max_nodes"),
        (dict(start_depth=13), "start_depth"),
        (dict(start_splits=-0.5), "start_splits"),
        (dict(start_splits=True), "start_splits"),
        (dict(refine_nodes=-1), "refine_nodes"),
        (dict(refine_nodes=1.5), "refine_nodes"),
    ]
    for kwargs, name in bad:
        with pytest.raises(ValueError, match=f"^{name}: expected"):
            PoseBoundOptions(**kwargs)
        # certify_cells' keywords and the campaign settings name their own argument
        keyword = next(k for k, v in POSE_BOUND_KEYWORDS.items() if v == name)
        chosen = {"pose_bound_timeout": 1.0, keyword: kwargs[name]}
        with pytest.raises(ValueError, match=f"^{keyword}: expected"):
            Settings("c", "d", **chosen).pose_bound_options()
        with pytest.raises(ValueError, match=f"^local_pose_bound: {keyword}: expected"):
            pose_bound_options("local_pose_bound: ", **chosen)


def test_pose_bound_options_skip_without_seconds_but_check_the_rest():
    assert pose_bound_options() is None
    assert Settings("c", "d").pose_bound_options() is None
    options = Settings("c", "d", pose_bound_timeout=5.0, pose_bound_nodes=0).pose_bound_options()
    assert (options.timeout, options.max_nodes) == (5.0, 0)
    with pytest.raises(ValueError, match=r"^pose_bound_stride: expected an odd integer"):
        Settings("c", "d", pose_bound_stride=2).pose_bound_options()
    with pytest.raises(ValueError, match=r"^pose_bound_timeout: expected None or seconds > 0"):
        pose_bound_options(pose_bound_timeout=0)
    with pytest.raises(ValueError, match=r"^x: unknown settings \['pose_bound_speed'\]"):
        pose_bound_options("x: ", pose_bound_speed=2)


def test_the_allocation_options_are_checked_once_for_every_caller():
    assert AllocationOptions() == AllocationOptions("auto", 60.0, None)
    assert Settings("c", "d", nodes=2).allocation_options().max_nodes == 2
    bad = [
        (dict(method="exact"), "method", "method"),
        (dict(timeout=0), "timeout", "timeout"),
        (dict(timeout=True), "timeout", "timeout"),
        (dict(max_nodes=0), "max_nodes", "nodes"),
        (dict(max_nodes=2.5), "max_nodes", "nodes"),
    ]
    for kwargs, name, setting in bad:
        (value,) = kwargs.values()
        with pytest.raises(ValueError, match=f"^{name}: expected"):
            AllocationOptions(**kwargs)
        with pytest.raises(ValueError, match=f"^{setting}: expected"):
            Settings("c", "d", **{setting: value}).allocation_options()
        with pytest.raises(ValueError, match=f"^allocation: {setting}: expected"):
            allocation_options("allocation: ", **{setting: value})
