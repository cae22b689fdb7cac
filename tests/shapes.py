"""Generated test objects, one per class of object a user brings (sizes in mm, +z up as designed).

Each builder returns a closed genus-0 ``trimesh.Trimesh`` in its natural size, except
:func:`point_cloud_scan`, which returns a scan's points (no faces). :data:`CLASSES` maps a class
name to its builder; :func:`write_shape` writes one to a file the pipeline can load (PLY; a point
cloud as a PLY with a vertex element only). ``bench/corpus.py`` imports this module too.
"""
from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np
import trimesh

SECTIONS = 96
"""Angular sections of the solids of revolution."""


def revolved(profile: list[tuple[float, float]]) -> trimesh.Trimesh:
    """Solid of revolution about +z of a closed ``(radius, height)`` profile running from the axis
    at the bottom, around the outside, back to the axis at the top (mm)."""
    return trimesh.creation.revolve(np.asarray(profile, dtype=np.float64), sections=SECTIONS)


def plate() -> trimesh.Trimesh:
    """A dinner plate (240 mm across, 22 mm high, 4 mm thick): flat bottom, sloped rim."""
    return revolved([(0, 0), (70, 0), (120, 18), (120, 22), (116, 22), (68, 4), (0, 4)])


def bowl_with_foot_ring() -> trimesh.Trimesh:
    """A bowl (150 mm across, 70 mm high, 4 mm wall) standing on a 6 mm foot ring (r 34-40 mm)."""
    return revolved([
        (0, 6), (34, 6), (34, 0), (40, 0), (41, 6), (62, 26), (75, 70), (71, 70), (58, 29), (38, 10), (0, 10),
    ])


def bust_with_cut_base() -> trimesh.Trimesh:
    """A bust (head, neck, shoulders) cut flat at the chest: 160 mm high, base 44 mm in radius."""
    profile = [(0, 0), (44, 0), (58, 18), (60, 34), (40, 50), (20, 62), (19, 78)]
    profile += [(36 * np.sin(t), 115 - 36 * np.cos(t)) for t in np.linspace(0.55, np.pi, 14)]
    mesh = revolved(profile)
    nose = np.array([0.0, 36.0, 112.0])  # a bump on the face breaks the symmetry
    offset = mesh.vertices - nose
    mesh.vertices += np.array([0.0, 1.0, 0.0]) * 10.0 * np.exp(-(offset**2).sum(axis=1) / 120.0)[:, None]
    return mesh


def vase() -> trimesh.Trimesh:
    """A thin-walled vase (100 mm across, 180 mm high, 3 mm wall) with a neck 26 mm across and a flared
    lip: a finger reaches only the top of its inside."""
    return revolved([
        (0, 0), (40, 0), (50, 40), (48, 100), (16, 150), (13, 165), (18, 180), (15, 180), (10, 165), (13, 150),
        (45, 100), (47, 40), (37, 3), (0, 3),
    ])


def box() -> trimesh.Trimesh:
    """A closed box, 120 x 80 x 50 mm, its faces subdivided to about 5 mm edges."""
    mesh = trimesh.creation.box(extents=(120.0, 80.0, 50.0))
    vertices, faces = trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, max_edge=5.0)
    return trimesh.Trimesh(vertices, faces)


def phone() -> trimesh.Trimesh:
    """A phone-sized slab, 150 x 75 x 8 mm, its four upright edges rounded (8 mm radius), its faces
    subdivided to about 3 mm edges: a thin object whose top is a wide flat disc for the grid."""
    length, width, corner_radius = 150.0, 75.0, 8.0
    mesh = trimesh.creation.box(extents=(length, width, 8.0))
    vertices, faces = trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, max_edge=3.0)
    inner = np.array([length / 2 - corner_radius, width / 2 - corner_radius])
    xy = vertices[:, :2]  # a view: moving it moves the vertices
    nearest = np.clip(xy, -inner, inner)  # the point of the inset rectangle nearest each vertex
    offset = xy - nearest
    reach = np.linalg.norm(offset, axis=1)
    corner = reach > 1e-9
    xy[corner] = nearest[corner] + offset[corner] / reach[corner, None] * np.minimum(reach[corner], corner_radius)[:, None]
    return trimesh.Trimesh(vertices, faces)


