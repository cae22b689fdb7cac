"""Nesting of trace outlines onto cutter mats (paper section 7.2).

Sheet frame: mm, origin at the sheet's bottom-left corner, y up (the cut-sheet writer flips y for
SVG). A part is placed by rotating its outline (in its unfolded frame) by ``rotation_deg`` about the
origin, counter-clockwise, then translating by ``translation``; no mirroring, so every part stays
"seen from outside".

Parts go into the usable rectangle (sheet minus ``margin_mm`` on each side) at least ``spacing_mm``
apart, with free rotation. The primary nester is spyrrow (sparrow strip packing, no-fit free
rotation): the strip runs along the sheet's longer side with the shorter side as its height; when
the packed strip is a little longer than a sheet (up to ``RETRY_OVERFLOW`` sheet lengths), spyrrow
gets one more run with ``retry_seconds``; then the parts lying wholly inside the first sheet length
are kept there and the rest are packed again onto the next sheet (a part that fits the sheet only at
an angle spyrrow did not use gets a sheet of its own at a fitting rotation). The fallback (used when
spyrrow is disabled, raises, or its result fails the overlap/gap/fit check) is shelf packing of
minimum rotated bounding boxes, first fit by decreasing height. Every result is verified with
shapely: parts inside their sheet, no overlaps, every gap >= ``spacing_mm``.
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
from .outline import TraceOutlines

RETRY_OVERFLOW = 1.25
"""spyrrow retries only when the packed strip is at most this many sheet lengths long (a better
packing may then save the extra sheet)."""

MATS_MM = {"12x12": (292.0, 292.0), "12x24": (290.0, 600.0)}
"""Cut areas of the Cricut mats (width, height) in mm, measured in Design Space."""


class Params(NodeParams):
    mat: Literal["12x12", "12x24", "custom"] = Field("12x12", description="Cricut mat, or custom sheet size")
    sheet_width_mm: float | None = Field(None, gt=0, description="custom sheet width (mm), with mat: custom")
    sheet_height_mm: float | None = Field(None, gt=0, description="custom sheet height (mm), with mat: custom")
    margin_mm: float = Field(1.0, ge=0, description="empty border inside the cut area (mm)")
    spacing_mm: float = Field(1.0, ge=0, description="smallest gap between two parts (mm)")
    nester: Literal["spyrrow", "shelf"] = Field("spyrrow", description="nesting engine; shelf = simple fallback")
    seconds: int = Field(10, ge=1, description="spyrrow time budget per sheet (s); wall time is about twice that")
    retry_seconds: int = Field(
        30, ge=0, description="when the parts overflow a sheet by up to 25 %: one more spyrrow run with this "
        "budget (s) before spilling onto another sheet; 0 = no retry"
    )
    workers: int = Field(1, ge=1, description="spyrrow threads")
    seed: int = Field(0, description="spyrrow random seed")
    shape_tolerance_mm: float = Field(0.05, gt=0, description="outline simplification for the nester (mm), compensated")

    @model_validator(mode="after")
    def _custom_size(self):
        custom = self.sheet_width_mm is not None or self.sheet_height_mm is not None
        if (self.mat == "custom") != custom or (custom and None in (self.sheet_width_mm, self.sheet_height_mm)):
            raise ValueError("give both sheet_width_mm and sheet_height_mm exactly when mat is custom")
        return self

    def sheet_size(self) -> tuple[float, float]:
        if self.mat == "custom":
            return float(self.sheet_width_mm), float(self.sheet_height_mm)
        return MATS_MM[self.mat]


@dataclasses.dataclass(frozen=True)
class NestedSheets:
    """Placement of every part of a :class:`TraceOutlines` on sheets (module conventions)."""

    sheet_width_mm: float
    sheet_height_mm: float
    sheet_count: int
    part_sheet: np.ndarray  # (N,) int64
    rotation_deg: np.ndarray  # (N,) float64, CCW about the origin of the part's frame
    translation: np.ndarray  # (N, 2) float64, mm, applied after the rotation
    nester: str  # the nester that produced this placement ("spyrrow" or "shelf")
    fallback_reason: str  # why the fallback ran ("" when spyrrow succeeded or shelf was asked for)
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


def _fit_angles(polygon: Polygon, long_side: float, short_side: float) -> np.ndarray:
    """Rotations (deg, 0.5 deg grid) at which the polygon's bounding box fits long x short."""
    hull = np.asarray(polygon.convex_hull.exterior.coords)
    angles = np.radians(np.arange(0.0, 180.0, 0.5))
    c, s = np.cos(angles), np.sin(angles)
    x = np.outer(c, hull[:, 0]) - np.outer(s, hull[:, 1])
    y = np.outer(s, hull[:, 0]) + np.outer(c, hull[:, 1])
    fits = (np.ptp(x, axis=1) <= long_side) & (np.ptp(y, axis=1) <= short_side)
    return np.degrees(angles[fits])


