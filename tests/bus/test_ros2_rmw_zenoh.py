"""ROS 2 in rmw_zenoh's key layout on real Zenoh sessions: a scripted publisher puts CDR samples as an
rmw_zenoh_cpp node would (``<domain>/<topic>/<dds type>/<RIHS01 hash>`` keys, attachments with
sequence number, timestamp and GID) and the live source assembles frames, reading each sample's
type from its key (colour as CompressedImage) and counting a sequence gap; and our publisher's
answers arrive in that layout, deserialise with rosbags and announce themselves in the graph.
Bad input tried: a sample whose attachment is garbage (counted, the frame still made)."""

from __future__ import annotations

import io
import os
import threading
import time

import numpy as np
import zenoh
from PIL import Image
from ros2_support import MS, _stream, body_pose
from rosbags.typesys import Stores, get_typestore

from openfusion.bus import free_loopback_port
from openfusion.sources.cdr import (
    CompressedImageMsg,
    decode_image,
    encode_compressed_image,
    image_to_array,
)
from openfusion.sources.ros2 import T_BODY_OPTICAL, Ros2Config, Ros2Publisher, Ros2Source, Ros2Topics
from openfusion.sources.ros_layout import make_attachment, parse_attachment, topic_key
from openfusion.testing.bus import wait_for_subscriber, wait_until

TYPES = {"color": "sensor_msgs/msg/CompressedImage", "depth": "sensor_msgs/msg/Image",
         "camera_info": "sensor_msgs/msg/CameraInfo", "odometry": "nav_msgs/msg/Odometry"}


def _conf(port: int, *, listen: bool) -> zenoh.Config:
    c = zenoh.Config()
    c.insert_json5("mode", '"peer"')
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("listen/endpoints" if listen else "connect/endpoints", f'["tcp/127.0.0.1:{port}"]')
    return c


def _as_png(payload: bytes) -> bytes:
    """The scripted rig's colour Image, re-sent as a PNG CompressedImage."""
    msg = decode_image(payload)
    buf = io.BytesIO()
    Image.fromarray(image_to_array(msg)).save(buf, format="PNG")
    return encode_compressed_image(CompressedImageMsg(msg.header, "png", buf.getvalue()))


def test_live_source_in_the_rmw_zenoh_layout() -> None:
    port = free_loopback_port()
    topics = Ros2Topics(layout="rmw_zenoh", domain_id=7)
    with zenoh.open(_conf(port, listen=True)) as pub_session:
        source = Ros2Source(Ros2Config(topics=topics), zenoh_config=_conf(port, listen=False), idle_timeout_s=1.0)
        assert source.keys["color"] == "7/camera/color/image_raw/*/*"
        keys = {kind: topic_key(topics.streams()[kind], layout="rmw_zenoh", domain_id=7, typename=TYPES[kind])
                for kind in TYPES}
        for key in keys.values():
            wait_for_subscriber(pub_session, key)
        gids = {kind: os.urandom(16) for kind in TYPES}  # one GID per publisher, as rmw_zenoh gives
        publishers = {kind: pub_session.declare_publisher(key) for kind, key in keys.items()}

        def publish() -> None:
            seq = dict.fromkeys(TYPES, 0)
            for i, (kind, payload) in enumerate(_stream()):
                seq[kind] += 1
                if kind == "odometry" and seq[kind] == 30:
                    seq[kind] += 1  # one odometry sample "lost" on the way: a gap of one
                attachment = make_attachment(seq[kind], time.time_ns(), gids[kind])
                if i == 0:  # the CameraInfo (its only sample)
                    attachment = b"\x01garbage"  # bad input: unreadable attachment, payload still good
                publishers[kind].put(_as_png(payload) if kind == "color" else payload, attachment=attachment)
                time.sleep(0.002)  # a camera's pace, not a wait: the source's queue holds 256 samples

        thread = threading.Thread(target=publish)
        thread.start()
        try:
            frames = list(source)
        finally:
            thread.join()
            source.close()
            for pub in publishers.values():
                pub.undeclare()
    assert [f.stamp_ns for f in frames] == [k * 100 * MS + 3 * MS for k in range(1, 6)]
    assert source.dropped_samples == 0 and source.lost_samples == 1 and source.bad_attachments == 1
    for f in frames:
        np.testing.assert_allclose(f.T_world_cam, body_pose(f.stamp_ns) @ T_BODY_OPTICAL, atol=2e-4)
        assert f.color.dtype == np.uint8 and f.color.shape == (24, 32, 3)


def test_publisher_answers_arrive_in_the_rmw_zenoh_layout_and_deserialise_with_rosbags() -> None:
    from types import SimpleNamespace

    from openfusion.app.ros_publish_cmd import QUERY_MARKERS_TOPIC, QUERY_POINTS_TOPIC, publish_answers

    port = free_loopback_port()
    ts = get_typestore(Stores.ROS2_HUMBLE)
    got: list[tuple[str, bytes, bytes | None]] = []
    with zenoh.open(_conf(port, listen=True)) as robot, zenoh.open(_conf(port, listen=False)) as ours:
        sub = robot.declare_subscriber("0/openfusion/query/**",
                                       lambda s: got.append((str(s.key_expr), s.payload.to_bytes(),
                                                             s.attachment.to_bytes() if s.attachment else None)))
        publisher = Ros2Publisher(ours, layout="rmw_zenoh", distro="humble")
        markers_key = publisher.key(QUERY_MARKERS_TOPIC, "visualization_msgs/msg/MarkerArray")
        wait_for_subscriber(ours, markers_key)
        hit = SimpleNamespace(key=3, score=0.7, label="lamp", bbox_min=np.zeros(3), bbox_max=np.ones(3),
                              points=np.random.default_rng(0).random((10, 3)))
        reply = SimpleNamespace(regions=[hit])
        for _ in range(2):
            publish_answers(publisher, ["lamp"], [reply], frame_id="map", stamp_ns=1, distro="humble")
        wait_until(lambda: len(got) >= 4, timeout_s=30)
        tokens = [str(r.ok.key_expr) for r in robot.liveliness().get("@ros2_lv/0/**") if r.ok is not None]
        publisher.close()
        sub.undeclare()
    by_key: dict[str, list] = {}
    for key, payload, attachment in got:
        by_key.setdefault(key, []).append((payload, attachment))
    points_key = topic_key(QUERY_POINTS_TOPIC, layout="rmw_zenoh", typename="sensor_msgs/msg/PointCloud2",
                           distro="humble")
    assert set(by_key) == {markers_key, points_key}
    assert markers_key.startswith("0/openfusion/query/markers/visualization_msgs::msg::dds_::MarkerArray_/RIHS01_")
    markers = ts.deserialize_cdr(by_key[markers_key][0][0], "visualization_msgs/msg/MarkerArray").markers
    assert markers[2].text == "lamp 0.70"
    assert ts.deserialize_cdr(by_key[points_key][0][0], "sensor_msgs/msg/PointCloud2").width == 10
    seqs = [parse_attachment(att).sequence_number for _payload, att in by_key[markers_key]]
    assert seqs == [1, 2]
    assert any("/NN/%/%/openfusion" in t for t in tokens)
    assert any("/MP/%/%/openfusion/%openfusion%query%markers/visualization_msgs::msg::dds_::MarkerArray_/" in t
               for t in tokens), tokens
