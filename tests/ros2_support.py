"""A scripted ROS 2 camera rig for the ROS 2 source's tests (tests/unit and tests/bus): CDR-encoded
CameraInfo, 100 Hz odometry of a moving body and 10 Hz color + depth images, in arrival order."""

from __future__ import annotations

import numpy as np

from openfusion.poses import matrix_to_quat
from openfusion.sources.cdr import (
    CameraInfoMsg,
    Header,
    OdometryMsg,
    array_to_image,
    encode_camera_info,
    encode_image,
    encode_odometry,
)

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