def radial(direction_radius: Callable[[np.ndarray], np.ndarray], subdivisions: int = 6) -> trimesh.Trimesh:
    """An icosphere whose vertex in unit direction ``d`` moves to ``direction_radius(d) * d``."""
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions)
    directions = np.asarray(sphere.vertices)
    return trimesh.Trimesh(directions * direction_radius(directions)[:, None], sphere.faces)


def four_legged_figurine(soles: bool = True) -> trimesh.Trimesh:
    """An animal figurine: an ellipsoid body (110 x 50 x 40 mm) on four legs, a head bump in front;
    stands on the legs' flat soles (z = -45 mm), or with ``soles=False`` on their rounded ends
    (hooves: almost no flat contact, z = -63 mm)."""
    axes = np.array([55.0, 25.0, 20.0])

    def radius(d: np.ndarray) -> np.ndarray:
        body = 1.0 / np.sqrt(((d / axes) ** 2).sum(axis=1))
        extra = np.zeros(len(d))
        for sx in (-1, 1):
            for sy in (-1, 1):
                leg = np.array([0.62 * sx, 0.3 * sy, -0.72])
                leg /= np.linalg.norm(leg)
                angle = np.arccos(np.clip(d @ leg, -1, 1))
                extra = np.maximum(extra, 60.0 * np.exp(-((angle / 0.16) ** 4)))
        head = np.array([0.9, 0.0, 0.43])
        angle = np.arccos(np.clip(d @ (head / np.linalg.norm(head)), -1, 1))
        return body + extra + 18.0 * np.exp(-((angle / 0.35) ** 2))

    mesh = radial(radius)
    vertices = mesh.vertices.copy()
    if soles:
        vertices[:, 2] = np.maximum(vertices[:, 2], -45.0)
    return trimesh.Trimesh(vertices, mesh.faces)


def figure_on_two_legs(arms_out: bool, subdivisions: int) -> trimesh.Trimesh:
    """An ellipsoid body (48 x 30 x 80 mm) with a head on top and two legs parted like a person's, each
    ending in a small flat sole (about 100 mm^2); with ``arms_out`` two arms about 13 mm thick stretched
    out sideways; an icosphere of ``subdivisions`` made radial."""
    axes = np.array([24.0, 15.0, 40.0])

    def radius(d: np.ndarray) -> np.ndarray:
        body = 1.0 / np.sqrt(((d / axes) ** 2).sum(axis=1))
        limbs = np.zeros(len(d))
        for side in (-1, 1):
            leg = np.array([0.35 * side, 0.0, -0.94]) / np.hypot(0.35, 0.94)
            limbs = np.maximum(limbs, 45.0 * np.exp(-((np.arccos(np.clip(d @ leg, -1, 1)) / 0.13) ** 4)))
            if arms_out:
                arm = np.array([side * 0.94, 0.0, 0.34]) / np.hypot(0.94, 0.34)
                limbs = np.maximum(limbs, 62.0 * np.exp(-((np.arccos(np.clip(d @ arm, -1, 1)) / 0.09) ** 4)))
        head = 22.0 * np.exp(-((np.arccos(np.clip(d[:, 2], -1, 1)) / 0.3) ** 2))
        return body + limbs + head

    mesh = radial(radius, subdivisions)
    vertices = mesh.vertices.copy()
    vertices[:, 2] = np.maximum(vertices[:, 2], vertices[:, 2].min() + 8.0)
    return trimesh.Trimesh(vertices, mesh.faces)


def standing_figure() -> trimesh.Trimesh:
    """A figure standing on two legs (:func:`figure_on_two_legs`), 133 mm high. Lying on its front or
    back it touches the table along a longer strip than its soles."""
    return figure_on_two_legs(arms_out=False, subdivisions=6)


