"""Nesting of trace outlines onto cutter mats (paper section 7.2).

Sheet frame: mm, origin at the sheet's bottom-left corner, y up (the cut-sheet writer flips y for
SVG). A part is placed by rotating its outline (in its unfolded frame) by ``rotation_deg`` about the
origin, counter-clockwise, then translating by ``translation``; no mirroring, so every part stays
"seen from outside".

Parts go into the usable rectangle (sheet minus ``margin_mm`` on each side) at least ``spacing_mm``
apart. ``mat: auto`` takes the smallest mat that holds every part at some rotation (12 x 12 in,
then 12 x 24 in). The primary nester is :mod:`.raster_nest` (deterministic bottom-left fill on a
``pixel_mm`` grid, along a strip that runs along the sheet's longer side): it runs with 72, 96, ...
up to ``max_rotations`` trial angles per part and stops as soon as a pass no longer saves a sheet
or shortens the last sheet's strip by ``min_gain``, so its work grows with the parts and with how
much more angles still help (a pass stops as soon as its placement so far is worse than the best
pass's: it would end worse and stop the passes). A placement on one sheet ends the passes: no pass
can save a sheet there, and the last strip's length changes from pass to pass without a trend. The
fallback (``nester: shelf``, or when the raster result fails the check) is shelf packing of minimum
rotated bounding boxes, first fit by decreasing height. Every result is verified with shapely: parts
inside their sheet, no overlaps, every gap >= ``spacing_mm``.
"""
from __future__ import annotations

import dataclasses
from typing import Literal

import numpy as np
import shapely
from pydantic import Field, model_validator
from shapely import affinity
from shapely.geometry import Polygon

from ...graph.errors import UserError
from ...graph.node import NodeParams, node
from .mats import MARGIN_MM, MATS_MM, fit_angles, usable_sides
from .outline import TraceOutlines
from .raster_nest import Part, raster_nest

ROTATION_STEP = 24
"""Trial angles added per raster pass (the first pass has three steps' worth)."""


class Params(NodeParams):
    mat: Literal["auto", "12x12", "12x24", "custom"] = Field(
        "auto", description="Cricut mat; auto = the smallest that holds every part; or a custom sheet size")
    sheet_width_mm: float | None = Field(None, gt=0, description="custom sheet width (mm), with mat: custom")
    sheet_height_mm: float | None = Field(None, gt=0, description="custom sheet height (mm), with mat: custom")
    margin_mm: float = Field(MARGIN_MM, ge=0, description="empty border inside the cut area (mm)")
    spacing_mm: float = Field(1.0, ge=0, description="smallest gap between two parts (mm)")
    nester: Literal["raster", "shelf"] = Field("raster", description="nesting engine; shelf = simple fallback")
    pixel_mm: float = Field(0.5, gt=0, le=5, description="raster nester cell size (mm)")
    max_rotations: int = Field(120, ge=3 * ROTATION_STEP, description="most trial angles per part (raster nester)")
    finalists: int = Field(4, ge=1, description="angles per part placed exactly after a coarse ranking")
    min_gain: float = Field(0.01, ge=0, description="relative strip shortening a raster pass must bring to go on")

    @model_validator(mode="after")
    def _custom_size(self):
        custom = self.sheet_width_mm is not None or self.sheet_height_mm is not None
        if (self.mat == "custom") != custom or (custom and None in (self.sheet_width_mm, self.sheet_height_mm)):
            raise ValueError("give both sheet_width_mm and sheet_height_mm exactly when mat is custom")
        return self


@dataclasses.dataclass(frozen=True)
class NestedSheets:
    """Placement of every part of a :class:`TraceOutlines` on sheets (module conventions)."""

    mat: str  # "12x12", "12x24" or "custom"
    mat_reason: str  # why this mat (one sentence)
    sheet_width_mm: float
    sheet_height_mm: float
    sheet_count: int
    part_sheet: np.ndarray  # (N,) int64
    rotation_deg: np.ndarray  # (N,) float64, CCW about the origin of the part's frame
    translation: np.ndarray  # (N, 2) float64, mm, applied after the rotation
    nester: str  # the nester that produced this placement ("raster" or "shelf")
    fallback_reason: str  # why the fallback ran ("" when the raster nester succeeded or shelf was asked for)
    rotations: int  # trial angles per part of the kept raster pass (0 for shelf)
    spacing_mm: float
    min_gap_mm: float  # smallest distance between two parts on one sheet (inf with < 2 parts per sheet)
    overlaps: int  # part pairs on one sheet closer than spacing_mm (0 for an accepted placement)
    parts_area_mm2: float
    material_use: float  # parts area / (sheet_count * sheet area)
    used_length_mm: float  # extent of the last sheet's parts along the sheet's longer side


def place(polygon: Polygon, rotation_deg: float, translation) -> Polygon:
    """The placed part: rotate CCW about the origin, then translate."""
    return affinity.translate(affinity.rotate(polygon, rotation_deg, origin=(0, 0)), *translation)


def placed_polygons(outlines: TraceOutlines, nested: NestedSheets) -> list[Polygon]:
    return [
        place(outlines.polygon(i), float(nested.rotation_deg[i]), nested.translation[i]) for i in range(outlines.count)
    ]


