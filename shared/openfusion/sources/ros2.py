"""ROS 2 topics over Zenoh as a frame source, without a ROS install.

Two key layouts (``openfusion.sources.ros_layout``), chosen by ``Ros2Topics.layout``:
``bridge`` (zenoh-bridge-ros2dds: topic ``/ns/topic`` on key ``ns/topic``) and ``rmw_zenoh``
(ROS 2 nodes run with ``RMW_IMPLEMENTATION=rmw_zenoh_cpp``: ``<domain_id>/<topic>/<type>/<hash>``,
the type read from each sample's key, sequence gaps counted from its attachment). Payloads are CDR,
decoded through ``rosbags`` (``openfusion.sources.cdr``). ``Ros2Source`` subscribes to a color
image, a registered depth image (e.g. ``aligned_depth_to_color``), the color ``CameraInfo`` and
either ``Odometry`` or ``TFMessage``, and assembles canonical frames. ``Ros2FrameAssembler`` is the
pure logic; the rosbag2 reader (``openfusion.sources.rosbag``) feeds the same assembler.

The pure part, topics, config and the assembler with what it converts from ROS conventions, is
:mod:`openfusion.sources.ros2_frames` (its names are re-exported here); here the Zenoh side: the
source's subscriptions, the publisher, and the ``ros2:`` source spec.

Decoding happens in the iterating thread: Zenoh callbacks only hand the payload to a bounded
queue (a full queue drops the sample and counts it), so a slow consumer never blocks the bus.
"""

from __future__ import annotations

import json
import logging
import os
import queue
import threading
import time
from collections.abc import Iterator
from typing import Any

import numpy as np

from openfusion.frame import Frame
from openfusion.sources.base import FrameSource, Skip
from openfusion.sources.cdr import CdrError, dds_type_name, type_hash
from openfusion.sources.ros2_frames import CAMERA_INFO as CAMERA_INFO
from openfusion.sources.ros2_frames import COMPRESSED_IMAGE as COMPRESSED_IMAGE
from openfusion.sources.ros2_frames import IMAGE as IMAGE
from openfusion.sources.ros2_frames import KIND_TYPES as KIND_TYPES
from openfusion.sources.ros2_frames import ODOMETRY as ODOMETRY
from openfusion.sources.ros2_frames import STRING as STRING
from openfusion.sources.ros2_frames import (  # the pure part; names re-exported, callers name them here
    T_BODY_OPTICAL,
    Ros2Config,
    Ros2FrameAssembler,
    Ros2Topics,
)
from openfusion.sources.ros2_frames import TF_MESSAGE as TF_MESSAGE
from openfusion.sources.ros2_frames import guess_image_type as guess_image_type
from openfusion.sources.ros_layout import LAYOUTS, make_attachment, parse_attachment, topic_key, type_from_key

logger = logging.getLogger(__name__)


class Ros2Source(FrameSource):
    """Frames from ROS 2 topics over Zenoh, in either key layout (see module docstring).

    ``session``: an open ``zenoh.Session`` to subscribe with (shared with the caller), or None
    to open one from ``zenoh_config`` (a ``zenoh.Config``; default: peer mode). Iteration ends
    after ``idle_timeout_s`` without samples (None: runs until ``close()``).

    Counters: ``dropped_samples`` (the bounded queue was full), ``lost_samples`` (rmw_zenoh layout:
    gaps in a publisher's sequence numbers, read from the attachments), ``bad_attachments``.
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
        config = config or Ros2Config()
        t = config.topics
        where = f"domain {t.domain_id}" if t.layout == "rmw_zenoh" else (t.namespace or "default")
        super().__init__(f"ros2[{t.layout}]:{where}", max_frames=max_frames)
        self.config = config
        self.idle_timeout_s = idle_timeout_s
        self._queue: queue.Queue[tuple[str, bytes, str | None]] = queue.Queue(maxsize=queue_size)
        self.dropped_samples = 0
        self.lost_samples = 0
        self.bad_attachments = 0
        self._last_seq: dict[bytes, int] = {}
        self._closed = threading.Event()
        import zenoh  # the core dependency; imported here so decoding alone never needs it

        self._own_session = session is None
        self._session = session if session is not None else zenoh.open(zenoh_config or zenoh.Config())
        self.keys = {kind: t.subscription_key(kind) for kind in t.streams()}
        self._subscribers = [
            self._session.declare_subscriber(key, self._callback(kind)) for kind, key in self.keys.items()
        ]
        logger.info("ROS 2 source (%s layout) subscribed to %s", t.layout, self.keys)

    def _callback(self, kind: str):  # noqa: ANN202 - zenoh sample handler
        rmw_zenoh = self.config.topics.layout == "rmw_zenoh"

        def on_sample(sample: Any) -> None:
            typename = None
            if rmw_zenoh:
                typename = type_from_key(str(sample.key_expr))
                self._count_sequence(sample.attachment)
            try:
                self._queue.put_nowait((kind, sample.payload.to_bytes(), typename))
            except queue.Full:
                self.dropped_samples += 1

        return on_sample

    def _count_sequence(self, attachment: Any) -> None:
        """rmw_zenoh: a gap in one publisher's sequence numbers counts the samples lost on the way."""
        try:
            att = parse_attachment(attachment.to_bytes() if attachment is not None else None)
        except CdrError as exc:
            if not self.bad_attachments:
                logger.warning("ROS 2 source: a sample's rmw_zenoh attachment is unreadable (%s); counted", exc)
            self.bad_attachments += 1
            return
        last = self._last_seq.get(att.source_gid)
        if last is not None and att.sequence_number > last + 1:
            self.lost_samples += att.sequence_number - last - 1
        self._last_seq[att.source_gid] = att.sequence_number

    def _produce(self) -> Iterator[Frame | Skip]:
        assembler = Ros2FrameAssembler(self.config, source=self.name)
        last = time.monotonic()
        while not self._closed.is_set():
            try:
                kind, payload, typename = self._queue.get(timeout=0.05)
            except queue.Empty:
                if self.idle_timeout_s is not None and time.monotonic() - last > self.idle_timeout_s:
                    break
                continue
            last = time.monotonic()
            yield from assembler.feed(kind, payload, typename)
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


