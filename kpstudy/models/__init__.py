"""Keypoint networks and what makes, feeds, trains and evaluates them.

The networks: backbones that output unnormalised heatmaps (:mod:`~kpstudy.models.cnn`,
:mod:`~kpstudy.models.resnet`, by name in :mod:`~kpstudy.models.backbones`), the target
heads (softmax → DSNT or argmax, :mod:`~kpstudy.models.heads`) and the proxy head that
turns the heatmaps into a verifiable per-keypoint classification
(:mod:`~kpstudy.models.proxy`, on the pooling cells of :mod:`~kpstudy.models.pooling`;
docs/design.md §4.4–4.5). Around them: :mod:`~kpstudy.models.preprocess` (F0: resize to
the model input, pixel maps), :mod:`~kpstudy.models.data` (a dataset split as network
inputs), :mod:`~kpstudy.models.training` (``python -m kpstudy train``, checkpoints),
:mod:`~kpstudy.models.certified` (the verifier's bound term of verification-friendly
training, §4.5b) and :mod:`~kpstudy.models.evaluation` (``python -m kpstudy evaluate``:
PCK, the pose through PnP, the fraction in Ξ).

Every backbone has class attributes ``input_size`` (square input side, pixels) and
``heatmap_size`` (square heatmap side, pixels) and uses only the operators the verifier
bounds (:mod:`kpstudy.verify.graph`).

May import: the infrastructure (``kpstudy._checks``, ``kpstudy._memo``, ``kpstudy.io``),
:mod:`kpstudy.pose` and :mod:`kpstudy.verify` (docs/design.md §2).
"""

from kpstudy.models.backbones import BACKBONES, build_backbone
from kpstudy.models.certified import (
    BOUND_METHODS,
    BatchStatistics,
    HullSampler,
    bound_graph,
    hull_bounds,
    occluder_patches,
    robust_heatmap_loss,
)
from kpstudy.models.cnn import HeatmapCNN, HeatmapCNNAffineDecoder
from kpstudy.models.data import SPLITS, KeypointSet, load_keypoint_set
from kpstudy.models.evaluation import evaluate, pose_errors
from kpstudy.models.heads import (
    TargetModel,
    argmax_keypoints,
    dsnt_keypoints,
    softmax_heatmaps,
)
from kpstudy.models.pooling import (
    CellAvgPool2d,
    PoolParams,
    build_cell_pool,
    cell_bounds,
    cell_index,
    keypoint_pooling,
    num_cells,
    pooling_params,
)
from kpstudy.models.preprocess import (
    resize_to_input,
    scale_factors,
    to_image_pixels,
    to_input_pixels,
    to_model_input,
)
from kpstudy.models.proxy import KeypointProxy, build_proxy
from kpstudy.models.resnet import HeatmapResNet18
from kpstudy.models.training import (
    CERTIFIED_WEIGHT,
    TrainConfig,
    TrainingDiverged,
    check_device,
    config_of,
    heatmap_loss,
    heatmap_targets,
    load_checkpoint,
    pck,
    plot_history,
    predict,
    train,
    weights_digest,
)

__all__ = [
    "BACKBONES",
    "BOUND_METHODS",
    "CERTIFIED_WEIGHT",
    "SPLITS",
    "BatchStatistics",
    "CellAvgPool2d",
    "HeatmapCNN",
    "HeatmapCNNAffineDecoder",
    "HeatmapResNet18",
    "HullSampler",
    "KeypointProxy",
    "KeypointSet",
    "PoolParams",
    "TargetModel",
    "TrainConfig",
    "TrainingDiverged",
    "argmax_keypoints",
    "bound_graph",
    "build_backbone",
    "build_cell_pool",
    "build_proxy",
    "cell_bounds",
    "cell_index",
    "check_device",
    "config_of",
    "dsnt_keypoints",
    "evaluate",
    "heatmap_loss",
    "heatmap_targets",
    "hull_bounds",
    "keypoint_pooling",
    "load_checkpoint",
    "load_keypoint_set",
    "num_cells",
    "occluder_patches",
    "pck",
    "plot_history",
    "pooling_params",
    "pose_errors",
    "predict",
    "resize_to_input",
    "robust_heatmap_loss",
    "scale_factors",
    "softmax_heatmaps",
    "to_image_pixels",
    "to_input_pixels",
    "to_model_input",
    "train",
    "weights_digest",
]
