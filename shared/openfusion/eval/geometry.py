"""Geometry metrics: accuracy and completeness of a reconstruction against a ground-truth surface.

- accuracy: mean distance from each reconstructed point to its nearest ground-truth point
  (metres, and in voxels). Also the median and the 90th percentile.
- completeness: share of *observed* ground-truth points that have a reconstructed point within
  ``completeness_voxels`` voxels (default 2).

"Observed" ground-truth points are those seen by at least one frame: :class:`ObservedSurface`
projects every ground-truth point into each frame and keeps it when it falls inside the image,
within the depth range, and within ``depth_tolerance_m`` of the measured depth at that pixel
(a depth test, so occluded points are not counted). Completeness therefore measures the
fusion, not the camera path.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass

import numpy as np
from scipy.spatial import cKDTree

from openfusion.frame import CameraIntrinsics
from openfusion.poses import check_pose

logger = logging.getLogger(__name__)


def _as_points(points: np.ndarray, what: str) -> np.ndarray:
    p = np.asarray(points)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"{what} must be an (N, 3) array, got shape {p.shape}")
    if not np.isfinite(p).all():
        raise ValueError(f"{what} contains NaN or inf")
    return p.astype(np.float64, copy=False)


def nearest_distances(
    query_points: np.ndarray, reference_points: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Distance (m) and index of the nearest reference point for every query point."""
    q = _as_points(query_points, "query points")
    r = _as_points(reference_points, "reference points")
    if len(r) == 0:
        raise ValueError("reference point set is empty")
    if len(q) == 0:
        return np.zeros(0), np.zeros(0, dtype=np.int64)
    dist, idx = cKDTree(r).query(q, k=1, workers=-1)
    return np.asarray(dist, dtype=np.float64), np.asarray(idx, dtype=np.int64)


