"""Write any frame source as a rosbag2 (sqlite3 or MCAP) with ``rosbags``' writer: the inverse of
:mod:`openfusion.sources.rosbag`, for tests, demos and users who want a bag of a dataset.

Per frame, all stamped with the frame's ``stamp_ns``: ``/odom`` (``nav_msgs/Odometry``, world
``odom`` -> body ``base_link``, body pose ``T_world_cam @ inv(T_BODY_OPTICAL)``, so the reader's
default REP-103 camera mount gives ``T_world_cam`` back), ``/camera/color/camera_info``,
``/camera/color/image_raw`` (``rgb8``) or ``.../compressed`` (JPEG/PNG),
``/camera/aligned_depth_to_color/image_raw`` (``16UC1`` mm, or ``32FC1`` m for float depth) or
``.../compressedDepth`` (PNG 16-bit), and with ground truth ``/openfusion/instance`` (``32SC1``)
and ``/openfusion/instance_categories`` (``std_msgs/String``, JSON).
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from openfusion.frame import Frame
from openfusion.poses import matrix_to_quat
from openfusion.sources.cdr import (
    CameraInfoMsg,
    Header,
    OdometryMsg,
    array_to_compressed,
    array_to_image,
    encode_camera_info,
    encode_compressed_image,
    encode_image,
    encode_odometry,
    encode_string,
    typestore,
)
from openfusion.sources.ros2 import CAMERA_INFO, COMPRESSED_IMAGE, IMAGE, ODOMETRY, STRING, T_BODY_OPTICAL

COLOR_TOPIC = "/camera/color/image_raw"
DEPTH_TOPIC = "/camera/aligned_depth_to_color/image_raw"
INFO_TOPIC = "/camera/color/camera_info"
ODOM_TOPIC = "/odom"
INSTANCE_TOPIC = "/openfusion/instance"
CATEGORIES_TOPIC = "/openfusion/instance_categories"


def write_rosbag(
    frames: Iterable[Frame],
    path: str | Path,
    *,
    storage: str = "mcap",
    distro: str = "jazzy",
    color_format: str = "rgb8",
    depth_format: str = "16UC1",
    with_instances: bool = True,
) -> int:
    """Write ``frames`` to a new bag folder ``path``; returns the number of frames written.

    ``storage``: ``mcap`` or ``sqlite3``. ``color_format``: ``rgb8``, ``bgr8``, ``jpeg`` or ``png``
    (the last two as ``CompressedImage``). ``depth_format``: ``16UC1`` (raw) or ``compressedDepth``.
    """
    from rosbags.rosbag2 import StoragePlugin, Writer

    plugins = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}
    if storage not in plugins:
        raise ValueError(f"storage must be mcap or sqlite3, got {storage!r}")
    store = typestore(distro)
    compressed_color = color_format in ("jpeg", "png")
    compressed_depth = depth_format == "compressedDepth"
    color_topic = COLOR_TOPIC.rsplit("/", 1)[0] + "/compressed" if compressed_color else COLOR_TOPIC
    depth_topic = DEPTH_TOPIC.rsplit("/", 1)[0] + "/compressedDepth" if compressed_depth else DEPTH_TOPIC
    T_optical_body = np.linalg.inv(T_BODY_OPTICAL)
    count = 0
    with Writer(Path(path), version=9, storage_plugin=plugins[storage]) as writer:
        conn = {
            "odom": writer.add_connection(ODOM_TOPIC, ODOMETRY, typestore=store),
            "info": writer.add_connection(INFO_TOPIC, CAMERA_INFO, typestore=store),
            "color": writer.add_connection(color_topic, COMPRESSED_IMAGE if compressed_color else IMAGE, typestore=store),
            "depth": writer.add_connection(depth_topic, COMPRESSED_IMAGE if compressed_depth else IMAGE, typestore=store),
        }
        if with_instances:
            conn["instance"] = writer.add_connection(INSTANCE_TOPIC, IMAGE, typestore=store)
            conn["categories"] = writer.add_connection(CATEGORIES_TOPIC, STRING, typestore=store)
        for frame in frames:
            t = int(frame.stamp_ns)
            h, w = frame.depth.shape
            T_body = np.asarray(frame.T_world_cam, dtype=np.float64) @ T_optical_body
            odo = OdometryMsg(Header(t, "odom"), "base_link", T_body[:3, 3], matrix_to_quat(T_body[:3, :3]))
            writer.write(conn["odom"], t, encode_odometry(odo, distro=distro))
            K = frame.intrinsics.K
            info = CameraInfoMsg(Header(t, "camera_color_optical_frame"), h, w, "plumb_bob", np.zeros(5), K, np.eye(3),
                                 np.hstack([K, np.zeros((3, 1))]))
            writer.write(conn["info"], t, encode_camera_info(info, distro=distro))
            if with_instances and frame.instance is not None:
                cats = json.dumps({str(k): v for k, v in sorted(frame.instance_categories.items())})
                writer.write(conn["categories"], t, encode_string(cats, distro=distro))
            frame_id = "camera_color_optical_frame"
            if compressed_color:
                msg = array_to_compressed(frame.color, color_format, stamp_ns=t, frame_id=frame_id)
                writer.write(conn["color"], t, encode_compressed_image(msg, distro=distro))
            else:
                img = array_to_image(frame.color, color_format, stamp_ns=t, frame_id=frame_id)
                writer.write(conn["color"], t, encode_image(img, distro=distro))
            if compressed_depth:
                depth_mm = _depth_mm(frame)
                msg = array_to_compressed(depth_mm, "16UC1; compressedDepth png", stamp_ns=t, frame_id=frame_id)
                writer.write(conn["depth"], t, encode_compressed_image(msg, distro=distro))
            else:
                if frame.depth.dtype == np.uint16 and frame.depth_scale != 1000.0:
                    depth, enc = _depth_mm(frame), "16UC1"
                elif frame.depth.dtype == np.uint16:
                    depth, enc = frame.depth, "16UC1"
                else:
                    depth, enc = frame.depth.astype(np.float32), "32FC1"
                writer.write(conn["depth"], t, encode_image(array_to_image(depth, enc, stamp_ns=t, frame_id=frame_id),
                                                            distro=distro))
            if with_instances and frame.instance is not None:
                inst = array_to_image(frame.instance.astype(np.int32), "32SC1", stamp_ns=t, frame_id=frame_id)
                writer.write(conn["instance"], t, encode_image(inst, distro=distro))
            count += 1
    return count


def _depth_mm(frame: Frame) -> np.ndarray:
    """Depth as uint16 millimetres (the ROS 16UC1 convention)."""
    metres = frame.depth.astype(np.float64) / float(frame.depth_scale)
    return np.clip(np.round(metres * 1000.0), 0, 65535).astype(np.uint16)
