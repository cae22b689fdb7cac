"""Heuristic phase-1 selections: a greedy construction, an even pick over the candidate order, a
C1/C2 repair, a best-improvement swap local search on (radius, sum of distance**power) and moves that
bring in both curves of a crossing at once. They give the CP-SAT model its caps and hints. Units: mm."""
from __future__ import annotations

import numpy as np

from ...graph.errors import UserError
from .problem import PHASE1_POWER, SelectionProblem, evaluate_selection

PAIR_MOVE_TRIES = 24
"""Crossings near the farthest sample that :func:`pair_move` tries, nearest first."""

PAIR_MOVE_ROUNDS = 8
"""Most pair moves :func:`heuristic_selection` makes, each followed by :func:`local_search`."""


def _adjacency(pairs: np.ndarray, count_a: int, count_b: int) -> tuple[list[set], list[set]]:
    left = [set() for _ in range(count_a)]
    right = [set() for _ in range(count_b)]
    for a, b in pairs:
        left[a].add(int(b))
        right[b].add(int(a))
    return left, right


def greedy_selection(problem: SelectionProblem, n_drive: int, n_sense: int) -> tuple[np.ndarray, np.ndarray]:
    """Feasible C1-C3 selection built by adding the curve that most lowers sum_k min(dist_k, cap)."""
    D = problem.distance
    ntx, nrx = len(problem.tx_usable), len(problem.rx_usable)
    usable_c = problem.tx_usable[problem.cross_tx] & problem.rx_usable[problem.cross_rx]
    if not usable_c.any():
        raise UserError(
            "no Tx/Rx curve pair crosses exactly once on the sensing surface: "
            "sample more curves or narrow the Rx angle range"
        )
    cap = float(D.max()) + 1.0
    tx_tx, _ = _adjacency(problem.tx_conflicts, ntx, ntx)
    for a, b in problem.tx_conflicts:
        tx_tx[b].add(int(a))
    rx_rx, _ = _adjacency(problem.rx_conflicts, nrx, nrx)
    for a, b in problem.rx_conflicts:
        rx_rx[b].add(int(a))
    tx_multi, rx_multi = _adjacency(problem.multi_pairs, ntx, nrx)
    by_tx = [np.flatnonzero((problem.cross_tx == a) & usable_c) for a in range(ntx)]
    by_rx = [np.flatnonzero((problem.cross_rx == b) & usable_c) for b in range(nrx)]

    first = np.flatnonzero(usable_c)[np.argmin(np.minimum(D[:, usable_c], cap).sum(axis=0))]
    tx_sel, rx_sel = {int(problem.cross_tx[first])}, {int(problem.cross_rx[first])}
    nearest = np.minimum(D[:, first], cap)
    while True:
        best = (nearest.sum() - 1e-9, None, None, None)
        for layer, chosen, other, limit, usable, same, multi, by in (
            ("tx", tx_sel, rx_sel, n_drive, problem.tx_usable, tx_tx, tx_multi, by_tx),
            ("rx", rx_sel, tx_sel, n_sense, problem.rx_usable, rx_rx, rx_multi, by_rx),
        ):
            if len(chosen) >= limit:
                continue
            other_mask = np.zeros(nrx if layer == "tx" else ntx, dtype=bool)
            other_mask[list(other)] = True
            cross_other = problem.cross_rx if layer == "tx" else problem.cross_tx
            for cand in np.flatnonzero(usable):
                if cand in chosen or same[cand] & chosen or multi[cand] & other:
                    continue
                new = by[cand][other_mask[cross_other[by[cand]]]]
                if len(new) == 0:
                    continue
                score = np.minimum(nearest, D[:, new].min(axis=1)).sum()
                if score < best[0]:
                    best = (score, layer, int(cand), new)
        if best[1] is None:
            break
        (tx_sel if best[1] == "tx" else rx_sel).add(best[2])
        nearest = np.minimum(nearest, D[:, best[3]].min(axis=1))
    return np.array(sorted(tx_sel), dtype=np.int64), np.array(sorted(rx_sel), dtype=np.int64)


