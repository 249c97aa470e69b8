"""The ROS 2 source on a real Zenoh session: frames published in the zenoh-bridge-ros2dds key
layout over loopback are assembled into canonical frames."""

from __future__ import annotations

import socket
import threading
import time

import numpy as np

from openfusion.poses import matrix_to_quat, pose_from_tum
from openfusion.sources.cdr import (
    CameraInfoMsg,
    Header,
    OdometryMsg,
    array_to_image,
    encode_camera_info,
    encode_image,
    encode_odometry,
)
from openfusion.sources.ros2 import T_BODY_OPTICAL, Ros2Config, Ros2Source, Ros2Topics
from openfusion.testing.bus import wait_for_subscriber

MS = 1_000_000


def body_pose(t_ns: int) -> np.ndarray:
    t = t_ns / 1e9
    yaw = 0.5 * t
    T = np.eye(4)
    T[:3, :3] = [[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]]
    T[:3, 3] = [t, 0.2 * t, 0.0]
    return T


def _odom(t_ns: int, frame: str = "odom") -> bytes:
    T = body_pose(t_ns)
    return encode_odometry(OdometryMsg(Header(t_ns, frame), "base_link", T[:3, 3], matrix_to_quat(T[:3, :3])))


K = np.array([[50.0, 0, 15.5], [0, 51.0, 11.5], [0, 0, 1]])


def _info() -> bytes:
    return encode_camera_info(
        CameraInfoMsg(Header(0, "cam"), 24, 32, "plumb_bob", np.zeros(5), K, np.eye(3), np.hstack([K, np.zeros((3, 1))]))
    )


def _stream(depth_encoding: str = "16UC1"):
    """(kind, payload) in arrival order: CameraInfo, 100 Hz odometry, 10 Hz color+depth."""
    rng = np.random.default_rng(0)
    events = [(0, "camera_info", _info())]
    for k in range(60):
        events.append((k * 10 * MS + 2 * MS, "odometry", _odom(k * 10 * MS)))
    for k in range(1, 6):
        t = k * 100 * MS + 3 * MS
        color = rng.integers(0, 255, (24, 32, 3), dtype=np.uint8)
        if depth_encoding == "16UC1":
            depth = rng.integers(0, 5000, (24, 32), dtype=np.uint16)
        else:
            depth = rng.random((24, 32), dtype=np.float32) * 3
        events.append((t + 20 * MS, "color", encode_image(array_to_image(color, "bgr8", stamp_ns=t, frame_id="cam"))))
        events.append((t + 25 * MS, "depth", encode_image(array_to_image(depth, depth_encoding, stamp_ns=t, frame_id="cam"))))
    events.sort(key=lambda e: e[0])
    return [(kind, payload) for _, kind, payload in events]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _pose_parts(t_ns: int):  # noqa: ANN202 - test helper
    T = body_pose(t_ns)
    return T[:3, 3], matrix_to_quat(T[:3, :3])


def test_loopback_zenoh_source() -> None:
    """End to end on loopback: a publisher session puts CDR payloads on the keys a
    zenoh-bridge-ros2dds with namespace 'bot1' would use; Ros2Source yields the frames."""
    import zenoh

    port = _free_port()

    def conf(*, listen: bool) -> zenoh.Config:
        c = zenoh.Config()
        c.insert_json5("mode", '"peer"')
        c.insert_json5("scouting/multicast/enabled", "false")
        if listen:
            c.insert_json5("listen/endpoints", f'["tcp/127.0.0.1:{port}"]')
        else:
            c.insert_json5("connect/endpoints", f'["tcp/127.0.0.1:{port}"]')
        return c

    topics = Ros2Topics(namespace="bot1")
    with zenoh.open(conf(listen=True)) as pub_session:
        source = Ros2Source(Ros2Config(topics=topics), zenoh_config=conf(listen=False), idle_timeout_s=1.0)
        assert source.keys["color"] == "bot1/camera/color/image_raw"
        keys = source.keys
        for key in keys.values():  # the source's subscriptions have reached the publishing session
            wait_for_subscriber(pub_session, key)

        def publish() -> None:
            for kind, payload in _stream():
                pub_session.put(keys[kind], payload)
                time.sleep(0.002)  # a camera's pace, not a wait: the source's queue holds 256 samples

        thread = threading.Thread(target=publish)
        thread.start()
        try:
            frames = list(source)
        finally:
            thread.join()
            source.close()
    assert [f.stamp_ns for f in frames] == [k * 100 * MS + 3 * MS for k in range(1, 6)]
    assert source.dropped_samples == 0
    np.testing.assert_allclose(
        frames[-1].T_world_cam, pose_from_tum(*_pose_parts(frames[-1].stamp_ns)) @ T_BODY_OPTICAL, atol=2e-4
    )