def choose_mat(outlines: TraceOutlines, params: Params) -> tuple[str, float, float, str]:
    """(mat, width, height, reason): the asked mat, or with ``auto`` the smallest that holds every
    part; UserError naming the first part that fits no candidate sheet at any rotation."""
    if params.mat == "custom":
        candidates = {"custom": (float(params.sheet_width_mm), float(params.sheet_height_mm))}
    else:
        candidates = MATS_MM if params.mat == "auto" else {params.mat: MATS_MM[params.mat]}
    polygons = [outlines.polygon(i) for i in range(outlines.count)]
    misfits = []  # (mat, first part that fits it at no rotation)
    for name, (width, height) in candidates.items():
        long_side, short_side = usable_sides(width, height, params.margin_mm)
        misfit = next((i for i, p in enumerate(polygons) if len(fit_angles(p, long_side, short_side)) == 0), None)
        if misfit is None:
            if params.mat != "auto":
                return name, width, height, f"mat: {name} was asked for"
            if not misfits:
                return name, width, height, f"the smallest mat ({name}) holds every part"
            return name, width, height, f"{outlines.names[misfits[0][1]]} does not fit the {misfits[0][0]} mat"
        misfits.append((name, misfit))
    rect = np.asarray(polygons[misfit].minimum_rotated_rectangle.exterior.coords)
    sides = sorted(np.linalg.norm(np.diff(rect[:3], axis=0), axis=1))
    hint = "use mat: auto or 12x24" if params.mat == "12x12" else "use a larger custom sheet"
    raise UserError(
        f"{outlines.names[misfit]} is {sides[1]:.0f} x {sides[0]:.0f} mm flat and does not fit the {width:g} x "
        f"{height:g} mm sheet (margin {params.margin_mm:g} mm) at any rotation; {hint}, or let fab.outline split it "
        "(fit_mat)"
    )


def _to_sheet(rotation: float, translation, width: float, height: float, margin: float):
    """Strip frame (x along the longer sheet side, y along the shorter, origin at the usable corner)
    -> sheet frame: identity plus margin for landscape sheets, a quarter turn for portrait ones."""
    if width >= height:
        return rotation, (translation[0] + margin, translation[1] + margin)
    short = width - 2 * margin
    return rotation + 90.0, (margin + short - translation[1], margin + translation[0])


def _strip_score(strip, polygons: list[Polygon]) -> tuple[int, float]:
    """(sheets, used length of the last sheet along the strip) of a strip-frame placement."""
    sheets = [s for s, _, _ in strip]
    last = [place(p, r, t).bounds for p, (s, r, t) in zip(polygons, strip) if s == max(sheets)]
    return max(sheets) + 1, max(b[2] for b in last) - min(b[0] for b in last)


def _raster(polygons: list[Polygon], params: Params, long_side: float, short_side: float):
    """Raster passes with more angles until a pass no longer helps; (strip placement, angles)."""
    order = sorted(range(len(polygons)), key=lambda i: (-polygons[i].minimum_rotated_rectangle.area, i))
    parts = [Part(p, params.spacing_mm, params.pixel_mm, long_side, short_side) for p in polygons]
    best, best_score, best_rotations = None, None, 0
    for rotations in range(3 * ROTATION_STEP, params.max_rotations + 1, ROTATION_STEP):
        strip = raster_nest(parts, long_side, short_side, params.spacing_mm, params.pixel_mm, rotations,
                            params.finalists, order, best_score)
        if strip is None:  # already worse than the best: it would end worse and stop the passes
            break
        score = _strip_score(strip, polygons)
        if best is not None and (score[0] > best_score[0] or (
                score[0] == best_score[0] and score[1] > (1 - params.min_gain) * best_score[1])):
            if score < best_score:
                best, best_score, best_rotations = strip, score, rotations
            break
        best, best_score, best_rotations = strip, score, rotations
        if best_score[0] == 1:
            break
    return best, best_rotations


def _shelf(polygons: list[Polygon], params: Params, long_side: float, short_side: float):
    """First-fit decreasing-height shelves of minimum rotated bounding boxes, sheet after sheet."""
    gap = params.spacing_mm
    boxes = []
    for p in polygons:
        rect = np.asarray(p.minimum_rotated_rectangle.exterior.coords)
        edge = rect[1] - rect[0] if np.linalg.norm(rect[1] - rect[0]) >= np.linalg.norm(rect[2] - rect[1]) else rect[2] - rect[1]
        rotation = -np.degrees(np.arctan2(edge[1], edge[0]))
        x0, y0, x1, y1 = affinity.rotate(p, rotation, origin=(0, 0)).bounds
        if x1 - x0 > long_side or y1 - y0 > short_side:
            rotation = float(fit_angles(p, long_side, short_side)[0])
            x0, y0, x1, y1 = affinity.rotate(p, rotation, origin=(0, 0)).bounds
        boxes.append((rotation, x0, y0, x1 - x0, y1 - y0))
    order = sorted(range(len(polygons)), key=lambda i: -boxes[i][4])
    shelves: list[list[float]] = []  # [sheet, y, height, used length]
    sheet_top: list[float] = []  # next free y per sheet
    result = {}
    for i in order:
        rotation, x0, y0, w, h = boxes[i]
        shelf = next((s for s in shelves if s[2] >= h and s[3] + w <= long_side), None)
        if shelf is None:
            sheet = next((k for k, top in enumerate(sheet_top) if top + h <= short_side), None)
            if sheet is None:
                sheet_top.append(0.0)
                sheet = len(sheet_top) - 1
            shelf = [sheet, sheet_top[sheet], h, 0.0]
            sheet_top[sheet] += h + gap
            shelves.append(shelf)
        result[i] = (shelf[0], rotation, (shelf[3] - x0, shelf[1] - y0))
        shelf[3] += w + gap
    return [result[i] for i in range(len(polygons))], 0