def mesh_distances(points: np.ndarray, vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Exact distance (m) from each point to a triangle mesh (Open3D RaycastingScene)."""
    import open3d as o3d  # local: only this function needs it

    q = _as_points(points, "query points")
    v = np.ascontiguousarray(vertices, dtype=np.float32)
    t = np.ascontiguousarray(triangles, dtype=np.uint32)
    if v.ndim != 2 or v.shape[1] != 3 or t.ndim != 2 or t.shape[1] != 3 or len(t) == 0:
        raise ValueError(f"mesh must be (V, 3) vertices and (T>0, 3) triangles, got {v.shape}, {t.shape}")
    if t.max() >= len(v):
        raise ValueError("mesh triangle indices out of range")
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor.from_numpy(v), o3d.core.Tensor.from_numpy(t))
    if len(q) == 0:
        return np.zeros(0)
    d = scene.compute_distance(o3d.core.Tensor.from_numpy(np.ascontiguousarray(q, dtype=np.float32)))
    return d.numpy().astype(np.float64)


class ObservedSurface:
    """Tracks which ground-truth points at least one frame has seen (projection + depth test).

    Feed it every integrated frame with :meth:`add_view`; read :attr:`mask`.
    """

    def __init__(
        self,
        gt_points: np.ndarray,
        *,
        depth_tolerance_m: float,
        depth_min_m: float = 0.1,
        depth_max_m: float = 6.0,
    ) -> None:
        if not depth_tolerance_m > 0:
            raise ValueError(f"depth_tolerance_m must be positive, got {depth_tolerance_m}")
        if not 0 <= depth_min_m < depth_max_m:
            raise ValueError(f"need 0 <= depth_min_m < depth_max_m, got {depth_min_m}, {depth_max_m}")
        self._points = _as_points(gt_points, "ground-truth points")
        self.depth_tolerance_m = float(depth_tolerance_m)
        self.depth_min_m = float(depth_min_m)
        self.depth_max_m = float(depth_max_m)
        self.mask = np.zeros(len(self._points), dtype=bool)
        self.num_views = 0

    def add_view(self, depth_m: np.ndarray, intrinsics: CameraIntrinsics, T_world_cam: np.ndarray) -> int:
        """Mark the points this view sees; returns how many it sees (new or not)."""
        depth = np.asarray(depth_m, dtype=np.float32)
        if depth.shape != (intrinsics.height_px, intrinsics.width_px):
            raise ValueError(
                f"depth is {depth.shape[1]}x{depth.shape[0]}, intrinsics are for "
                f"{intrinsics.width_px}x{intrinsics.height_px}"
            )
        T = check_pose(T_world_cam)
        R, t = T[:3, :3], T[:3, 3]
        p_cam = (self._points - t) @ R  # = R^T (p - t), row vectors
        z = p_cam[:, 2]
        valid = (z > self.depth_min_m) & (z < self.depth_max_m)
        idx = np.flatnonzero(valid)
        zs = z[idx]
        u = np.rint(intrinsics.fx * p_cam[idx, 0] / zs + intrinsics.cx).astype(np.int64)
        v = np.rint(intrinsics.fy * p_cam[idx, 1] / zs + intrinsics.cy).astype(np.int64)
        inside = (u >= 0) & (u < intrinsics.width_px) & (v >= 0) & (v < intrinsics.height_px)
        idx, u, v, zs = idx[inside], u[inside], v[inside], zs[inside]
        d = depth[v, u]
        seen = np.isfinite(d) & (d > 0) & (np.abs(zs - d) <= self.depth_tolerance_m)
        self.mask[idx[seen]] = True
        self.num_views += 1
        return int(seen.sum())


@dataclass(frozen=True)
class GeometryMetrics:
    """Accuracy (reconstruction -> GT) and completeness (observed GT -> reconstruction)."""

    accuracy_m: float
    accuracy_vox: float
    accuracy_median_m: float
    accuracy_p90_m: float
    completeness: float
    completeness_threshold_m: float
    num_reconstructed: int
    num_gt: int
    num_gt_observed: int
    voxel_size_m: float

    def to_dict(self) -> dict:
        return {
            k: (None if isinstance(v, float) and not np.isfinite(v) else v) for k, v in asdict(self).items()
        }


def geometry_metrics(
    reconstructed_points: np.ndarray,
    gt_points: np.ndarray,
    *,
    voxel_size_m: float,
    observed_mask: np.ndarray | None = None,
    completeness_voxels: float = 2.0,
    accuracy_distances_m: np.ndarray | None = None,
) -> GeometryMetrics:
    """Accuracy and completeness of ``reconstructed_points`` against ``gt_points``.

    ``observed_mask`` (bool per GT point, from :class:`ObservedSurface`) restricts completeness
    to observed GT points; ``None`` uses all GT points. ``accuracy_distances_m`` (one per
    reconstructed point, e.g. :func:`mesh_distances` to the GT mesh) replaces the default
    nearest-GT-point distance, which over-estimates by about half the GT sampling spacing.
    """
    if not voxel_size_m > 0:
        raise ValueError(f"voxel_size_m must be positive, got {voxel_size_m}")
    recon = _as_points(reconstructed_points, "reconstructed points")
    gt = _as_points(gt_points, "ground-truth points")
    if len(gt) == 0:
        raise ValueError("ground-truth point set is empty")
    if observed_mask is None:
        observed = np.ones(len(gt), dtype=bool)
    else:
        observed = np.asarray(observed_mask, dtype=bool)
        if observed.shape != (len(gt),):
            raise ValueError(
                f"observed_mask must have one entry per GT point ({len(gt)}), got {observed.shape}"
            )
    threshold_m = float(completeness_voxels) * float(voxel_size_m)
    if len(recon) == 0:
        logger.warning("reconstruction is empty: accuracy undefined, completeness 0")
        acc = med = p90 = float("nan")
        comp = 0.0
    else:
        if accuracy_distances_m is None:
            d_acc, _ = nearest_distances(recon, gt)
        else:
            d_acc = np.asarray(accuracy_distances_m, dtype=np.float64)
            if d_acc.shape != (len(recon),):
                raise ValueError(
                    f"accuracy_distances_m must have one entry per reconstructed point ({len(recon)}), "
                    f"got {d_acc.shape}"
                )
        acc, med, p90 = float(d_acc.mean()), float(np.median(d_acc)), float(np.percentile(d_acc, 90))
        obs_pts = gt[observed]
        if len(obs_pts) == 0:
            logger.warning("no ground-truth point is observed: completeness undefined")
            comp = float("nan")
        else:
            d_comp, _ = nearest_distances(obs_pts, recon)
            comp = float(np.mean(d_comp <= threshold_m))
    return GeometryMetrics(
        accuracy_m=acc,
        accuracy_vox=acc / voxel_size_m,
        accuracy_median_m=med,
        accuracy_p90_m=p90,
        completeness=comp,
        completeness_threshold_m=threshold_m,
        num_reconstructed=int(len(recon)),
        num_gt=int(len(gt)),
        num_gt_observed=int(observed.sum()),
        voxel_size_m=float(voxel_size_m),
    )
