"""The output specification: per keypoint, the target cell beats every other cell.

The proxy model's output is the concatenation of one group per keypoint (its pooled
cells, flattened). For a verified keypoint k with target cell ``t_k`` the property is
``y[t_k] − y[j] > 0`` for every other cell ``j`` of the group: one *margin row* per
``j``. A group whose target is ``None`` (a keypoint left out: not visible, an outlier)
contributes no rows. Ties count as violations: an argmax tie is not a certified cell.
"""

from __future__ import annotations

import operator

import numpy as np
import torch


class ArgmaxSpec:
    """Per-group argmax property of a concatenated output.

    Parameters
    ----------
    group_sizes : sequence of int
        Output entries per group (keypoint), each >= 1.
    targets : sequence of int or None
        Target index within each group, or ``None`` to leave the group out.

    Attributes
    ----------
    n_outputs : int
        ``sum(group_sizes)``, the output size the spec expects.
    row_group, row_pos, row_neg : LongTensor, shape (R,)
        Margin row ``r`` is ``y[row_pos[r]] − y[row_neg[r]]`` of group ``row_group[r]``
        (global output indices).

    Examples
    --------
    >>> spec = ArgmaxSpec([3, 2], [0, None])
    >>> spec.margins(torch.tensor([[2.0, 1.0, 0.5, 9.0, 9.0]]))
    tensor([[1.0000, 1.5000]])
    """

    def __init__(self, group_sizes, targets) -> None:
        sizes = list(group_sizes)
        targets = list(targets)
        if not sizes:
            raise ValueError("group_sizes: expected at least one group")
        for g, s in enumerate(sizes):
            if isinstance(s, bool) or not isinstance(s, (int, np.integer)) or s < 1:
                raise ValueError(f"group_sizes[{g}]: expected an integer >= 1, got {s!r}")
        if len(targets) != len(sizes):
            raise ValueError(
                f"targets: expected one entry per group ({len(sizes)}), got {len(targets)}"
            )
        for g, (t, s) in enumerate(zip(targets, sizes)):
            if t is None:
                continue
            if isinstance(t, bool) or not isinstance(t, (int, np.integer)) or not 0 <= t < s:
                raise ValueError(
                    f"targets[{g}]: expected None or an integer in [0, {s}), got {t!r}"
                )
        self.group_sizes = [operator.index(s) for s in sizes]
        self.targets = [None if t is None else operator.index(t) for t in targets]
        self.offsets = np.concatenate([[0], np.cumsum(self.group_sizes)]).tolist()
        self.n_outputs = self.offsets[-1]
        group, pos, neg = [], [], []
        for g, t in enumerate(self.targets):
            if t is None:
                continue
            others = [j for j in range(self.group_sizes[g]) if j != t]
            group += [g] * len(others)
            pos += [self.offsets[g] + t] * len(others)
            neg += [self.offsets[g] + j for j in others]
        self.row_group = torch.tensor(group, dtype=torch.long)
        self.row_pos = torch.tensor(pos, dtype=torch.long)
        self.row_neg = torch.tensor(neg, dtype=torch.long)
        self.active_groups = [g for g, t in enumerate(self.targets) if t is not None]

    @property
    def n_rows(self) -> int:
        return len(self.row_group)

    @property
    def n_groups(self) -> int:
        return len(self.group_sizes)

    def check_output(self, n_outputs: int) -> None:
        """Refuse a model whose flattened output size is not ``n_outputs``."""
        if n_outputs != self.n_outputs:
            raise ValueError(
                f"spec: expected a model with {self.n_outputs} outputs "
                f"(sum of group_sizes), got {n_outputs}"
            )

    def margins(self, y: torch.Tensor) -> torch.Tensor:
        """Margins ``(B, R)`` of outputs ``y (B, n_outputs)``; the property needs all > 0."""
        return y[:, self.row_pos] - y[:, self.row_neg]

    def group_min(self, row_values: torch.Tensor, fill: float = float("inf")) -> torch.Tensor:
        """Per-group minimum ``(B, n_groups)`` of row values ``(B, R)``; ``fill`` for groups
        without rows."""
        B = row_values.shape[0]
        out = torch.full((B, self.n_groups), fill, dtype=row_values.dtype)
        index = self.row_group.expand(B, -1)
        return out.scatter_reduce(1, index, row_values, reduce="amin", include_self=True)

    def to_polytope(self, big_m: float = 1e9) -> tuple[np.ndarray, np.ndarray]:
        """The paper's output polytope ``A y ≤ b`` (its eq. for ``A_k``, ``b_k``).

        Block-diagonal over groups: for a verified group, row ``j ≠ t`` is
        ``y_j − y_t ≤ 0`` and row ``t`` is ``−y_t ≤ M``; a group left out has ``A_k = I``,
        ``b_k = M``. The paper's rows are non-strict; :meth:`margins` is strict.

        Returns
        -------
        A : ndarray, shape (n_outputs, n_outputs)
        b : ndarray, shape (n_outputs,)
        """
        n = self.n_outputs
        A, b = np.zeros((n, n)), np.zeros(n)
        for g, t in enumerate(self.targets):
            lo, size = self.offsets[g], self.group_sizes[g]
            idx = np.arange(lo, lo + size)
            if t is None:
                A[idx, idx] = 1.0
                b[idx] = big_m
                continue
            A[idx, idx] = 1.0
            A[idx, lo + t] = -1.0
            b[lo + t] = big_m
        return A, b
