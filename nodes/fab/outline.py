"""Flat trace outlines: unfolded centrelines -> closed cut polygons (paper section 7.1).

Each unfolded trace (:class:`retrotouch.nodes.fab.unfold.UnfoldedTraces`, same 2D frame: mm, seen from
outside, base end at the origin) becomes one closed polygon without holes, the union of

* the centreline buffered to the layout's ``trace_width_mm`` (round caps and joins),
* a landmark disc of ``landmark_radius_mm`` at every crossing with the other layer (0 disables),
* an electrode pad disc of the layout's ``pad_radius_mm`` centred at every pad position of the unfolding,
* a rectangular solder tab ``solder_tab_length_mm`` x ``solder_tab_width_mm`` continuing the trace
  beyond its base end along the end tangent; the channel name (``Tx03``) is written inside the tab
  as glyph outlines (the label layer, drawn with a pen, never cut). The tab is where the wire is
  soldered, so the name is at hand when wiring.

Pockets these shapes enclose of up to ``fill_hole_mm2`` (e.g. between the tab, a sharp first bend and
a pad) are filled: too small to cut, and copper of the same trace.

Self-overlap: a trace whose flat outline would touch itself (two stretches of the trace, far apart
along it, closer than their radii plus ``self_clearance_mm``) is split into pieces that do not,
numbered from the base end (``Tx03.1``, ``Tx03.2``...; every piece gets its own named tab at its
base-side end, which overlaps the neighbouring piece on the object and is soldered to it), or, with
``on_self_overlap: error``, reported as a UserError. "Far apart along it" means an arc distance
above pi/2 times the contact distance, which no bend gentler than a half turn reaches.

Mat size: a piece that would not fit the usable area of ``fit_mat`` (inside the default nesting
margin) at any rotation, or whose convex hull would cover more than ``max_hull_share`` of that area
(a helix on a plate unfolds to a spiral the size of the sheet, which nothing else can share), ends
at the last sample where it still does, and the next piece starts there, the same way: its tab
overlaps the previous piece's end (the joint, soldered on the object), so no trace is too long for
the cutter. ``TraceOutlines.joints`` counts the joints.
"""
from __future__ import annotations

import dataclasses
from typing import Literal

import numpy as np
import shapely
from pydantic import Field
from shapely.geometry import LineString, MultiPoint, Point, Polygon

from ...graph.errors import UserError
from ...graph.node import NodeParams, node
from .mats import MARGIN_MM, MATS_MM, points_fit_angles, usable_sides
from .unfold import UnfoldedTraces, point_at_arc


class Params(NodeParams):
    landmark_radius_mm: float = Field(1.0, ge=0, description="landmark disc radius at every crossing (mm); 0 = none")
    solder_tab_length_mm: float = Field(9.0, gt=0, description="solder tab length beyond the base end (mm)")
    solder_tab_width_mm: float = Field(4.0, gt=0, description="solder tab width (mm)")
    label_height_mm: float = Field(2.4, gt=0, description="largest label glyph height (mm); shrunk to fit the tab")
    label_margin_mm: float = Field(0.5, ge=0, description="clearance between the label and the tab edge (mm)")
    self_clearance_mm: float = Field(0.5, ge=0, description="smallest gap between two stretches of one trace (mm)")
    on_self_overlap: Literal["split", "error"] = Field("split", description="split self-overlapping traces or fail")
    fit_mat: Literal["12x12", "12x24", "none"] = Field(
        "12x12", description="split traces into pieces that fit this mat (inside the default margin); none = never")
    max_hull_share: float = Field(
        0.15, gt=0, le=1, description="split traces into pieces whose convex hull covers at most this share of fit_mat's "
                                      "usable area (a curled trace left whole takes a sheet to itself)")
    arc_segments: int = Field(8, ge=2, le=64, description="polygon segments per quarter circle")
    simplify_mm: float = Field(
        0.01, ge=0, le=0.1, description="farthest (mm) an outline may move as the vertices it does not need are "
                                        "dropped (Douglas-Peucker); 0 keeps every vertex")
    fill_hole_mm2: float = Field(
        8.0, gt=0, description="holes of a part up to this area (mm2) are filled: pockets between the tab, a sharp "
                               "bend and a pad, too small to cut")


