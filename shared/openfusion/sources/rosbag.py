"""rosbag2 recordings (a bag folder, or one ``.mcap`` / ``.db3`` file) as a playback frame source.

``rosbags`` reads the bag (sqlite3 and MCAP storage, with or without ``metadata.yaml``); every
message goes, in recorded order, through the same :class:`~openfusion.sources.ros2.Ros2FrameAssembler`
as the live ROS 2 source, so decoding, stamp pairing, pose interpolation and the conversions are
one code path. What is converted from (ROS conventions -> design.md section 3):

- colour ``sensor_msgs/Image`` (rgb8/bgr8/rgba8/bgra8/mono8 is refused as colour) or
  ``CompressedImage`` JPEG/PNG -> RGB uint8;
- registered depth ``Image`` 16UC1 (mm) or ``compressedDepth`` PNG 16-bit -> uint16,
  ``depth_scale = 1000``; ``Image`` 32FC1 (m) -> float32, ``depth_scale = 1``;
- ``CameraInfo.k`` -> intrinsics; the camera's optical frame (x right, y down, z forward) is
  already our OpenCV camera convention;
- pose from ``nav_msgs/Odometry`` (``header.frame_id`` = world, ``child_frame_id`` = body) or
  ``/tf`` (``world_frame`` -> ``body_frame``): ``T_world_cam = T_world_body @ T_body_cam``, with
  ``T_body_cam`` the REP-103 body -> optical rotation (``camera_frame=rep103``, default: the body
  is x forward, y left, z up) or identity (``camera_frame=optical``: the tracked frame is the
  camera's ``*_optical_frame``). The world frame is whatever the bag's odometry/tf world is.
- optional ground truth: an instance image ``32SC1`` and a ``std_msgs/String`` of JSON
  ``{"id": "category"}``, passed on as the frame's ``instance``/``instance_categories``.

Topics are found by type and name (a colour ``Image``/``CompressedImage`` with ``color``/``rgb``
in its name before any other, a depth one with ``depth``, the ``CameraInfo`` beside the colour
topic, the first ``Odometry`` or else ``/tf``) unless given: spec options
``rosbag:PATH,color=/cam/image,depth=/cam/depth,camera_info=...,odometry=...,tf=/tf,
world_frame=map,body_frame=base_link,camera_frame=rep103|optical,instance=...,
instance_categories=...``. :meth:`RosbagSource.describe` says what the
bag has and which topics are used (logged, and printed by ``openfusion run``). A bag without a
colour, depth, camera info or pose topic is refused when opened, naming what it has.

Playback: ``live = False``, so the bridge paces it at the recorded rate (the frames' stamps) or,
with ``rate_hz = 0``, as fast as geometry takes frames (flow control), like a dataset.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from openfusion.frame import Frame
from openfusion.sources.base import FrameSource, Skip, SourceError
from openfusion.sources.ros2 import (
    CAMERA_INFO,
    COMPRESSED_IMAGE,
    IMAGE,
    ODOMETRY,
    STRING,
    T_BODY_OPTICAL,
    TF_MESSAGE,
    Ros2Config,
    Ros2FrameAssembler,
    Ros2Topics,
)

logger = logging.getLogger(__name__)

#: spec options of ``rosbag:PATH,key=value,...``
OPTION_KEYS: tuple[str, ...] = ("color", "depth", "camera_info", "odometry", "tf", "instance", "instance_categories",
                                "world_frame", "body_frame", "camera_frame", "pair_tolerance_ms")
_TOPIC_KINDS = ("color", "depth", "camera_info", "odometry", "tf", "instance", "instance_categories")


def parse_rosbag_spec(rest: str) -> tuple[Path, dict[str, str]]:
    """``PATH[,key=value...]`` -> (path, options); SourceError for an unknown key or a bad item."""
    path_text, *items = rest.split(",")
    if not path_text.strip():
        raise SourceError("rosbag source needs a path: rosbag:/data/run (a bag folder) or rosbag:/data/run.mcap")
    options: dict[str, str] = {}
    for item in filter(None, (i.strip() for i in items)):
        key, sep, value = item.partition("=")
        if not sep or not value.strip():
            raise SourceError(f"rosbag option {item!r} must look like key=value (e.g. rosbag:PATH,color=/camera/image)")
        if key.strip() not in OPTION_KEYS:
            raise SourceError(f"unknown rosbag option {key.strip()!r}; known: {', '.join(OPTION_KEYS)}")
        options[key.strip()] = value.strip()
    camera = options.get("camera_frame", "rep103")
    if camera not in ("rep103", "optical"):
        raise SourceError(f"rosbag option camera_frame must be rep103 or optical, got {camera!r}")
    path = Path(path_text.strip()).expanduser()
    if not path.exists():
        raise SourceError(f"rosbag source: {path} does not exist (a rosbag2 folder, or a .mcap/.db3 file)")
    return path, options


def _last(name: str) -> str:
    return name.rstrip("/").rsplit("/", 1)[-1].lower()


def _parent(name: str) -> str:
    return name.rstrip("/").rsplit("/", 1)[0]


@dataclass(frozen=True)
class BagTopics:
    """What a bag has (topic -> type) and which topic serves each stream (kind -> topic)."""

    found: dict[str, str]
    used: dict[str, str]

    def describe(self, path: Path) -> str:
        have = ", ".join(f"{t} ({ty})" for t, ty in sorted(self.found.items()))
        use = ", ".join(f"{k}={t}" for k, t in self.used.items())
        return f"rosbag {path}: topics {have}; using {use}"


def choose_topics(found: dict[str, str], options: dict[str, str], *, path: Path) -> BagTopics:
    """Pick the topic of each stream (options first, then by type and name; module docstring)."""
    images = [t for t, ty in found.items() if ty in (IMAGE, COMPRESSED_IMAGE)]
    used: dict[str, str] = {}
    for kind in _TOPIC_KINDS:
        if kind in options:
            topic = options[kind] if options[kind].startswith("/") else "/" + options[kind]
            if topic not in found:
                raise SourceError(f"rosbag {path}: option {kind}={options[kind]} names no topic of the bag; it has "
                                  + ", ".join(f"{t} ({ty})" for t, ty in sorted(found.items())))
            used[kind] = topic

    def pick(candidates: list[str], *prefer: str) -> str | None:
        for word in prefer:
            for t in candidates:
                if word in t.lower():
                    return t
        return candidates[0] if candidates else None

    def is_depth(t: str) -> bool:
        return "depth" in t.lower()

    def is_gt(t: str) -> bool:
        return any(w in t.lower() for w in ("instance", "label", "segment", "mask"))

    taken = set(used.values())
    if "instance" not in used:
        inst = pick([t for t in images if found[t] == IMAGE and is_gt(t) and t not in taken], "instance")
        if inst:
            used["instance"] = inst
    if "color" not in used:
        color = pick([t for t in images if not is_depth(t) and not is_gt(t) and t not in taken], "color", "rgb", "image")
        if color:
            used["color"] = color
    if "depth" not in used:
        depth = pick([t for t in images if is_depth(t) and not is_gt(t) and t not in taken], "aligned", "registered",
                     "depth")
        if depth:
            used["depth"] = depth
    if "camera_info" not in used:
        infos = [t for t, ty in found.items() if ty == CAMERA_INFO]
        color_ns = _parent(_parent(used["color"])) if "color" in used else ""
        same = [t for t in infos if "depth" not in t.lower() and color_ns and t.startswith(color_ns)]
        chosen = pick(same or infos, "color", "rgb")
        if chosen:
            used["camera_info"] = chosen
    if "odometry" not in used and "tf" not in used:
        odom = pick([t for t, ty in found.items() if ty == ODOMETRY], "odom")
        if odom:
            used["odometry"] = odom
        else:
            tf = pick([t for t, ty in found.items() if ty == TF_MESSAGE and "static" not in t], "/tf")
            if tf:
                used["tf"] = tf
    if "instance" in used and "instance_categories" not in used:
        cats = pick([t for t, ty in found.items() if ty == STRING], "categor")
        if cats:
            used["instance_categories"] = cats
    missing = [k for k in ("color", "depth", "camera_info") if k not in used]
    if "odometry" not in used and "tf" not in used:
        missing.append("odometry or tf")
    if missing:
        have = ", ".join(f"{t} ({ty})" for t, ty in sorted(found.items())) or "no topics"
        raise SourceError(f"rosbag {path} has no {', no '.join(missing)} topic; it has {have}. Name topics with "
                          "rosbag:PATH,color=/topic,depth=/topic,camera_info=/topic,odometry=/topic")
    order = [k for k in _TOPIC_KINDS if k in used]
    return BagTopics(found=dict(found), used={k: used[k] for k in order})


def _open_reader(path: Path) -> Any:
    from rosbags.rosbag2 import Reader

    try:
        reader = Reader(path)
        reader.open()
    except Exception as exc:  # noqa: BLE001 - rosbags raises several types for an unreadable bag
        raise SourceError(f"rosbag {path} cannot be read as a rosbag2 (folder with metadata.yaml, .mcap or .db3): "
                          f"{type(exc).__name__}: {exc}") from None
    return reader


def inspect_bag(path: Path, options: dict[str, str] | None = None) -> BagTopics:
    """Open a bag's index only (no messages) and choose its topics; SourceError when it lacks one."""
    reader = _open_reader(path)
    try:
        found = {c.topic: c.msgtype for c in reader.connections}
    finally:
        reader.close()
    return choose_topics(found, options or {}, path=path)


