"""The phase-1 model as one solver-neutral 0-1 linear program (rows over integer-coefficient columns),
handed unchanged to CP-SAT or to HiGHS (:mod:`retrotouch.nodes.layout.solvers`). Units: levels are
distances in units of the model's resolution (integers).

Columns: ``x_a`` (Tx ``a`` selected), ``y_b`` (Rx ``b``), ``act_c`` (crossing ``c`` active, only
crossings within some sample's cap), per sample ``k`` and each of its distinct levels
``l_k1 < ... < l_kJ`` but the last, ``u_kj`` ("sample ``k`` is still uncovered at ``l_kj``", so its
distance is at least ``l_k(j+1)``), and one global ``z_t = [R >= t]`` per radius level ``t`` in
``(r_low, cap]`` with ``r_low = max_k l_k1`` (no selection has a smaller radius), so that
``R = r_low + sum_t z_t``.

Rows: C3 (``sum x <= N_drive``, ``sum y <= N_sense``), C1/C2 (``x_a + x_a' <= 1``, ``y_b + y_b' <= 1``,
``x_a + y_b <= 1``), ``act_c <= x_a``, ``act_c <= y_b``, ``act_c >= x_a + y_b - 1``, the covering chain
``u_k1 + S_k1 >= 1``, ``u_kj + S_kj >= u_k(j-1)``, ``S_kJ >= u_k(J-1)`` (``S_kj`` the sum of ``act`` over the
crossings at level ``l_kj``), ``u_kj <= u_k(j-1)``, and the radius ``z_t >= z_(t+1)``,
``z_(l_k(j+1)) >= u_kj``. The radius rows are the p-center formulation of Elloumi, Labbe and Pochet
(2004): one radius chain shared by all samples, whose LP relaxation is much tighter than a per-sample
big-M ``R >= l_(j+1) u_kj``; the integer points are the same.

Stage 1 minimises ``sum_t z_t`` (``R`` minus the constant ``r_low``); stage 2 fixes ``z_t = 0`` for
``t > R*`` and minimises ``sum_k sum_j (l_k(j+1)^p - l_kj^p) u_kj`` (the sum of level**p minus the
constant ``sum_k l_k1^p``), the radius formulation of the p-median problem (Elloumi 2010).
"""
from __future__ import annotations

import dataclasses

import numpy as np

from .problem import SelectionProblem


@dataclasses.dataclass(frozen=True)
class LinearModel:
    """A 0-1 program ``row_lo <= A v <= row_hi`` in CSR form (``A`` integer), all columns binary."""

    n_tx: int
    n_rx: int
    act_crossings: np.ndarray  # (Na,) candidate crossing of each act column
    act_tx: np.ndarray  # (Na,) Tx curve of each act column
    act_rx: np.ndarray  # (Na,) Rx curve of each act column
    u_sample: np.ndarray  # (Nu,) sample of each u column
    u_level: np.ndarray  # (Nu,) level l_kj of each u column (uncovered at it)
    u_next: np.ndarray  # (Nu,) level l_k(j+1) (the distance when uncovered)
    r_low: int  # radius lower bound (levels)
    cap: int  # largest radius level in the model
    offsets: np.ndarray  # (rows + 1,) CSR row starts
    columns: np.ndarray  # (nnz,) column of each entry
    values: np.ndarray  # (nnz,) int64 coefficient
    row_lo: np.ndarray  # (rows,) float, -inf when none
    row_hi: np.ndarray  # (rows,) float, +inf when none
    col_hi: np.ndarray  # (cols,) 0 or 1
    constant_power_sum: float  # sum_k l_k1**p, the part of stage 2's objective no column carries
    power: int

    @property
    def n_cols(self) -> int:
        return len(self.col_hi)

    @property
    def act_start(self) -> int:
        return self.n_tx + self.n_rx

    @property
    def u_start(self) -> int:
        return self.act_start + len(self.act_crossings)

    @property
    def z_start(self) -> int:
        return self.u_start + len(self.u_sample)

    def radius_objective(self) -> np.ndarray:
        """Stage 1: the radius in levels minus ``r_low`` (``sum_t z_t``)."""
        cost = np.zeros(self.n_cols, dtype=np.int64)
        cost[self.z_start:] = 1
        return cost

    def power_objective(self) -> np.ndarray:
        """Stage 2: the sum over samples of level**p minus ``constant_power_sum`` (int64)."""
        cost = np.zeros(self.n_cols, dtype=np.int64)
        p = self.power
        cost[self.u_start:self.z_start] = self.u_next.astype(np.int64) ** p - self.u_level.astype(np.int64) ** p
        return cost

    def radius_fixed(self, radius_level: int) -> "LinearModel":
        """The same model with ``R <= radius_level`` (``z_t = 0`` above it; u columns that would need
        more fixed at 0 too, which the rows imply but presolve need not find)."""
        col_hi = self.col_hi.copy()
        col_hi[self.z_start + max(radius_level - self.r_low, 0):] = 0
        col_hi[self.u_start:self.z_start][self.u_next > radius_level] = 0
        return dataclasses.replace(self, col_hi=col_hi)

    def column_values(self, tx: np.ndarray, rx: np.ndarray, nearest_level: np.ndarray) -> np.ndarray:
        """Every column at its tight value for a selection (``nearest_level`` per sample, levels)."""
        v = np.zeros(self.n_cols, dtype=np.int64)
        v[tx] = 1
        v[self.n_tx + rx] = 1
        v[self.act_start:self.u_start] = v[self.act_tx] * v[self.n_tx + self.act_rx]
        v[self.u_start:self.z_start] = nearest_level[self.u_sample] > self.u_level
        radius = int(min(nearest_level.max(), self.cap))
        v[self.z_start:self.z_start + max(radius - self.r_low, 0)] = 1
        return v