def _score(nearest: np.ndarray, resolution_mm: float, secondary: bool, power: int) -> tuple[np.ndarray, np.ndarray]:
    """Lexicographic (quantised radius, sum of distance**power) of nearest-distance columns (K, ...)."""
    radius = np.ceil(nearest.max(axis=0) / resolution_mm - 1e-9)
    if not secondary:
        return radius, np.zeros_like(radius)
    return radius, ((nearest / resolution_mm) ** power).sum(axis=0)


def _layer_nearest(Dpad: np.ndarray, pair: np.ndarray, layer: str, other: list) -> np.ndarray:
    """(K, curves of ``layer``): each sample's nearest distance over the crossings of each curve with the
    ``other`` layer's selected curves (inf without any); ``pair[a, b]`` is the column of ``Dpad`` of
    crossing (Tx a, Rx b), its last column inf."""
    if not other:
        return np.full((len(Dpad), pair.shape[0] if layer == "tx" else pair.shape[1]), np.inf)
    cols = pair[:, other] if layer == "tx" else pair[other, :].T
    return Dpad[:, cols].min(axis=2)


def _move_tables(problem: SelectionProblem):
    """(``pair`` (Ntx, Nrx) the column of each pair's crossing in ``Dpad``, ``Dpad`` (K, C + 1) the sample
    distances of the usable crossings (inf for the others and in the padding column C, the column of a pair
    that does not cross once), Tx x Tx and Rx x Rx conflict matrices, the C2 matrix (Ntx, Nrx)), bool."""
    ntx, nrx = len(problem.tx_usable), len(problem.rx_usable)
    C = len(problem.cross_tx)
    pair = np.full((ntx, nrx), C, dtype=np.int64)
    pair[problem.cross_tx, problem.cross_rx] = np.arange(C)
    usable_c = problem.tx_usable[problem.cross_tx] & problem.rx_usable[problem.cross_rx]
    Dpad = np.hstack([np.where(usable_c[None, :], problem.distance, np.inf), np.full((len(problem.distance), 1), np.inf)])
    tx_conf = np.zeros((ntx, ntx), dtype=bool)
    tx_conf[problem.tx_conflicts[:, 0], problem.tx_conflicts[:, 1]] = True
    tx_conf |= tx_conf.T
    rx_conf = np.zeros((nrx, nrx), dtype=bool)
    rx_conf[problem.rx_conflicts[:, 0], problem.rx_conflicts[:, 1]] = True
    rx_conf |= rx_conf.T
    multi = np.zeros((ntx, nrx), dtype=bool)
    multi[problem.multi_pairs[:, 0], problem.multi_pairs[:, 1]] = True
    return pair, Dpad, tx_conf, rx_conf, multi


def local_search(
    problem: SelectionProblem,
    tx: np.ndarray,
    rx: np.ndarray,
    n_drive: int,
    n_sense: int,
    secondary: bool,
    resolution_mm: float,
    max_moves: int = 200,
    power: int = PHASE1_POWER,
) -> tuple[np.ndarray, np.ndarray, int]:
    """Best-improvement swap/add local search from a feasible selection, on the phase-1 objective.

    A move replaces (or, below the channel limit, adds) one curve of either layer by a candidate that
    keeps C1/C2; moves are scored lexicographically by (radius at ``resolution_mm``, summed sample
    distance when ``secondary``). Returns (tx, rx, moves made).
    """
    pair, Dpad, tx_conf, rx_conf, multi = _move_tables(problem)
    T, R = list(tx), list(rx)
    start = _layer_nearest(Dpad, pair, "tx", R)[:, T].min(axis=1) if T else np.full(len(Dpad), np.inf)
    current = _score(start[:, None], resolution_mm, secondary, power)
    current = (current[0][0], current[1][0])
    moves = 0
    while moves < max_moves:
        best = (current, None)
        for layer in ("tx", "rx"):
            own, other = (T, R) if layer == "tx" else (R, T)
            limit = n_drive if layer == "tx" else n_sense
            usable = problem.tx_usable if layer == "tx" else problem.rx_usable
            conf = tx_conf if layer == "tx" else rx_conf
            reach = _layer_nearest(Dpad, pair, layer, other)  # a curve's crossings with the other layer's selection
            removals = list(own) + ([None] if len(own) < limit else [])
            for out in removals:
                kept = [c for c in own if c != out]
                ok = usable.copy()
                ok[own] = False
                if kept:
                    ok &= ~conf[:, kept].any(axis=1)
                if other:
                    ok &= ~(multi[:, other] if layer == "tx" else multi[other, :].T).any(axis=1)
                cands = np.flatnonzero(ok)
                if len(cands) == 0 or not other:
                    continue
                base = reach[:, kept].min(axis=1) if kept else np.full(len(Dpad), np.inf)
                new = np.minimum(base[:, None], reach[:, cands])
                radius, total = _score(new, resolution_mm, secondary, power)
                i = np.lexsort((total, radius))[0]
                if (radius[i], total[i]) < best[0]:
                    best = ((radius[i], total[i]), (layer, out, int(cands[i])))
        if best[1] is None:
            break
        layer, out, into = best[1]
        own = T if layer == "tx" else R
        if out is not None:
            own.remove(out)
        own.append(into)
        current = best[0]
        moves += 1
    return np.array(sorted(T), dtype=np.int64), np.array(sorted(R), dtype=np.int64), moves


