"""``layout.screen``: which branches of the layout sweep are worth finishing.

After phase 1's radius stage (``layout.coverage``) every branch has a radius and a lower bound no
layout of it can beat (:class:`retrotouch.nodes.layout.selection.RadiusStage`). ``layout.pick_best``
takes the smallest coverage radius first, and counts radii within ``radius_tolerance_mm`` of it as
equal; so a branch whose lower bound exceeds the smallest stage-1 radius by more than that tolerance
cannot be chosen, unless finishing (trimming crowded free ends, relaxing pads) makes the best branches
worse. ``margin_mm`` allows for that, and the ``keep_at_least`` branches with the smallest stage-1
radii are finished in any case. Another kept branch whose stage-1 radius is beyond the threshold while
its bound is not (a trust region's bound is weak) is first put to the proof in ``layout.finish``: the
model with every sample's cap at the threshold, proven infeasible, screens it out too.
``layout.pick_best`` checks afterwards that no screened branch could have tied the chosen one, and
says so when one could. Units: mm.
"""
from __future__ import annotations

import dataclasses
import math

from pydantic import Field

from ...graph.node import NodeParams, node
from .selection import RadiusStage


@dataclasses.dataclass(frozen=True)
class BranchStart:
    """One branch after phase 1's radius stage (``layout.coverage``): the radius stage (None when phase 1
    cannot be set up, ``message`` says why), the report so far and the parameters it is solved with,
    which ``layout.finish`` uses too (it rebuilds the phase-1 problem from them)."""

    params: dict  # the OptimizeParams fields
    family: str
    angle_deg: float
    base: dict
    stage: RadiusStage | None
    message: str


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


class ScreenParams(NodeParams):
    radius_tolerance_mm: float = Field(
        1.0, ge=0, description="coverage radii within this of the best count as equal (as best.radius_tolerance_mm)"
    )
    margin_mm: float | None = Field(
        1.0, ge=0, description="finish also the branches whose lower bound is within this beyond (mm); null: finish every branch"
    )
    keep_at_least: int = Field(2, ge=1, description="finish at least this many branches, those with the smallest stage-1 radii")


def _note(screen: Screen) -> str:
    return screen.summary


@node("layout.screen", params=ScreenParams, inputs=("branches",), outputs=("screen",), note=_note)
def screen(params: ScreenParams, branches: list[BranchStart]) -> Screen:
    """The threshold on the branches' stage-1 lower bounds up to which ``layout.finish`` completes them."""
    staged = [b.stage for b in branches if b.stage is not None]
    if params.margin_mm is None or len(staged) <= params.keep_at_least:
        return Screen(math.inf, math.inf, f"all {len(branches)} branches kept")
    radii = sorted(s.radius_mm for s in staged)
    threshold = radii[0] + params.radius_tolerance_mm + params.margin_mm
    cut = Screen(threshold, radii[params.keep_at_least - 1], "")
    kept = sum(cut.keeps(b) for b in branches)
    return dataclasses.replace(cut, summary=(
        f"{kept} of {len(branches)} branches kept: the others' coverage radius is proven above {threshold:.1f} mm "
        f"(best stage-1 radius {radii[0]:.1f} mm + tolerance + margin; the {params.keep_at_least} best kept in any case)"))