def figure_arms_out() -> trimesh.Trimesh:
    """The standing figure with its arms stretched out sideways (a T pose), 212 mm across. Each hand lies
    about a fifth farther from the base (a sole, grown up its leg for the wiring), along the surface,
    than the top of the head."""
    return figure_on_two_legs(arms_out=True, subdivisions=7)


def lying_spoon() -> trimesh.Trimesh:
    """A spoon-like solid lying on its curved back: an oval bowl (70 x 44 mm) and a 110 mm handle,
    along x, 14 mm high; nothing on it is flat."""
    profile = [(0.0, 0.0)]
    profile += [(22 * np.sin(t), 35 - 35 * np.cos(t)) for t in np.linspace(0.15, np.pi * 0.85, 12)]
    profile += [(6.0, 80.0), (5.0, 150.0), (7.0, 170.0), (6.0, 178.0), (0.0, 180.0)]
    mesh = revolved(profile)
    vertices = mesh.vertices[:, [2, 0, 1]] * np.array([1.0, 1.0, 0.32])  # along x, flattened
    return trimesh.Trimesh(vertices, mesh.faces[:, [0, 1, 2]])


def metal_spoon() -> trimesh.Trimesh:
    """A metal spoon: a 1.6 mm sheet, an oval bowl (70 x 44 mm, 10 mm deep, its tip and neck curving up
    4 mm) and a handle (8-14 mm wide) rising 8 mm more to its end, 182 mm long along x, bowl up."""
    x = np.linspace(0.0, 182.0, 183)
    bowl = 22.0 * np.sqrt(np.clip(1.0 - ((x - 35.0) / 35.0) ** 2, 0.0, None))
    handle = np.where(x >= 55.0, np.interp(x, [55.0, 150.0, 176.0, 182.0], [4.0, 5.0, 7.0, 1.0]), 0.0)
    half_width = np.maximum(np.maximum(bowl, handle), 1.0)
    across = np.linspace(-1.0, 1.0, 31)
    rings = []  # one closed cross-section per x: the top side across, then the bottom side back
    for xi, w in zip(x, half_width):
        y = across * w
        depth = -10.0 * np.clip(1.0 - ((xi - 35.0) / 35.0) ** 2 - (y / 22.0) ** 2, 0.0, None)
        bend = 4.0 * min((xi - 35.0) / 35.0, 1.0) ** 2  # the bowl's tip and neck curve up
        lift = 8.0 * np.clip((xi - 70.0) / 112.0, 0.0, 1.0) ** 1.5
        mid = depth + bend + lift
        top = np.column_stack([np.full_like(y, xi), y, mid + 0.8])
        bottom = np.column_stack([np.full_like(y, xi), y, mid - 0.8])[::-1]
        rings.append(np.vstack([top, bottom]))
    n, k = len(rings), len(rings[0])  # the two ends closed by fans around their centres
    vertices = np.vstack(rings + [rings[0].mean(axis=0, keepdims=True), rings[-1].mean(axis=0, keepdims=True)])
    first, last = n * k, n * k + 1
    j = np.arange(k)
    caps = np.vstack([np.column_stack([np.full(k, first), (j + 1) % k, j]),
                      np.column_stack([np.full(k, last), (n - 1) * k + j, (n - 1) * k + (j + 1) % k])])
    return swept(vertices, n, k, caps)


def starfish() -> trimesh.Trimesh:
    """A starfish toy lying on the table: a core 30 mm in radius and five arms reaching 80 mm from its
    middle, 20 mm thick there and 10 mm at the arms' tips, rounded all over (146 x 153 x 20 mm): a
    lying top whose arms point five ways."""
    def radius(d: np.ndarray) -> np.ndarray:
        arm = np.abs(np.cos(2.5 * np.arctan2(d[:, 1], d[:, 0]))) ** 4
        flat = np.hypot(d[:, 0], d[:, 1])
        half_thickness = 10.0 - 5.0 * arm
        reach = 30.0 + 50.0 * arm  # mm in the table's plane
        return 1.0 / np.sqrt((flat / reach) ** 2 + (d[:, 2] / half_thickness) ** 2)

    return radial(radius)


