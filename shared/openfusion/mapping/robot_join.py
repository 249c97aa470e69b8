"""Joining a robot's odometry frame to the map's frame: a submap of its frames registered to the map.

Each robot reports poses in its own odometry frame (``T_odom_cam``); the map needs ``T_map_cam``.
The transform between them, ``T_map_odom``, is either given (config) or found here: the robot's
first frames are back-projected into a *submap* (points in its odometry frame, thinned to one per
``join_voxel_m`` cell) and registered to the map's surface points:

- **with a guess** (a transform from config, or the one in use when a joined robot is re-checked):
  Open3D point-to-plane ICP from the guess, coarse to fine;
- **without a guess**: a global search, then the same ICP. The search assumes what every ground
  robot's odometry gives (REP-105: ``odom`` is gravity-aligned, z up, as the map is): the unknown
  is a yaw and a translation. FPFH features (Open3D) pair each submap point with the map points
  whose features are closest; for every yaw on a 1 degree grid each pair votes for the translation
  that would bring its submap point onto its map point, and the translation bin with the most votes
  is that yaw's candidate. Right pairs agree, wrong ones scatter, so a few per cent of right pairs
  are enough. Roll and pitch left over are ICP's (it runs in 6 DoF).

Why the search is written here (numpy) and not Open3D's ``registration_ransac_based_on_feature_matching``:
on the built-in room that RANSAC (5 cm cells, 100k iterations, mutual filter) was wrong on all four
submaps tried (1.6-4.3 m, 66-180 degrees off), because a room of planes and boxes gives few
distinctive features and a random 3-pair sample is rarely all right; the vote above, on the same
features, found the two overlapping submaps to 0.9-1.0 cm and 0.1 degrees.

A registration is **accepted** only when all of these hold (parameters :class:`JoinParams`):

1. ``fitness`` -- the share of submap points whose nearest map point (within two cells) is within
   ``join_fit_distance_m`` of the point's plane -- is at least ``join_min_fitness``;
2. the RMS plane distance of those points is at most ``join_max_rmse_m``;
3. no distinct alignment fits nearly as well: the best other candidate's fitness (after its own ICP;
   distinct: more than 10 degrees or 0.3 m away) is at most ``join_max_ambiguity`` of the best's
   (identical rooms, a symmetric corridor: several alignments fit, none is taken);
4. the fit constrains every direction: the point-to-plane information matrix
   ``H = sum J^T J`` with ``J = [p x n, n]`` has, in its translation block and in its rotation
   block, a weakest eigenvalue of at least ``join_min_constraint`` of the strongest (a corridor's
   walls and floor do not fix the position along it: its translation block is near singular).

Limits (docs/MULTI_ROBOT.md): a submap that sees only what is alike in several places (a bare
corridor, identical rooms) is held, by rules 3 and 4, until the robot sees something that tells
the places apart; a submap with little overlap with the map is held by rule 1 until the robot
reaches mapped space; a map frame that is not gravity-aligned needs a guess.
"""

from __future__ import annotations

import collections
import logging
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import open3d as o3d
from scipy.ndimage import binary_dilation
from scipy.spatial import cKDTree

from openfusion.frame import CameraIntrinsics, Frame, resize_nearest
from openfusion.mapping.params import JoinParams
from openfusion.poses import check_pose

logger = logging.getLogger(__name__)

_REG = o3d.pipelines.registration
YAW_STEP_DEG = 1.0  # the global search's yaw grid
HORIZONTAL_NORMAL_Z = 0.8  # a surface whose normal has |z| at least this is horizontal (floor, ceiling, table)
_CANDIDATES = 24  # distinct candidates of a global search (checked against the views when they are given)
_ICP_CANDIDATES = 8  # of those, the best this many are refined by ICP
_START_CONFLICT_FACTOR = 4.0  # a start may contradict the views this many times join_max_conflict
_DISTINCT_YAW_DEG = 10.0
_DISTINCT_TRANSLATION_M = 0.3


