"""Bags for the rosbag2 tests, written with rosbags' own writer and rosbags' own message classes (the
independent implementation: nothing of openfusion's encoders is used), and the f-mIoU of a map of
the synthetic scene (the ConceptFusion protocol of openfusion.eval, on the world's ground truth)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from openfusion.frame import Frame
from openfusion.poses import matrix_to_quat
from openfusion.sources.ros2 import T_BODY_OPTICAL

STORES = {"humble": Stores.ROS2_HUMBLE, "jazzy": Stores.ROS2_JAZZY}
PLUGINS = {"sqlite3": StoragePlugin.SQLITE3, "mcap": StoragePlugin.MCAP}


class RosbagsMessages:
    """Messages built with a rosbags type store's classes and serialised by rosbags."""

    def __init__(self, distro: str) -> None:
        self.ts = get_typestore(STORES[distro])
        self.t = self.ts.types

    def cdr(self, msg: object) -> bytes:
        return bytes(self.ts.serialize_cdr(msg, msg.__msgtype__))

    def header(self, stamp_ns: int, frame_id: str) -> object:
        sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
        return self.t["std_msgs/msg/Header"](stamp=self.t["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec),
                                             frame_id=frame_id)

    def image(self, arr: np.ndarray, encoding: str, stamp_ns: int, *, data: bytes | None = None,
              height: int | None = None, width: int | None = None) -> object:
        a = np.ascontiguousarray(arr)
        h, w = a.shape[:2]
        raw = a.tobytes() if data is None else data
        step = len(a.tobytes()) // h
        return self.t["sensor_msgs/msg/Image"](header=self.header(stamp_ns, "cam"), height=height or h, width=width or w,
                                               encoding=encoding, is_bigendian=0, step=step,
                                               data=np.frombuffer(raw, np.uint8))

    def compressed(self, payload: bytes, fmt: str, stamp_ns: int) -> object:
        return self.t["sensor_msgs/msg/CompressedImage"](header=self.header(stamp_ns, "cam"), format=fmt,
                                                         data=np.frombuffer(payload, np.uint8))

    def camera_info(self, K: np.ndarray, w: int, h: int, stamp_ns: int) -> object:
        roi = self.t["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        return self.t["sensor_msgs/msg/CameraInfo"](
            header=self.header(stamp_ns, "cam"), height=h, width=w, distortion_model="plumb_bob", d=np.zeros(5),
            k=np.asarray(K, float).ravel(), r=np.eye(3).ravel(), p=np.hstack([K, np.zeros((3, 1))]).ravel(),
            binning_x=0, binning_y=0, roi=roi)

    def odometry(self, T_world_body: np.ndarray, stamp_ns: int) -> object:
        t = self.t
        p, q = T_world_body[:3, 3], matrix_to_quat(T_world_body[:3, :3])
        pose = t["geometry_msgs/msg/Pose"](position=t["geometry_msgs/msg/Point"](x=p[0], y=p[1], z=p[2]),
                                           orientation=t["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]))
        vec = t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
        return t["nav_msgs/msg/Odometry"](
            header=self.header(stamp_ns, "odom"), child_frame_id="base_link",
            pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
            twist=t["geometry_msgs/msg/TwistWithCovariance"](twist=t["geometry_msgs/msg/Twist"](linear=vec, angular=vec),
                                                              covariance=np.zeros(36)))

    def string(self, text: str) -> object:
        return self.t["std_msgs/msg/String"](data=text)


def write_frames_bag(path: Path, frames: list[Frame], *, storage: str, distro: str, extra=None) -> None:  # noqa: ANN001
    """A bag of ``frames`` (rgb8 colour, 16UC1 depth, CameraInfo, odometry of the REP-103 body,
    32SC1 instances + categories) written by rosbags; ``extra(writer, msgs, conns)`` may add more."""
    m = RosbagsMessages(distro)
    T_optical_body = np.linalg.inv(T_BODY_OPTICAL)
    with Writer(path, version=9, storage_plugin=PLUGINS[storage]) as w:
        conns = {
            "odom": w.add_connection("/odom", "nav_msgs/msg/Odometry", typestore=m.ts),
            "info": w.add_connection("/camera/color/camera_info", "sensor_msgs/msg/CameraInfo", typestore=m.ts),
            "color": w.add_connection("/camera/color/image_raw", "sensor_msgs/msg/Image", typestore=m.ts),
            "depth": w.add_connection("/camera/aligned_depth_to_color/image_raw", "sensor_msgs/msg/Image", typestore=m.ts),
            "instance": w.add_connection("/gt/instance", "sensor_msgs/msg/Image", typestore=m.ts),
            "cats": w.add_connection("/gt/instance_categories", "std_msgs/msg/String", typestore=m.ts),
        }
        for f in frames:
            t = f.stamp_ns
            h, wpx = f.depth.shape
            w.write(conns["odom"], t, m.cdr(m.odometry(f.T_world_cam @ T_optical_body, t)))
            w.write(conns["info"], t, m.cdr(m.camera_info(f.intrinsics.K, wpx, h, t)))
            w.write(conns["cats"], t, m.cdr(m.string(json.dumps({str(k): v for k, v in f.instance_categories.items()}))))
            w.write(conns["color"], t, m.cdr(m.image(f.color, "rgb8", t)))
            w.write(conns["depth"], t, m.cdr(m.image(f.depth.astype("<u2"), "16UC1", t)))
            w.write(conns["instance"], t, m.cdr(m.image(f.instance.astype("<i4"), "32SC1", t)))
            if extra is not None:
                extra(w, m, conns, f)


def synthetic_f_miou(volume: object, dictionary: object, *, seed: int, text_encoder: object,
                     spacing_m: float = 0.05) -> float:
    """f-mIoU of a map of ``synthetic:seed=N`` against the world's ground truth (every class queried)."""
    from openfusion.eval.saved_map import synthetic_map_quality

    return synthetic_map_quality(volume, dictionary, seed=seed, text_encoder=text_encoder, spacing_m=spacing_m)["f_mIoU"]
