"""data_gen: the study's synthetic data, from trimesh models (``python -m data_gen …``).

Pipeline: :mod:`~data_gen.airplane` (the airliner mesh and its 23 keypoints from
:mod:`~data_gen.keypoints`) and :mod:`~data_gen.occluders` (apron vehicles, crew,
equipment) → :mod:`~data_gen.scene` (camera framing, sun, asphalt, markings) drawn by
:mod:`~data_gen.render` (OpenGL on a headless EGL context) → :mod:`~data_gen.dataset`
(COCO keypoints, masks, depth) → :mod:`~data_gen.perturb` (objects via
:mod:`~data_gen.patches`, blocks, brightness, contrast; ``hull_vertices``) →
:mod:`~data_gen.gallery` (figures to look at). Every draw takes an explicit seed.
"""
