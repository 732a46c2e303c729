"""A stand-in for batched PnP, for the tests of what PnP's callers make of its ``valid``
flag."""

import numpy as np
import torch

from kpstudy.pose.pnp import PnPResult


def flagged_pnp(valid: bool):
    """A stand-in batched PnP: the initial pose itself (zero error), ``valid`` as given."""

    def solve(P, V, K, init, **kw):
        n = len(V)
        R = np.broadcast_to(np.asarray(init[0], float), (n, 3, 3)).copy()
        t = np.broadcast_to(np.asarray(init[1], float), (n, 3)).copy()
        out = (R, t, np.full(n, valid), np.zeros(n), np.ones(n))
        if isinstance(V, torch.Tensor):
            out = tuple(torch.from_numpy(x) for x in out)
        return PnPResult(*out)

    return solve