@dataclasses.dataclass(frozen=True)
class TraceOutlines:
    """Cut outlines of all traces (parts), in their unfolded frames (mm, seen from outside)."""

    names: tuple[str, ...]  # (N,) part names: "Tx03", or "Tx03.1", "Tx03.2" for a split trace
    trace_names: tuple[str, ...]  # names of the unfolded traces ("Tx03"), indexed by ``trace``
    trace: np.ndarray  # (N,) int64 index into UnfoldedTraces
    arc_range: np.ndarray  # (N, 2) float64 arc interval of the trace this part covers (mm)
    ring: np.ndarray  # (R, 2) float64 exterior rings, not repeating the first point
    ring_offsets: np.ndarray  # (N + 1,) int64
    centre: np.ndarray  # (Q, 2) float64 centrelines
    centre_offsets: np.ndarray  # (N + 1,) int64
    pad_xy: np.ndarray  # (M, 2) electrode pad centres
    pad_part: np.ndarray  # (M,) int64
    landmark_xy: np.ndarray  # (L, 2) landmark centres (crossings)
    landmark_part: np.ndarray  # (L,) int64
    landmark_other: np.ndarray  # (L,) int64 trace of the other layer crossing there (index into trace_names)
    tab: np.ndarray  # (N, 4, 2) solder tab corners
    label: np.ndarray  # (S, 2) label glyph outline points
    label_offsets: np.ndarray  # (G + 1,) int64 closed glyph polylines
    label_part: np.ndarray  # (G,) int64
    area_mm2: np.ndarray  # (N,) float64
    split_traces: tuple[str, ...]  # traces that were split (to avoid self-overlap, or to fit the mat)
    split_reasons: tuple[str, ...]  # per split trace: "overlaps itself", "longer than the 12x12 mat", "curls over more than <max_hull_share> of the mat", joined by ", "
    width_mm: float
    pad_radius_mm: float
    landmark_radius_mm: float

    @property
    def count(self) -> int:
        return len(self.names)

    @property
    def joints(self) -> int:
        """Places where two pieces of one split trace are soldered together."""
        return self.count - len(np.unique(self.trace))

    def polygon(self, i: int) -> Polygon:
        return Polygon(self.ring[self.ring_offsets[i] : self.ring_offsets[i + 1]])

    def label_polylines(self, i: int, rotation_deg: float = 0.0) -> list[np.ndarray]:
        """Glyph outlines of part ``i`` in its frame; turned a half turn about the tab centre when,
        once the part is rotated CCW by ``rotation_deg``, they would read right to left (or
        downwards), so that placed they read left to right (or upwards)."""
        glyphs = [self.label[self.label_offsets[g] : self.label_offsets[g + 1]] for g in np.nonzero(self.label_part == i)[0]]
        along = self.tab[i, 3] - self.tab[i, 0]  # the reading direction: along the tab, away from the trace
        reading = (np.degrees(np.arctan2(along[1], along[0])) + rotation_deg) % 360.0
        if reading <= 90.0 + 1e-6 or reading > 270.0 + 1e-6:
            return glyphs
        centre = self.tab[i].mean(axis=0)
        return [2 * centre - g for g in glyphs]


