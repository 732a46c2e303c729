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
bounds (``kpstudy.verify.graph``).

May import: the infrastructure (``kpstudy._checks``, ``_memo``, ``_lazy``, ``io``),
:mod:`kpstudy.pose` and :mod:`kpstudy.verify` (docs/design.md §2).
"""

from kpstudy._lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "backbones": (
            "BACKBONES",
            "build_backbone",
        ),
        "certified": (
            "BOUND_METHODS",
            "BatchStatistics",
            "HullSampler",
            "bound_graph",
            "hull_bounds",
            "occluder_patches",
            "robust_heatmap_loss",
        ),
        "cnn": (
            "HeatmapCNN",
            "HeatmapCNNAffineDecoder",
        ),
        "data": (
            "SPLITS",
            "KeypointSet",
            "load_keypoint_set",
        ),
        "evaluation": (
            "evaluate",
            "pose_errors",
        ),
        "heads": (
            "TargetModel",
            "argmax_keypoints",
            "dsnt_keypoints",
            "softmax_heatmaps",
        ),
        "pooling": (
            "CellAvgPool2d",
            "PoolParams",
            "build_cell_pool",
            "cell_bounds",
            "cell_index",
            "cell_params",
            "keypoint_cells",
            "keypoint_pooling",
            "num_cells",
            "pooling_params",
        ),
        "preprocess": (
            "resize_to_input",
            "scale_factors",
            "to_image_pixels",
            "to_input_pixels",
            "to_model_input",
        ),
        "proxy": (
            "KeypointProxy",
            "build_proxy",
        ),
        "resnet": ("HeatmapResNet18",),
        "training": (
            "CERTIFIED_WEIGHT",
            "TrainConfig",
            "TrainingDiverged",
            "check_device",
            "config_of",
            "heatmap_loss",
            "heatmap_targets",
            "load_checkpoint",
            "pck",
            "plot_history",
            "predict",
            "train",
            "weights_digest",
        ),
    },
)
