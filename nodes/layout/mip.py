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
    """Accumulates blocks of rows ``lo <= sum coef * col <= hi`` (entries flat, in row order)."""

    def __init__(self):
        self.lengths: list[np.ndarray] = []
        self.cols: list[np.ndarray] = []
        self.vals: list[np.ndarray] = []
        self.lo: list[np.ndarray] = []
        self.hi: list[np.ndarray] = []

    def block(self, lengths, cols, vals, lo, hi) -> None:
        lengths = np.asarray(lengths, dtype=np.int64)
        self.lengths.append(lengths)
        self.cols.append(np.asarray(cols, dtype=np.int64))
        self.vals.append(np.asarray(vals, dtype=np.int64))
        self.lo.append(np.broadcast_to(np.asarray(lo, dtype=float), lengths.shape))
        self.hi.append(np.broadcast_to(np.asarray(hi, dtype=float), lengths.shape))

    def add(self, cols, vals, lo=-np.inf, hi=np.inf) -> None:
        self.block([len(cols)], cols, vals, [lo], [hi])

    def tuples(self, cols: tuple[np.ndarray, ...], vals: tuple[int, ...], lo=-np.inf, hi=np.inf) -> None:
        """One row per index ``i`` over the columns ``cols[0][i], cols[1][i], ...`` with ``vals``."""
        n = len(cols[0])
        self.block(np.full(n, len(cols)), np.stack(cols, axis=1).reshape(-1), np.tile(vals, n), lo, hi)

    def csr(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        lengths = np.concatenate(self.lengths)
        return (np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64), np.concatenate(self.cols),
                np.concatenate(self.vals), np.concatenate(self.lo), np.concatenate(self.hi))


@dataclasses.dataclass(frozen=True)
class _Shells:
    """Per sample, its distinct levels within its cap (shells), in sample then level order."""

    sample: np.ndarray  # (S,) sample of each shell
    level: np.ndarray  # (S,) its level
    start: np.ndarray  # (S,) first entry of the shell in the flat (sample, crossing) list
    size: np.ndarray  # (S,) crossings at that level
    first: np.ndarray  # (S,) bool, the sample's lowest level
    last: np.ndarray  # (S,) bool, the sample's highest level
    next_level: np.ndarray  # (S,) the next level of the sample (the level itself for the last)


def _shells(entry_sample: np.ndarray, entry_level: np.ndarray) -> _Shells:
    new = np.concatenate([[True], (entry_sample[1:] != entry_sample[:-1]) | (entry_level[1:] != entry_level[:-1])])
    start = np.flatnonzero(new)
    sample, level = entry_sample[start], entry_level[start]
    first = np.concatenate([[True], sample[1:] != sample[:-1]])
    last = np.concatenate([sample[1:] != sample[:-1], [True]])
    next_level = np.where(last, level, np.append(level[1:], 0))
    return _Shells(sample, level, start, np.diff(np.append(start, len(entry_sample))), first, last, next_level)


def _chain_rows(rows: _Rows, shells: _Shells, entry_col: np.ndarray, u_start: int, z_start: int, r_low: int) -> None:
    """Per shell, in order: the covering row (its crossings, its ``u``, minus the previous ``u``), then
    unless it is the sample's last, ``u <= previous u`` (not for the first) and ``z >= u`` where the
    next level exceeds ``r_low``."""
    more = ~shells.last
    u = u_start + np.cumsum(more) - 1  # this shell's u column (where more)
    prev = np.append(0, u[:-1])  # the previous shell's u (where not first)
    mono = more & ~shells.first
    link = more & (shells.next_level > r_low)
    per_shell = 1 + mono + link
    row0 = np.cumsum(per_shell) - per_shell  # the covering row of each shell
    length = np.zeros(int(per_shell.sum()), dtype=np.int64)
    length[row0] = shells.size + more + ~shells.first
    length[row0[mono] + 1] = 2
    length[row0[link] + 1 + mono[link]] = 2
    offsets = np.cumsum(length) - length
    cols = np.empty(int(length.sum()), dtype=np.int64)
    vals = np.empty_like(cols)
    shell_of = np.repeat(np.arange(len(shells.size)), shells.size)
    at = offsets[row0][shell_of] + np.arange(len(entry_col)) - shells.start[shell_of]
    cols[at], vals[at] = entry_col, 1
    end = offsets[row0] + shells.size
    cols[end[more]], vals[end[more]] = u[more], 1
    back = ~shells.first
    cols[end[back] + more[back]], vals[end[back] + more[back]] = prev[back], -1
    at = offsets[row0[mono] + 1]
    cols[at], vals[at], cols[at + 1], vals[at + 1] = u[mono], 1, prev[mono], -1
    at = offsets[row0[link] + 1 + mono[link]]
    cols[at], vals[at] = z_start + shells.next_level[link] - r_low - 1, 1
    cols[at + 1], vals[at + 1] = u[link], -1
    lo = np.full(len(length), -np.inf)
    hi = np.full(len(length), np.inf)
    lo[row0] = np.where(shells.first, 1.0, 0.0)
    hi[row0[mono] + 1] = 0.0
    lo[row0[link] + 1 + mono[link]] = 0.0
    rows.block(length, cols, vals, lo, hi)