def check_fits(outlines: TraceOutlines, params: Params) -> None:
    """UserError naming the first part that fits the usable sheet area at no rotation."""
    width, height = params.sheet_size()
    long_side = max(width, height) - 2 * params.margin_mm
    short_side = min(width, height) - 2 * params.margin_mm
    for i in range(outlines.count):
        polygon = outlines.polygon(i)
        if len(_fit_angles(polygon, long_side, short_side)) == 0:
            rect = np.asarray(polygon.minimum_rotated_rectangle.exterior.coords)
            sides = sorted(np.linalg.norm(np.diff(rect[:3], axis=0), axis=1))
            hint = "use mat: 12x24 (290 x 600 mm)" if params.mat == "12x12" else "use a larger custom sheet"
            raise UserError(
                f"{outlines.names[i]} is {sides[1]:.0f} x {sides[0]:.0f} mm flat and fits the "
                f"{width:g} x {height:g} mm sheet (margin {params.margin_mm:g} mm) at no rotation; "
                f"{hint}, or scale the object down"
            )


def _to_sheet(rotation: float, translation, width: float, height: float, margin: float):
    """Strip frame (x along the longer sheet side, y along the shorter, origin at the usable corner)
    -> sheet frame: identity plus margin for landscape sheets, a quarter turn for portrait ones."""
    if width >= height:
        return rotation, (translation[0] + margin, translation[1] + margin)
    short = width - 2 * margin
    return rotation + 90.0, (margin + short - translation[1], margin + translation[0])


def _nester_shape(polygon: Polygon, tolerance: float) -> list[tuple[float, float]]:
    """Simplified exterior that still contains the outline (buffered by the simplification tolerance)."""
    shape = polygon.simplify(tolerance, preserve_topology=True).buffer(tolerance, quad_segs=2, join_style="mitre")
    shape = Polygon(shape.exterior).simplify(tolerance / 4, preserve_topology=True)
    return [tuple(p) for p in np.asarray(shape.exterior.coords)[:-1]]