class Ros2Publisher:
    """Publishes CDR payloads on ROS 2 topics over Zenoh, in the ``bridge`` or ``rmw_zenoh`` layout
    (``openfusion.sources.ros_layout``), so ROS 2 tools (RViz, Foxglove, ``ros2 topic echo``) get them.

    ``bridge``: a plain put on ``[namespace/]topic``; zenoh-bridge-ros2dds on the ROS side turns it
    into a DDS publication once a ROS node subscribes (the bridge routes Zenoh -> DDS for the topics
    ROS subscribers ask for, with the type the subscriber declares).
    ``rmw_zenoh``: a put on ``<domain>/<topic>/<dds type>/<RIHS01 hash>`` of the ``distro``'s type
    definition, with the attachment (sequence number, source timestamp, this publisher's GID), and
    liveliness tokens for the node (``openfusion``) and each publisher in rmw_zenoh's graph format
    (``@ros2_lv/<domain>/<zid>/<node id>/<entity id>/<NN|MP>/%/<namespace>/<node>[/<topic>/<type>/
    <hash>/<qos>]``), so ``ros2 topic list`` on the robot shows the topics.
    """

    NODE_NAME = "openfusion"

    def __init__(self, session: Any, *, layout: str = "bridge", namespace: str = "", domain_id: int = 0,
                 distro: str = "jazzy", keyed_attachment: bool = False) -> None:
        if layout not in LAYOUTS:
            raise ValueError(f"unknown key layout {layout!r}; known: {', '.join(LAYOUTS)}")
        self.session = session
        self.layout = layout
        self.namespace = namespace.strip("/")
        self.domain_id = int(domain_id)
        self.distro = distro
        self.keyed_attachment = keyed_attachment
        self._publishers: dict[tuple[str, str], Any] = {}
        self._tokens: list[Any] = []
        self._seq: dict[str, int] = {}
        self._gids: dict[str, bytes] = {}
        self._zid = str(session.info.zid())
        if layout == "rmw_zenoh":
            ns = "%" + self.namespace.replace("/", "%") if self.namespace else "%"
            self._tokens.append(session.liveliness().declare_token(
                f"@ros2_lv/{self.domain_id}/{self._zid}/0/0/NN/%/{ns}/{self.NODE_NAME}"))

    def key(self, topic: str, typename: str) -> str:
        return topic_key(topic, layout=self.layout, namespace=self.namespace, domain_id=self.domain_id,
                         typename=typename, distro=self.distro)

    def _publisher(self, topic: str, typename: str) -> Any:
        pub = self._publishers.get((topic, typename))
        if pub is None:
            import zenoh

            key = self.key(topic, typename)
            # block rather than drop when the link's queue is full: a map cloud is megabytes, sent
            # seconds apart, and a dropped one is gone until the next round (ROS "reliable")
            pub = self.session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
            self._publishers[(topic, typename)] = pub
            if self.layout == "rmw_zenoh":
                self._gids[key] = os.urandom(16)
                ns = "%" + self.namespace.replace("/", "%") if self.namespace else "%"
                fq = "/" + "/".join(p for p in (self.namespace, topic.strip("/")) if p)
                entity = len(self._publishers) + 10
                self._tokens.append(self.session.liveliness().declare_token(
                    f"@ros2_lv/{self.domain_id}/{self._zid}/0/{entity}/MP/%/{ns}/{self.NODE_NAME}/"
                    f"{fq.replace('/', '%')}/{dds_type_name(typename)}/{type_hash(typename, distro=self.distro)}/"
                    "::,1:,:,:,,"))
            logger.info("publishing ROS 2 topic %s (%s) on %s", topic, typename, key)
        return pub

    def wait_for_subscribers(self, topics: list[tuple[str, str]], timeout_s: float) -> list[str]:
        """Declare the publishers of ``topics`` ((topic, typename) pairs) and wait up to ``timeout_s``
        until each has a matching subscriber (a one-shot round would otherwise go out before the
        route to a subscriber that is already there exists). Returns the topics still without one."""
        from openfusion.bus.session import is_matching  # the bus (and zenoh) only where publishing

        pubs = {topic: self._publisher(topic, typename) for topic, typename in topics}
        deadline = time.monotonic() + timeout_s
        while True:
            waiting = [t for t, pub in pubs.items() if not is_matching(pub.matching_status)]
            if not waiting or time.monotonic() >= deadline:
                return waiting
            time.sleep(0.02)

    def publish(self, topic: str, typename: str, payload: bytes) -> None:
        """Put one CDR ``payload`` of ``typename`` on ``topic``."""
        pub = self._publisher(topic, typename)
        if self.layout != "rmw_zenoh":
            pub.put(payload)
            return
        key = self.key(topic, typename)
        seq = self._seq.get(key, 0) + 1
        self._seq[key] = seq
        pub.put(payload, attachment=make_attachment(seq, time.time_ns(), self._gids[key], keyed=self.keyed_attachment))

    def flush(self, timeout_s: float = 10.0) -> None:
        """Return once what was put has left this session: one query through the router on a key
        no queryable serves (the router's final reply comes back on the same link, after the puts
        queued before the query). Closing a session drops what its queue still holds: a one-shot
        round's map cloud (megabytes, sent last) was lost that way when ``--once`` exited at once."""
        replies = self.session.get(f"openfusion/@flush/{os.urandom(8).hex()}", timeout=timeout_s)
        for _reply in replies:  # none expected: the iteration ends with the router's final reply
            pass

    def close(self) -> None:
        for pub in self._publishers.values():
            pub.undeclare()
        for token in self._tokens:
            token.undeclare()
        self._publishers, self._tokens = {}, []