def pair_move(
    problem: SelectionProblem,
    tx: np.ndarray,
    rx: np.ndarray,
    n_drive: int,
    n_sense: int,
    secondary: bool,
    resolution_mm: float,
    power: int = PHASE1_POWER,
    tries: int = PAIR_MOVE_TRIES,
) -> tuple[np.ndarray, np.ndarray] | None:
    """The best move that brings in both curves of a crossing near the sample farthest from the
    selection, or None if none improves (radius at ``resolution_mm``, then summed ``distance**power``
    when ``secondary``).

    A swap of :func:`local_search` changes one curve, so it never reaches a crossing neither of whose
    curves is selected: alone, either curve adds no crossing there (a limb that only its own Tx and Rx
    candidates reach). For each of the ``tries`` usable crossings nearest that sample, the move adds
    its Tx and Rx curves, drops the selected curves they conflict with (C1, C2) and then, above a
    channel limit, the curve of that layer whose loss costs least.
    """
    pair, Dpad, tx_conf, rx_conf, multi = _move_tables(problem)

    def nearest_of(T: list, R: list) -> np.ndarray:
        return Dpad[:, pair[np.ix_(T, R)].ravel()].min(axis=1) if T and R else np.full(len(Dpad), np.inf)

    def score(nearest: np.ndarray) -> tuple:
        radius, total = _score(nearest[:, None], resolution_mm, secondary, power)
        return radius[0], total[0]

    def cheapest_drop(own: list, keep: int, layer: str, other: list) -> list:
        reach = _layer_nearest(Dpad, pair, layer, other)[:, own]  # (K, len(own))
        losses = []
        for i, curve in enumerate(own):
            if curve == keep:
                continue
            radius, total = _score(np.delete(reach, i, axis=1).min(axis=1)[:, None], resolution_mm, secondary, power)
            losses.append(((radius[0], total[0]), curve))
        return [c for c in own if c != min(losses)[1]]

    T0, R0 = [int(a) for a in tx], [int(b) for b in rx]
    nearest = nearest_of(T0, R0)
    current = score(nearest)
    far = int(np.argmax(nearest))
    selected_t = np.isin(np.arange(pair.shape[0]), T0)
    selected_r = np.isin(np.arange(pair.shape[1]), R0)
    columns = np.flatnonzero(np.isfinite(Dpad[far, :-1]) & (Dpad[far, :-1] < nearest[far])
                             & ~(selected_t[problem.cross_tx] & selected_r[problem.cross_rx])
                             & ~multi[problem.cross_tx, problem.cross_rx])  # laid along each other: C2 too
    best = (current, None)
    for column in columns[np.argsort(Dpad[far, columns], kind="stable")[:tries]]:
        t, r = int(problem.cross_tx[column]), int(problem.cross_rx[column])
        T = [a for a in T0 if a == t or not (tx_conf[t, a] or multi[a, r])] + ([] if t in T0 else [t])
        R = [b for b in R0 if b == r or not (rx_conf[r, b] or multi[t, b])] + ([] if r in R0 else [r])
        if len(T) > n_drive:
            T = cheapest_drop(T, t, "tx", R)
        if len(R) > n_sense:
            R = cheapest_drop(R, r, "rx", T)
        key = score(nearest_of(T, R))
        if key < best[0]:
            best = (key, (T, R))
    if best[1] is None:
        return None
    T, R = best[1]
    return np.array(sorted(T), dtype=np.int64), np.array(sorted(R), dtype=np.int64)