@dataclass(frozen=True)
class Registration:
    """The outcome of one registration of a submap (or a frame) to the map."""

    T_map_odom: np.ndarray  # (4, 4) the transform found (even when not accepted)
    fitness: float  # share of submap points on the map's surface after registration
    rmse_m: float  # RMS plane distance of those points
    runner_up_fitness: float  # the best distinct other alignment's fitness (0: none)
    constraint: float  # weakest/strongest eigenvalue of the information matrix (min of both blocks)
    method: str  # "icp" (from a guess) or "global"
    accepted: bool
    reason: str  # why it was not accepted ("" when it was)
    source_points: int
    target_points: int

    def correction_from(self, T_map_odom: np.ndarray) -> tuple[float, float]:
        """(metres, degrees) between this transform and ``T_map_odom``, measured on the robot's
        odometry origin and heading."""
        return pose_difference(T_map_odom, self.T_map_odom)


def pose_difference(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
    """Translation (m) and rotation angle (degrees) of ``inv(T_a) @ T_b``."""
    delta = np.linalg.solve(np.asarray(T_a, np.float64), np.asarray(T_b, np.float64))
    cos = (np.trace(delta[:3, :3]) - 1.0) / 2.0
    return float(np.linalg.norm(delta[:3, 3])), float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def depth_points(depth_m: np.ndarray, intrinsics: CameraIntrinsics, T_world_cam: np.ndarray, *,
                 stride_px: int = 1, depth_max_m: float = 6.0) -> np.ndarray:
    """The valid pixels of a depth image (metres, ``intrinsics`` of its size; every
    ``stride_px``-th row and column) as (N, 3) float64 points in the frame of ``T_world_cam``."""
    T = np.asarray(T_world_cam, np.float64)
    depth = np.asarray(depth_m)[::stride_px, ::stride_px]
    K = intrinsics
    v, u = np.mgrid[0:depth_m.shape[0]:stride_px, 0:depth_m.shape[1]:stride_px]
    valid = (depth > 0) & (depth <= depth_max_m) & np.isfinite(depth)
    z = depth[valid].astype(np.float64)
    x = (u[valid] - K.cx) / K.fx * z
    y = (v[valid] - K.cy) / K.fy * z
    return np.c_[x, y, z] @ T[:3, :3].T + T[:3, 3]


def backproject_depth(frame: Frame, T_world_cam: np.ndarray | None = None, *, stride_px: int = 4,
                      depth_max_m: float = 6.0) -> np.ndarray:
    """The frame's valid depth pixels (every ``stride_px``-th row and column) as (N, 3) float64
    points in the frame of ``T_world_cam`` (default: the frame's own pose)."""
    T = frame.T_world_cam if T_world_cam is None else T_world_cam
    return depth_points(frame.depth_m(), frame.intrinsics, T, stride_px=stride_px, depth_max_m=depth_max_m)


def thin(points: np.ndarray, cell_m: float) -> np.ndarray:
    """One point (the mean) per ``cell_m`` cell (Open3D's voxel down-sampling)."""
    if len(points) == 0:
        return np.zeros((0, 3), np.float64)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))
    return np.asarray(cloud.voxel_down_sample(cell_m).points)


class Submap:
    """A robot's last ``window_frames`` frames as points in its own odometry frame, thinned to one
    per ``cell_m`` cell. A window, not everything since the start: a robot that started in a room
    the map has not seen joins once its recent frames are in mapped space (its first frames would
    only lower the fit), and memory stays bounded however long it is held."""

    def __init__(self, cell_m: float, *, window_frames: int = 40, stride_px: int = 4) -> None:
        self.cell_m = cell_m
        self.stride_px = stride_px
        self.num_frames = 0  # every frame added since the last clear
        self._window: collections.deque[tuple[Frame, np.ndarray]] = collections.deque(maxlen=window_frames)
        self._points: np.ndarray | None = None

    @property
    def points(self) -> np.ndarray:
        """The window's points, thinned (computed once per change)."""
        if self._points is None:
            parts = [pts for _frame, pts in self._window]
            self._points = thin(np.concatenate(parts), self.cell_m) if parts else np.zeros((0, 3), np.float64)
        return self._points

    @property
    def frames(self) -> list[Frame]:
        """The frames in the window, oldest first."""
        return [frame for frame, _pts in self._window]

    def __len__(self) -> int:
        return len(self.points)

    def add(self, frame: Frame) -> None:
        """Add one frame at its own (odometry) pose."""
        self._window.append((frame, thin(backproject_depth(frame, stride_px=self.stride_px), self.cell_m)))
        self._points = None
        self.num_frames += 1

    def clear(self) -> None:
        self.num_frames = 0
        self._window.clear()
        self._points = None


