"""Virtual cameras for pictures of a map: an overview from above and outside the map's box.

The overview camera sits on a ray from the centre of the map's bounding box, ``azimuth_deg``
around the up axis and ``elevation_deg`` above the horizontal, and looks at the map. Its
distance is the smallest at which the map's points (all but a few outliers) lie inside the image
(with ``margin``), and the look-at point is shifted so they sit in the middle: the map fills the
picture whatever its size or shape. Combined with back-face
culling in :mod:`openfusion.viz.render` this gives a "doll's house" view of a room scan: the
ceiling and the walls between the camera and the room are seen from behind and disappear.

Poses are camera-to-world ``T_world_cam`` with OpenCV axes (x right, y down, z forward).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from openfusion.frame import CameraIntrinsics
from openfusion.poses import look_at
from openfusion.viz.errors import VizError

UP_AXES: dict[str, tuple[float, float, float]] = {
    "+z": (0.0, 0.0, 1.0),
    "-z": (0.0, 0.0, -1.0),
    "+y": (0.0, 1.0, 0.0),
    "-y": (0.0, -1.0, 0.0),
    "+x": (1.0, 0.0, 0.0),
    "-x": (-1.0, 0.0, 0.0),
}
MIN_IMAGE_SIDE_PX = 16
MAX_IMAGE_SIDE_PX = 8192


@dataclass(frozen=True)
class VirtualCamera:
    """A pose and pinhole intrinsics to render from."""

    T_world_cam: np.ndarray
    intrinsics: CameraIntrinsics

    @property
    def position_m(self) -> np.ndarray:
        return self.T_world_cam[:3, 3].copy()


def check_image_size(width_px: int, height_px: int) -> None:
    """VizError unless both sides are integers in [16, 8192]."""
    for name, value in (("width", width_px), ("height", height_px)):
        if not isinstance(value, (int, np.integer)) or not MIN_IMAGE_SIDE_PX <= value <= MAX_IMAGE_SIDE_PX:
            raise VizError(
                f"image {name} must be an integer between {MIN_IMAGE_SIDE_PX} and {MAX_IMAGE_SIDE_PX} px, got {value!r}"
            )


def check_view_angles(*, azimuth_deg: float, elevation_deg: float, fov_deg: float) -> None:
    """VizError unless the overview camera can take these angles: a finite azimuth, an elevation
    in [-89, 89] and a horizontal field of view in [5, 150] degrees."""
    if not (math.isfinite(elevation_deg) and -89.0 <= elevation_deg <= 89.0):
        raise VizError(f"elevation must be between -89 and 89 degrees, got {elevation_deg}")
    if not math.isfinite(azimuth_deg):
        raise VizError(f"azimuth must be finite, got {azimuth_deg}")
    if not (math.isfinite(fov_deg) and 5.0 <= fov_deg <= 150.0):
        raise VizError(f"field of view must be between 5 and 150 degrees, got {fov_deg}")


def pinhole(width_px: int, height_px: int, *, fov_deg: float) -> CameraIntrinsics:
    """Square-pixel intrinsics with a horizontal field of view of ``fov_deg``, principal point at the
    image centre (pixel centres at integer coordinates)."""
    check_image_size(width_px, height_px)
    if not (math.isfinite(fov_deg) and 5.0 <= fov_deg <= 150.0):
        raise VizError(f"field of view must be between 5 and 150 degrees, got {fov_deg}")
    f = (width_px / 2.0) / math.tan(math.radians(fov_deg) / 2.0)
    return CameraIntrinsics(int(width_px), int(height_px), f, f, (width_px - 1) / 2.0, (height_px - 1) / 2.0)


def robust_bounds(points: np.ndarray, *, quantile: float = 0.002) -> tuple[np.ndarray, np.ndarray]:
    """(min, max) corners of ``points`` (N, 3), ignoring the ``quantile`` outermost on each side per axis."""
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    if len(pts) == 0:
        raise VizError("cannot frame an empty map: it has no surface")
    lo = np.quantile(pts, quantile, axis=0)
    hi = np.quantile(pts, 1.0 - quantile, axis=0)
    return lo, hi


def _basis(up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    helper = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    a = np.cross(up, helper)
    a /= np.linalg.norm(a)
    b = np.cross(up, a)
    return a, b


def _extent(T_world_cam: np.ndarray, intr: CameraIntrinsics, points: np.ndarray, quantile: float) -> np.ndarray | None:
    """[u_lo, u_hi, v_lo, v_hi] of the points' image coordinates relative to the principal point, as
    fractions of the half image size (inside the image: all within [-1, 1]), ignoring the ``quantile``
    outermost on each side; None when more than that fraction of points is behind the camera."""
    T_cam_world = np.linalg.inv(T_world_cam)
    pc = points @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
    front = pc[:, 2] > 1e-3
    if (~front).sum() > quantile * len(pc):
        return None
    pc = pc[front]
    u = intr.fx * pc[:, 0] / pc[:, 2] / (intr.width_px / 2.0)
    v = intr.fy * pc[:, 1] / pc[:, 2] / (intr.height_px / 2.0)
    return np.array(
        [np.quantile(u, quantile), np.quantile(u, 1 - quantile), np.quantile(v, quantile), np.quantile(v, 1 - quantile)]
    )


def _fits(T_world_cam: np.ndarray, intr: CameraIntrinsics, points: np.ndarray, margin: float, quantile: float) -> bool:
    ext = _extent(T_world_cam, intr, points, quantile)
    return ext is not None and bool(np.abs(ext).max() <= 1.0 / margin)


def overview_camera(
    points: np.ndarray,
    *,
    width_px: int = 1024,
    height_px: int = 768,
    up: str = "+z",
    azimuth_deg: float = 235.0,
    elevation_deg: float = 55.0,
    fov_deg: float = 45.0,
    margin: float = 1.05,
    outlier_quantile: float = 0.002,
    max_fit_points: int = 20_000,
) -> VirtualCamera:
    """A camera above and outside the bounding box of ``points`` looking at the map (module docstring).

    The distance is the smallest at which all but ``outlier_quantile`` of the points (on each side)
    fall inside the image with ``margin``; the view is then re-centred on them.
    """
    if up not in UP_AXES:
        raise VizError(f"unknown up axis {up!r}; use one of {', '.join(UP_AXES)}")
    check_view_angles(azimuth_deg=azimuth_deg, elevation_deg=elevation_deg, fov_deg=fov_deg)
    if not (math.isfinite(margin) and margin >= 1.0):
        raise VizError(f"margin must be >= 1, got {margin}")
    intr = pinhole(width_px, height_px, fov_deg=fov_deg)
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    lo, hi = robust_bounds(pts, quantile=outlier_quantile)
    if len(pts) > max_fit_points:
        # sorted first, so the same point set gives the same camera whatever order it came in
        pts = pts[np.lexsort(pts.T[::-1])]
        pts = pts[np.random.default_rng(0).choice(len(pts), size=max_fit_points, replace=False)]
    target = (lo + hi) / 2.0
    up_v = np.asarray(UP_AXES[up])
    a, b = _basis(up_v)
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    direction = math.cos(el) * (math.cos(az) * a + math.sin(az) * b) + math.sin(el) * up_v
    radius = max(float(np.linalg.norm(hi - lo)) / 2.0, 0.05)
    q = outlier_quantile

    def pose_at(centre: np.ndarray, distance: float) -> np.ndarray:
        return look_at(centre + direction * distance, centre, up=tuple(up_v))

    def fit_distance(centre: np.ndarray) -> float:
        near, far = radius * 0.05, radius * 2.0
        while not _fits(pose_at(centre, far), intr, pts, margin, q):
            far *= 2.0
            if far > radius * 1e4:  # a finite box always fits eventually; guard a degenerate one
                break
        for _ in range(40):
            mid = (near + far) / 2.0
            if _fits(pose_at(centre, mid), intr, pts, margin, q):
                far = mid
            else:
                near = mid
        return far

    distance = fit_distance(target)
    for _ in range(2):  # shift the look-at point so the points sit in the middle of the image
        T = pose_at(target, distance)
        ext = _extent(T, intr, pts, q)
        if ext is None:
            break
        du = (ext[0] + ext[1]) / 2.0 * (intr.width_px / 2.0) / intr.fx * distance
        dv = (ext[2] + ext[3]) / 2.0 * (intr.height_px / 2.0) / intr.fy * distance
        target = target + T[:3, 0] * du + T[:3, 1] * dv
        distance = fit_distance(target)
    return VirtualCamera(pose_at(target, distance), intr)