class RosbagSource(FrameSource):
    """Frames of a rosbag2 recording (module docstring). ``options``: the spec options as keyword
    arguments (strings), e.g. ``RosbagSource(path, color="/cam/image", camera_frame="optical")``."""

    live = False

    def __init__(self, path: str | Path, *, max_frames: int | None = None, **options: str) -> None:
        self.path = Path(path).expanduser()
        unknown = sorted(set(options) - set(OPTION_KEYS))
        if unknown:
            raise SourceError(f"unknown rosbag option(s) {', '.join(unknown)}; known: {', '.join(OPTION_KEYS)}")
        super().__init__(f"rosbag:{self.path.name}", max_frames=max_frames)
        self.options = {k: str(v) for k, v in options.items()}
        self.topics = inspect_bag(self.path, self.options)
        used = self.topics.used
        camera = self.options.get("camera_frame", "rep103")
        ros_topics = Ros2Topics(
            color=used["color"], depth=used["depth"], camera_info=used["camera_info"],
            odometry=used.get("odometry"), tf=used.get("tf"), instance=used.get("instance"),
            instance_categories=used.get("instance_categories"),
            color_type=self.topics.found[used["color"]], depth_type=self.topics.found[used["depth"]],
        )
        kwargs: dict[str, Any] = {}
        if "pair_tolerance_ms" in self.options:
            kwargs["pair_tolerance_ns"] = int(float(self.options["pair_tolerance_ms"]) * 1e6)
        self.config = Ros2Config(
            topics=ros_topics,
            world_frame=self.options.get("world_frame", "odom" if "tf" in used else ""),
            body_frame=self.options.get("body_frame", "base_link"),
            T_body_cam=np.eye(4) if camera == "optical" else T_BODY_OPTICAL.copy(),
            **kwargs,
        )
        self._kind_of = {topic: kind for kind, topic in used.items()}
        logger.info("%s", self.describe())

    def describe(self) -> str:
        """The topics the bag has and the ones used, one line."""
        return self.topics.describe(self.path)

    def _produce(self) -> Iterator[Frame | Skip]:
        assembler = Ros2FrameAssembler(self.config, source=self.name)
        reader = _open_reader(self.path)
        try:
            connections = [c for c in reader.connections if c.topic in self._kind_of]
            for conn, _log_ns, raw in reader.messages(connections=connections):
                yield from assembler.feed(self._kind_of[conn.topic], raw, conn.msgtype)
            yield from assembler.flush()
        finally:
            reader.close()