# ------------------------------------------------------------------ building blocks
def _cloud(points: np.ndarray, cell_m: float) -> o3d.geometry.PointCloud:
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))
    cloud = cloud.voxel_down_sample(cell_m)
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2.0 * cell_m, max_nn=30))
    return cloud


def _yaw(deg: float) -> np.ndarray:
    a = np.deg2rad(deg)
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def _structure(cloud: o3d.geometry.PointCloud) -> np.ndarray:
    """The points of ``cloud`` on surfaces that are not horizontal (walls, furniture sides): what
    tells places apart from above. Floors, ceilings and table tops fit almost any alignment."""
    normals = np.asarray(cloud.normals)
    return np.asarray(cloud.points)[np.abs(normals[:, 2]) < HORIZONTAL_NORMAL_Z]


def _occupancy(points_xy: np.ndarray, origin_xy: np.ndarray, shape: tuple[int, int], cell_m: float) -> np.ndarray:
    grid = np.zeros(shape, np.float32)
    ij = np.floor((points_xy - origin_xy) / cell_m).astype(np.int64)
    inside = (ij >= 0).all(axis=1) & (ij[:, 0] < shape[0]) & (ij[:, 1] < shape[1])
    grid[ij[inside, 0], ij[inside, 1]] = 1.0
    return grid


def _z_offset(source: o3d.geometry.PointCloud, target: o3d.geometry.PointCloud, cell_m: float) -> float:
    """The height shift that best lays the source's horizontal surfaces (floor, table tops) on the
    target's: 1-D correlation of their height histograms."""
    heights = []
    for cloud in (source, target):
        flat = np.abs(np.asarray(cloud.normals)[:, 2]) >= HORIZONTAL_NORMAL_Z
        heights.append(np.asarray(cloud.points)[flat, 2])
    if min(len(h) for h in heights) == 0:
        return 0.0
    lo = min(h.min() for h in heights)
    hi = max(h.max() for h in heights)
    bins = np.arange(lo - cell_m, hi + 2 * cell_m, cell_m)
    h_src = np.histogram(heights[0], bins)[0].astype(np.float64)
    h_tgt = np.histogram(heights[1], bins)[0].astype(np.float64)
    corr = np.correlate(h_tgt, h_src, mode="full")
    return float((int(np.argmax(corr)) - (len(h_src) - 1)) * cell_m)


def _search(source: o3d.geometry.PointCloud, target: o3d.geometry.PointCloud,
            cell_m: float) -> list[tuple[float, np.ndarray]]:
    """Correlative search (module docstring): for every yaw on the grid, the floor-plane shift that
    lays most of the source's structure cells on the target's, by FFT correlation; returns
    (share of source cells on target cells, T_target_source), best first."""
    src = _structure(source)
    tgt = _structure(target)
    if len(src) == 0 or len(tgt) == 0:
        return []
    origin = tgt[:, :2].min(axis=0) - cell_m
    shape = tuple(int(n) for n in np.ceil((tgt[:, :2].max(axis=0) + cell_m - origin) / cell_m)) + (0,)
    target_grid = binary_dilation(_occupancy(tgt[:, :2], origin, shape[:2], cell_m)).astype(np.float32)
    centre = src.mean(axis=0)
    # scipy.signal is imported here, not at the top: it pulls in scipy.stats (0.6 s), and every
    # geometry process imports this module at start while few ever search without a guess.
    from scipy.signal import fftconvolve

    dz = _z_offset(source, target, cell_m)
    found = []
    for yaw in np.arange(0.0, 360.0, YAW_STEP_DEG):
        R = _yaw(yaw)
        turned = (src[:, :2] - centre[:2]) @ R[:2, :2].T
        lo = turned.min(axis=0)
        size = tuple(int(n) + 1 for n in np.ceil((turned.max(axis=0) - lo) / cell_m))
        source_grid = _occupancy(turned, lo, size, cell_m)
        # Every placement with any overlap ("full"): the submap may reach past the map's extent.
        score = fftconvolve(target_grid, source_grid[::-1, ::-1], mode="full")
        i, j = np.unravel_index(int(np.argmax(score)), score.shape)
        share = float(score[i, j]) / float(source_grid.sum())
        # Source cell 0 (at lo) lands on target cell (i - size[0] + 1, j - size[1] + 1).
        placed = np.array([i - size[0] + 1, j - size[1] + 1])
        shift_xy = origin + placed * cell_m - lo - R[:2, :2] @ centre[:2]
        found.append((share, _pose(R, np.array([shift_xy[0], shift_xy[1], dz]))))
    found.sort(key=lambda item: -item[0])
    return found