def build_model(problem: SelectionProblem, n_drive: int, n_sense: int, q: np.ndarray, sample_cap: np.ndarray,
                power: int) -> LinearModel:
    """The model over the crossings within each sample's cap ``sample_cap`` (levels); ``q`` is the (K, C)
    quantised distance matrix."""
    n_tx, n_rx = len(problem.tx_usable), len(problem.rx_usable)
    order = np.argsort(q, axis=1, kind="stable")
    counts = (q <= sample_cap[:, None]).sum(axis=1)
    within = np.arange(q.shape[1])[None, :] < counts[:, None]
    entry_cross, entry_sample = order[within], np.repeat(np.arange(len(q)), counts)
    shells = _shells(entry_sample, q[entry_sample, entry_cross])
    act_crossings = np.unique(entry_cross)
    act_col = np.full(q.shape[1], -1, dtype=np.int64)
    act_col[act_crossings] = n_tx + n_rx + np.arange(len(act_crossings))
    more = ~shells.last
    u_sample, u_level, u_next = shells.sample[more], shells.level[more], shells.next_level[more]
    first_levels = shells.level[shells.first]
    r_low = int(first_levels.max())
    cap = int(sample_cap.max())
    u_start = n_tx + n_rx + len(act_crossings)
    z_start = u_start + len(u_sample)
    n_cols = z_start + max(cap - r_low, 0)

    rows = _Rows()
    rows.add(np.arange(n_tx), np.ones(n_tx), hi=n_drive)
    rows.add(n_tx + np.arange(n_rx), np.ones(n_rx), hi=n_sense)
    rows.tuples((problem.tx_conflicts[:, 0], problem.tx_conflicts[:, 1]), (1, 1), hi=1)
    rows.tuples((n_tx + problem.rx_conflicts[:, 0], n_tx + problem.rx_conflicts[:, 1]), (1, 1), hi=1)
    rows.tuples((problem.multi_pairs[:, 0], n_tx + problem.multi_pairs[:, 1]), (1, 1), hi=1)
    act_tx, act_rx = problem.cross_tx[act_crossings], n_tx + problem.cross_rx[act_crossings]
    act = act_col[act_crossings]
    rows.tuples((act, act_tx), (1, -1), hi=0)
    rows.tuples((act, act_rx), (1, -1), hi=0)
    rows.tuples((act, act_tx, act_rx), (1, -1, -1), lo=-1)
    _chain_rows(rows, shells, act_col[entry_cross], u_start, z_start, r_low)
    rows.tuples((np.arange(z_start, n_cols - 1), np.arange(z_start + 1, n_cols)), (1, -1), lo=0)
    offsets, columns, values, row_lo, row_hi = rows.csr()

    col_hi = np.ones(n_cols, dtype=np.int64)
    col_hi[np.flatnonzero(~problem.tx_usable)] = 0
    col_hi[n_tx + np.flatnonzero(~problem.rx_usable)] = 0
    return LinearModel(
        n_tx=n_tx, n_rx=n_rx, act_crossings=act_crossings,
        act_tx=problem.cross_tx[act_crossings], act_rx=problem.cross_rx[act_crossings],
        u_sample=u_sample.astype(np.int64), u_level=u_level.astype(np.int64), u_next=u_next.astype(np.int64),
        r_low=r_low, cap=cap, offsets=offsets, columns=columns, values=values, row_lo=row_lo, row_hi=row_hi,
        col_hi=col_hi, constant_power_sum=float(sum(int(level) ** power for level in first_levels.tolist())), power=power,
    )