def label_glyphs(text: str, origin: np.ndarray, direction: np.ndarray, box_length: float, box_height: float,
                 max_height: float) -> list[np.ndarray]:
    """Closed glyph outlines of ``text`` centred at ``origin``, reading along ``direction``, scaled to
    fit a ``box_length`` x ``box_height`` box with cap height at most ``max_height`` (mm)."""
    from matplotlib.font_manager import FontProperties  # heavy: imported when used
    from matplotlib.textpath import TextPath

    path = TextPath((0, 0), text, size=1.0, prop=FontProperties(family="DejaVu Sans"))
    polygons = [np.asarray(p) for p in path.to_polygons(closed_only=True) if len(p) >= 3]
    allpts = np.concatenate(polygons)
    lo, hi = allpts.min(axis=0), allpts.max(axis=0)
    extent = np.maximum(hi - lo, 1e-9)
    scale = min(box_length / extent[0], box_height / extent[1], max_height / extent[1])
    centre = (lo + hi) / 2
    normal = np.array([-direction[1], direction[0]])
    frame = np.stack([direction, normal])  # rows: x-axis, y-axis of the text
    return [origin + ((p - centre) * scale) @ frame for p in polygons]


def _first_conflict(samples: np.ndarray, radius: np.ndarray, u: np.ndarray, clearance: float) -> tuple[float, float] | None:
    """The conflicting sample pair (lo, hi distance from the base) with the smallest hi, or None.

    Two samples conflict when their discs come closer than ``clearance`` (distance < r_i + r_j +
    clearance) while they are more than pi/2 times that contact distance apart along the trace.
    """
    from scipy.spatial import cKDTree  # heavy: imported when used

    pairs = cKDTree(samples).query_pairs(2 * radius.max() + clearance, output_type="ndarray")
    if len(pairs) == 0:
        return None
    i, j = pairs[:, 0], pairs[:, 1]
    contact = radius[i] + radius[j] + clearance
    bad = (np.linalg.norm(samples[i] - samples[j], axis=1) < contact) & (np.abs(u[i] - u[j]) > np.pi / 2 * contact)
    if not bad.any():
        return None
    lo, hi = np.minimum(u[i], u[j])[bad], np.maximum(u[i], u[j])[bad]
    k = int(np.argmin(hi))
    return float(lo[k]), float(hi[k])


def _sub_polyline(points: np.ndarray, arc: np.ndarray, a0: float, a1: float) -> np.ndarray:
    """The polyline between arc lengths a0 < a1 (clamped to the polyline)."""
    a0, a1 = max(a0, 0.0), min(a1, float(arc[-1]))
    inside = (arc > a0) & (arc < a1)
    ends = [np.array([np.interp(a, arc, points[:, 0]), np.interp(a, arc, points[:, 1])]) for a in (a0, a1)]
    return np.vstack([ends[0], points[inside], ends[1]])


def _trace_discs(params: Params, unfolded: UnfoldedTraces, c: int):
    """Landmark and pad discs of trace ``c``: (marks, pad marks, centres, radii, distances from the base end)."""
    rows = unfolded.trace(c)
    length = float(unfolded.arc[rows][-1])
    u_of = (lambda a: length - a) if unfolded.base_at_end[c] else (lambda a: a)
    marks = np.nonzero(unfolded.mark_trace == c)[0]
    pad_marks = marks[unfolded.mark_pad[marks]]
    disc_xy = np.vstack([unfolded.mark_xy[marks], unfolded.pad_xy[pad_marks]])
    disc_r = np.concatenate([np.full(len(marks), max(params.landmark_radius_mm, unfolded.trace_width_mm / 2)),
                             np.full(len(pad_marks), unfolded.pad_radius_mm)])
    disc_u = np.concatenate([u_of(unfolded.mark_arc[marks]), u_of(unfolded.pad_arc[pad_marks])])
    return marks, pad_marks, disc_xy, disc_r, disc_u