def _distinct(T: np.ndarray, others: list[np.ndarray]) -> bool:
    for other in others:
        metres, degrees = pose_difference(other, T)
        if metres < _DISTINCT_TRANSLATION_M and degrees < _DISTINCT_YAW_DEG:
            return False
    return True


def _icp(source: o3d.geometry.PointCloud, target: o3d.geometry.PointCloud, T_guess: np.ndarray,
         cell_m: float, *, scales: tuple[float, ...]) -> np.ndarray:
    """Point-to-plane ICP at correspondence distances of ``scales`` cells, coarse to fine."""
    T = np.asarray(T_guess, np.float64)
    for cells in scales:
        T = _REG.registration_icp(
            source, target, cells * cell_m, T, _REG.TransformationEstimationPointToPlane(),
            _REG.ICPConvergenceCriteria(max_iteration=20)).transformation
    return np.asarray(T)


@dataclass(frozen=True)
class _Fit:
    fitness: float
    rmse_m: float
    constraint: float


def _fit(source: np.ndarray, source_normals: np.ndarray, target: np.ndarray, target_normals: np.ndarray,
         tree: cKDTree, T: np.ndarray, params: JoinParams) -> _Fit:
    """How well ``source`` moved by ``T`` lies on the target surface (module docstring, rules 1, 2, 4).
    Fitness counts the source's structure points (not horizontal): a floor fits any alignment
    that levels it."""
    moved = source @ T[:3, :3].T + T[:3, 3]
    distance, index = tree.query(moved, k=1, distance_upper_bound=2.0 * params.join_voxel_m)
    near = np.isfinite(distance)
    plane = np.full(len(source), np.inf)
    plane[near] = np.abs(np.einsum("ij,ij->i", moved[near] - target[index[near]], target_normals[index[near]]))
    on = plane <= params.join_fit_distance_m
    structure = np.abs(source_normals[:, 2]) < HORIZONTAL_NORMAL_Z
    fitness = float((on & structure).sum()) / max(int(structure.sum()), 1)
    if not on.any():
        return _Fit(fitness, float("inf"), 0.0)
    rmse = float(np.sqrt(np.mean(plane[on] ** 2)))
    p, n = moved[on], target_normals[index[on]]
    J = np.c_[np.cross(p - p.mean(axis=0), n), n]
    H = J.T @ J
    ratios = []
    for block in (H[:3, :3], H[3:, 3:]):
        eig = np.linalg.eigvalsh(block)
        ratios.append(float(eig[0] / eig[-1]) if eig[-1] > 0 else 0.0)
    return _Fit(fitness, rmse, min(ratios))


def _decide(fit: _Fit, runner_up: float, params: JoinParams) -> str:
    """Why a registration is refused ("" when it is accepted), rules 1-4 of the module docstring."""
    if fit.fitness < params.join_min_fitness:
        return f"fitness {fit.fitness:.2f} < {params.join_min_fitness:.2f} (too little of the submap is on the map)"
    if fit.rmse_m > params.join_max_rmse_m:
        return f"rmse {fit.rmse_m * 100:.1f} cm > {params.join_max_rmse_m * 100:.1f} cm"
    if runner_up > params.join_max_ambiguity * fit.fitness:
        return (f"ambiguous: another alignment fits {runner_up:.2f} against {fit.fitness:.2f} "
                f"(> {params.join_max_ambiguity:.2f} of it)")
    if fit.constraint < params.join_min_constraint:
        return (f"under-constrained: the weakest direction holds {fit.constraint:.3f} of the strongest "
                f"(< {params.join_min_constraint:.3f}; a corridor or a bare wall)")
    return ""