class _Rows:
    """Accumulates rows ``lo <= sum coef * col <= hi``."""

    def __init__(self):
        self.cols: list[np.ndarray] = []
        self.vals: list[np.ndarray] = []
        self.lo: list[float] = []
        self.hi: list[float] = []

    def add(self, cols, vals, lo=-np.inf, hi=np.inf) -> None:
        self.cols.append(np.asarray(cols, dtype=np.int64))
        self.vals.append(np.asarray(vals, dtype=np.int64))
        self.lo.append(lo)
        self.hi.append(hi)

    def pairs(self, left: np.ndarray, right: np.ndarray, vals: tuple[int, int], lo=-np.inf, hi=np.inf) -> None:
        """One two-column row per (left, right) pair."""
        for a, b in zip(left.tolist(), right.tolist()):
            self.add((a, b), vals, lo, hi)


def build_model(problem: SelectionProblem, n_drive: int, n_sense: int, q: np.ndarray, sample_cap: np.ndarray,
                power: int) -> LinearModel:
    """The model over the crossings within each sample's cap ``sample_cap`` (levels); ``q`` is the (K, C)
    quantised distance matrix."""
    n_tx, n_rx = len(problem.tx_usable), len(problem.rx_usable)
    order = np.argsort(q, axis=1, kind="stable")
    within = [order[k, : int(np.searchsorted(q[k, order[k]], sample_cap[k], side="right"))] for k in range(len(q))]
    act_crossings = np.unique(np.concatenate(within))
    act_col = np.full(q.shape[1], -1, dtype=np.int64)
    act_col[act_crossings] = n_tx + n_rx + np.arange(len(act_crossings))
    chains = []  # per sample: levels, shells
    u_sample, u_level, u_next = [], [], []
    for k, w in enumerate(within):
        levels, shell_of = np.unique(q[k, w], return_inverse=True)
        chains.append((levels, [act_col[w[shell_of == j]] for j in range(len(levels))]))
        u_sample += [k] * (len(levels) - 1)
        u_level += levels[:-1].tolist()
        u_next += levels[1:].tolist()
    r_low = max(int(levels[0]) for levels, _ in chains)
    cap = int(sample_cap.max())
    u_start = n_tx + n_rx + len(act_crossings)
    z_start = u_start + len(u_sample)
    n_cols = z_start + max(cap - r_low, 0)

    rows = _Rows()
    rows.add(np.arange(n_tx), np.ones(n_tx), hi=n_drive)
    rows.add(n_tx + np.arange(n_rx), np.ones(n_rx), hi=n_sense)
    rows.pairs(problem.tx_conflicts[:, 0], problem.tx_conflicts[:, 1], (1, 1), hi=1)
    rows.pairs(n_tx + problem.rx_conflicts[:, 0], n_tx + problem.rx_conflicts[:, 1], (1, 1), hi=1)
    rows.pairs(problem.multi_pairs[:, 0], n_tx + problem.multi_pairs[:, 1], (1, 1), hi=1)
    act_tx, act_rx = problem.cross_tx[act_crossings], n_tx + problem.cross_rx[act_crossings]
    act = act_col[act_crossings]
    rows.pairs(act, act_tx, (1, -1), hi=0)
    rows.pairs(act, act_rx, (1, -1), hi=0)
    for c, a, b in zip(act.tolist(), act_tx.tolist(), act_rx.tolist()):
        rows.add((c, a, b), (1, -1, -1), lo=-1)
    u = u_start
    for levels, shells in chains:
        for j, shell in enumerate(shells):
            last = j == len(shells) - 1
            prev = [] if j == 0 else [u - 1]
            mine = [] if last else [u]
            rows.add(np.concatenate([shell, mine, prev]).astype(np.int64),
                     [1] * len(shell) + [1] * len(mine) + [-1] * len(prev), lo=1 if j == 0 else 0)
            if not last:
                if prev:
                    rows.add((u, u - 1), (1, -1), hi=0)
                if levels[j + 1] > r_low:
                    rows.add((z_start + int(levels[j + 1]) - r_low - 1, u), (1, -1), lo=0)
                u += 1
    for t in range(z_start, n_cols - 1):
        rows.add((t, t + 1), (1, -1), lo=0)

    lengths = np.array([len(c) for c in rows.cols], dtype=np.int64)
    col_hi = np.ones(n_cols, dtype=np.int64)
    col_hi[np.flatnonzero(~problem.tx_usable)] = 0
    col_hi[n_tx + np.flatnonzero(~problem.rx_usable)] = 0
    return LinearModel(
        n_tx=n_tx, n_rx=n_rx, act_crossings=act_crossings,
        act_tx=problem.cross_tx[act_crossings], act_rx=problem.cross_rx[act_crossings],
        u_sample=np.array(u_sample, dtype=np.int64), u_level=np.array(u_level, dtype=np.int64),
        u_next=np.array(u_next, dtype=np.int64), r_low=r_low, cap=cap,
        offsets=np.concatenate([[0], np.cumsum(lengths)]), columns=np.concatenate(rows.cols),
        values=np.concatenate(rows.vals), row_lo=np.array(rows.lo, dtype=float), row_hi=np.array(rows.hi, dtype=float),
        col_hi=col_hi, constant_power_sum=float(sum(int(levels[0]) ** power for levels, _ in chains)), power=power,
    )
