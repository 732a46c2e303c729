"""reachable_argmax: sound supersets of each group's argmax, exact where the answer is known."""

import pytest
import torch
from torch import nn

from kpstudy.verify import ConvexHull, Parallelotope, reachable_argmax
from tests.helpers.verify_nets import (
    MixedNet,
    PatchNet,
    PoolProxy,
    TinyResNet,
    block_hull_vertices,
    hull_vertices,
)

#: A node budget (a few seconds of search here; the searches that end take at most ~260
#: nodes), so the sets do not depend on the machine's speed; the timeout (s) only caps a
#: stalled run.
NODES, CAP = 300, 600.0


def sampled_argmax(model, input_set, group_sizes, count=2000):
    """Per group, the set of argmax indices over Dirichlet, vertex and edge samples."""
    lam = torch.cat(
        [
            input_set.sample(count, 1),
            input_set.sample(count // 4, 2, "vertices"),
            input_set.sample(count // 2, 3, "edges"),
        ]
    )
    with torch.no_grad():
        y = model(input_set.image(lam)).flatten(1)
    out, lo = [], 0
    for s in group_sizes:
        out.append(set(y[:, lo : lo + s].argmax(1).tolist()))
        lo += s
    return out


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("n", [1, 3, 6])
@pytest.mark.parametrize("method", ["forward", "zonotope"])
def test_possible_sets_contain_every_sampled_argmax(seed, n, method):
    model = MixedNet(seed)
    hull = ConvexHull(hull_vertices(seed, n, (2, 8, 8), spread=0.5))
    sizes = [3, 3]
    regions = reachable_argmax(model, hull, sizes, method=method, max_nodes=NODES, timeout=CAP)
    sampled = sampled_argmax(model, hull, sizes)
    for g in range(2):
        assert sampled[g] <= set(regions.possible[g].tolist())
        assert set(regions.reached(g).tolist()) <= set(regions.possible[g].tolist())
        for index, lam in regions.witnesses[g].items():  # every witness reproduces
            assert bool(hull.contains_lambda(lam))
            y = model(hull.image(lam[None])).flatten(1)[:, 3 * g : 3 * g + 3]
            assert int(y.argmax()) == index


@pytest.mark.parametrize("seed", range(2))
def test_block_hulls_of_a_residual_network_keep_every_sampled_argmax(seed):
    """Per heatmap of a tiny ResNet (strided residual blocks, a transposed-convolution
    decoder) over a hull of 3×3 block occlusions, the zonotope search's possible pixels
    hold every sampled argmax, and each witness reproduces its pixel."""
    model = TinyResNet(seed)
    hull = ConvexHull(block_hull_vertices(seed))
    sizes = [16 * 16] * 3
    regions = reachable_argmax(model, hull, sizes, method="zonotope", max_nodes=64, timeout=CAP)
    sampled = sampled_argmax(model, hull, sizes)
    for g, size in enumerate(sizes):
        possible = set(regions.possible[g].tolist())
        assert sampled[g] <= possible and len(possible) < size  # sound, and it decides
        for index, lam in regions.witnesses[g].items():
            y = model(hull.image(lam[None])).flatten(1)[:, size * g : size * (g + 1)]
            assert int(y.argmax()) == index


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("method", ["forward", "zonotope"])
def test_pool_proxy_groups_of_unequal_size(seed, method):
    model = PoolProxy(seed)
    hull = ConvexHull(hull_vertices(seed, 3, (1, 10, 10), spread=0.4))
    regions = reachable_argmax(
        model, hull, model.group_sizes, method=method, samples=0, max_nodes=NODES, timeout=CAP
    )
    sampled = sampled_argmax(model, hull, model.group_sizes)
    for g, size in enumerate(model.group_sizes):
        possible = set(regions.possible[g].tolist())
        assert sampled[g] <= possible and max(possible) < size


@pytest.mark.parametrize("seed", range(3))
def test_a_search_reading_symbols_from_blocks_finds_what_a_dense_output_gives(seed):
    """A heatmap-shaped output keeps its error symbols in blocks, which the search reads
    where it needs them; a flattened output is dense. Same possible sets and witnesses,
    and they contain every sampled argmax."""
    net = PatchNet(seed).double()
    hull = ConvexHull(hull_vertices(seed, 3, (2, 8, 8), spread=0.5, dtype=torch.float64))
    sizes = [256] * 3  # one group per heatmap channel
    kw = dict(method="zonotope", max_nodes=24, timeout=CAP)
    blocks = reachable_argmax(net, hull, sizes, **kw)
    dense = reachable_argmax(nn.Sequential(net, nn.Flatten()), hull, sizes, **kw)
    sampled = sampled_argmax(net, hull, sizes)
    for g in range(3):
        assert blocks.possible[g].tolist() == dense.possible[g].tolist()
        assert sorted(blocks.witnesses[g]) == sorted(dense.witnesses[g])
        assert sampled[g] <= set(blocks.possible[g].tolist())
    assert sum(len(p) for p in blocks.possible) < 3 * 256  # the bounds decided something


def test_parallelotope_and_ibp_are_sound_too():
    model = MixedNet(7)
    box = Parallelotope(hull_vertices(7, 2, (2, 8, 8), spread=0.5))
    regions = reachable_argmax(model, box, [2, 4], method="ibp", max_nodes=NODES, timeout=CAP)
    sampled = sampled_argmax(model, box, [2, 4])
    assert all(s <= set(p.tolist()) for s, p in zip(sampled, regions.possible))


class Segment(nn.Module):
    """On the segment λ ∈ [0, 1]: y = [1 − λ, λ, 0.2, −1] (group 0) and [λ, 0.3] (group 1).

    Index 0 wins on λ < 1/2, index 1 on λ > 1/2; 0.2 and −1 never win. In group 1, 0.3
    wins on λ < 0.3 and λ on λ > 0.3.
    """

    def __init__(self):
        super().__init__()
        self.fc = nn.Linear(1, 6).double()
        with torch.no_grad():
            self.fc.weight.copy_(torch.tensor([[-1.0], [1.0], [0.0], [0.0], [1.0], [0.0]]))
            self.fc.bias.copy_(torch.tensor([1.0, 0.0, 0.2, -1.0, 0.0, 0.3]))

    def forward(self, x):
        return self.fc(x)


def test_regions_are_exact_on_a_known_network():
    hull = ConvexHull(torch.tensor([[0.0], [1.0]], dtype=torch.float64))
    regions = reachable_argmax(Segment(), hull, [4, 2], samples=0, max_nodes=NODES, timeout=CAP)
    assert regions.possible[0].tolist() == [0, 1]
    assert regions.possible[1].tolist() == [0, 1]
    assert regions.complete and not regions.stats["timed_out"]
    assert regions.nodes > 1  # the root alone cannot drop index 2 (0.2 < 1/2 needs a split)
    lam = regions.witnesses[0][1]
    assert lam.item() > 0.5


def test_a_spent_budget_keeps_the_sets_sound():
    hull = ConvexHull(torch.tensor([[0.0], [1.0]], dtype=torch.float64))
    regions = reachable_argmax(Segment(), hull, [4, 2], samples=0, max_nodes=1, timeout=CAP)
    assert regions.stats["stopped"] == "nodes" and not regions.stats["timed_out"]
    assert {0, 1, 2} <= set(regions.possible[0].tolist())  # not yet refined, still sound
    assert 3 not in regions.possible[0]  # −1 is beaten everywhere, even at the root
    assert not regions.complete and regions.gap[0] >= 1


@pytest.mark.parametrize("start_depth", [1, 3])
def test_a_search_started_below_the_root_finds_the_same_exact_sets(start_depth):
    hull = ConvexHull(torch.tensor([[0.0], [1.0]], dtype=torch.float64))
    budget = dict(samples=0, max_nodes=NODES, timeout=CAP)
    whole = reachable_argmax(Segment(), hull, [4, 2], **budget)
    deep = reachable_argmax(Segment(), hull, [4, 2], start_depth=start_depth, **budget)
    assert deep.complete and deep.stats["depth"] >= start_depth
    assert [p.tolist() for p in deep.possible] == [p.tolist() for p in whole.possible]
    assert deep.nodes >= 2**start_depth  # every node of the first level is bounded


def test_a_search_started_below_the_root_stays_sound_when_its_budget_runs_out():
    model = MixedNet(0)
    hull = ConvexHull(hull_vertices(0, 2, (2, 8, 8)))
    regions = reachable_argmax(
        model, hull, [3, 3], start_depth=4, max_nodes=3, batch=1, samples=256, timeout=CAP
    )
    assert regions.stats["stopped"] == "nodes"
    for g in range(2):  # every index some sample reaches is in the possible set
        assert set(regions.reached(g)) <= set(regions.possible[g].tolist())
    lam = hull.sample(512, seed=9)
    with torch.no_grad():
        y = model(hull.image(lam)).flatten(1).reshape(-1, 2, 3).argmax(-1)
    for g in range(2):
        assert set(y[:, g].tolist()) <= set(regions.possible[g].tolist())


def test_a_focused_search_splits_only_for_the_indices_it_is_given():
    hull = ConvexHull(torch.tensor([[0.0], [1.0]], dtype=torch.float64))
    budget = dict(samples=0, max_nodes=NODES, timeout=CAP)
    # Nothing in focus: the root closes at once and keeps what it cannot beat there.
    idle = reachable_argmax(Segment(), hull, [4, 2], focus=[[], []], **budget)
    assert idle.nodes == 1 and {0, 1, 2} <= set(idle.possible[0].tolist())
    # Index 2 of group 0 (0.2, never the argmax) in focus: splits remove it.
    aimed = reachable_argmax(Segment(), hull, [4, 2], focus=[[2], []], **budget)
    whole = reachable_argmax(Segment(), hull, [4, 2], **budget)
    assert 2 not in aimed.possible[0] and 1 < aimed.nodes <= whole.nodes
    for g in range(2):  # still sound: every index the whole search keeps is kept
        assert set(whole.possible[g].tolist()) <= set(aimed.possible[g].tolist())
    with pytest.raises(ValueError, match="^focus"):
        reachable_argmax(Segment(), hull, [4, 2], focus=[[4], []], **budget)
    with pytest.raises(ValueError, match="^focus"):
        reachable_argmax(Segment(), hull, [4, 2], focus=[[0]], **budget)


@pytest.mark.parametrize("seed", range(3))
def test_a_focused_search_is_sound(seed):
    model = MixedNet(seed)
    hull = ConvexHull(hull_vertices(seed, 3, (2, 8, 8), spread=0.5))
    focus = [[seed % 3], [0, 2]]
    regions = reachable_argmax(
        model, hull, [3, 3], method="zonotope", focus=focus, max_nodes=NODES, timeout=CAP
    )
    sampled = sampled_argmax(model, hull, [3, 3])
    assert all(s <= set(p.tolist()) for s, p in zip(sampled, regions.possible))


@pytest.mark.parametrize("seed", range(2))
def test_a_resumed_search_goes_on_as_one_longer_search(seed):
    model = MixedNet(seed)
    hull = ConvexHull(hull_vertices(seed, 3, (2, 8, 8), spread=0.5))
    search = dict(method="zonotope", start_depth=2, timeout=CAP)
    first = reachable_argmax(model, hull, [3, 3], max_nodes=4, **search)
    assert first.nodes == 4 and first.frontier is not None
    resumed = reachable_argmax(model, hull, [3, 3], max_nodes=4, resume=first, **search)
    whole = reachable_argmax(model, hull, [3, 3], max_nodes=8, **search)
    assert resumed.nodes == whole.nodes - first.nodes  # no node bounded twice
    for g in range(2):
        assert resumed.possible[g].tolist() == whole.possible[g].tolist()
        assert set(resumed.witnesses[g]) == set(whole.witnesses[g])
        assert set(resumed.possible[g].tolist()) <= set(first.possible[g].tolist())


@pytest.mark.parametrize("seed", range(2))
def test_a_search_resumed_with_another_focus_is_sound(seed):
    model = MixedNet(seed)
    hull = ConvexHull(hull_vertices(seed, 3, (2, 8, 8), spread=0.5))
    search = dict(method="zonotope", timeout=CAP)
    first = reachable_argmax(model, hull, [3, 3], max_nodes=3, focus=[[0], []], **search)
    second = reachable_argmax(
        model, hull, [3, 3], max_nodes=20, focus=[[1, 2], [0, 1, 2]], resume=first, **search
    )
    third = reachable_argmax(model, hull, [3, 3], max_nodes=20, resume=second, **search)
    sampled = sampled_argmax(model, hull, [3, 3])
    for later, earlier in ((second, first), (third, second)):
        for g in range(2):
            assert sampled[g] <= set(later.possible[g].tolist())
            assert set(later.possible[g].tolist()) <= set(earlier.possible[g].tolist())
    with pytest.raises(ValueError, match="^resume"):
        reachable_argmax(model, hull, [2, 4], max_nodes=1, resume=first, **search)


@pytest.mark.parametrize("seed", range(2))
def test_a_callers_witnesses_stand_for_the_samples(seed):
    """Witnesses a caller found (passed with ``samples=0``) give the search the samples'
    reached sets, hence the same nodes and possible sets."""
    model = MixedNet(seed)
    hull = ConvexHull(hull_vertices(seed, 3, (2, 8, 8), spread=0.5))
    search = dict(method="zonotope", max_nodes=NODES, timeout=CAP)
    alone = reachable_argmax(model, hull, [3, 3], samples=64, **search)
    lam = hull.sample(64, 0)
    with torch.no_grad():
        best = model(hull.image(lam)).flatten(1).unflatten(1, (2, 3)).argmax(-1)  # (64, 2)
    given = [{}, {}]
    for point, indices in zip(lam, best.tolist()):
        for g, i in enumerate(indices):
            given[g].setdefault(i, point)
    taken = reachable_argmax(model, hull, [3, 3], samples=0, witnesses=given, **search)
    assert taken.nodes == alone.nodes
    assert [p.tolist() for p in taken.possible] == [p.tolist() for p in alone.possible]
    assert [sorted(w) for w in taken.witnesses] == [sorted(w) for w in alone.witnesses]
    for g in range(2):
        assert set(given[g]) <= set(taken.witnesses[g])


def test_bad_input_is_named():
    model = MixedNet(0)
    hull = ConvexHull(hull_vertices(0, 2, (2, 8, 8)))
    for kwargs, name in [
        (dict(group_sizes=[3, 2]), "group_sizes"),
        (dict(group_sizes=[6, 0]), "group_sizes"),
        (dict(group_sizes=[6], method="crown"), "method"),
        (dict(group_sizes=[6], timeout=0), "timeout"),
        (dict(group_sizes=[6], candidates=0), "candidates"),
        (dict(group_sizes=[6], start_depth=-1), "start_depth"),
        (dict(group_sizes=[6], start_depth=13), "start_depth"),
        (dict(group_sizes=[6], start_depth=True), "start_depth"),
        (dict(group_sizes=[3, 3], witnesses=[{}]), "witnesses"),
        (dict(group_sizes=[3, 3], witnesses=[{3: torch.zeros(2)}, {}]), "witnesses"),
        (dict(group_sizes=[3, 3], witnesses=[{0: torch.zeros(3)}, {}]), "witnesses"),
    ]:
        with pytest.raises(ValueError, match=f"^{name}"):
            reachable_argmax(model, hull, **kwargs)
    assert reachable_argmax(model, hull, [6], max_nodes=1, timeout=CAP).gap.shape == (1,)


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("flatten", [False, True])
def test_a_zonotope_search_bounding_the_affine_tail_first_finds_what_the_full_pass_gives(
    seed, flatten
):
    """The patch decoder is affine after the last ReLU: each node is bounded there with
    its symbols in the radius first and carries them through the decoder (one heatmap
    channel per group, or the flattened output whole) only where that leaves an index
    without a witness. The same possible sets, witnesses and node count as a search that
    carries every node's symbols through the whole network."""
    net = PatchNet(seed).double()
    model = nn.Sequential(net, nn.Flatten()) if flatten else net
    hull = ConvexHull(hull_vertices(seed, 3, (2, 8, 8), spread=0.5, dtype=torch.float64))
    sizes = [256] * 3
    kw = dict(method="zonotope", max_nodes=40, timeout=CAP)
    split = reachable_argmax(model, hull, sizes, **kw)
    whole = reachable_argmax(model, hull, sizes, tail_first=False, **kw)
    assert split.nodes == whole.nodes
    for g in range(3):
        assert split.possible[g].tolist() == whole.possible[g].tolist()
        assert sorted(split.witnesses[g]) == sorted(whole.witnesses[g])
    assert sum(len(p) for p in split.possible) < 3 * 256