def _split_pieces(params: Params, width_mm: float, name: str, points: np.ndarray, arc: np.ndarray, at_end: bool,
                  discs: tuple) -> list[tuple[float, float, str]]:
    """Pieces [u0, u1) of one trace (u = distance from its base end, mm) with the reason each ends
    ("" for the last), grown from the base: each piece, with its own solder tab at u0, ends just
    before its first self-conflict, or where it would no longer fit ``fit_mat``."""
    _, _, disc_xy, disc_r, disc_u = discs
    w2, tab_len, tab_w2 = width_mm / 2, params.solder_tab_length_mm, params.solder_tab_width_mm / 2
    length = float(arc[-1])
    step = width_mm / 2
    u = np.append(np.arange(0.0, length, step), length)
    arc_of_u = length - u if at_end else u
    centre_samples = np.stack([np.interp(arc_of_u, arc, points[:, 0]), np.interp(arc_of_u, arc, points[:, 1])], axis=1)
    t = np.append(np.arange(0.0, tab_len, step), tab_len)
    pieces: list[tuple[float, float, str]] = []
    u0 = 0.0
    while True:
        tab_xy, tangent = point_at_arc(points, arc, length - u0 if at_end else u0)
        outward = tangent if at_end else -tangent
        keep_c, keep_d = u >= u0, disc_u >= u0
        samples = np.vstack([centre_samples[keep_c], disc_xy[keep_d], tab_xy + t[:, None] * outward])
        radius = np.concatenate([np.full(keep_c.sum(), w2), disc_r[keep_d], np.full(len(t), tab_w2)])
        sample_u = np.concatenate([u[keep_c], disc_u[keep_d], u0 - t])
        conflict = _first_conflict(samples, radius, sample_u, params.self_clearance_mm)
        u1, reason = np.inf, ""
        if conflict is not None:
            if params.on_self_overlap == "error":
                raise UserError(
                    f"{name} overlaps itself once unfolded ({conflict[1]:.1f} mm from its base end, "
                    f"{length:.1f} mm long); set on_self_overlap: split, or choose a layout without this curve"
                )
            lo, hi = conflict
            u1, reason = max(hi - min(0.25 * (hi - max(lo, u0)), 0.5), u0 + step), "overlaps itself"
            if u1 >= hi:
                raise UserError(f"{name} folds onto itself within {hi - u0:.1f} mm; it cannot be cut flat")
        fit = _fitting_end(params, samples, radius, sample_u, u0, min(u1, length))
        if fit is not None:
            u1, reason = fit
        pieces.append((u0, u1, reason))
        if not np.isfinite(u1):
            return pieces
        u0 = u1


def _fitting_end(params: Params, samples: np.ndarray, radius: np.ndarray, sample_u: np.ndarray, u0: float,
                 u1: float) -> tuple[float, str] | None:
    """None when the piece [u0, u1] (its samples' discs) fits ``fit_mat`` at some rotation and its
    convex hull covers at most ``max_hull_share`` of the mat's usable area, else (an end on the
    ``width_mm / 2`` sample grid that cuts [u0, u1] into as few pieces of equal length as the longest
    piece within both limits allows (shorter pieces pack better than one that just fits), the reason)."""
    if params.fit_mat == "none":
        return None
    long_side, short_side = usable_sides(*MATS_MM[params.fit_mat], MARGIN_MM)
    grow = 2 * float(radius.max())
    hull_limit = params.max_hull_share * long_side * short_side

    def fits_mat(end: float) -> bool:
        return len(points_fit_angles(samples[sample_u <= end], long_side - grow, short_side - grow)) > 0

    def fits(end: float) -> bool:
        return fits_mat(end) and MultiPoint(samples[sample_u <= end]).convex_hull.area <= hull_limit

    if fits(u1):
        return None
    reason = f"longer than the {params.fit_mat} mat" if not fits_mat(u1) else f"curls over more than {params.max_hull_share:g} of the mat"
    ends = np.unique(sample_u[(sample_u > u0) & (sample_u < u1)])
    lo, hi = 0, len(ends) - 1  # binary search for the last end that fits
    if len(ends) == 0 or not fits(ends[0]):
        raise UserError(f"a piece of {params.solder_tab_length_mm:g} mm tab and trace does not fit the {params.fit_mat} mat")
    while lo < hi:
        mid = (lo + hi + 1) // 2
        lo, hi = (mid, hi) if fits(ends[mid]) else (lo, mid - 1)
    target = u0 + (u1 - u0) / np.ceil((u1 - u0) / (ends[lo] - u0))
    k = int(np.searchsorted(ends, target, side="right")) - 1
    return float(ends[min(max(k, 0), lo)]), reason


