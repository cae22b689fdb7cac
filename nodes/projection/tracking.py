"""Track the known mesh in depth frames (stand-in for the paper's OVE6D on an Azure Kinect).

Pipeline per frame: back-project the valid depth pixels on a grid, drop a support plane (table)
larger than the object (RANSAC), keep the points near the tracked object and subsample them,
register them to the mesh with robust point-to-plane ICP (cKDTree over face centroids with face
normals, Huber weights, back-facing correspondences rejected) starting from the last pose (a
constant-velocity guess drifts: an error along a weakly constrained direction feeds back), gate
the result on the inlier fraction (a failed frame holds the last good pose; several in a row
trigger a new global search), and smooth the accepted poses (:mod:`.smoothing`).

The global search tries rotation hypotheses (the 60 rotations of the icosahedral group, each
combined with a translation aligning the centroid of the model's camera-facing surface with the
scene centroid), runs a short ICP from each and keeps the best by inlier fraction.

Conventions: :mod:`.camera`; poses are ``T_cam_obj`` (object -> depth camera, mm); frames come
from :mod:`.depth_frames`.
"""
from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from ..data.types import Mesh
from ..geometry.triangles import corners, cross_products, normals
from .camera import DeviceIntrinsics, invert_pose, normalised_coordinates, transform_points
from .depth_frames import DepthFrame
from .smoothing import PoseSmoother


@dataclasses.dataclass(frozen=True)
class TrackerSettings:
    """Tracking parameters (mm, degrees, Hz)."""

    sample_points: int = 1500  # depth points per ICP step
    grid_stride_px: int = 4  # depth pixels are first taken on this grid
    max_iterations: int = 20
    huber_mm: float = 2.0
    max_correspondence_mm: float = 20.0
    inlier_mm: float = 3.0
    min_inlier_fraction: float = 0.6  # gate: below this the frame is rejected and the last pose held
    reinit_after_frames: int = 5  # consecutive rejected frames before a new global search
    min_depth_mm: float = 100.0
    max_depth_mm: float = 3000.0
    remove_support_plane: bool = True  # drop a table/floor plane larger than the object
    plane_threshold_mm: float = 4.0
    min_plane_fraction: float = 0.2  # of the depth points, for a plane to count as support
    track_margin_mm: float = 30.0  # while tracking, keep points within model radius + margin of the object
    smooth_min_cutoff_hz: float = 1.5
    smooth_beta: float = 0.15  # One Euro speed coefficient (per mm/s, per deg/s)
    smooth_d_cutoff_hz: float = 1.0
    seed: int = 0


class ModelSurface:
    """The mesh as oriented planes for point-to-plane ICP: face centroids, unit normals and a cKDTree (object frame)."""

    def __init__(self, mesh: Mesh) -> None:
        tri = corners(mesh.vertices, mesh.faces)
        self.points = tri.mean(axis=1)
        self.normals, self.area = normals(tri)
        self.tree = cKDTree(self.points)
        self.centre = (self.points * self.area[:, None]).sum(axis=0) / self.area.sum()
        self.radius = float(np.linalg.norm(mesh.vertices - self.centre, axis=1).max())


def backproject(depth_mm: np.ndarray, camera: DeviceIntrinsics, settings: TrackerSettings) -> np.ndarray:
    """Camera-frame points (n, 3) mm of the valid pixels on the ``grid_stride_px`` grid within the depth range."""
    s = settings.grid_stride_px
    sub = depth_mm[::s, ::s]
    rows, cols = np.nonzero((sub > settings.min_depth_mm) & (sub < settings.max_depth_mm))
    z = sub[rows, cols].astype(np.float64)
    pix = np.stack([cols * s, rows * s], axis=1).astype(np.float64)
    xy = normalised_coordinates(pix, camera)
    return np.column_stack([xy * z[:, None], z])