#: options of the ``ros2:key=value,...`` source spec
SPEC_KEYS: tuple[str, ...] = ("layout", "connect", "namespace", "domain_id", "color", "depth", "camera_info",
                              "odometry", "tf", "world_frame", "body_frame", "camera_frame", "idle_timeout_s")


def ros2_config_from_spec(options: dict[str, str]) -> tuple[Ros2Config, dict[str, Any]]:
    """(config, Ros2Source keyword arguments) of ``ros2:`` spec options (strings); ValueError naming
    a bad one. ``connect=tcp/IP:PORT`` joins that Zenoh endpoint (the bridge's, or ``rmw_zenohd``'s
    ``tcp/ROBOT:7447``) in client mode; without it the session is a peer with multicast scouting."""
    unknown = sorted(set(options) - set(SPEC_KEYS))
    if unknown:
        raise ValueError(f"unknown ros2 option(s) {', '.join(unknown)}; known: {', '.join(SPEC_KEYS)}")
    topic_args: dict[str, Any] = {k: options[k] for k in ("color", "depth", "camera_info", "namespace") if k in options}
    if "odometry" in options or "tf" in options:
        topic_args["odometry"] = options.get("odometry")
        topic_args["tf"] = options.get("tf")
    topic_args["layout"] = options.get("layout", "bridge")
    topic_args["domain_id"] = int(options.get("domain_id", "0"))
    camera = options.get("camera_frame", "rep103")
    if camera not in ("rep103", "optical"):
        raise ValueError(f"camera_frame must be rep103 or optical, got {camera!r}")
    config = Ros2Config(topics=Ros2Topics(**topic_args), world_frame=options.get("world_frame", "odom"),
                        body_frame=options.get("body_frame", "base_link"),
                        T_body_cam=np.eye(4) if camera == "optical" else T_BODY_OPTICAL.copy())
    kwargs: dict[str, Any] = {}
    if "idle_timeout_s" in options:
        kwargs["idle_timeout_s"] = float(options["idle_timeout_s"])
    if "connect" in options:
        import zenoh

        zconf = zenoh.Config()
        zconf.insert_json5("mode", '"client"')
        zconf.insert_json5("connect/endpoints", json.dumps([options["connect"]]))
        kwargs["zenoh_config"] = zconf
    return config, kwargs