def verify(polygons: list[Polygon], sheets: np.ndarray, width: float, height: float, spacing: float,
           margin: float) -> tuple[float, int, int]:
    """(smallest gap between parts on one sheet, part pairs closer than ``spacing``, parts outside
    the usable sheet area)."""
    usable = shapely.box(margin, margin, width - margin, height - margin).buffer(1e-6)
    outside = sum(not usable.contains(p) for p in polygons)
    min_gap, close = np.inf, 0
    for sheet in np.unique(sheets):
        group = [polygons[i] for i in np.nonzero(sheets == sheet)[0]]
        if len(group) < 2:
            continue
        tree = shapely.STRtree(group)
        for reach in (spacing + 0.5, spacing + 10.0):  # the pairs within reach hold the smallest gap, if any
            near = tree.query(group, predicate="dwithin", distance=reach)
            near = near[:, near[0] < near[1]]
            if near.shape[1]:
                gap = shapely.distance(np.asarray(group)[near[0]], np.asarray(group)[near[1]]).min()
                break
        else:  # every gap exceeds spacing + 10 mm: find the nearest pair
            gap = tree.query_nearest(group, exclusive=True, return_distance=True, all_matches=False)[1].min()
        min_gap = min(min_gap, float(gap))
        pairs = tree.query(group, predicate="dwithin", distance=spacing - 1e-6) if spacing > 1e-6 else tree.query(
            group, predicate="intersects")
        close += int(np.sum(pairs[0] < pairs[1]))
    return float(min_gap), int(close), int(outside)


@node("fab.nest", params=Params, inputs=("outlines",), outputs=("nesting",))
def nest(params: Params, outlines: TraceOutlines) -> NestedSheets:
    """Place all trace outlines on as few cutter sheets as the nester manages, free rotation, at least
    ``spacing_mm`` apart, reproducibly; verified with shapely."""
    if outlines.count == 0:
        raise UserError("there are no traces to nest; check that the layout selected Tx and Rx curves")
    mat, width, height, mat_reason = choose_mat(outlines, params)
    long_side, short_side = usable_sides(width, height, params.margin_mm)
    polygons = [outlines.polygon(i) for i in range(outlines.count)]
    fallback_reason = ""
    for nester in (["raster", "shelf"] if params.nester == "raster" else ["shelf"]):
        try:
            strip, rotations = (_raster if nester == "raster" else _shelf)(polygons, params, long_side, short_side)
        except ValueError as error:  # the raster nester found no angle for a part: the shelves will
            if nester == "shelf":
                raise
            fallback_reason = f"raster nester failed: {error}"
            continue
        sheets = np.array([s for s, _, _ in strip], dtype=np.int64)
        placement = [_to_sheet(r, t, width, height, params.margin_mm) for _, r, t in strip]
        rotation = np.array([r for r, _ in placement], dtype=np.float64)
        translation = np.array([t for _, t in placement], dtype=np.float64).reshape(-1, 2)
        placed = [place(p, r, t) for p, r, t in zip(polygons, rotation, translation)]
        min_gap, close, outside = verify(placed, sheets, width, height, params.spacing_mm, params.margin_mm)
        if close == 0 and outside == 0:
            break
        if nester == "shelf":
            raise RuntimeError(f"shelf packing produced {close} close pairs and {outside} parts off the sheet")
        fallback_reason = f"raster result rejected: {close} part pairs closer than spacing, {outside} off the sheet"
    count = int(sheets.max()) + 1
    area = float(sum(p.area for p in polygons))
    last = [placed[i] for i in np.nonzero(sheets == count - 1)[0]]
    axis = 0 if width >= height else 1
    used_length = max(p.bounds[axis + 2] for p in last) - min(p.bounds[axis] for p in last)
    return NestedSheets(
        mat=mat,
        mat_reason=mat_reason,
        sheet_width_mm=width,
        sheet_height_mm=height,
        sheet_count=count,
        part_sheet=sheets,
        rotation_deg=rotation,
        translation=translation,
        nester=nester,
        fallback_reason=fallback_reason,
        rotations=rotations,
        spacing_mm=params.spacing_mm,
        min_gap_mm=min_gap,
        overlaps=close,
        parts_area_mm2=area,
        material_use=area / (count * width * height),
        used_length_mm=float(used_length),
    )