def _tab_corners(tab_xy: np.ndarray, direction: np.ndarray, length: float, half_width: float) -> np.ndarray:
    """(4, 2) corners of the solder tab starting at ``tab_xy`` and running along ``direction``."""
    normal = np.array([-direction[1], direction[0]])
    return np.array([
        tab_xy + half_width * normal,
        tab_xy - half_width * normal,
        tab_xy + length * direction - half_width * normal,
        tab_xy + length * direction + half_width * normal,
    ])


def _piece(params: Params, unfolded: UnfoldedTraces, c: int, discs: tuple, u0: float, u1: float, part_name: str):
    """One part of trace ``c`` between distances u0 < u1 from its base end: a dict of its arc range,
    ring, centreline, tab, area, glyphs, and its (landmark index, pad index) marks."""
    rows = unfolded.trace(c)
    points, arc = unfolded.points[rows], unfolded.arc[rows]
    length = float(arc[-1])
    at_end = bool(unfolded.base_at_end[c])
    marks, pad_marks = discs[0], discs[1]
    u_of = (lambda a: length - a) if at_end else (lambda a: a)
    a0, a1 = (length - u1, length - u0) if at_end else (u0, u1)
    centre = _sub_polyline(points, arc, a0, a1)
    tab_xy, tangent = point_at_arc(points, arc, length - u0 if at_end else u0)
    direction = tangent if at_end else -tangent
    tab_len, tab_w2 = params.solder_tab_length_mm, params.solder_tab_width_mm / 2
    tab = _tab_corners(tab_xy, direction, tab_len, tab_w2)
    shapes = [Polygon(tab)]
    line = LineString(centre) if np.ptp(centre, axis=0).max() > 0 else Point(centre[0])
    shapes.append(line.buffer(unfolded.trace_width_mm / 2, quad_segs=params.arc_segments))
    mark_u, pad_u = u_of(unfolded.mark_arc[marks]), u_of(unfolded.pad_arc[pad_marks])
    landmarks = marks[(mark_u >= u0) & (mark_u < u1)] if params.landmark_radius_mm > 0 else marks[:0]
    pads = pad_marks[(pad_u >= u0) & (pad_u < u1)]
    for m in landmarks:
        shapes.append(Point(unfolded.mark_xy[m]).buffer(params.landmark_radius_mm, quad_segs=params.arc_segments))
    for m in pads:
        shapes.append(Point(unfolded.pad_xy[m]).buffer(unfolded.pad_radius_mm, quad_segs=params.arc_segments))
    shape = shapely.unary_union(shapes)
    if shape.geom_type == "Polygon":  # fill pockets too small to cut (copper of one trace: no short)
        shape = Polygon(shape.exterior, [h for h in shape.interiors if Polygon(h).area > params.fill_hole_mm2])
    if shape.geom_type != "Polygon" or not shape.is_valid or len(shape.interiors) > 0:
        raise UserError(
            f"{part_name}: its outline is not one closed polygon without holes ({shape.geom_type}, "
            f"{len(getattr(shape, 'interiors', []))} holes); raise self_clearance_mm so the trace is split"
        )
    shape = shape.simplify(params.simplify_mm, preserve_topology=True)
    margin = params.label_margin_mm
    glyphs = label_glyphs(part_name, tab_xy + (tab_len / 2) * direction, direction,
                          tab_len - 2 * margin, 2 * tab_w2 - 2 * margin, params.label_height_mm)
    return {"arc": (max(a0, 0.0), min(a1, length)), "ring": np.asarray(shape.exterior.coords)[:-1],
            "centre": centre, "tab": tab, "area": shape.area, "glyphs": glyphs, "landmarks": landmarks, "pads": pads}


