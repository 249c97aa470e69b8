"""Canonical frame and camera types shared by sources, the map core, encoders and services.

Conventions (docs/ARCHITECTURE.md, "Conventions"): metres; right-handed; OpenCV camera axes
(x right, y down, z forward); ``T_world_cam`` is a 4x4 row-major camera-to-world pose.
Color and depth of a frame are registered and have the same size (readers resize color to
the depth camera).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from openfusion.poses import check_pose


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics in pixels for an image of ``width_px`` x ``height_px``."""

    width_px: int
    height_px: int
    fx: float
    fy: float
    cx: float
    cy: float

    def __post_init__(self) -> None:
        if self.width_px <= 0 or self.height_px <= 0:
            raise ValueError(f"image size must be positive, got {self.width_px}x{self.height_px}")
        if not (np.isfinite([self.fx, self.fy, self.cx, self.cy]).all() and self.fx > 0 and self.fy > 0):
            raise ValueError(f"focal lengths must be finite and positive, got fx={self.fx} fy={self.fy}")

    @property
    def K(self) -> np.ndarray:
        """3x3 float64 camera matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @classmethod
    def from_matrix(cls, K: np.ndarray, width_px: int, height_px: int) -> CameraIntrinsics:
        K = np.asarray(K, dtype=np.float64)
        return cls(int(width_px), int(height_px), float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))

    def scaled(self, width_px: int, height_px: int) -> CameraIntrinsics:
        """Intrinsics of the same camera resampled to ``width_px`` x ``height_px``.

        Uses the pixel-centre convention: a pixel centre u maps to (u + 0.5) * s - 0.5.
        """
        sx = width_px / self.width_px
        sy = height_px / self.height_px
        return CameraIntrinsics(
            int(width_px),
            int(height_px),
            self.fx * sx,
            self.fy * sy,
            (self.cx + 0.5) * sx - 0.5,
            (self.cy + 0.5) * sy - 0.5,
        )


@dataclass
class Frame:
    """One registered RGB-D observation with its camera-to-world pose.

    ``depth`` is either uint16 raw units with ``depth_scale`` units per metre (ScanNet 1000,
    TUM 5000, Replica 6553.5) or float32 metres with ``depth_scale == 1.0``; 0 (or NaN) = no
    measurement. Ground truth is optional: ``instance`` is an int32 HxW image with 0 = no
    instance, and ``instance_categories`` maps instance id -> raw category name
    (e.g. "office chair").
    """

    frame_id: int
    stamp_ns: int
    color: np.ndarray  # HxWx3 uint8 RGB
    depth: np.ndarray  # HxW uint16 (raw) or float32 (metres)
    depth_scale: float
    intrinsics: CameraIntrinsics
    T_world_cam: np.ndarray  # 4x4 float64 camera-to-world
    instance: np.ndarray | None = None
    instance_categories: dict[int, str] = field(default_factory=dict)
    source: str = ""

    def depth_m(self, size_hw: tuple[int, int] | None = None) -> np.ndarray:
        """Depth as float32 metres (0 where there is no measurement); at ``size_hw`` (height,
        width): :func:`resize_nearest` of it, converting only the pixels kept (frame selection reads
        a 64x48 sample of a 640x480 frame)."""
        depth = self.depth if size_hw is None else resize_nearest(self.depth, size_hw)
        if depth.dtype == np.float32 and self.depth_scale == 1.0:
            d = depth
        else:
            d = depth.astype(np.float32) / np.float32(self.depth_scale)
        return np.nan_to_num(d, nan=0.0, posinf=0.0, neginf=0.0)

    def validate(self) -> None:
        """Raise ValueError naming the first inconsistency (sizes, dtypes, pose)."""
        h, w = self.depth.shape[:2] if self.depth.ndim == 2 else (-1, -1)
        if self.depth.ndim != 2 or self.depth.dtype not in (np.uint16, np.float32):
            raise ValueError(f"depth must be HxW uint16 or float32, got {self.depth.dtype} {self.depth.shape}")
        if self.color.shape != (h, w, 3) or self.color.dtype != np.uint8:
            raise ValueError(f"color must be {h}x{w}x3 uint8, got {self.color.dtype} {self.color.shape}")
        if (self.intrinsics.width_px, self.intrinsics.height_px) != (w, h):
            raise ValueError(
                f"intrinsics are for {self.intrinsics.width_px}x{self.intrinsics.height_px}, depth is {w}x{h}"
            )
        if not (self.depth_scale > 0 and np.isfinite(self.depth_scale)):
            raise ValueError(f"depth_scale must be positive, got {self.depth_scale}")
        check_pose(self.T_world_cam)
        if self.instance is not None and (self.instance.shape != (h, w) or self.instance.dtype != np.int32):
            raise ValueError(f"instance must be {h}x{w} int32, got {self.instance.dtype} {self.instance.shape}")


def resize_nearest(image: np.ndarray, size_hw: tuple[int, int]) -> np.ndarray:
    """Nearest-neighbour resize of the first two axes to ``size_hw = (height, width)``, with the
    pixel-centre convention of :meth:`CameraIntrinsics.scaled` (labels are never blended). The
    one resize helper of the package (readers, encoders, the volume, services)."""
    H, W = image.shape[:2]
    h, w = size_hw
    if (H, W) == (h, w):
        return image
    rows = np.minimum(((np.arange(h) + 0.5) * (H / h)).astype(np.int64), H - 1)
    cols = np.minimum(((np.arange(w) + 0.5) * (W / w)).astype(np.int64), W - 1)
    return image[rows[:, None], cols[None, :]]
