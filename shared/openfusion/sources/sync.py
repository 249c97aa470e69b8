"""Pair camera images with poses from a separate tracker (Azure Kinect + Intel T265 and alike).

Pure logic, no drivers: the live source (``openfusion.sources.live``) and tests feed it
timestamped images and poses; it hands out canonical ``Frame`` objects.

Time
    Image and pose stamps may come from different clocks: ``t_image_clock = t_pose +
    clock_offset_ns``. The offset is configured, or estimated (``estimate_clock_offset=True``)
    from host receive times: for each stream the minimum of ``host_ns - device_ns`` over the
    samples seen is its clock offset plus its smallest latency (exposure/readout + transport),
    so the difference of the two minima is the offset between the device clocks, biased by the
    difference of the two minimum latencies. Known fixed latencies (``image_latency_ns``,
    ``pose_latency_ns``, e.g. half the exposure time plus USB transfer) are subtracted; what is
    left is the jitter floor, well under a millisecond with a few hundred samples.

Pairing
    ``mode="nearest"``: each image gets the pose nearest in time when one lies within
    ``max_dt_ns`` (10 ms default), else it is dropped (``no_pose_within_tolerance``).
    ``mode="interpolate"``: the pose at the image time is interpolated between the two poses
    around it (linear translation, SLERP rotation) unless they are more than ``max_pose_gap_ns``
    apart (``pose_gap``); an image with no pose after it by the time it is resolved is dropped
    as ``pose_timeout``, one before the oldest kept pose as ``outside_pose_range``. An image waits until a pose later than its time (+ ``max_dt_ns``
    in nearest mode) has arrived, so a pose arriving a little late still counts; it is resolved
    with what is there once ``max_wait_ns`` of newer images have piled up behind it.

Disorder
    Poses may arrive out of order within ``reorder_window_ns`` (inserted in order, counted as
    ``out_of_order``); older ones are rejected (``late``), as are duplicates. An image older
    than one already handed out is dropped (``out_of_order_image``).

Frames (what is converted)
    A T265 reports the pose of its body in its world, both with axes x right, y up, z back.
    ``T_world_cam = A_world @ T_t265world_t265body @ T_tracker_cam`` where ``T_tracker_cam`` is the
    camera-to-T265 extrinsic from config (the camera's pose in the T265 body frame, camera axes
    OpenCV). Its default is the pure axis change ``diag(1, -1, -1)``: camera at the T265,
    looking the same way. ``A_world`` turns the T265 world into a z-up world (x right,
    y forward, z up at the start pose) when ``world_axes="z_up"`` (default), identity for
    ``"t265"``. For a tracker that already reports OpenCV-axes camera poses set
    ``pose_axes="opencv"`` (then ``T_world_cam = T @ T_tracker_cam`` with an identity default);
    the ROS 2 source uses that form with the camera's pose in the odometry body frame.

Size
    Frames are downsampled to ``output_size=(width, height)`` (the paper runs at 640 x 360):
    color bilinear with antialiasing, depth nearest (never blends depths across edges),
    intrinsics scaled with the pixel-centre convention.
"""

from __future__ import annotations

import bisect
import logging
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from PIL import Image

from openfusion.frame import CameraIntrinsics, Frame, resize_nearest
from openfusion.poses import InvalidPoseError, check_pose, matrix_to_quat, quat_to_matrix, slerp

logger = logging.getLogger(__name__)

