"""kpstudy._memo: content-keyed caches of one process."""

import numpy as np

from kpstudy._memo import digest, remember


def test_the_digest_reads_shapes_and_float64_values_only():
    a = np.arange(6.0).reshape(2, 3)
    assert digest(a) == digest(a.tolist()) == digest(a.astype(np.float32)) == digest(a.T.T)
    assert digest(a) != digest(a.reshape(3, 2))  # the same values, another shape
    assert digest(a) != digest(a + 1e-12)
    assert digest(a, a) != digest(a) and digest(a, 2.0) == digest(a, np.float64(2))
    assert len(digest(a)) == 40 and int(digest(a), 16) >= 0


def test_remember_makes_each_key_once_and_drops_the_oldest_past_its_limit():
    cache, made = {}, []

    def make(key):
        return lambda: made.append(key) or key * 10

    assert [remember(cache, k, make(k), limit=2) for k in (1, 2, 1)] == [10, 20, 10]
    assert made == [1, 2]
    assert remember(cache, 3, make(3), limit=2) == 30
    assert list(cache) == [2, 3]  # key 1, the oldest made, went
    assert remember(cache, 1, make(1), limit=2) == 10 and made == [1, 2, 3, 1]