def support_plane_mask(
    points: np.ndarray, threshold_mm: float, min_fraction: float, min_extent_mm: float, rng: np.random.Generator
) -> np.ndarray:
    """(n,) bool: points on the dominant plane (RANSAC, 64 hypotheses on <= 2000 points, least-squares refit).

    All False unless the plane holds ``min_fraction`` of the points and spreads wider than
    ``min_extent_mm`` (95th percentile distance from its centroid): a table or floor, not a flat
    side of the object itself.
    """
    none = np.zeros(len(points), bool)
    if len(points) < 50:
        return none
    sub = points[rng.choice(len(points), min(len(points), 2000), replace=False)]
    tri = sub[rng.integers(0, len(sub), (64, 3))]
    normals = cross_products(tri)
    length = np.linalg.norm(normals, axis=1)
    good = length > 1e-6
    if not good.any():
        return none
    normals = normals[good] / length[good, None]
    offsets = np.einsum("ij,ij->i", normals, tri[good, 0])
    counts = (np.abs(sub @ normals.T - offsets) < threshold_mm).sum(axis=0)
    best = int(np.argmax(counts))
    mask = np.abs(points @ normals[best] - offsets[best]) < threshold_mm
    if mask.sum() >= 3:  # least-squares refit on the inliers
        centre = points[mask].mean(axis=0)
        normal = np.linalg.svd(points[mask] - centre, full_matrices=False)[2][2]
        mask = np.abs((points - centre) @ normal) < threshold_mm
    if mask.mean() < min_fraction:
        return none
    spread = np.percentile(np.linalg.norm(points[mask] - points[mask].mean(axis=0), axis=1), 95)
    return mask if spread > min_extent_mm else none


@dataclasses.dataclass(frozen=True)
class Registration:
    """ICP result: pose ``T_cam_obj``, fraction of scene points within ``inlier_mm`` of the surface, their RMS (mm)."""

    T_cam_obj: np.ndarray
    inlier_fraction: float
    rms_mm: float
    iterations: int


def icp_point_to_plane(
    scene_cam: np.ndarray,
    model: ModelSurface,
    T_cam_obj: np.ndarray,
    settings: TrackerSettings,
    iterations: int | None = None,
    max_correspondence_mm: float | None = None,
) -> Registration:
    """Robust point-to-plane ICP of camera-frame scene points onto the model, starting at ``T_cam_obj``.

    Each step moves the scene points in the object frame by a small rotation ``w`` and translation
    ``v`` minimising sum huber(n . (p + w x p + v - q)) over nearest face centroids ``q`` (normals
    ``n``) closer than ``max_correspondence_mm``; correspondences whose face points away from the
    camera are dropped.
    """
    max_iter = settings.max_iterations if iterations is None else iterations
    max_corr = settings.max_correspondence_mm if max_correspondence_mm is None else max_correspondence_mm
    T_obj_cam = invert_pose(T_cam_obj)
    it = 0
    for it in range(1, max_iter + 1):
        p = transform_points(T_obj_cam, scene_cam)
        dist, idx = model.tree.query(p, distance_upper_bound=max_corr, workers=1)
        ok = np.isfinite(dist)
        # camera centre in object frame; a visible face has its normal towards it
        eye = T_obj_cam[:3, 3]
        ok[ok] &= np.einsum("ij,ij->i", model.normals[idx[ok]], eye - p[ok]) > 0
        if ok.sum() < 6:
            break
        p_ok, q, n = p[ok], model.points[idx[ok]], model.normals[idx[ok]]
        r = np.einsum("ij,ij->i", n, p_ok - q)
        w = np.minimum(1.0, settings.huber_mm / np.maximum(np.abs(r), 1e-12))
        J = np.hstack([np.cross(p_ok, n), n])
        H = J.T @ (J * w[:, None])
        g = J.T @ (w * r)
        try:
            delta = -np.linalg.solve(H + 1e-9 * np.eye(6), g)
        except np.linalg.LinAlgError:
            break
        step = np.eye(4)
        step[:3, :3] = Rotation.from_rotvec(delta[:3]).as_matrix()
        step[:3, 3] = delta[3:]
        T_obj_cam = step @ T_obj_cam
        if np.linalg.norm(delta[:3]) < 1e-5 and np.linalg.norm(delta[3:]) < 1e-3:
            break
    p = transform_points(T_obj_cam, scene_cam)
    dist, _ = model.tree.query(p, distance_upper_bound=settings.inlier_mm * 4, workers=1)
    # centroid distance overestimates the plane distance by up to the face radius; use a plane test
    dist_plane = _plane_distance(model, p, dist)
    inl = dist_plane < settings.inlier_mm
    frac = float(inl.mean()) if len(p) else 0.0
    rms = float(np.sqrt(np.mean(dist_plane[inl] ** 2))) if inl.any() else float("inf")
    return Registration(invert_pose(T_obj_cam), frac, rms, it)


def _plane_distance(model: ModelSurface, p: np.ndarray, centroid_dist: np.ndarray) -> np.ndarray:
    """Distance from points to the plane of their nearest face (inf where no face was near)."""
    out = np.full(len(p), np.inf)
    near = np.isfinite(centroid_dist)
    if near.any():
        _, idx = model.tree.query(p[near], workers=1)
        out[near] = np.abs(np.einsum("ij,ij->i", model.normals[idx], p[near] - model.points[idx]))
    return out