def _repair(problem: SelectionProblem, tx: np.ndarray, rx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Drop curves until C1/C2 hold: repeatedly remove the curve in the most violated constraints."""
    T, R = set(int(a) for a in tx), set(int(b) for b in rx)
    while True:
        count: dict[tuple[str, int], int] = {}
        for layer, pairs, left, right in (("tx", problem.tx_conflicts, T, T), ("rx", problem.rx_conflicts, R, R)):
            for a, b in pairs:
                if a in left and b in right:
                    count[(layer, int(a))] = count.get((layer, int(a)), 0) + 1
                    count[(layer, int(b))] = count.get((layer, int(b)), 0) + 1
        for a, b in problem.multi_pairs:
            if a in T and b in R:
                count[("tx", int(a))] = count.get(("tx", int(a)), 0) + 1
                count[("rx", int(b))] = count.get(("rx", int(b)), 0) + 1
        if not count:
            return np.array(sorted(T), dtype=np.int64), np.array(sorted(R), dtype=np.int64)
        layer, curve = max(count, key=lambda key: (count[key], key))
        (T if layer == "tx" else R).discard(curve)


def heuristic_selection(
    problem: SelectionProblem, n_drive: int, n_sense: int, secondary: bool, resolution_mm: float,
    power: int = PHASE1_POWER,
) -> tuple[np.ndarray, np.ndarray, dict]:
    """The better of two starts, improved by :func:`local_search`: the greedy construction and an evenly
    spread pick over the candidate order (curves are traced in angular order, so evenly spaced indices
    spread over the surface; Tx lanes, each listed after its field line, and the limbs' curves, listed
    after the family's, are left out of it), repaired for C1/C2; then, in turns, a move that brings in
    both curves of a crossing (:func:`pair_move`) and the local search again. Without the secondary
    objective only the even pick is used, since the greedy construction optimises the summed distance."""
    usable_t, usable_r = np.flatnonzero(problem.tx_usable), np.flatnonzero(problem.rx_usable)
    if problem.tx_lanes is not None:
        usable_t = usable_t[~problem.tx_lanes[usable_t]]
    if problem.limb_curves is not None:
        usable_t, usable_r = usable_t[~problem.limb_curves[0][usable_t]], usable_r[~problem.limb_curves[1][usable_r]]
    starts = {"greedy": greedy_selection(problem, n_drive, n_sense)}
    if len(usable_t) and len(usable_r):
        even_t = usable_t[np.unique(np.floor(np.arange(min(n_drive, len(usable_t))) * len(usable_t) / min(n_drive, len(usable_t))).astype(int))]
        even_r = usable_r[np.unique(np.floor(np.arange(min(n_sense, len(usable_r))) * len(usable_r) / min(n_sense, len(usable_r))).astype(int))]
        starts["even"] = _repair(problem, even_t, even_r)
    if not secondary and "even" in starts:
        del starts["greedy"]  # the greedy construction minimises the summed distance: not in the ablation
    report = {}
    scored = []
    for name, (tx, rx) in starts.items():
        _, nearest = evaluate_selection(problem, tx, rx)
        radius, total = _score(nearest[:, None], resolution_mm, secondary, power)
        report[name] = {"radius_mm": float(nearest.max()), "mean_mm": float(nearest.mean())}
        scored.append(((radius[0], total[0]), name))
    name = min(scored)[1]
    tx, rx, moves = local_search(problem, *starts[name], n_drive, n_sense, secondary, resolution_mm, power=power)
    pair_moves = 0
    while pair_moves < PAIR_MOVE_ROUNDS:
        moved = pair_move(problem, tx, rx, n_drive, n_sense, secondary, resolution_mm, power)
        if moved is None:
            break
        tx, rx, more = local_search(problem, *moved, n_drive, n_sense, secondary, resolution_mm, power=power)
        pair_moves, moves = pair_moves + 1, moves + more
    _, nearest = evaluate_selection(problem, tx, rx)
    report["local_search"] = {"start": name, "moves": moves, "pair_moves": pair_moves, "radius_mm": float(nearest.max()),
                              "mean_mm": float(nearest.mean())}
    return tx, rx, report
