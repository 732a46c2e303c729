"""Small content-keyed caches of one process: a campaign's hulls of one seed image ask for
the same pose sensitivity and allocations (:mod:`kpstudy.certify.allocation_method`)."""

from __future__ import annotations

import hashlib
from collections.abc import Callable

import numpy as np


def digest(*arrays) -> str:
    """SHA-1 of the shapes and float64 values of ``arrays`` (array-likes)."""
    out = hashlib.sha1()
    for value in arrays:
        value = np.ascontiguousarray(np.asarray(value), dtype=np.float64)
        out.update(repr(value.shape).encode() + value.tobytes())
    return out.hexdigest()


def remember(cache: dict, key, make: Callable, limit: int):
    """``cache[key]``, made by ``make()`` if missing; past ``limit`` entries the oldest go."""
    if key not in cache:
        value = make()
        while len(cache) >= limit:
            cache.pop(next(iter(cache)))
        cache[key] = value
    return cache[key]
