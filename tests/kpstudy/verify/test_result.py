"""kpstudy.verify.result: a run's margin bracket, from its statistics."""

import math

import torch

from kpstudy.verify.result import Counterexample, Result


def result(**stats) -> Result:
    return Result("unknown", ["unknown"] * 3, None, 1.0, 4, stats)


def test_the_bracket_is_the_worst_group_between_the_root_bound_and_the_attacks():
    r = result(root_margin=[-0.5, -2.0, 1.0], attack_margin=[0.3, 0.1, 2.0])
    assert r.margin_bracket() == (-2.0, 0.1)


def test_groups_without_rows_do_not_count_and_an_unbounded_root_gives_no_lower_end():
    inf = math.inf
    r = result(root_margin=[-9.0, -1.0, 0.5], attack_margin=[inf, 0.2, 0.7])
    assert r.margin_bracket() == (-1.0, 0.2)  # group 0 has no rows (excluded)
    assert result(root_margin=None, attack_margin=[0.4]).margin_bracket() == (None, 0.4)
    unbounded = result(root_margin=[-inf, 0.0], attack_margin=[0.1, 0.3])
    assert unbounded.margin_bracket() == (None, 0.1)
    assert result().margin_bracket() == (None, None)


def test_a_violated_result_carries_its_counterexample():
    point = torch.tensor([0.25, 0.75])
    found = Counterexample(point, torch.zeros(1, 2, 2), group=1, margin=-0.125)
    r = Result("violated", ["holds", "violated"], found, 0.5, 3)
    assert r.counterexample.group == 1 and r.counterexample.margin < 0 and r.stats == {}
    assert result().stats is not result().stats  # each its own dictionary