#: camera (OpenCV: x right, y down, z forward) -> T265 body (x right, y up, z back) rotation
T265_FROM_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])
#: T265 world (x right, y up, z back) -> z-up world (x right, y forward, z up)
ZUP_FROM_T265_WORLD = np.array(
    [[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
)


@dataclass(frozen=True)
class SyncConfig:
    """Pairing, clock, extrinsic and output-size settings (units in the names)."""

    mode: Literal["nearest", "interpolate"] = "nearest"
    max_dt_ns: int = 10_000_000
    max_pose_gap_ns: int = 100_000_000
    clock_offset_ns: int = 0
    estimate_clock_offset: bool = False
    min_offset_samples: int = 10
    image_latency_ns: int = 0
    pose_latency_ns: int = 0
    reorder_window_ns: int = 50_000_000
    pose_history_ns: int = 2_000_000_000
    max_wait_ns: int = 200_000_000
    T_tracker_cam: tuple[tuple[float, ...], ...] | None = None
    pose_axes: Literal["t265", "opencv"] = "t265"
    world_axes: Literal["z_up", "t265"] = "z_up"
    output_size: tuple[int, int] | None = (640, 360)

    def __post_init__(self) -> None:
        if self.mode not in ("nearest", "interpolate"):
            raise ValueError(f"mode must be 'nearest' or 'interpolate', got {self.mode!r}")
        if self.max_dt_ns <= 0 or self.max_pose_gap_ns <= 0 or self.max_wait_ns <= 0:
            raise ValueError("max_dt_ns, max_pose_gap_ns and max_wait_ns must be positive")
        if self.reorder_window_ns < 0 or self.pose_history_ns <= self.reorder_window_ns:
            raise ValueError("need 0 <= reorder_window_ns < pose_history_ns")
        if self.T_tracker_cam is not None:
            check_pose(self.T_tracker_cam, what="T_tracker_cam (the camera pose in the T265 frame)", rotation_atol=1e-6)
        if self.output_size is not None and (self.output_size[0] <= 0 or self.output_size[1] <= 0):
            raise ValueError(f"output_size must be (width, height) > 0, got {self.output_size}")

    def extrinsic(self) -> np.ndarray:
        if self.T_tracker_cam is not None:
            return np.asarray(self.T_tracker_cam, dtype=np.float64)
        return T265_FROM_OPENCV.copy() if self.pose_axes == "t265" else np.eye(4)

    def world_transform(self) -> np.ndarray:
        return ZUP_FROM_T265_WORLD.copy() if self.pose_axes == "t265" and self.world_axes == "z_up" else np.eye(4)


@dataclass
class SyncStats:
    """Counters: inputs, frames out, images dropped and poses rejected by reason."""

    images_in: int = 0
    poses_in: int = 0
    frames_out: int = 0
    images_dropped: dict[str, int] = field(default_factory=dict)
    poses_rejected: dict[str, int] = field(default_factory=dict)
    poses_out_of_order: int = 0
    clock_offset_ns: int | None = None

    def drop(self, reason: str) -> None:
        self.images_dropped[reason] = self.images_dropped.get(reason, 0) + 1

    def reject(self, reason: str) -> None:
        self.poses_rejected[reason] = self.poses_rejected.get(reason, 0) + 1


class ClockOffsetEstimator:
    """Minimum of ``host_ns - device_ns`` per stream; their difference is the clock offset."""

    def __init__(self) -> None:
        self._min: dict[str, int] = {}
        self._count: dict[str, int] = {}

    def add(self, stream: str, device_ns: int, host_ns: int) -> None:
        d = int(host_ns) - int(device_ns)
        self._min[stream] = min(self._min.get(stream, d), d)
        self._count[stream] = self._count.get(stream, 0) + 1

    def count(self, stream: str) -> int:
        return self._count.get(stream, 0)

    def offset_ns(self, from_stream: str, to_stream: str) -> int | None:
        """Add to a ``from_stream`` stamp to express it on ``to_stream``'s clock."""
        if from_stream not in self._min or to_stream not in self._min:
            return None
        return self._min[from_stream] - self._min[to_stream]


class PoseBuffer:
    """Time-sorted recent poses (stamps on the pose clock) with bounded history."""

    def __init__(self, *, reorder_window_ns: int, history_ns: int, stats: SyncStats) -> None:
        self.reorder_window_ns = reorder_window_ns
        self.history_ns = history_ns
        self.stats = stats
        self.stamps: list[int] = []
        self.poses: list[np.ndarray] = []

    @property
    def newest_ns(self) -> int | None:
        return self.stamps[-1] if self.stamps else None

    def add(self, stamp_ns: int, T: np.ndarray) -> bool:
        """Insert a pose; False (and counted) when it is late, a duplicate or not finite."""
        try:
            T = check_pose(T, what="tracker pose")
        except InvalidPoseError:
            self.stats.reject("invalid")
            return False
        newest = self.newest_ns
        if newest is not None and stamp_ns <= newest:
            if stamp_ns < newest - self.reorder_window_ns:
                self.stats.reject("late")
                return False
            i = bisect.bisect_left(self.stamps, stamp_ns)
            if i < len(self.stamps) and self.stamps[i] == stamp_ns:
                self.stats.reject("duplicate")
                return False
            self.stamps.insert(i, stamp_ns)
            self.poses.insert(i, T)
            self.stats.poses_out_of_order += 1
            return True
        self.stamps.append(stamp_ns)
        self.poses.append(T)
        cutoff = stamp_ns - self.history_ns
        if self.stamps[0] < cutoff:
            k = bisect.bisect_left(self.stamps, cutoff)
            del self.stamps[:k]
            del self.poses[:k]
        return True

    def nearest(self, t_ns: int) -> tuple[np.ndarray | None, int]:
        """(pose, |dt| ns) of the sample nearest to ``t_ns``; (None, 0) when empty."""
        if not self.stamps:
            return None, 0
        i = bisect.bisect_left(self.stamps, t_ns)
        best, best_dt = None, None
        for j in (i - 1, i):
            if 0 <= j < len(self.stamps):
                dt = abs(self.stamps[j] - t_ns)
                if best_dt is None or dt < best_dt:
                    best, best_dt = j, dt
        return self.poses[best], int(best_dt)

    def interpolate(self, t_ns: int, *, max_gap_ns: int) -> tuple[np.ndarray | None, str]:
        """(pose, "") or (None, "outside_pose_range" | "pose_gap")."""
        if not self.stamps or t_ns < self.stamps[0] or t_ns > self.stamps[-1]:
            return None, "outside_pose_range"
        i = bisect.bisect_left(self.stamps, t_ns)
        if self.stamps[i] == t_ns:
            return self.poses[i].copy(), ""
        t0, t1 = self.stamps[i - 1], self.stamps[i]
        if t1 - t0 > max_gap_ns:
            return None, "pose_gap"
        alpha = (t_ns - t0) / (t1 - t0)
        T0, T1 = self.poses[i - 1], self.poses[i]
        T = np.eye(4)
        T[:3, :3] = quat_to_matrix(slerp(matrix_to_quat(T0[:3, :3]), matrix_to_quat(T1[:3, :3]), alpha))
        T[:3, 3] = (1.0 - alpha) * T0[:3, 3] + alpha * T1[:3, 3]
        return T, ""


def downsample_rgbd(
    color: np.ndarray, depth: np.ndarray, intrinsics: CameraIntrinsics, size: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray, CameraIntrinsics]:
    """Resize registered color (bilinear, antialiased) and depth (nearest) to ``size=(w, h)``."""
    w, h = size
    if (intrinsics.width_px, intrinsics.height_px) == (w, h):
        return color, depth, intrinsics
    color_out = np.asarray(Image.fromarray(color).resize((w, h), Image.Resampling.BILINEAR))
    depth_out = resize_nearest(depth, (h, w))
    return color_out, depth_out, intrinsics.scaled(w, h)


@dataclass
class _PendingImage:
    stamp_ns: int
    frame_id: int
    color: np.ndarray
    depth: np.ndarray
    depth_scale: float
    instance: np.ndarray | None = None
    instance_categories: dict[int, str] | None = None


class FrameSynchronizer:
    """Feed images and poses in arrival order; collect the frames each call returns."""

    def __init__(self, config: SyncConfig, intrinsics: CameraIntrinsics, *, source: str = "live") -> None:
        self.config = config
        self.intrinsics = intrinsics
        self.source = source
        self.stats = SyncStats()
        self.poses = PoseBuffer(
            reorder_window_ns=config.reorder_window_ns, history_ns=config.pose_history_ns, stats=self.stats
        )
        self._clock = ClockOffsetEstimator()
        self._pending: list[_PendingImage] = []
        self._last_out_ns: int | None = None
        self._next_id = 0
        self._extrinsic = config.extrinsic()
        self._world = config.world_transform()

    # --------------------------------------------------------------------------- clock

    def clock_offset_ns(self) -> int | None:
        """Current pose->image clock offset (None while an estimate lacks samples)."""
        if not self.config.estimate_clock_offset:
            return self.config.clock_offset_ns
        if min(self._clock.count("pose"), self._clock.count("image")) < self.config.min_offset_samples:
            return None
        off = self._clock.offset_ns("pose", "image")
        if off is None:
            return None
        off += self.config.image_latency_ns - self.config.pose_latency_ns
        self.stats.clock_offset_ns = off
        return off

    # ---------------------------------------------------------------------------- input

    def add_pose(self, stamp_ns: int, T_pose: np.ndarray, *, host_ns: int | None = None) -> list[Frame]:
        """A tracker pose (T265 body in T265 world, see module docstring) at ``stamp_ns`` on
        the pose clock. Returns the frames this pose completed."""
        self.stats.poses_in += 1
        if host_ns is not None:
            self._clock.add("pose", stamp_ns, host_ns)
        elif self.config.estimate_clock_offset:
            raise ValueError("estimate_clock_offset needs host_ns with every pose")
        self.poses.add(int(stamp_ns), T_pose)
        return self._emit(force=False)

    def add_image(
        self,
        stamp_ns: int,
        color: np.ndarray,
        depth: np.ndarray,
        *,
        depth_scale: float,
        host_ns: int | None = None,
        frame_id: int | None = None,
        instance: np.ndarray | None = None,
        instance_categories: dict[int, str] | None = None,
    ) -> list[Frame]:
        """A registered color+depth image at ``stamp_ns`` (image clock), optionally with its
        ground-truth instance image (HxW int32) and categories. Returns completed frames."""
        self.stats.images_in += 1
        if host_ns is not None:
            self._clock.add("image", stamp_ns, host_ns)
        elif self.config.estimate_clock_offset:
            raise ValueError("estimate_clock_offset needs host_ns with every image")
        stamp_ns = int(stamp_ns)
        if self._last_out_ns is not None and stamp_ns <= self._last_out_ns:
            self.stats.drop("out_of_order_image")
            return self._emit(force=False)
        fid = self._next_id if frame_id is None else int(frame_id)
        self._next_id = fid + 1
        item = _PendingImage(stamp_ns, fid, color, depth, float(depth_scale), instance, instance_categories)
        keys = [p.stamp_ns for p in self._pending]
        i = bisect.bisect_right(keys, stamp_ns)
        if i > 0 and keys[i - 1] == stamp_ns:
            self.stats.drop("duplicate_image")
            return self._emit(force=False)
        self._pending.insert(i, item)
        return self._emit(force=False)

    def flush(self) -> list[Frame]:
        """Resolve every waiting image with the poses there are (end of stream)."""
        return self._emit(force=True)

    @property
    def pending(self) -> int:
        return len(self._pending)

    # ---------------------------------------------------------------------------- pairing

    def _emit(self, *, force: bool) -> list[Frame]:
        out: list[Frame] = []
        offset = self.clock_offset_ns()
        cfg = self.config
        while self._pending:
            img = self._pending[0]
            newest_img = self._pending[-1].stamp_ns
            stale = newest_img - img.stamp_ns > cfg.max_wait_ns
            if offset is None:
                if force or stale:
                    self._pending.pop(0)
                    self.stats.drop("clock_offset_unknown")
                    continue
                break
            t_pose = img.stamp_ns - offset  # the image time on the pose clock
            newest_pose = self.poses.newest_ns
            wait_until = t_pose + (cfg.max_dt_ns if cfg.mode == "nearest" else 0)
            if not force and not stale and (newest_pose is None or newest_pose < wait_until):
                break
            self._pending.pop(0)
            self._last_out_ns = img.stamp_ns
            T_body = self._pose_for(t_pose)
            if T_body is None:
                continue
            out.append(self._make_frame(img, T_body))
        return out

    def _pose_for(self, t_pose_ns: int) -> np.ndarray | None:
        cfg = self.config
        if cfg.mode == "nearest":
            T, dt = self.poses.nearest(t_pose_ns)
            if T is None or dt > cfg.max_dt_ns:
                self.stats.drop("no_pose_within_tolerance")
                return None
            return T
        T, reason = self.poses.interpolate(t_pose_ns, max_gap_ns=cfg.max_pose_gap_ns)
        if T is None:
            newest = self.poses.newest_ns
            # resolved before any later pose came (stalled tracker or end of stream)
            self.stats.drop("pose_timeout" if newest is not None and t_pose_ns > newest else reason)
        return T

    def camera_pose(self, T_pose: np.ndarray) -> np.ndarray:
        """``T_world_cam`` of a tracker pose (axis change, world transform and extrinsic)."""
        T = self._world @ np.asarray(T_pose, dtype=np.float64) @ self._extrinsic
        # re-orthonormalise: interpolation and float error must not leave a skewed rotation
        U, _, Vt = np.linalg.svd(T[:3, :3])
        T[:3, :3] = U @ Vt
        return T

    def _make_frame(self, img: _PendingImage, T_body: np.ndarray) -> Frame:
        color, depth, intr = img.color, img.depth, self.intrinsics
        if self.config.output_size is not None:
            color, depth, intr = downsample_rgbd(color, depth, intr, self.config.output_size)
        instance = img.instance
        if instance is not None and instance.shape != depth.shape:
            instance = resize_nearest(instance, depth.shape[:2])
        self.stats.frames_out += 1
        return Frame(
            frame_id=img.frame_id,
            stamp_ns=img.stamp_ns,
            color=color,
            depth=depth,
            depth_scale=img.depth_scale,
            intrinsics=intr,
            T_world_cam=self.camera_pose(T_body),
            instance=instance,
            instance_categories=dict(img.instance_categories or {}),
            source=self.source,
        )
