"""Tiny backbones and scenes for the pose-bound method's tests (kpstudy.certify.pose_bound_*):
heatmaps that peak where a test says, a two-image hull, and a tolerance that a chosen
move of keypoint 0 leaves."""

import numpy as np
import torch
from torch import nn

from kpstudy.certify import pose_bound_rules as rules
from kpstudy.models.preprocess import to_image_pixels
from kpstudy.verify import ConvexHull

HM = 64  # heatmap side


class Peaks(nn.Module):
    """A backbone whose heatmaps peak at fixed pixels ``(K, 2)`` (u, v), and at ``moved``
    instead for images brighter than 0.5 (the hull's second vertex)."""

    heatmap_size = input_size = HM

    def __init__(self, peaks, moved=None):
        super().__init__()
        self.peaks = np.asarray(peaks, dtype=np.int64)
        self.moved = self.peaks if moved is None else np.asarray(moved, dtype=np.int64)

    def forward(self, x):
        out = torch.zeros(len(x), len(self.peaks), HM, HM)
        for b, image in enumerate(x):
            peaks = self.moved if image.mean() > 0.5 else self.peaks
            for k, (u, v) in enumerate(peaks):
                out[b, k, v, u] = 1.0
        return out


class Ramp(nn.Module):
    """A differentiable backbone: keypoint k's heatmap is ``1 − b`` at ``peaks[k]`` and
    ``b·gain[k]`` at ``moved[k]`` (0 elsewhere), ``b`` the image's mean brightness."""

    heatmap_size = input_size = HM

    def __init__(self, peaks, moved, gain):
        super().__init__()
        self.peaks, self.moved = (np.asarray(p).astype(np.int64) for p in (peaks, moved))
        self.gain = torch.as_tensor(gain, dtype=torch.float32)

    def forward(self, x):
        b = x.flatten(1).mean(1)[:, None]  # (B, 1)
        out = x.new_zeros(len(x), len(self.peaks), HM * HM)
        index = lambda p: torch.as_tensor(p[:, 1] * HM + p[:, 0])[None, :, None]  # noqa: E731
        K = len(self.peaks)
        out = out.scatter_add(
            2, index(self.peaks).expand(len(x), -1, 1), (1 - b).expand(-1, K)[..., None]
        )
        moved = (b * self.gain.to(x.dtype)).expand(-1, K)[..., None]
        out = out.scatter_add(2, index(self.moved).expand(len(x), -1, 1), moved)
        return out.view(len(x), -1, HM, HM)


def unit_hull():
    return ConvexHull(torch.stack([torch.zeros(1, 2, 2), torch.ones(1, 2, 2)]))


def regions_with(centers, moves):
    """Each keypoint's rounded pixel, plus the pixels ``centers[k] + offset`` of ``moves``."""
    pixels = [[c] for c in centers]
    for k, offset in moves:
        pixels[k].append(centers[k] + np.asarray(offset))
    return pixels


def far_tolerance(scene):
    """Ξ that holds the seed's rounded pixels' pose but not the pose with keypoint 0 moved
    by 8 heatmap pixels (on one axis), and the index of that axis."""
    seed, R, t, factors, centers = scene
    near = [to_image_pixels(c[None], factors) for c in centers]
    far = list(near)
    far[0] = to_image_pixels(centers[0][None] + [8, 0], factors)
    e_near = rules.enumerated_pose_error(seed, near, R, t)
    e_far = rules.enumerated_pose_error(seed, far, R, t)
    axis = int(np.argmax(e_far / e_near))
    assert e_far[axis] > 2 * e_near[axis]
    eps = 2 * np.maximum(e_near, e_far)
    eps[axis] = 0.5 * (e_near[axis] + e_far[axis])
    return eps, axis
