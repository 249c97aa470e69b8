"""The synthetic world's camera: intrinsics, per-pixel rays and the walk around the room.

``default_intrinsics`` is a ScanNet/Kinect-like depth camera; ``_pixel_rays`` gives the
camera-frame ray directions of every pixel (cached per intrinsics) for the ray caster;
``camera_path`` is the smooth elliptic trajectory (camera-to-world poses, OpenCV axes) that
``SyntheticSource`` renders along: a closed lap of :data:`LAP_FRAMES` frames unless told otherwise,
walked again and again for longer paths (pose ``i`` is pose ``i mod lap``).
"""

from __future__ import annotations

import math

import numpy as np

from openfusion.frame import CameraIntrinsics
from openfusion.poses import look_at

#: Frames of one lap of the room when no lap is given (about 0.8 m/s at 30 fps).
LAP_FRAMES = 360

_RAY_CACHE: dict[CameraIntrinsics, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}


def _pixel_rays(intrinsics: CameraIntrinsics) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Camera-frame ray directions ``(ux, uy, 1)`` per pixel (z = 1, so t_hit is the z depth):
    contiguous (h, w) float32 ``ux``, ``uy`` and the inverse ray lengths (rotation keeps
    lengths, so they hold in the world too)."""
    cached = _RAY_CACHE.get(intrinsics)
    if cached is None:
        u = (np.arange(intrinsics.width_px, dtype=np.float64) - intrinsics.cx) / intrinsics.fx
        v = (np.arange(intrinsics.height_px, dtype=np.float64) - intrinsics.cy) / intrinsics.fy
        uu, vv = np.meshgrid(u, v)
        inv_len = 1.0 / np.sqrt(uu * uu + vv * vv + 1.0)
        cached = (uu.astype(np.float32), vv.astype(np.float32), inv_len.astype(np.float32))
        if len(_RAY_CACHE) > 8:
            _RAY_CACHE.clear()
        _RAY_CACHE[intrinsics] = cached
    return cached


def default_intrinsics(width_px: int = 640, height_px: int = 480) -> CameraIntrinsics:
    """A ScanNet/Kinect-like depth camera (fx = fy = 577.5 px at 640 wide), principal point centred."""
    f = 577.5 * width_px / 640.0
    return CameraIntrinsics(width_px, height_px, f, f, (width_px - 1) / 2.0, (height_px - 1) / 2.0)


def camera_path(
    room_size_m: tuple[float, float, float], seed: int, num_frames: int, *, frames_per_lap: int | None = None
) -> np.ndarray:
    """(num_frames, 4, 4) smooth camera-to-world poses: an elliptic walk around the room's
    middle at about 1.45 m, always looking across the room at the furniture.

    Position and look-at target are sums of sinusoids in the frame index, so both the
    path and the orientation are smooth; ``frames_per_lap`` (default :data:`LAP_FRAMES`) is the
    number of frames of one lap. A path longer than a lap walks the same lap again: pose ``i``
    equals pose ``i mod frames_per_lap`` exactly.
    """
    W, D, _ = room_size_m
    lap = frames_per_lap if frames_per_lap is not None else LAP_FRAMES
    if lap < 2:
        raise ValueError(f"frames_per_lap must be >= 2, got {lap}")
    phase0 = (seed % 97) / 97.0 * 2 * math.pi
    ax, ay = max(W / 2 - 1.2, 0.4), max(D / 2 - 1.2, 0.4)
    poses = np.empty((num_frames, 4, 4))
    for i in range(num_frames):
        if i >= lap:  # the next lap: the very same poses
            poses[i] = poses[i % lap]
            continue
        th = phase0 + 2 * math.pi * i / lap
        pos = np.array([W / 2 + ax * math.cos(th), D / 2 + ay * math.sin(th), 1.45 + 0.08 * math.sin(3 * th)])
        sweep = th + math.pi + 0.5 * math.sin(2 * th)
        target = np.array(
            [W / 2 + 0.9 * ax * math.cos(sweep), D / 2 + 0.9 * ay * math.sin(sweep), 0.75 + 0.2 * math.sin(2 * th + 1.0)]
        )
        poses[i] = look_at(pos, target)
    return poses