def swept(vertices: np.ndarray, sections: int, size: int, caps: np.ndarray) -> trimesh.Trimesh:
    """A closed mesh from ``sections`` closed cross-sections of ``size`` points each (the first
    ``sections * size`` rows of ``vertices``, section by section), consecutive ones joined by quads
    split in two, and the ``caps`` faces closing the two ends; faces turned outward."""
    i, j = np.meshgrid(np.arange(sections - 1), np.arange(size), indexing="ij")
    a, b = i * size + j, i * size + (j + 1) % size
    c, d = a + size, b + size
    sides = np.vstack([np.column_stack([a.ravel(), b.ravel(), d.ravel()]), np.column_stack([a.ravel(), d.ravel(), c.ravel()])])
    mesh = trimesh.Trimesh(vertices, np.vstack([sides, caps]))
    if mesh.volume < 0:
        mesh.invert()
    return mesh


def point_cloud_scan(seed: int = 0) -> np.ndarray:
    """``(n, 3)`` points (mm) of a scanned bust: about 60,000 surface samples with 0.3 mm noise,
    two holes (no samples within 12 mm of two surface points) and three loose fragments (small
    clusters of floor and stray points away from the object)."""
    rng = np.random.default_rng(seed)
    mesh = bust_with_cut_base()
    points = np.asarray(trimesh.sample.sample_surface_even(mesh, 60000, seed=seed)[0])
    for centre in (np.array([0.0, -58.0, 30.0]), np.array([30.0, 0.0, 118.0])):
        points = points[np.linalg.norm(points - centre, axis=1) > 12.0]
    points = points + rng.normal(scale=0.3, size=points.shape)
    fragments = [rng.normal(loc, scale, size=(count, 3)) for loc, scale, count in (
        ((110.0, 0.0, 5.0), 4.0, 300), ((-90.0, 60.0, 20.0), 3.0, 150), ((0.0, 0.0, 200.0), 2.0, 80),
    )]
    return np.vstack([points, *fragments])


CLASSES: dict[str, Callable[[], trimesh.Trimesh | np.ndarray]] = {
    "plate": plate,
    "bowl_foot_ring": bowl_with_foot_ring,
    "four_legged_figurine": four_legged_figurine,
    "standing_figure": standing_figure,
    "figure_arms_out": figure_arms_out,
    "lying_spoon": lying_spoon,
    "metal_spoon": metal_spoon,
    "bust_cut_base": bust_with_cut_base,
    "box": box,
    "phone": phone,
    "starfish": starfish,
    "vase": vase,
    "point_cloud_scan": point_cloud_scan,
}
"""Class name -> builder (a mesh, or the points of a scan)."""


def write_point_cloud_ply(path: Path, points: np.ndarray) -> None:
    """A binary little-endian PLY holding only a float32 ``vertex`` element (x, y, z)."""
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(points)}\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
    )
    path.write_bytes(header.encode("ascii") + np.asarray(points, dtype="<f4").tobytes())


def write_shape(name: str, folder: Path) -> Path:
    """Write class ``name``'s shape as ``folder/<name>.ply`` and return the path."""
    shape = CLASSES[name]()
    path = Path(folder) / f"{name}.ply"
    if isinstance(shape, trimesh.Trimesh):
        shape.export(str(path))
    else:
        write_point_cloud_ply(path, shape)
    return path


def diagonal_mm(name: str) -> float:
    """Bounding-box diagonal (mm) of class ``name``'s shape: its natural size."""
    shape = CLASSES[name]()
    points = shape.vertices if isinstance(shape, trimesh.Trimesh) else shape
    return float(np.linalg.norm(np.ptp(points, axis=0)))
