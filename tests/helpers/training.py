"""The tiny training recipe the model tests share (tests/kpstudy/models/conftest.py trains it
once on the tiny rendered dataset)."""

from kpstudy.models.training import TrainConfig

TINY = TrainConfig(epochs=3, batch_size=4, images=8, lr=3e-3, seed=1)
