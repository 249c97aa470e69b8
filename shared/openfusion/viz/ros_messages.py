"""Map answers as ROS 2 messages, so RViz and Foxglove show them: ``sensor_msgs/PointCloud2`` and
``visualization_msgs/MarkerArray``, serialised to CDR with ``rosbags`` (Humble or Jazzy layout).

PointCloud2 layout (one row, ``is_dense``, little-endian, 20 bytes a point): ``x``, ``y``, ``z``
float32 (metres, world frame) at offsets 0/4/8; ``rgb`` at 12 as RViz reads colour (float32 field
whose bytes are the packed ``0x00RRGGBB`` uint32); ``region`` int32 at 16 (region key, -1 = none).
RViz: PointCloud2 display, Color Transformer "RGB8"; Foxglove: colour by ``rgb`` or ``region``.

MarkerArray of a query answer: a DELETEALL first (the previous answer's markers go), then per
region a translucent CUBE on its bounding box (namespace ``openfusion/boxes``, id = rank) and a
TEXT_VIEW_FACING label ``"<label> <score>"`` above it (``openfusion/labels``); colour = the
answer's highlight colour for its rank (``openfusion.viz.palette``).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from openfusion.sources.cdr import DEFAULT_DISTRO, Header, default_message, ros_header, serialize
from openfusion.viz.palette import highlight_color

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
MARKER_ARRAY = "visualization_msgs/msg/MarkerArray"
_FLOAT32, _INT32 = 7, 5  # sensor_msgs/PointField datatypes
POINT_STEP = 20
MARKER_CUBE, MARKER_TEXT, MARKER_DELETEALL = 1, 9, 3


def pack_rgb(colors: np.ndarray) -> np.ndarray:
    """(N, 3) uint8 -> (N,) float32 whose bytes are ``0x00RRGGBB`` (the PCL/RViz ``rgb`` field)."""
    c = np.asarray(colors, dtype=np.uint32).reshape(-1, 3)
    return ((c[:, 0] << 16) | (c[:, 1] << 8) | c[:, 2]).astype(np.uint32).view(np.float32)


def point_cloud2(points: np.ndarray, colors: np.ndarray, keys: np.ndarray, *, frame_id: str, stamp_ns: int,
                 distro: str = DEFAULT_DISTRO) -> bytes:
    """CDR ``PointCloud2`` of ``points`` (N, 3) m, ``colors`` (N, 3) uint8, ``keys`` (N,) int."""
    pts = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    n = len(pts)
    if len(colors) != n or len(keys) != n:
        raise ValueError(f"points ({n}), colors ({len(colors)}) and keys ({len(keys)}) differ in length")
    rec = np.zeros(n, dtype=np.dtype({"names": ["x", "y", "z", "rgb", "region"],
                                      "formats": ["<f4", "<f4", "<f4", "<f4", "<i4"],
                                      "offsets": [0, 4, 8, 12, 16], "itemsize": POINT_STEP}))
    rec["x"], rec["y"], rec["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    rec["rgb"] = pack_rgb(colors)
    rec["region"] = np.asarray(keys, dtype=np.int64).astype(np.int32)
    fields = [default_message("sensor_msgs/msg/PointField", distro=distro, name=name, offset=off, datatype=dt, count=1)
              for name, off, dt in (("x", 0, _FLOAT32), ("y", 4, _FLOAT32), ("z", 8, _FLOAT32), ("rgb", 12, _FLOAT32),
                                    ("region", 16, _INT32))]
    msg = default_message(POINTCLOUD2, distro=distro, header=ros_header(Header(stamp_ns, frame_id), distro=distro),
                          height=1, width=n, fields=fields, is_bigendian=False, point_step=POINT_STEP,
                          row_step=POINT_STEP * n, data=np.frombuffer(rec.tobytes(), dtype=np.uint8), is_dense=True)
    return serialize(msg, distro=distro)


def _color(rgb: Sequence[int], alpha: float, distro: str) -> Any:
    r, g, b = (float(v) / 255.0 for v in rgb)
    return default_message("std_msgs/msg/ColorRGBA", distro=distro, r=r, g=g, b=b, a=float(alpha))


def _pose(center: np.ndarray, distro: str) -> Any:
    point = default_message("geometry_msgs/msg/Point", distro=distro, x=float(center[0]), y=float(center[1]),
                            z=float(center[2]))
    quat = default_message("geometry_msgs/msg/Quaternion", distro=distro, w=1.0)
    return default_message("geometry_msgs/msg/Pose", distro=distro, position=point, orientation=quat)


def answer_markers(hits: Sequence[Any], *, frame_id: str, stamp_ns: int, distro: str = DEFAULT_DISTRO) -> bytes:
    """CDR ``MarkerArray`` of ranked region hits (each with ``bbox_min``, ``bbox_max``, ``label``,
    ``score``, ``key``; e.g. :class:`~openfusion.wire.schemas.query.RegionHit`)."""
    header = ros_header(Header(stamp_ns, frame_id), distro=distro)
    markers = [default_message("visualization_msgs/msg/Marker", distro=distro, header=header, ns="openfusion",
                               action=MARKER_DELETEALL)]
    for rank, hit in enumerate(hits):
        lo = np.asarray(hit.bbox_min, dtype=np.float64)
        hi = np.asarray(hit.bbox_max, dtype=np.float64)
        size = np.maximum(hi - lo, 0.01)
        center = (lo + hi) / 2.0
        rgb = highlight_color(rank)
        scale = default_message("geometry_msgs/msg/Vector3", distro=distro, x=float(size[0]), y=float(size[1]),
                                z=float(size[2]))
        markers.append(default_message("visualization_msgs/msg/Marker", distro=distro, header=header,
                                       ns="openfusion/boxes", id=rank, type=MARKER_CUBE, pose=_pose(center, distro),
                                       scale=scale, color=_color(rgb, 0.35, distro)))
        top = center.copy()
        top[2] = hi[2] + 0.1  # above the box (z up, the map's convention for answers shown in RViz)
        text_scale = default_message("geometry_msgs/msg/Vector3", distro=distro, z=0.12)
        label = f"{hit.label or f'region {hit.key}'} {float(hit.score):.2f}"
        markers.append(default_message("visualization_msgs/msg/Marker", distro=distro, header=header,
                                       ns="openfusion/labels", id=rank, type=MARKER_TEXT, pose=_pose(top, distro),
                                       scale=text_scale, color=_color(rgb, 1.0, distro), text=label))
    return serialize(default_message(MARKER_ARRAY, distro=distro, markers=markers), distro=distro)


def answer_cloud(hits: Sequence[Any], *, frame_id: str, stamp_ns: int, distro: str = DEFAULT_DISTRO) -> bytes:
    """CDR ``PointCloud2`` of the points of ranked hits (those that carry points), each hit in its
    rank's highlight colour, ``region`` = its key."""
    pts, cols, keys = [np.zeros((0, 3), np.float32)], [np.zeros((0, 3), np.uint8)], [np.zeros(0, np.int64)]
    for rank, hit in enumerate(hits):
        if hit.points is None or len(hit.points) == 0:
            continue
        p = np.asarray(hit.points, dtype=np.float32).reshape(-1, 3)
        pts.append(p)
        cols.append(np.tile(np.asarray(highlight_color(rank), np.uint8), (len(p), 1)))
        keys.append(np.full(len(p), int(hit.key), np.int64))
    return point_cloud2(np.concatenate(pts), np.concatenate(cols), np.concatenate(keys), frame_id=frame_id,
                        stamp_ns=stamp_ns, distro=distro)