def _flat(arrays: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(concatenated (R, 2) rows, (len + 1,) int64 offsets)."""
    rows = np.concatenate(arrays) if arrays else np.zeros((0, 2))
    return rows, np.concatenate([[0], np.cumsum([len(a) for a in arrays])]).astype(np.int64)


def _assemble(params: Params, unfolded: UnfoldedTraces, parts: list[tuple[str, int, dict]],
              split: list[str], reasons: list[str]) -> TraceOutlines:
    """TraceOutlines from (part name, trace, piece dict) in part order."""
    ring, ring_offsets = _flat([p["ring"] for _, _, p in parts])
    centre, centre_offsets = _flat([p["centre"] for _, _, p in parts])
    label, label_offsets = _flat([g for _, _, p in parts for g in p["glyphs"]])
    landmarks = np.concatenate([p["landmarks"] for _, _, p in parts] or [[]]).astype(np.int64)
    pads = np.concatenate([p["pads"] for _, _, p in parts] or [[]]).astype(np.int64)

    def owner(key: str) -> np.ndarray:
        return np.repeat(np.arange(len(parts), dtype=np.int64), [len(p[key]) for _, _, p in parts])

    return TraceOutlines(
        names=tuple(name for name, _, _ in parts),
        trace_names=unfolded.names,
        trace=np.asarray([c for _, c, _ in parts], dtype=np.int64),
        arc_range=np.asarray([p["arc"] for _, _, p in parts], dtype=np.float64).reshape(-1, 2),
        ring=ring,
        ring_offsets=ring_offsets,
        centre=centre,
        centre_offsets=centre_offsets,
        pad_xy=np.asarray(unfolded.pad_xy[pads], dtype=np.float64).reshape(-1, 2),
        pad_part=owner("pads"),
        landmark_xy=np.asarray(unfolded.mark_xy[landmarks], dtype=np.float64).reshape(-1, 2),
        landmark_part=owner("landmarks"),
        landmark_other=np.asarray(unfolded.mark_other[landmarks], dtype=np.int64),
        tab=np.asarray([p["tab"] for _, _, p in parts], dtype=np.float64).reshape(-1, 4, 2),
        label=label,
        label_offsets=label_offsets,
        label_part=owner("glyphs"),
        area_mm2=np.asarray([p["area"] for _, _, p in parts], dtype=np.float64),
        split_traces=tuple(split),
        split_reasons=tuple(reasons),
        width_mm=unfolded.trace_width_mm,
        pad_radius_mm=unfolded.pad_radius_mm,
        landmark_radius_mm=params.landmark_radius_mm,
    )


@node("fab.outline", params=Params, inputs=("unfolded",), outputs=("outlines",))
def outline(params: Params, unfolded: UnfoldedTraces) -> TraceOutlines:
    """Outline every unfolded trace as one closed polygon with landmarks, electrode pads and a named
    solder tab; split (or report) traces whose outline would overlap itself."""
    parts, split, reasons = [], [], []
    for c in range(unfolded.count):
        rows = unfolded.trace(c)
        discs = _trace_discs(params, unfolded, c)
        pieces = _split_pieces(params, unfolded.trace_width_mm, unfolded.names[c], unfolded.points[rows], unfolded.arc[rows],
                               bool(unfolded.base_at_end[c]), discs)
        if len(pieces) > 1:
            split.append(unfolded.names[c])
            reasons.append(", ".join(sorted({r for _, _, r in pieces if r})))
        for number, (u0, u1, _) in enumerate(pieces, start=1):
            part_name = unfolded.names[c] if len(pieces) == 1 else f"{unfolded.names[c]}.{number}"
            parts.append((part_name, c, _piece(params, unfolded, c, discs, u0, u1, part_name)))
    return _assemble(params, unfolded, parts, split, reasons)
