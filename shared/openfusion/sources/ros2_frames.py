"""ROS 2 messages of a camera and its pose into canonical frames: the pure logic, no bus.

:class:`Ros2FrameAssembler` turns CDR payloads of the streams :class:`Ros2Topics` names (color,
registered depth, the color ``CameraInfo``, ``Odometry`` or ``TFMessage``, optional ground truth)
into frames, as :class:`Ros2Config` says; the live source over Zenoh
(:class:`openfusion.sources.ros2.Ros2Source`) and the rosbag2 reader (:mod:`openfusion.sources.rosbag`)
feed it the same way. Payloads are CDR, decoded through ``rosbags`` (:mod:`openfusion.sources.cdr`);
nothing here imports Zenoh.

What is converted (from ROS conventions into design.md section 3)
    - color ``sensor_msgs/Image`` ``rgb8``/``bgr8``/``rgba8``/``bgra8`` or ``CompressedImage``
      JPEG/PNG -> RGB uint8; depth ``16UC1`` (millimetres, ROS convention) or ``compressedDepth``
      PNG 16-bit -> uint16 with ``depth_scale = 1000``; ``32FC1`` (metres) -> float32 with
      ``depth_scale = 1.0``. Optional ground truth: an instance image ``32SC1`` (0 = none) and a
      ``std_msgs/String`` topic with the JSON object ``{"id": "category", ...}``, passed on as the
      frame's ``instance`` / ``instance_categories`` so the gt encoder can run.
    - intrinsics from the latest ``CameraInfo.k`` (row-major 3x3) of the color camera.
    - pose: ``Odometry`` gives the body (``child_frame_id``) in ``header.frame_id``; a
      ``TFMessage`` transform with the configured ``world_frame``/``body_frame`` gives the
      same. ``T_world_cam = T_world_body @ T_body_cam`` with ``T_body_cam`` from config; its
      default is the REP-103 body -> optical rotation (body x forward, y left, z up; ROS optical
      frame z forward, x right, y down = our OpenCV camera axes) at the body origin. Use identity
      when the tracked frame is already the camera's ``*_optical_frame``.
    - color and depth (and instance) are paired by header stamp (within ``pair_tolerance_ns``),
      then given a pose by ``openfusion.sources.sync.FrameSynchronizer`` (same clock: offset 0).
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field, replace

import numpy as np

from openfusion.frame import CameraIntrinsics, Frame
from openfusion.poses import pose_from_tum
from openfusion.sources.base import Skip
from openfusion.sources.cdr import (
    CdrError,
    compressed_to_array,
    decode_camera_info,
    decode_compressed_image,
    decode_image,
    decode_odometry,
    decode_string,
    decode_tf_message,
    full_type_name,
    image_to_array,
)
from openfusion.sources.ros_layout import LAYOUTS, topic_key
from openfusion.sources.sync import FrameSynchronizer, SyncConfig

logger = logging.getLogger(__name__)

#: REP-103 body (x forward, y left, z up) -> camera optical frame (x right, y down, z forward)
T_BODY_OPTICAL = np.array(
    [[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
)


IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
ODOMETRY = "nav_msgs/msg/Odometry"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
STRING = "std_msgs/msg/String"
#: the message type each kind of topic carries (images: Image or CompressedImage)
KIND_TYPES: dict[str, tuple[str, ...]] = {
    "color": (IMAGE, COMPRESSED_IMAGE),
    "depth": (IMAGE, COMPRESSED_IMAGE),
    "camera_info": (CAMERA_INFO,),
    "odometry": (ODOMETRY,),
    "tf": (TF_MESSAGE,),
    "instance": (IMAGE,),
    "instance_categories": (STRING,),
}


def guess_image_type(topic: str) -> str:
    """``.../compressed`` and ``.../compressedDepth`` (image_transport's names) are CompressedImage."""
    return COMPRESSED_IMAGE if topic.rstrip("/").rsplit("/", 1)[-1].lower().startswith("compressed") else IMAGE


@dataclass(frozen=True)
class Ros2Topics:
    """ROS 2 topic names of the streams (leading '/' optional) and the Zenoh key layout.

    ``layout``: ``bridge`` (zenoh-bridge-ros2dds; ``namespace`` = its ``--namespace``) or
    ``rmw_zenoh`` (``domain_id`` = the robot's ``ROS_DOMAIN_ID``). ``color_type``/``depth_type``:
    ``sensor_msgs/msg/Image`` or ``sensor_msgs/msg/CompressedImage`` (None: guessed from the
    topic name; in the rmw_zenoh layout the key says). ``instance``/``instance_categories``:
    optional ground-truth topics (module docstring)."""

    color: str = "camera/color/image_raw"
    depth: str = "camera/aligned_depth_to_color/image_raw"
    camera_info: str = "camera/color/camera_info"
    odometry: str | None = "odom"
    tf: str | None = None
    namespace: str = ""
    instance: str | None = None
    instance_categories: str | None = None
    color_type: str | None = None
    depth_type: str | None = None
    layout: str = "bridge"
    domain_id: int = 0

    def __post_init__(self) -> None:
        if self.layout not in LAYOUTS:
            raise ValueError(f"unknown key layout {self.layout!r}; known: {', '.join(LAYOUTS)}")
        for kind, given in (("color", self.color_type), ("depth", self.depth_type)):
            if given is not None and full_type_name(given) not in KIND_TYPES[kind]:
                raise ValueError(f"{kind}_type must be one of {', '.join(KIND_TYPES[kind])}, got {given!r}")

    def key(self, topic: str) -> str:
        """The zenoh-bridge-ros2dds key of a topic (the bridge layout)."""
        return topic_key(topic, layout="bridge", namespace=self.namespace)

    def streams(self) -> dict[str, str]:
        """kind -> topic name of every configured stream."""
        out = {"color": self.color, "depth": self.depth, "camera_info": self.camera_info}
        for kind in ("odometry", "tf", "instance", "instance_categories"):
            topic = getattr(self, kind)
            if topic:
                out[kind] = topic
        return out

    def type_for(self, kind: str) -> str:
        """The message type expected on a kind's topic."""
        if kind in ("color", "depth"):
            given = self.color_type if kind == "color" else self.depth_type
            return full_type_name(given) if given else guess_image_type(getattr(self, kind))
        return KIND_TYPES[kind][0]

    def subscription_key(self, kind: str) -> str:
        topic = self.streams()[kind]
        return topic_key(topic, layout=self.layout, namespace=self.namespace, domain_id=self.domain_id)


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
    """Turns CDR payloads of the streams into frames (pure logic; ``Ros2Source`` and the rosbag2
    reader feed it). Every bad message is one ``Skip`` with a reason; the stream goes on."""

    def __init__(self, config: Ros2Config, *, source: str = "ros2") -> None:
        self.config = config
        self.source = source
        self.intrinsics: CameraIntrinsics | None = None
        self._sync: FrameSynchronizer | None = None
        self._color: dict[int, np.ndarray] = {}
        self._depth: dict[int, tuple[np.ndarray, float]] = {}
        self._instance: dict[int, np.ndarray] = {}
        self._categories: dict[int, str] = {}
        self._early_poses: list[tuple[int, np.ndarray]] = []
        self._wants_instance = bool(config.topics.instance)
        self.skipped: dict[str, int] = {}
        self._sync_seen: dict[str, int] = {}

    def _skip(self, reason: str, detail: str) -> Skip:
        self.skipped[reason] = self.skipped.get(reason, 0) + 1
        return Skip(reason, detail)

    def feed(self, kind: str, payload: bytes | memoryview, typename: str | None = None) -> list[Frame | Skip]:
        """``kind`` is one of color, depth, camera_info, odometry, tf, instance,
        instance_categories; ``typename`` the message type when the transport says (rmw_zenoh key,
        bag metadata), else the configured one. Returns the frames this sample completed and a
        ``Skip`` for every message or image dropped on the way."""
        out = self._feed(kind, payload, typename)
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

    def _feed(self, kind: str, payload: bytes | memoryview, typename: str | None) -> list[Frame | Skip]:
        if kind not in KIND_TYPES:
            raise ValueError(f"unknown topic kind {kind!r}")
        typename = full_type_name(typename) if typename else self.config.topics.type_for(kind)
        if typename not in KIND_TYPES[kind]:
            return [self._skip(f"wrong_type_{kind}", f"{kind} topic carries {typename}, expected "
                               f"{' or '.join(KIND_TYPES[kind])}")]
        try:
            if kind == "camera_info":
                return self._camera_info(payload)
            if kind in ("color", "depth", "instance"):
                return self._image(kind, payload, typename)
            if kind == "instance_categories":
                return self._instance_categories(payload)
            if kind == "odometry":
                odo = decode_odometry(payload)
                if self.config.world_frame and odo.header.frame_id.strip("/") != self.config.world_frame:
                    return [self._skip("pose_wrong_frame", f"odometry in {odo.header.frame_id!r}, expected {self.config.world_frame!r}")]
                return self._pose(odo.header.stamp_ns, odo.position, odo.orientation_xyzw)
            out: list[Frame | Skip] = []
            for tf in decode_tf_message(payload):
                if (tf.header.frame_id.strip("/"), tf.child_frame_id.strip("/")) == (
                    self.config.world_frame,
                    self.config.body_frame,
                ):
                    out += self._pose(tf.header.stamp_ns, tf.translation, tf.rotation_xyzw)
            return out
        except CdrError as exc:
            return [self._skip(f"bad_{kind}", f"cannot read {kind} message ({typename}): {exc}")]

    def _instance_categories(self, payload: bytes | memoryview) -> list[Frame | Skip]:
        text = decode_string(payload)
        try:
            mapping = {int(k): str(v) for k, v in json.loads(text).items()}
        except (ValueError, TypeError, AttributeError) as exc:
            raise CdrError(f"instance categories are not a JSON object {{id: category}}: {exc}") from None
        self._categories.update(mapping)
        return []

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
            for stamp, T in self._early_poses:
                self._sync.poses.add(stamp, T)
            self._early_poses = []
        return []

    def _image(self, kind: str, payload: bytes | memoryview, typename: str) -> list[Frame | Skip]:
        if typename == COMPRESSED_IMAGE:
            cmsg = decode_compressed_image(payload)
            arr, stamp, encoding = compressed_to_array(cmsg), cmsg.header.stamp_ns, cmsg.format
        else:
            msg = decode_image(payload)
            arr, stamp, encoding = image_to_array(msg), msg.header.stamp_ns, msg.encoding
        if kind == "color":
            if arr.ndim != 3:
                return [self._skip("bad_color", f"color topic has encoding {encoding!r} (single channel)")]
            self._color[stamp] = arr
        elif kind == "instance":
            if arr.dtype != np.int32:
                return [self._skip("bad_instance", f"instance topic has encoding {encoding!r}, expected 32SC1")]
            self._instance[stamp] = arr
        else:
            if arr.dtype == np.uint16:
                self._depth[stamp] = (arr, 1000.0)
            elif arr.dtype == np.float32:
                self._depth[stamp] = (arr, 1.0)
            else:
                return [self._skip("depth_dtype", f"depth topic has encoding {encoding!r}, expected 16UC1 or 32FC1")]
        return self._pair()

    @staticmethod
    def _nearest(store: dict, t: int, tol: int) -> int | None:
        match = min(store, key=lambda s: abs(s - t), default=None)
        return match if match is not None and abs(match - t) <= tol else None

    def _pair(self) -> list[Frame | Skip]:
        out: list[Frame | Skip] = []
        tol = self.config.pair_tolerance_ns
        for tc in sorted(self._color):
            match = self._nearest(self._depth, tc, tol)
            inst_match = self._nearest(self._instance, tc, tol) if self._wants_instance else None
            if match is None or (self._wants_instance and inst_match is None):
                continue
            color = self._color.pop(tc)
            depth, scale = self._depth.pop(match)
            instance = self._instance.pop(inst_match) if inst_match is not None else None
            if self._sync is None or self.intrinsics is None:
                out.append(self._skip("no_camera_info", f"image at {tc} ns before any CameraInfo"))
                continue
            shape = (self.intrinsics.height_px, self.intrinsics.width_px)
            if color.shape[:2] != depth.shape or depth.shape != shape or (instance is not None and instance.shape != shape):
                inst = f", instance {instance.shape[1]}x{instance.shape[0]}" if instance is not None else ""
                out.append(
                    self._skip(
                        "size_mismatch",
                        f"color {color.shape[1]}x{color.shape[0]}, depth {depth.shape[1]}x{depth.shape[0]}{inst}, "
                        f"CameraInfo {self.intrinsics.width_px}x{self.intrinsics.height_px}: subscribe to a registered depth",
                    )
                )
                continue
            cats = dict(self._categories) if instance is not None else None
            out += self._sync.add_image(tc, color, depth, depth_scale=scale, instance=instance, instance_categories=cats)
        # unmatched images older than 1 s are given up
        newest = max([*self._color, *self._depth, *self._instance], default=0)
        for store, kind in ((self._color, "color"), (self._depth, "depth"), (self._instance, "instance")):
            for t in [t for t in store if t < newest - 1_000_000_000]:
                del store[t]
                out.append(self._skip(f"unpaired_{kind}", f"{kind} image at {t} ns found no partner within {tol} ns"))
        return out

    def _pose(self, stamp_ns: int, t_xyz: np.ndarray, q_xyzw: np.ndarray) -> list[Frame | Skip]:
        if not (np.isfinite(t_xyz).all() and np.isfinite(q_xyzw).all()) or np.linalg.norm(q_xyzw) < 1e-6:
            return [self._skip("invalid_pose", f"pose at {stamp_ns} ns is not finite / has a zero quaternion")]
        T = pose_from_tum(t_xyz, q_xyzw)
        if self._sync is None:  # no camera yet: kept (the last 2 s) for the synchroniser CameraInfo starts
            self._early_poses.append((stamp_ns, T))
            horizon = stamp_ns - self.config.sync.pose_history_ns
            self._early_poses = [(t, P) for t, P in self._early_poses if t >= horizon]
            return []
        return list(self._sync.add_pose(stamp_ns, T))

    def flush(self) -> list[Frame | Skip]:
        """Resolve waiting images at the end of the stream."""
        out: list[Frame | Skip] = list(self._sync.flush()) if self._sync is not None else []
        return out + self._sync_drops()

    @property
    def sync_stats(self):  # noqa: ANN201 - SyncStats or None
        return self._sync.stats if self._sync is not None else None
