"""``layout.prescreen`` and ``layout.screen``: which branches of the layout sweep are worth phase 1's
radius stage, and which of those are worth finishing.

``layout.pick_best`` takes the smallest coverage radius first, and counts radii within
``radius_tolerance_mm`` of it as equal; so a branch whose coverage radius is proven to exceed a radius
another branch reaches by more than that tolerance cannot be chosen, unless finishing (trimming
crowded free ends, relaxing pads) makes the best branches worse. ``margin_mm`` allows for that, and
the ``keep_at_least`` branches with the smallest radii go on in any case. The rule is applied twice:

- ``layout.prescreen``, before any radius stage, on what ``layout.bound`` finds cheaply per branch
  (:class:`BranchBound`): the radius of phase 1's heuristic start (a selection, which the stage only
  improves on) and the layer relaxation's lower bound (:mod:`retrotouch.nodes.layout.bounds`);
  ``layout.coverage`` solves the radius stage of the branches it keeps only;
- ``layout.screen``, after it, on the stage-1 radii and lower bounds
  (:class:`retrotouch.nodes.layout.selection.RadiusStage`), with the prescreen's parameters (set once,
  on ``layout.prescreen``). Another kept branch whose stage-1 radius is beyond the threshold while its
  bound is not (a trust region's bound is weak) is first put to the proof in ``layout.finish``: the
  model with every sample's cap at the threshold, proven infeasible, screens it out too.

Both compare a branch also with the ``earlier`` branches, those of the Tx poles swept before its own
(the fallback's second pole against the first): the radii another pole reaches count as reached, and
the ``keep_at_least`` smallest are taken over both, so a second pole whose branches cannot beat the
first's solves none of them. A branch whose phase-1 start is an earlier branch's (:func:`start_digest`:
two Tx poles on one vertex, the top pole of most objects being the far pole) is not solved again. The
branch with the smallest stage-1 radius always passes the prescreen (its bound is below that radius,
which is below every start's). ``layout.pick_best`` checks afterwards that no screened branch could
have tied the chosen one, and says so when one could. Units: mm.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from collections.abc import Sequence

import numpy as np
from pydantic import Field

from ...graph.node import NodeParams, node
from .selection import RadiusStage


@dataclasses.dataclass(frozen=True)
class BranchBound:
    """One branch before phase 1's radius stage (``layout.bound``): the parameters it is solved with (the
    OptimizeParams fields, which ``layout.coverage`` and ``layout.finish`` use too), the report so far,
    phase 1's heuristic start (Tx ids, Rx ids, its report), its radius and a lower bound on any of the
    branch's layouts' (all None when phase 1 cannot be set up, ``message`` says why)."""

    params: dict
    family: str
    angle_deg: float
    base: dict
    start: tuple[np.ndarray, np.ndarray, dict] | None
    start_radius_mm: float | None
    lower_bound_mm: float | None
    message: str


@dataclasses.dataclass(frozen=True)
class BranchStart:
    """One branch after phase 1's radius stage (``layout.coverage``): the radius stage (None when phase 1
    cannot be set up or ``layout.prescreen`` dropped the branch, ``message`` says why), the report so
    far and the parameters it is solved with, which ``layout.finish`` uses too (it rebuilds the
    phase-1 problem from them)."""

    params: dict  # the OptimizeParams fields
    family: str
    angle_deg: float
    base: dict
    stage: RadiusStage | None
    message: str
    prescreened_bound_mm: float | None = None  # the lower bound of a branch ``layout.prescreen`` dropped (stage None)
    repeated: bool = False  # ``layout.prescreen`` dropped it: an earlier Tx pole's branch had its phase-1 start


@dataclasses.dataclass(frozen=True)
class Screen:
    """Which branches ``layout.finish`` completes (``layout.screen``): those whose radius stage's lower
    bound is at most ``threshold_mm`` (inf: all), and surely those whose stage-1 radius is at most
    ``sure_mm``; ``summary`` says how many and why."""

    threshold_mm: float
    sure_mm: float
    summary: str

    def keeps(self, branch: BranchStart) -> bool:
        stage = branch.stage
        return stage is None or stage.lower_bound_mm <= self.threshold_mm or stage.radius_mm <= self.sure_mm

    def needs_proof(self, branch: BranchStart) -> bool:
        """A kept branch not sure to be finished whose stage-1 radius is beyond the threshold."""
        return branch.stage is not None and branch.stage.radius_mm > max(self.threshold_mm, self.sure_mm)


def start_digest(bound: BranchBound) -> str:
    """A digest of what phase 1 starts a branch from: family, angle, parameters, candidate counts, the
    heuristic start (curves and report) and the two radii; equal for the branches of two Tx poles that
    are one vertex."""
    tx, rx, report = bound.start if bound.start is not None else ((), (), None)
    fields = [bound.family, bound.angle_deg, bound.params, bound.base, report, bound.start_radius_mm, bound.lower_bound_mm]
    digest = hashlib.sha256(json.dumps(fields, sort_keys=True, default=repr).encode())
    for ids in (tx, rx):
        digest.update(np.asarray(ids, dtype=np.int64).tobytes() + b"|")
    return digest.hexdigest()


@dataclasses.dataclass(frozen=True)
class PreScreen:
    """Which branches ``layout.coverage`` solves (``layout.prescreen``): those whose lower bound is at
    most ``threshold_mm`` (inf: all), and surely those whose start's radius is at most ``sure_mm``, but
    none whose :func:`start_digest` is in ``repeats`` (an earlier Tx pole's branch solved it);
    ``settings`` the ScreenParams fields, which ``layout.screen`` applies too; ``summary`` says how
    many and why."""

    threshold_mm: float
    sure_mm: float
    settings: dict
    summary: str
    repeats: tuple[str, ...] = ()

    def repeated(self, bound: BranchBound) -> bool:
        return bound.lower_bound_mm is not None and start_digest(bound) in self.repeats

    def keeps(self, bound: BranchBound) -> bool:
        return not self.repeated(bound) and (bound.lower_bound_mm is None or bound.lower_bound_mm <= self.threshold_mm
                                             or bound.start_radius_mm <= self.sure_mm)


class ScreenParams(NodeParams):
    radius_tolerance_mm: float = Field(
        1.0, ge=0, description="coverage radii within this of the best count as equal (as best.radius_tolerance_mm)"
    )
    margin_mm: float | None = Field(
        1.0, ge=0, description="solve and finish also the branches whose lower bound is within this beyond (mm); null: "
        "solve and finish every branch"
    )
    keep_at_least: int = Field(2, ge=1, description="solve at least this many branches, those with the smallest starts, "
                               "and finish as many, those with the smallest stage-1 radii")


def _cut(params: ScreenParams, radii: list[float]) -> tuple[float, float] | None:
    """(threshold, sure) radii of the rule in the module docstring over the branches' ``radii``; None
    when every branch goes on."""
    if params.margin_mm is None or len(radii) <= params.keep_at_least:
        return None
    radii = sorted(radii)
    return radii[0] + params.radius_tolerance_mm + params.margin_mm, radii[params.keep_at_least - 1]


def _summary(value: Screen | PreScreen) -> str:
    return value.summary


def _best_text(what: str, own: list[float], earlier: list[float]) -> str:
    """``"best <what> R mm"``, saying when an earlier Tx pole's branch reaches it."""
    best = min(own + earlier)
    return f"best {what} {best:.1f} mm" + (", an earlier Tx pole's" if best not in own else "")


@node("layout.prescreen", params=ScreenParams, inputs=("bounds", "earlier"), outputs=("prescreen",), note=_summary)
def prescreen(params: ScreenParams, bounds: list[BranchBound], earlier: list[BranchBound]) -> PreScreen:
    """The threshold on the branches' lower bounds up to which ``layout.coverage`` solves their radius
    stage; ``earlier``: the branches of the Tx poles swept before (module docstring)."""
    solved_before = {start_digest(b) for b in earlier if b.lower_bound_mm is not None}
    digests = [start_digest(b) if b.lower_bound_mm is not None else None for b in bounds]
    twins = sum(d in solved_before for d in digests)
    repeats = tuple(sorted({d for d in digests if d in solved_before}))
    bounded = [b for b, d in zip(bounds, digests) if d is not None and d not in solved_before]
    again = f"; {twins} the same as an earlier Tx pole's, not solved again" if twins else ""
    own = [b.start_radius_mm for b in bounded]
    others = [b.start_radius_mm for b in earlier if b.lower_bound_mm is not None]
    cut = _cut(params, own + others)
    if twins and not bounded:
        return PreScreen(math.inf, math.inf, params.model_dump(), f"none solved: {twins} branches the same as an earlier "
                         "Tx pole's", repeats)
    if cut is None:
        return PreScreen(math.inf, math.inf, params.model_dump(), f"all {len(bounds) - twins} branches solved{again}",
                         repeats)
    threshold, sure = cut
    kept = sum(PreScreen(threshold, sure, {}, "").keeps(b) for b in bounded)
    return PreScreen(threshold, sure, params.model_dump(), (
        f"{kept} of {len(bounded)} branches solved: the others' coverage radius is proven above {threshold:.1f} mm "
        f"({_best_text('heuristic start', own, others)} + tolerance + margin; the {params.keep_at_least} best starts "
        f"solved in any case){again}"), repeats)


def screen_branches(params: ScreenParams, branches: list[BranchStart], earlier: Sequence[BranchStart] = ()) -> Screen:
    """The threshold on the branches' stage-1 lower bounds up to which ``layout.finish`` completes them;
    ``earlier``: the branches of the Tx poles swept before (module docstring)."""
    staged = [b.stage for b in branches if b.stage is not None]
    own = [s.radius_mm for s in staged]
    others = [b.stage.radius_mm for b in earlier if b.stage is not None]
    cut = _cut(params, own + others)
    if cut is None:
        return Screen(math.inf, math.inf, f"all {len(staged)} solved branches kept")
    threshold, sure = cut
    kept = sum(Screen(threshold, sure, "").keeps(b) for b in branches if b.stage is not None)
    return Screen(threshold, sure, (
        f"{kept} of {len(staged)} solved branches kept: the others' coverage radius is proven above {threshold:.1f} mm "
        f"({_best_text('stage-1 radius', own, others)} + tolerance + margin; the {params.keep_at_least} best kept in "
        "any case)"))


@node("layout.screen", inputs=("branches", "prescreen", "earlier"), outputs=("screen",), note=_summary)
def screen(params: NodeParams, branches: list[BranchStart], prescreen: PreScreen, earlier: list[BranchStart]) -> Screen:
    """:func:`screen_branches` with the prescreen's parameters."""
    return screen_branches(ScreenParams.model_validate(prescreen.settings), branches, earlier)
