"""data_gen: synthetic overhead airplane scenes for kpstudy.

Defines the canonical 23 airplane keypoints (:mod:`data_gen.keypoints`) and the
overhead camera model (:mod:`data_gen.camera`).
"""