def global_registration(scene_cam: np.ndarray, model: ModelSurface, settings: TrackerSettings) -> Registration:
    """Pose from scratch: 60 rotation hypotheses x centroid alignment, short ICP each, best refined."""
    c_scene = scene_cam.mean(axis=0)
    view = c_scene / np.linalg.norm(c_scene)
    rng = np.random.default_rng(settings.seed)
    coarse = scene_cam[rng.choice(len(scene_cam), min(400, len(scene_cam)), replace=False)]
    candidates: list[Registration] = []
    for rot in Rotation.create_group("I"):
        R = rot.as_matrix()
        facing = (model.normals @ R.T) @ view < 0
        w = model.area * facing
        c_front = (model.points * w[:, None]).sum(axis=0) / max(w.sum(), 1e-12)
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = c_scene - R @ c_front
        candidates.append(icp_point_to_plane(coarse, model, T, settings, iterations=12, max_correspondence_mm=60.0))
    candidates.sort(key=lambda reg: (-reg.inlier_fraction, reg.rms_mm))
    refined = [icp_point_to_plane(scene_cam, model, c.T_cam_obj, settings, iterations=30) for c in candidates[:3]]
    return max(refined, key=lambda reg: (reg.inlier_fraction, -reg.rms_mm))


@dataclasses.dataclass(frozen=True)
class TrackResult:
    """Per-frame result: ``status`` is 'found' (global search), 'tracked', 'held' (gate failed) or 'searching' (no pose yet).

    ``T_cam_obj`` is the smoothed pose to render with (None while searching); ``raw_T_cam_obj`` the
    last accepted ICP pose.
    """

    status: str
    T_cam_obj: np.ndarray | None
    raw_T_cam_obj: np.ndarray | None
    inlier_fraction: float
    rms_mm: float


class DepthTracker:
    """Stateful tracker of one mesh in a stream of depth frames."""

    def __init__(self, mesh: Mesh, camera: DeviceIntrinsics, settings: TrackerSettings = TrackerSettings()) -> None:
        self.model = ModelSurface(mesh)
        self.camera, self.settings = camera, settings
        self.rng = np.random.default_rng(settings.seed)
        self.smoother = PoseSmoother(settings.smooth_min_cutoff_hz, settings.smooth_beta, settings.smooth_d_cutoff_hz)
        self.raw: np.ndarray | None = None
        self.smoothed: np.ndarray | None = None
        self.rejected_in_row = 0

    def scene_points(self, frame: DepthFrame, searching: bool) -> np.ndarray:
        """The depth points to register: support plane removed, cropped around the tracked object, subsampled."""
        s = self.settings
        points = backproject(frame.depth_mm, self.camera, s)
        if s.remove_support_plane:
            plane = support_plane_mask(points, s.plane_threshold_mm, s.min_plane_fraction, 1.5 * self.model.radius, self.rng)
            points = points[~plane]
        if not searching and self.raw is not None:
            centre = transform_points(self.raw, self.model.centre[None])[0]
            points = points[np.linalg.norm(points - centre, axis=1) < self.model.radius + s.track_margin_mm]
        if len(points) > s.sample_points:
            points = points[self.rng.choice(len(points), s.sample_points, replace=False)]
        return points

    def update(self, frame: DepthFrame) -> TrackResult:
        s = self.settings
        searching = self.raw is None or self.rejected_in_row >= s.reinit_after_frames
        scene = self.scene_points(frame, searching)
        if len(scene) < 50:
            reg = None
        elif searching:
            reg = global_registration(scene, self.model, s)
        else:
            reg = icp_point_to_plane(scene, self.model, self.raw, s)
        if reg is not None and reg.inlier_fraction >= s.min_inlier_fraction:
            if searching:
                self.smoother.reset()
            self.raw = reg.T_cam_obj
            self.smoothed = self.smoother.update(reg.T_cam_obj, frame.timestamp_s)
            self.rejected_in_row = 0
            return TrackResult("found" if searching else "tracked", self.smoothed, self.raw, reg.inlier_fraction, reg.rms_mm)
        self.rejected_in_row += 1
        frac = reg.inlier_fraction if reg is not None else 0.0
        rms = reg.rms_mm if reg is not None else float("inf")
        if self.raw is None:
            return TrackResult("searching", None, None, frac, rms)
        return TrackResult("held", self.smoothed, self.raw, frac, rms)


def pose_error(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """(rotation error in degrees, translation error in mm) between two poses."""
    dR = Rotation.from_matrix(T_est[:3, :3] @ T_true[:3, :3].T)
    return float(np.rad2deg(dR.magnitude())), float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3]))