# ------------------------------------------------------------------ registration
def view_conflict(frames: Sequence[Frame], T_map_odom: np.ndarray,
                  render_depth: Callable[[np.ndarray, CameraIntrinsics], np.ndarray], *,
                  tolerance_m: float, downscale: int = 4) -> float:
    """The share of pixels, over ``frames`` seen through ``T_map_odom``, where the map has a
    surface clearly in front of what the robot saw (``render_depth`` of the map at the frame's map
    pose is shorter than the observed depth by more than ``tolerance_m``): the robot looked through
    where the map says a wall is. Aligned, that does not happen (a static scene); misaligned, it
    does wherever a wall of the map falls into the robot's free space. Pixels where either depth is
    missing, or where the robot sees something nearer than the map (a new object, or a part of the
    map not seen yet), count for neither side. 0.0 when no pixel is comparable."""
    conflicts = compared = 0
    for frame in frames:
        K = frame.intrinsics
        small = K.scaled(max(1, K.width_px // downscale), max(1, K.height_px // downscale))
        observed = resize_nearest(frame.depth_m(), (small.height_px, small.width_px))
        rendered = render_depth(np.asarray(T_map_odom, np.float64) @ np.asarray(frame.T_world_cam, np.float64), small)
        both = (observed > 0) & np.isfinite(observed) & (rendered > 0) & np.isfinite(rendered)
        both &= ~_depth_edges(observed, tolerance_m)  # a pixel off at an outline is resolution, not misalignment
        compared += int(both.sum())
        conflicts += int((both & (rendered < observed - tolerance_m)).sum())
    return conflicts / compared if compared else 0.0


def _depth_edges(depth_m: np.ndarray, step_m: float) -> np.ndarray:
    """Pixels next to a depth step larger than ``step_m`` (or a missing depth) in their 3x3 block."""
    valid = (depth_m > 0) & np.isfinite(depth_m)
    filled = np.where(valid, depth_m, np.nan)
    padded = np.pad(filled, 1, mode="edge")
    h, w = depth_m.shape
    blocks = np.stack([padded[dy:dy + h, dx:dx + w] for dy in range(3) for dx in range(3)])
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN blocks: no depth around, masked anyway
        spread = np.nanmax(blocks, axis=0) - np.nanmin(blocks, axis=0)
    return ~(np.isfinite(spread) & (spread <= step_m)) | ~np.all(np.isfinite(blocks), axis=0)


def register_submap(submap_points: np.ndarray, map_points: np.ndarray, params: JoinParams, *,
                    guess: np.ndarray | None = None, extra_starts: Sequence[np.ndarray] = (),
                    conflict: Callable[[np.ndarray], float] | None = None) -> Registration:
    """Register a submap (points in the robot's odometry frame) to the map's surface points.

    ``guess``: ``T_map_odom`` to start ICP from (method ``icp``); None searches globally (method
    ``global``, gravity-aligned frames), with ``extra_starts`` as more candidates (each competes
    with the search's: the ambiguity rule holds for all). ``conflict``: the share of the submap's
    views that a candidate contradicts (:func:`view_conflict`); a candidate over
    ``join_max_conflict`` is out (rule 5) before the best and its runner-up are chosen. The result
    says whether it is accepted and why not."""
    if guess is not None:
        guess = check_pose(guess, what="guess (T_map_odom)")
    cell = params.join_voxel_m
    source = _cloud(submap_points, cell)
    target = _cloud(map_points, cell)
    n_src, n_tgt = len(source.points), len(target.points)
    method = "icp" if guess is not None else "global"
    if n_src < params.join_min_submap_points or n_tgt < params.join_min_submap_points:
        reason = (f"too few points to register (submap {n_src}, map {n_tgt}; at least "
                  f"{params.join_min_submap_points} each)")
        T = np.eye(4) if guess is None else np.asarray(guess, np.float64)
        return Registration(T, 0.0, float("inf"), 0.0, 0.0, method, False, reason, n_src, n_tgt)
    # Fine clouds (half a cell) for the last ICP step and the fit.
    fine_source = _cloud(submap_points, cell / 2.0)
    fine_target = _cloud(map_points, cell / 2.0)
    src_pts, src_normals = np.asarray(fine_source.points), np.asarray(fine_source.normals)
    tgt_pts, tgt_normals = np.asarray(fine_target.points), np.asarray(fine_target.normals)
    tree = cKDTree(tgt_pts)
    if guess is not None:
        starts = [np.asarray(guess, np.float64)]
    else:
        starts = _global_candidates(source, target, params) + [check_pose(T, what="start") for T in extra_starts]
        if conflict is not None:
            # Views first (a few small renders each): a start that contradicts them by far is out
            # before it costs an ICP. Loose, as a start is still centimetres off.
            starts = [T for T in starts if conflict(T) <= _START_CONFLICT_FACTOR * params.join_max_conflict]
            if not starts:
                reason = "every alignment the search found contradicts the robot's views"
                return Registration(np.eye(4), 0.0, float("inf"), 0.0, 0.0, method, False, reason, n_src, n_tgt)
    coarse: list[tuple[float, np.ndarray]] = []
    for start in starts[:_ICP_CANDIDATES]:
        T = _icp(source, target, start, cell, scales=(3.0, 1.5))
        if _distinct(T, [other for _, other in coarse]):
            coarse.append((_fit(src_pts, src_normals, tgt_pts, tgt_normals, tree, T, params).fitness, T))
    coarse.sort(key=lambda item: -item[0])
    refused: list[tuple[float, float]] = []  # (fitness, conflict) of candidates rule 5 took out
    fits: list[tuple[_Fit, np.ndarray]] = []
    for fitness, T in coarse:
        if len(fits) == 2:  # the answer and its runner-up
            break
        T = _icp(fine_source, fine_target, T, cell / 2.0, scales=(1.5,))
        if not _distinct(T, [other for _, other in fits]):
            continue
        if conflict is not None:
            share = conflict(T)
            if share > params.join_max_conflict:
                refused.append((fitness, share))
                continue
        fits.append((_fit(src_pts, src_normals, tgt_pts, tgt_normals, tree, T, params), T))
    if not fits:
        fitness, share = refused[0] if refused else (0.0, 0.0)
        reason = (f"every alignment contradicts the robot's views (the best fitting one, {fitness:.2f}, has the "
                  f"map's surface in front of {share:.0%} of what it saw)")
        T = starts[0] if starts else np.eye(4)
        return Registration(T, 0.0, float("inf"), 0.0, 0.0, method, False, reason, n_src, n_tgt)
    fits.sort(key=lambda item: -item[0].fitness)
    best, T_best = fits[0]
    runner_up = fits[1][0].fitness if len(fits) > 1 else 0.0
    reason = _decide(best, runner_up, params)
    return Registration(T_best, best.fitness, best.rmse_m, runner_up, best.constraint, method, not reason, reason,
                        n_src, n_tgt)


def _global_candidates(source: o3d.geometry.PointCloud, target: o3d.geometry.PointCloud,
                       params: JoinParams) -> list[np.ndarray]:
    """Distinct starting transforms of the correlative search (module docstring), best first."""
    starts: list[np.ndarray] = []
    for _share, T in _search(source, target, params.join_voxel_m):
        if _distinct(T, starts):
            starts.append(T)
        if len(starts) == _CANDIDATES:
            break
    return starts


def recheck(frame_points: np.ndarray, map_points: np.ndarray, T_map_odom: np.ndarray,
            params: JoinParams) -> Registration:
    """Register one frame's points (odometry frame) to the map's surface in view, from the
    transform in use (a joined robot's periodic re-check)."""
    return register_submap(frame_points, map_points, params, guess=T_map_odom)
