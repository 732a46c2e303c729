"""Keypoint networks: backbones that output unnormalised heatmaps, and the proxy head
that turns them into a verifiable per-keypoint classification (DESIGN.md §4.5)."""

from kpstudy.models.cnn import HeatmapCNN
from kpstudy.models.proxy import KeypointProxy, build_proxy

__all__ = ["HeatmapCNN", "KeypointProxy", "build_proxy"]
