"""ROS 2 topics over Zenoh as a frame source, without a ROS install.

zenoh-bridge-ros2dds publishes each ROS 2 topic ``/ns/topic`` on the Zenoh key ``ns/topic``
(prefixed by the bridge's ``--namespace`` if set) with the raw CDR payload (see
``openfusion.sources.cdr``). ``Ros2Source`` subscribes to a color image, a registered depth
image (e.g. ``aligned_depth_to_color``), the color ``CameraInfo`` and either ``Odometry`` or
``TFMessage``, and assembles canonical frames.

What is converted
    - color ``rgb8``/``bgr8``/``rgba8``/``bgra8`` -> RGB uint8; depth ``16UC1`` (millimetres,
      ROS convention) -> uint16 with ``depth_scale = 1000``; ``32FC1`` (metres) -> float32
      with ``depth_scale = 1.0``.
    - intrinsics from the latest ``CameraInfo.k`` (row-major 3x3) of the color camera.
    - pose: ``Odometry`` gives the body (``child_frame_id``) in ``header.frame_id``; a
      ``TFMessage`` transform with the configured ``world_frame``/``body_frame`` gives the
      same. ``T_world_cam = T_world_body @ T_body_cam`` with ``T_body_cam`` from config; its
      default is the REP-103 body -> optical rotation (body x forward, y left, z up; optical
      z forward, x right, y down) at the body origin. Use identity when the tracked frame is
      already the camera's ``*_optical_frame``.
    - color and depth are paired by header stamp (within ``pair_tolerance_ns``), then given
      a pose by ``openfusion.sources.sync.FrameSynchronizer`` (same clock: offset 0).

Decoding happens in the iterating thread: Zenoh callbacks only hand the payload to a bounded
queue (a full queue drops the sample and counts it), so a slow consumer never blocks the bus.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from openfusion.frame import CameraIntrinsics, Frame
from openfusion.poses import pose_from_tum
from openfusion.sources.base import FrameSource, Skip
from openfusion.sources.cdr import (
    CdrError,
    decode_camera_info,
    decode_image,
    decode_odometry,
    decode_tf_message,
    image_to_array,
)
from openfusion.sources.sync import FrameSynchronizer, SyncConfig

logger = logging.getLogger(__name__)

#: REP-103 body (x forward, y left, z up) -> camera optical frame (x right, y down, z forward)
T_BODY_OPTICAL = np.array(
    [[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
)


@dataclass(frozen=True)
class Ros2Topics:
    """Zenoh keys of the ROS 2 topics (topic names without the leading '/')."""

    color: str = "camera/color/image_raw"
    depth: str = "camera/aligned_depth_to_color/image_raw"
    camera_info: str = "camera/color/camera_info"
    odometry: str | None = "odom"
    tf: str | None = None
    namespace: str = ""

    def key(self, topic: str) -> str:
        topic = topic.strip("/")
        ns = self.namespace.strip("/")
        return f"{ns}/{topic}" if ns else topic


@dataclass
class Ros2Config:
    """Topics, frames and pairing options of a ``Ros2Source``."""

    topics: Ros2Topics = field(default_factory=Ros2Topics)
    world_frame: str = "odom"
    body_frame: str = "base_link"
    T_body_cam: np.ndarray = field(default_factory=lambda: T_BODY_OPTICAL.copy())
    pair_tolerance_ns: int = 5_000_000
    sync: SyncConfig = field(default_factory=lambda: SyncConfig(mode="interpolate", pose_axes="opencv", output_size=None))

    def __post_init__(self) -> None:
        if self.topics.odometry is None and self.topics.tf is None:
            raise ValueError("Ros2Config needs a pose topic: topics.odometry or topics.tf")
        T = np.asarray(self.T_body_cam, dtype=np.float64)
        if T.shape != (4, 4) or not np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-6):
            raise ValueError("T_body_cam must be a 4x4 rigid transform")
        self.sync = replace(self.sync, pose_axes="opencv", T_tracker_cam=tuple(map(tuple, T)))


class Ros2FrameAssembler:
    """Turns decoded-topic payloads into frames (pure logic; ``Ros2Source`` feeds it)."""

    def __init__(self, config: Ros2Config, *, source: str = "ros2") -> None:
        self.config = config
        self.source = source
        self.intrinsics: CameraIntrinsics | None = None
        self._sync: FrameSynchronizer | None = None
        self._color: dict[int, np.ndarray] = {}
        self._depth: dict[int, tuple[np.ndarray, float]] = {}
        self.skipped: dict[str, int] = {}
        self._sync_seen: dict[str, int] = {}

    def _skip(self, reason: str, detail: str) -> Skip:
        self.skipped[reason] = self.skipped.get(reason, 0) + 1
        return Skip(reason, detail)

    def feed(self, kind: str, payload: bytes | memoryview) -> list[Frame | Skip]:
        """``kind`` is one of color, depth, camera_info, odometry, tf. Returns the frames this
        sample completed and a ``Skip`` for every image dropped on the way."""
        out = self._feed(kind, payload)
        return out + self._sync_drops()

    def _sync_drops(self) -> list[Frame | Skip]:
        """A ``Skip`` per image the synchroniser dropped since the last call."""
        if self._sync is None:
            return []
        out: list[Frame | Skip] = []
        for reason, count in self._sync.stats.images_dropped.items():
            new = count - self._sync_seen.get(reason, 0)
            out += [Skip(reason, f"image dropped by the pose synchroniser ({reason})")] * new
            self._sync_seen[reason] = count
        return out

    def _feed(self, kind: str, payload: bytes | memoryview) -> list[Frame | Skip]:
        try:
            if kind == "camera_info":
                return self._camera_info(payload)
            if kind in ("color", "depth"):
                return self._image(kind, payload)
            if kind == "odometry":
                odo = decode_odometry(payload)
                if self.config.world_frame and odo.header.frame_id.strip("/") != self.config.world_frame:
                    return [self._skip("pose_wrong_frame", f"odometry in {odo.header.frame_id!r}, expected {self.config.world_frame!r}")]
                return self._pose(odo.header.stamp_ns, odo.position, odo.orientation_xyzw)
            if kind == "tf":
                out: list[Frame | Skip] = []
                for tf in decode_tf_message(payload):
                    if (tf.header.frame_id.strip("/"), tf.child_frame_id.strip("/")) == (
                        self.config.world_frame,
                        self.config.body_frame,
                    ):
                        out += self._pose(tf.header.stamp_ns, tf.translation, tf.rotation_xyzw)
                return out
        except CdrError as exc:
            return [self._skip(f"bad_{kind}", f"cannot decode {kind} message: {exc}")]
        raise ValueError(f"unknown topic kind {kind!r}")

    def _camera_info(self, payload: bytes | memoryview) -> list[Frame | Skip]:
        info = decode_camera_info(payload)
        K = info.k
        if not (np.isfinite(K).all() and K[0, 0] > 0 and K[1, 1] > 0 and info.width > 0 and info.height > 0):
            return [self._skip("bad_camera_info", f"CameraInfo has no usable K ({K.ravel().tolist()})")]
        intr = CameraIntrinsics.from_matrix(K, info.width, info.height)
        if intr != self.intrinsics:
            if self.intrinsics is not None:
                logger.warning("camera intrinsics changed from %s to %s", self.intrinsics, intr)
            self.intrinsics = intr
            old = self._sync
            self._sync = FrameSynchronizer(self.config.sync, intr, source=self.source)
            self._sync_seen = {}
            if old is not None:  # keep the poses already received
                for stamp, T in zip(old.poses.stamps, old.poses.poses, strict=True):
                    self._sync.poses.add(stamp, T)
        return []

    def _image(self, kind: str, payload: bytes | memoryview) -> list[Frame | Skip]:
        msg = decode_image(payload)
        arr = image_to_array(msg)
        stamp = msg.header.stamp_ns
        if kind == "color":
            if arr.ndim != 3:
                return [self._skip("bad_color", f"color topic has encoding {msg.encoding!r} (single channel)")]
            self._color[stamp] = arr
        else:
            if arr.dtype == np.uint16:
                self._depth[stamp] = (arr, 1000.0)
            elif arr.dtype == np.float32:
                self._depth[stamp] = (arr, 1.0)
            else:
                return [self._skip("depth_dtype", f"depth topic has encoding {msg.encoding!r}, expected 16UC1 or 32FC1")]
        return self._pair()

    def _pair(self) -> list[Frame | Skip]:
        out: list[Frame | Skip] = []
        tol = self.config.pair_tolerance_ns
        for tc in sorted(self._color):
            match = min(self._depth, key=lambda td: abs(td - tc), default=None)
            if match is None or abs(match - tc) > tol:
                continue
            color = self._color.pop(tc)
            depth, scale = self._depth.pop(match)
            if self._sync is None or self.intrinsics is None:
                out.append(self._skip("no_camera_info", f"image at {tc} ns before any CameraInfo"))
                continue
            if color.shape[:2] != depth.shape or depth.shape != (self.intrinsics.height_px, self.intrinsics.width_px):
                out.append(
                    self._skip(
                        "size_mismatch",
                        f"color {color.shape[1]}x{color.shape[0]}, depth {depth.shape[1]}x{depth.shape[0]}, "
                        f"CameraInfo {self.intrinsics.width_px}x{self.intrinsics.height_px}: subscribe to a registered depth",
                    )
                )
                continue
            out += self._sync.add_image(tc, color, depth, depth_scale=scale)
        # unmatched images older than 1 s are given up
        newest = max([*self._color, *self._depth], default=0)
        for store, kind in ((self._color, "color"), (self._depth, "depth")):
            for t in [t for t in store if t < newest - 1_000_000_000]:
                del store[t]
                out.append(self._skip(f"unpaired_{kind}", f"{kind} image at {t} ns found no partner within {tol} ns"))
        return out

    def _pose(self, stamp_ns: int, t_xyz: np.ndarray, q_xyzw: np.ndarray) -> list[Frame | Skip]:
        if not (np.isfinite(t_xyz).all() and np.isfinite(q_xyzw).all()) or np.linalg.norm(q_xyzw) < 1e-6:
            return [self._skip("invalid_pose", f"pose at {stamp_ns} ns is not finite / has a zero quaternion")]
        if self._sync is None:
            return []  # no camera yet; poses start counting once CameraInfo arrived
        return list(self._sync.add_pose(stamp_ns, pose_from_tum(t_xyz, q_xyzw)))

    def flush(self) -> list[Frame | Skip]:
        """Resolve waiting images at the end of the stream."""
        out: list[Frame | Skip] = list(self._sync.flush()) if self._sync is not None else []
        return out + self._sync_drops()

    @property
    def sync_stats(self):  # noqa: ANN201 - SyncStats or None
        return self._sync.stats if self._sync is not None else None


class Ros2Source(FrameSource):
    """Frames from ROS 2 topics bridged into Zenoh (see module docstring).

    ``session``: an open ``zenoh.Session`` to subscribe with (shared with the caller), or None
    to open one from ``zenoh_config`` (a ``zenoh.Config``; default: peer mode). Iteration ends
    after ``idle_timeout_s`` without samples (None: runs until ``close()``).
    """

    live = True

    def __init__(
        self,
        config: Ros2Config | None = None,
        *,
        session: Any = None,
        zenoh_config: Any = None,
        idle_timeout_s: float | None = None,
        queue_size: int = 256,
        max_frames: int | None = None,
    ) -> None:
        super().__init__("ros2:" + ((config.topics.namespace if config else "") or "default"), max_frames=max_frames)
        self.config = config or Ros2Config()
        self.idle_timeout_s = idle_timeout_s
        self._queue: queue.Queue[tuple[str, bytes]] = queue.Queue(maxsize=queue_size)
        self.dropped_samples = 0
        self._closed = threading.Event()
        import zenoh  # the core dependency; imported here so decoding alone never needs it

        self._own_session = session is None
        self._session = session if session is not None else zenoh.open(zenoh_config or zenoh.Config())
        t = self.config.topics
        kinds = {"color": t.color, "depth": t.depth, "camera_info": t.camera_info}
        if t.odometry:
            kinds["odometry"] = t.odometry
        if t.tf:
            kinds["tf"] = t.tf
        self.keys = {kind: t.key(topic) for kind, topic in kinds.items()}
        self._subscribers = [
            self._session.declare_subscriber(key, self._callback(kind)) for kind, key in self.keys.items()
        ]
        logger.info("ROS 2 source subscribed to %s", self.keys)

    def _callback(self, kind: str):  # noqa: ANN202 - zenoh sample handler
        def on_sample(sample: Any) -> None:
            try:
                self._queue.put_nowait((kind, sample.payload.to_bytes()))
            except queue.Full:
                self.dropped_samples += 1

        return on_sample

    def _produce(self) -> Iterator[Frame | Skip]:
        assembler = Ros2FrameAssembler(self.config, source=self.name)
        last = time.monotonic()
        while not self._closed.is_set():
            try:
                kind, payload = self._queue.get(timeout=0.05)
            except queue.Empty:
                if self.idle_timeout_s is not None and time.monotonic() - last > self.idle_timeout_s:
                    break
                continue
            last = time.monotonic()
            yield from assembler.feed(kind, payload)
        yield from assembler.flush()

    def close(self) -> None:
        """Stop iteration, undeclare the subscribers and close an owned session."""
        self._closed.set()
        for sub in self._subscribers:
            sub.undeclare()
        self._subscribers = []
        if self._own_session:
            self._session.close()

    def __enter__(self) -> Ros2Source:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