def _spyrrow(polygons: list[Polygon], params: Params, long_side: float, short_side: float):
    """Strip-pack with spyrrow sheet by sheet; yields (sheet, rotation, strip translation) per part."""
    import spyrrow

    shapes = [_nester_shape(p, params.shape_tolerance_mm) for p in polygons]
    remaining = list(range(len(polygons)))
    result = {}
    sheet = 0
    def solve(indices: list[int], seconds: int):
        items = [spyrrow.Item(str(i), shapes[i], demand=1, allowed_orientations=None) for i in indices]
        instance = spyrrow.StripPackingInstance("retrotouch", strip_height=short_side, items=items)
        config = spyrrow.StripPackingConfig(
            early_termination=True,
            min_items_separation=params.spacing_mm if params.spacing_mm > 0 else None,
            total_computation_time=seconds,
            num_workers=params.workers,
            seed=params.seed,
        )
        return instance.solve(config)

    while remaining:
        solution = solve(remaining, params.seconds)
        if long_side < solution.width <= RETRY_OVERFLOW * long_side and params.retry_seconds > 0:
            retry = solve(remaining, params.retry_seconds)
            solution = retry if retry.width < solution.width else solution
        placed = {}
        for item in solution.placed_items:
            i = int(item.id)
            poly = place(Polygon(shapes[i]), item.rotation, item.translation)
            placed[i] = (item.rotation, item.translation, poly.bounds)
        if set(placed) != set(remaining):
            raise RuntimeError("spyrrow left parts unplaced")
        x0 = min(b[0] for _, _, b in placed.values())
        y0 = min(b[1] for _, _, b in placed.values())
        keep = [i for i in remaining if placed[i][2][2] - x0 <= long_side]
        if keep:
            for i in keep:
                rotation, (tx, ty), _ = placed[i]
                result[i] = (sheet, rotation, (tx - x0, ty - y0))
        else:  # only fits at an angle spyrrow did not try: alone on its sheet at a fitting rotation
            i = remaining[0]
            keep = [i]
            rotation = float(_fit_angles(polygons[i], long_side, short_side)[0])
            bx0, by0, _, _ = affinity.rotate(polygons[i], rotation, origin=(0, 0)).bounds
            result[i] = (sheet, rotation, (-bx0, -by0))
        remaining = [i for i in remaining if i not in keep]
        sheet += 1
    return [result[i] for i in range(len(polygons))]


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
            rotation = float(_fit_angles(p, long_side, short_side)[0])
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
    return [result[i] for i in range(len(polygons))]


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
        _, distance = tree.query_nearest(group, exclusive=True, return_distance=True, all_matches=False)
        min_gap = min(min_gap, float(distance.min()))
        pairs = tree.query(group, predicate="dwithin", distance=spacing - 1e-6) if spacing > 1e-6 else tree.query(
            group, predicate="intersects")
        close += int(np.sum(pairs[0] < pairs[1]))
    return float(min_gap), int(close), int(outside)


@node("fab.nest", params=Params, inputs=("outlines",), outputs=("nesting",))
def nest(params: Params, outlines: TraceOutlines) -> NestedSheets:
    """Place all trace outlines on as few cutter sheets as the nester manages, free rotation, at least
    ``spacing_mm`` apart; verified with shapely."""
    if outlines.count == 0:
        raise UserError("there are no traces to nest; check that the layout selected Tx and Rx curves")
    check_fits(outlines, params)
    width, height = params.sheet_size()
    long_side = max(width, height) - 2 * params.margin_mm
    short_side = min(width, height) - 2 * params.margin_mm
    polygons = [outlines.polygon(i) for i in range(outlines.count)]
    fallback_reason = ""
    attempts = ["spyrrow", "shelf"] if params.nester == "spyrrow" else ["shelf"]
    for nester in attempts:
        try:
            strip = (_spyrrow if nester == "spyrrow" else _shelf)(polygons, params, long_side, short_side)
        except Exception as error:  # noqa: BLE001 - any nester failure sends us to the fallback
            if nester == "shelf":
                raise
            fallback_reason = f"spyrrow failed: {type(error).__name__}: {error}"
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
        fallback_reason = f"spyrrow result rejected: {close} part pairs closer than spacing, {outside} off the sheet"
    count = int(sheets.max()) + 1
    area = float(sum(p.area for p in polygons))
    last = [placed[i] for i in np.nonzero(sheets == count - 1)[0]]
    axis = 0 if width >= height else 1
    used_length = max(p.bounds[axis + 2] for p in last) - min(p.bounds[axis] for p in last)
    return NestedSheets(
        sheet_width_mm=width,
        sheet_height_mm=height,
        sheet_count=count,
        part_sheet=sheets,
        rotation_deg=rotation,
        translation=translation,
        nester=nester,
        fallback_reason=fallback_reason,
        spacing_mm=params.spacing_mm,
        min_gap_mm=min_gap,
        overlaps=close,
        parts_area_mm2=area,
        material_use=area / (count * width * height),
        used_length_mm=float(used_length),
    )
