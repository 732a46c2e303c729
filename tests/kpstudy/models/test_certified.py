"""kpstudy.models.certified, verification-friendly training: random hulls, the bound term
(sound and differentiable), interval arithmetic, and a tiny certified training run."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn

from kpstudy.models import build_backbone
from kpstudy.models.certified import (
    MAX_COPIES,
    BatchStatistics,
    HullSampler,
    block_hull_points,
    bound_graph,
    hull_bounds,
    occluder_patches,
    photometric_pair,
    relu_instability,
    robust_heatmap_loss,
)
from kpstudy.models.training import TrainConfig, config_of, heatmap_loss, load_checkpoint, train
from kpstudy.verify import Box, ConvexHull, output_bounds
from kpstudy.verify.bounds import Region, propagate
from kpstudy.verify.graph import trace
from tests.helpers.verify_nets import MixedNet


@pytest.fixture(scope="module")
def patches():
    return occluder_patches()


class SmallHeatmapNet(nn.Module):
    """``(B, 3, 8, 8) → (B, 2, 8, 8)``: conv, batch norm, ReLU, affine upsampler."""

    input_size = heatmap_size = 8

    def __init__(self, seed=0):
        super().__init__()
        torch.manual_seed(seed)
        self.net = nn.Sequential(
            nn.Conv2d(3, 6, 3, 2, 1),
            nn.BatchNorm2d(6),
            nn.ReLU(),
            nn.Conv2d(6, 6, 3, 1, 1),
            nn.ReLU(),
            nn.ConvTranspose2d(6, 4, 4, 2, 1),
            nn.BatchNorm2d(4),
            nn.ConvTranspose2d(4, 2, 3, 1, 1),
        )

    def forward(self, x):
        return self.net(x)


def test_ibp_is_textbook_interval_arithmetic():
    torch.manual_seed(0)
    net = nn.Sequential(nn.Linear(6, 8), nn.ReLU(), nn.Linear(8, 8), nn.ReLU(), nn.Linear(8, 3))
    lower, upper = -torch.rand(6), torch.rand(6)
    lo, hi = lower.double(), upper.double()
    for layer in net:
        if isinstance(layer, nn.ReLU):
            lo, hi = lo.clamp_min(0), hi.clamp_min(0)
            continue
        W, b = layer.weight.double(), layer.bias.double()
        lo, hi = (
            W.clamp_min(0) @ lo + W.clamp_max(0) @ hi + b,
            W.clamp_min(0) @ hi + W.clamp_max(0) @ lo + b,
        )
    got_lo, got_hi = output_bounds(net, Box(lower, upper), "ibp")
    torch.testing.assert_close(got_lo.double(), lo, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(got_hi.double(), hi, atol=1e-5, rtol=1e-5)


def test_a_differentiable_graph_gives_the_folded_graphs_bounds():
    net = MixedNet(3)
    x = torch.rand(3, 2, 8, 8)
    coeff = torch.cat([x[:1], x[1:] - x[:1]])[None]
    region = Region.affine(coeff, "simplex")
    folded = propagate(trace(net, x[:1]), region)[0].bounds()
    live = propagate(trace(net, x[:1], differentiable=True), region)[0].bounds()
    for a, b in zip(folded, live):
        torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-4)


def test_random_hulls_are_the_studys_kinds(patches):
    sampler = HullSampler(patches, seed=3)
    images = torch.rand(40, 3, 64, 64)
    V = sampler(images)
    assert V.shape == (40, 1 + MAX_COPIES, 3, 64, 64)
    assert torch.equal(V[:, 0], images) and V.min() >= 0 and V.max() <= 1
    changed = (V[:, 1:] != V[:, :1]).any(2).flatten(2).sum(-1)  # pixels each copy changes
    copies = (changed > 0).sum(1)
    assert 1 <= copies.min() and copies.max() <= MAX_COPIES
    local = changed.amax(1) < 64 * 64 // 4  # objects and blocks change a few pixels
    assert local.any() and (~local).any()  # brightness and contrast change most of them
    sampler.reseed(5)
    first = sampler(images[:4])
    sampler.reseed(5)
    assert torch.equal(sampler(images[:4]), first)


@pytest.mark.parametrize(
    "method, scale, backbone", [("zonotope", 0.05, "cnn_patch"), ("forward", 0.5, "cnn_affine")]
)
def test_the_bound_term_contains_sampled_heatmaps_and_bounds_the_loss(
    patches, method, scale, backbone
):
    net = build_backbone(backbone).eval()
    torch.manual_seed(1)
    images = torch.rand(3, 3, 64, 64)
    V = HullSampler(patches, seed=1)(images)
    lower, upper = hull_bounds(bound_graph(net), V, scale=scale, method=method)
    keypoints, weights = torch.rand(1, 23, 2) * 63, torch.ones(1, 23)
    for b in range(3):
        hull = ConvexHull(V[b, 0] + scale * (V[b] - V[b, 0]))
        lam = hull.sample(64, seed=b).float()
        with torch.no_grad():
            h = net(hull.image(lam))
        assert (h >= lower[b] - 1e-4).all() and (h <= upper[b] + 1e-4).all()
        worst = robust_heatmap_loss(lower[b : b + 1], upper[b : b + 1], keypoints, weights, 1.0)
        each = [heatmap_loss(h[i : i + 1], keypoints, weights, 1.0) for i in range(len(h))]
        assert worst >= max(each) - 1e-4
    # Tight bounds: the term is the natural loss.
    with torch.no_grad():
        h = net(images[:1])
    torch.testing.assert_close(
        robust_heatmap_loss(h, h, keypoints, weights, 1.0),
        heatmap_loss(h, keypoints, weights, 1.0),
    )


@pytest.mark.parametrize("method", ["zonotope", "forward"])
def test_a_gradient_step_on_the_bound_term_lowers_it(method):
    net = SmallHeatmapNet().eval()
    graph = bound_graph(net)
    torch.manual_seed(2)
    x = torch.rand(4, 3, 8, 8)
    V = torch.stack([x, (x + 0.1 * torch.randn_like(x)).clamp(0, 1)], 1)
    keypoints, weights = torch.rand(4, 2, 2) * 7, torch.ones(4, 2)

    def term():
        return robust_heatmap_loss(*hull_bounds(graph, V, method=method), keypoints, weights, 1.0)

    before = term()
    before.backward()
    params = [p for p in net.parameters() if p.grad is not None]
    assert len(params) == len(list(net.parameters()))  # batch norms' affine too
    with torch.no_grad():
        for p in params:
            p -= 1e-3 * p.grad
    assert term() < before


def test_the_bound_pass_normalises_by_the_natural_passs_batch_statistics():
    net = SmallHeatmapNet().train()
    stats = BatchStatistics(net)
    with pytest.raises(RuntimeError, match="natural pass"):
        with stats.frozen():
            pass
    x = torch.rand(6, 3, 8, 8)
    natural = net(x)
    running = [m.running_mean.clone() for m in stats.norms]
    graph = bound_graph(net)
    with stats.frozen():
        assert not net.training
        lower, upper = hull_bounds(graph, torch.stack([x, x], 1))
        same = net(x)
    torch.testing.assert_close(same, natural)
    torch.testing.assert_close(lower, natural, atol=1e-5, rtol=1e-5)
    assert net.training
    for m, before in zip(stats.norms, running):
        assert torch.equal(m.running_mean, before)


def test_hull_scale_and_method_are_checked():
    net = SmallHeatmapNet().eval()
    with pytest.raises(ValueError, match="scale: expected a number in"):
        hull_bounds(bound_graph(net), torch.zeros(1, 2, 3, 8, 8), scale=2.0)
    with pytest.raises(ValueError, match="method: expected one of"):
        hull_bounds(bound_graph(net), torch.zeros(1, 2, 3, 8, 8), method="crown")
    with pytest.raises(ValueError, match="certified_method: expected one of"):
        TrainConfig(certified_method="ibp")


def test_bad_certified_config_is_named():
    with pytest.raises(ValueError, match="certified_weight"):
        TrainConfig(certified_weight=-1.0)
    with pytest.raises(ValueError, match="certified_start"):
        TrainConfig(certified_start=-1)
    with pytest.raises(ValueError, match="certified_hulls"):
        TrainConfig(certified_hulls=0)
    with pytest.raises(ValueError, match=r"certified_scale: expected a number in \(0, 1\]"):
        TrainConfig(certified_scale=0.0)


def test_a_tiny_certified_run_loads_evaluates_and_certifies(tiny_dataset, tmp_path):
    from kpstudy.certify.allocation_method import SeedImage
    from kpstudy.certify.hull import certify
    from kpstudy.models.data import load_keypoint_set
    from kpstudy.models.evaluation import evaluate

    config = TrainConfig(
        "cnn_patch",
        epochs=2,
        batch_size=4,
        images=8,
        seed=1,
        certified_weight=0.5,
        certified_hulls=2,
        certified_start=0,
        certified_ramp=1,
        certified_scale=0.05,
        stability_weight=1.0,
    )
    path = tmp_path / "cnn_patch.pt"
    state = train(tiny_dataset, path, config, progress=False)
    assert all(np.isfinite(row["bound_loss"]) for row in state["history"])
    assert all(0 <= row["instability"] < np.inf for row in state["history"])
    backbone, saved = load_checkpoint(path)
    assert saved["config"]["certified_weight"] == 0.5
    summary = evaluate(path, tiny_dataset, "test")[0]
    assert len(summary) > 0
    data = load_keypoint_set(tiny_dataset, "test", 64)
    seed = SeedImage.from_keypoint_set(data, 0)
    image = data.images[0]
    vertices = np.stack([image, np.clip(image + 1.0, 0, 255), np.clip(image - 1.0, 0, 255)])
    record = certify(
        backbone, vertices, seed, alpha=1e4, timeout=600, max_nodes=1000, check_samples=4
    )
    assert record["status"] == "holds"


def test_the_bound_terms_gradient_is_a_fixed_share_of_the_natural_ones():
    from kpstudy.models.training import _backward

    w = torch.tensor([1.0, 2.0], requires_grad=True)
    natural = (w**2).sum()  # gradient (2, 4)
    bound = 1e6 * w[0]  # gradient (1e6, 0): far larger
    _backward(natural, [(bound, 0.5)], [w])
    share = 0.5 * torch.tensor([2.0, 4.0]).norm() / 1e6
    torch.testing.assert_close(w.grad, torch.tensor([2.0 + share * 1e6, 4.0]))
    w.grad = None
    _backward((w**2).sum(), [(None, 0.5)], [w])
    torch.testing.assert_close(w.grad, torch.tensor([2.0, 4.0]))
    # Two terms: each gets its own share of the natural gradient's norm.
    w.grad = None
    _backward((w**2).sum(), [(1e6 * w[0], 0.5), (-3.0 * w[1], 2.0)], [w])
    natural_norm = torch.tensor([2.0, 4.0]).norm()
    expected = torch.tensor([2.0 + 0.5 * natural_norm, 4.0 - 2.0 * natural_norm])
    torch.testing.assert_close(w.grad, expected)


def test_photometric_pairs_are_the_studys_brightness_and_contrast_hulls():
    rng = np.random.default_rng(0)
    image = np.random.default_rng(1).uniform(0, 1, (3, 8, 8)).astype(np.float32)
    image[0, 0, 0], image[1, 0, 0] = 0.0, 1.0  # clipped pixels stay in [0, 1]
    bright = photometric_pair(image, "brightness", rng)
    d = bright[0] - image
    assert bright.shape == (2, 3, 8, 8) and 0 <= bright.min() and bright.max() <= 1
    inner = (image > 2 / 255) & (image < 1 - 2 / 255)
    assert np.ptp(d[inner]) < 1e-6 and 0 < d[inner][0] <= 2 / 255 + 1e-7
    np.testing.assert_allclose(bright[1][inner], image[inner] - d[inner][0], atol=1e-6)
    dark = photometric_pair(image, "contrast", rng)
    ratio = dark[0][image > 0.1] / image[image > 0.1]
    assert np.ptp(ratio[dark[0][image > 0.1] < 1]) < 1e-5 and 1 < ratio.max() <= 1.01 + 1e-6
    with pytest.raises(ValueError, match="kind: expected one of"):
        photometric_pair(image, "objects", rng)


def test_relu_instability_is_the_exact_band_of_an_affine_layer_over_the_hull():
    layer = nn.Sequential(nn.Conv2d(3, 4, 3, 1, 1), nn.BatchNorm2d(4)).eval()
    torch.manual_seed(3)
    x = torch.rand(2, 3, 6, 6)
    pairs = torch.stack([(x + 0.2).clamp(0, 1), (x - 0.3).clamp(0, 1)], 1)  # (B, 2, 3, 6, 6)
    with torch.no_grad():
        centre = layer(x)
        deltas = torch.stack([layer(pairs[:, i]) - centre for i in range(2)], 1)
        low = centre + deltas.amin(1).clamp_max(0)
        high = centre + deltas.amax(1).clamp_min(0)
        for b in range(2):  # the band holds every image of the hull and is reached
            hull = ConvexHull(torch.cat([x[b : b + 1], pairs[b]]))
            inside = layer(hull.image(hull.sample(256, seed=b).float()))
            assert (inside >= low[b] - 1e-5).all() and (inside <= high[b] + 1e-5).all()
            corners = layer(torch.cat([x[b : b + 1], pairs[b]]))
            assert torch.isclose(corners.amin(0), low[b], atol=1e-5).all()
    unstable = (low < 0) & (high > 0)
    assert unstable.any() and (~unstable).any()
    depth = torch.minimum(-low, high).clamp_min(0)  # zero where stable
    spread = centre.std((0, 2, 3), keepdim=True)
    torch.testing.assert_close(relu_instability(centre, deltas), (depth / spread).mean())
    assert relu_instability(centre.abs() + 1, deltas.clamp(-0.5, 0.5)) == 0  # all stable


def test_a_gradient_step_on_the_stability_term_lowers_it():
    from kpstudy.models.training import _StabilityTerm

    net = SmallHeatmapNet().net.train()
    term = _StabilityTerm(TrainConfig("cnn_affine", stability_weight=1.0, seed=4), net)
    torch.manual_seed(5)
    x = torch.rand(8, 3, 8, 8)

    def value():
        term.reseed(0)
        net(x)  # the natural pass the term reads
        return term(x)

    before = value()
    assert before > 0
    before.backward()
    with torch.no_grad():
        for p in net.parameters():
            if p.grad is not None:
                p -= 0.05 * p.grad
    assert value() < before
    with pytest.raises(ValueError, match="stability_weight: expected a backbone that starts"):
        _StabilityTerm(TrainConfig(stability_weight=1.0), nn.Sequential(nn.ReLU()))
    with pytest.raises(ValueError, match="stability_weight"):
        TrainConfig(stability_weight=-1.0)


def test_block_hull_points_are_the_image_its_blocked_copies_and_an_interior_point():
    images = torch.rand(2, 3, 8, 8)
    points = block_hull_points(images, np.random.default_rng(0), interior=2)
    assert points.shape == (2, 1 + MAX_COPIES + 2, 3, 8, 8)
    torch.testing.assert_close(points[:, 0], images)
    changed = (points[:, 1 : 1 + MAX_COPIES] != images[:, None]).any(2)  # (B, copies, 8, 8)
    assert (changed.sum((-2, -1)) <= 9).all() and changed.any((-2, -1)).all()
    rows, cols = changed.any(-1), changed.any(-2)  # each change is one 3×3 block
    assert (rows.sum(-1) <= 3).all() and (cols.sum(-1) <= 3).all()
    vertices, inner = points[:, : 1 + MAX_COPIES], points[:, 1 + MAX_COPIES :]
    assert (inner >= vertices.amin(1, keepdim=True) - 1e-6).all()
    assert (inner <= vertices.amax(1, keepdim=True) + 1e-6).all()
    assert ((inner != images[:, None]).any(2) <= changed.any(1, keepdim=True)).all()


def test_the_block_stability_term_reads_every_relu_and_a_step_lowers_it():
    from kpstudy.models.training import _BlockStabilityTerm

    net = SmallHeatmapNet().net.train()
    term = _BlockStabilityTerm(TrainConfig(stability_weight=1.0, stability_hulls="blocks"), net)
    torch.manual_seed(5)
    x = torch.rand(8, 3, 8, 8)

    def value():
        term.reseed(0)
        return term(x)

    before = value()
    assert before > 0
    before.backward()
    second = net[3].weight.grad  # after the first ReLU: the second ReLU's band is read too
    assert second is not None and second.abs().sum() > 0
    with torch.no_grad():
        for p in net.parameters():
            if p.grad is not None:
                p -= 0.05 * p.grad
    assert value() < before
    stable = nn.Sequential(nn.Conv2d(3, 2, 3, 1, 1), nn.ReLU(), nn.Conv2d(2, 2, 1), nn.ReLU())
    with torch.no_grad():
        stable[0].bias.fill_(100.0)
        stable[2].weight.abs_()
        stable[2].bias.fill_(100.0)
    term = _BlockStabilityTerm(TrainConfig(stability_weight=1.0, stability_hulls="blocks"), stable)
    assert term(x) == 0  # no ReLU a block can flip
    with pytest.raises(ValueError, match="stability_hulls: 'blocks' expected a backbone with"):
        _BlockStabilityTerm(TrainConfig(stability_hulls="blocks"), nn.Conv2d(3, 2, 1))
    with pytest.raises(ValueError, match="stability_hulls: expected one of"):
        TrainConfig(stability_hulls="objects")


def test_a_tiny_run_with_the_block_stability_term_records_it(tiny_dataset, tmp_path):
    config = TrainConfig(
        "cnn", epochs=1, batch_size=4, images=4, stability_weight=1.0, stability_hulls="blocks"
    )
    state = train(tiny_dataset, tmp_path / "cnn.pt", config, progress=False)
    assert 0 < state["history"][0]["instability"] < np.inf
    assert state["config"]["stability_hulls"] == "blocks"


def test_the_shipped_checkpoint_is_the_recipes_and_matches_its_card():
    import json

    from kpstudy.study.reproduction import (
        FRIENDLY_MODEL,
        FRIENDLY_STAGES,
        PROFILES,
        SHIPPED,
        follows_recipe,
        friendly_recipe,
        probe_input,
    )

    shipped = SHIPPED[FRIENDLY_MODEL]
    backbone, state = load_checkpoint(shipped)
    card = json.loads(shipped.with_suffix(".json").read_text())
    made = [TrainConfig(**c) for c in state["lineage"]] + [config_of(state)]
    assert len(made) == len(FRIENDLY_STAGES)
    for config, stage in zip(made, FRIENDLY_STAGES):
        assert {k: getattr(config, k) for k in stage} == stage
    assert card["recipe"] == state["config"] and card["lineage"] == state["lineage"]
    assert follows_recipe(state, friendly_recipe(PROFILES["quick"]))  # reproduce copies it
    assert not follows_recipe(state, friendly_recipe(PROFILES["quick"])[1:])
    assert "optimizer" not in state
    with torch.no_grad():
        h = backbone(probe_input()).double()
    assert h.sum().item() == pytest.approx(card["probe"]["sum"], rel=1e-5, abs=1e-3)
    assert h.abs().sum().item() == pytest.approx(card["probe"]["abs_sum"], rel=1e-5)
    argmax = next(row for row in card["test"] if row["head"] == "argmax")
    # The accuracy it was shipped for (README: PCK@2 0.98, inside Ξ at α = 1 0.705; the
    # natural CNN's 0.695 less 5 points is the floor).
    assert argmax["pck@2"] >= 0.95 and argmax["inside_xi@1"] >= 0.645


def test_ship_writes_a_finished_checkpoint_and_its_card(tiny_dataset, tmp_path):
    import json

    from kpstudy.study.reproduction import ship

    config = TrainConfig("cnn_patch", epochs=1, batch_size=4, images=4, seed=2)
    path = tmp_path / "trained.pt"
    train(tiny_dataset, path, config, progress=False)
    target = tmp_path / "shipped.pt"
    card = ship(path, tiny_dataset, target)
    state = torch.load(target, weights_only=True)
    assert "optimizer" not in state and state["dataset"]["path"] is None
    assert json.loads(target.with_suffix(".json").read_text()) == card
    assert train(tiny_dataset, target, config, progress=False)["epoch"] == 1  # finished
