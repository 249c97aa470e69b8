"""ROS 2 messages in CDR through ``rosbags`` (the field's well-kept pure-Python implementation), behind
a thin adapter.

``rosbags`` knows every standard ROS 2 message type (its Humble and Jazzy type stores; a topic's
type name picks the definition) and does the CDR work: encapsulation header (``00 01`` little-,
``00 00`` big-endian), alignment, strings, sequences, and size checks. What this module adds:

- :func:`deserialize` / :func:`serialize` by type name (``sensor_msgs/msg/Image`` or the short
  ``sensor_msgs/Image``) with one error type, :class:`CdrError`, for every malformed payload;
- small typed views of the few messages the frame sources read (:class:`ImageMsg`,
  :class:`CameraInfoMsg`, :class:`OdometryMsg`, :class:`TransformStampedMsg`,
  :class:`CompressedImageMsg`) and their encoders, for tests, simulators and tools;
- pixels: :func:`image_to_array` (``Image``: rgb8/bgr8/rgba8/bgra8/mono8, 16UC1/mono16, 32FC1,
  32SC1; ``step`` row padding and ``is_bigendian`` honoured) and :func:`compressed_to_array`
  (``CompressedImage``: JPEG/PNG colour through Pillow, and ``compressedDepth`` PNG 16-bit depth
  as ``compressed_depth_image_transport`` writes it: a 12-byte config header, then the PNG).

Written by hand only what ``rosbags`` does not do: turning a decoded image into numpy pixels.
"""

from __future__ import annotations

import io
import struct
from dataclasses import dataclass, field
from functools import cache
from typing import Any

import numpy as np

from openfusion.errors import OpenFusionError

ENCAPSULATION_LE = b"\x00\x01\x00\x00"
ENCAPSULATION_BE = b"\x00\x00\x00\x00"
#: ROS 2 distributions whose type stores we read and write (message layouts of every standard type)
DISTROS: tuple[str, ...] = ("humble", "jazzy")
DEFAULT_DISTRO = "jazzy"


class CdrError(OpenFusionError, ValueError):
    """A payload that is not a valid CDR encoding of the expected message (or an image whose pixels
    cannot be read: unknown encoding, sizes that disagree)."""


@cache
def typestore(distro: str = DEFAULT_DISTRO) -> Any:
    """The ``rosbags`` type store of a ROS 2 distribution (``humble`` or ``jazzy``)."""
    from rosbags.typesys import Stores, get_typestore

    stores = {"humble": Stores.ROS2_HUMBLE, "jazzy": Stores.ROS2_JAZZY}
    if distro not in stores:
        raise ValueError(f"unknown ROS 2 distribution {distro!r}; known: {', '.join(DISTROS)}")
    return get_typestore(stores[distro])


def full_type_name(typename: str) -> str:
    """``sensor_msgs/Image`` -> ``sensor_msgs/msg/Image`` (a full name is returned unchanged)."""
    parts = typename.strip("/").split("/")
    if len(parts) == 2:
        return f"{parts[0]}/msg/{parts[1]}"
    return "/".join(parts)


def message_class(typename: str, *, distro: str = DEFAULT_DISTRO) -> Any:
    """The ``rosbags`` dataclass of a message type (to build messages for :func:`serialize`)."""
    name = full_type_name(typename)
    try:
        return typestore(distro).types[name]
    except KeyError:
        raise CdrError(f"unknown ROS 2 message type {typename!r} in the {distro} type store") from None


_NUMPY_OF = {"bool": np.bool_, "byte": np.uint8, "char": np.uint8, "int8": np.int8, "uint8": np.uint8,
             "int16": np.int16, "uint16": np.uint16, "int32": np.int32, "uint32": np.uint32, "int64": np.int64,
             "uint64": np.uint64, "float32": np.float32, "float64": np.float64}


def _default_value(node: Any, distro: str) -> Any:
    from rosbags.interfaces import Nodetype

    kind, arg = node
    if kind == Nodetype.BASE:
        name = arg[0]
        return "" if name == "string" else False if name == "bool" else 0.0 if name.startswith("float") else 0
    if kind == Nodetype.NAME:
        return default_message(arg, distro=distro)
    sub, length = arg
    n = length if kind == Nodetype.ARRAY else 0
    if sub[0] == Nodetype.BASE and sub[1][0] in _NUMPY_OF:  # array / sequence of a primitive: numpy
        return np.zeros(n, dtype=_NUMPY_OF[sub[1][0]])
    return [_default_value(sub, distro) for _ in range(n)]


def default_message(typename: str, *, distro: str = DEFAULT_DISTRO, **fields: Any) -> Any:
    """A message of ``typename`` with every field at its zero value except ``fields``: builds the
    messages whose field lists differ between distributions (``Marker`` gained texture and mesh
    fields after Humble) from one call."""
    name = full_type_name(typename)
    store = typestore(distro)
    try:
        _consts, defs = store.fielddefs[name]
    except KeyError:
        raise CdrError(f"unknown ROS 2 message type {typename!r} in the {distro} type store") from None
    unknown = set(fields) - {f for f, _ in defs}
    if unknown:
        raise ValueError(f"{name} has no field(s) {', '.join(sorted(unknown))}")
    values = {f: fields[f] if f in fields else _default_value(node, distro) for f, node in defs}
    return store.types[name](**values)


def deserialize(payload: bytes | memoryview, typename: str, *, distro: str = DEFAULT_DISTRO) -> Any:
    """A CDR payload (encapsulation header included) as a ``rosbags`` message object; CdrError for
    anything that is not a whole, valid message of ``typename``."""
    from rosbags.serde import SerdeError

    name = full_type_name(typename)
    store = typestore(distro)
    if name not in store.types:
        raise CdrError(f"unknown ROS 2 message type {typename!r} in the {distro} type store")
    try:
        return store.deserialize_cdr(payload, name)
    except (SerdeError, ValueError, IndexError, KeyError, TypeError, struct.error) as exc:
        raise CdrError(f"not a valid CDR {name} ({len(payload)} bytes): {exc}") from None


def serialize(message: Any, typename: str | None = None, *, distro: str = DEFAULT_DISTRO) -> bytes:
    """A ``rosbags`` message object as a little-endian CDR payload (encapsulation header included)."""
    name = full_type_name(typename or message.__msgtype__)
    return bytes(typestore(distro).serialize_cdr(message, name))


def type_hash(typename: str, *, distro: str = DEFAULT_DISTRO) -> str:
    """REP-2016 type hash (``RIHS01_<sha256>``) of a message type, as rmw_zenoh puts it in its keys."""
    return typestore(distro).hash_rihs01(full_type_name(typename))


def dds_type_name(typename: str) -> str:
    """``sensor_msgs/msg/Image`` -> ``sensor_msgs::msg::dds_::Image_`` (the DDS name rmw_zenoh keys use)."""
    pkg, kind, name = full_type_name(typename).split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


# ------------------------------------------------------------------------------------ typed views


@dataclass
class Header:
    stamp_ns: int
    frame_id: str


@dataclass
class ImageMsg:
    header: Header
    height: int
    width: int
    encoding: str
    is_bigendian: bool
    step: int
    data: bytes | memoryview | np.ndarray


@dataclass
class CompressedImageMsg:
    header: Header
    format: str
    data: bytes | memoryview | np.ndarray


@dataclass
class CameraInfoMsg:
    header: Header
    height: int
    width: int
    distortion_model: str
    d: np.ndarray
    k: np.ndarray  # (3, 3)
    r: np.ndarray  # (3, 3)
    p: np.ndarray  # (3, 4)
    binning_x: int = 0
    binning_y: int = 0
    roi: tuple[int, int, int, int, bool] = (0, 0, 0, 0, False)


@dataclass
class OdometryMsg:
    header: Header
    child_frame_id: str
    position: np.ndarray  # (3,)
    orientation_xyzw: np.ndarray  # (4,)
    pose_covariance: np.ndarray = field(default_factory=lambda: np.zeros(36))
    linear: np.ndarray = field(default_factory=lambda: np.zeros(3))
    angular: np.ndarray = field(default_factory=lambda: np.zeros(3))
    twist_covariance: np.ndarray = field(default_factory=lambda: np.zeros(36))


@dataclass
class TransformStampedMsg:
    header: Header
    child_frame_id: str
    translation: np.ndarray  # (3,)
    rotation_xyzw: np.ndarray  # (4,)


def _header(h: Any) -> Header:
    nanosec = int(h.stamp.nanosec)
    if nanosec >= 1_000_000_000:
        raise CdrError(f"header.stamp.nanosec {nanosec} is not below 1e9")
    return Header(int(h.stamp.sec) * 1_000_000_000 + nanosec, str(h.frame_id))


def ros_header(h: Header, *, distro: str = DEFAULT_DISTRO) -> Any:
    """A ``std_msgs/Header`` object of a :class:`Header`."""
    sec, nanosec = divmod(int(h.stamp_ns), 1_000_000_000)
    time_cls = message_class("builtin_interfaces/msg/Time", distro=distro)
    return message_class("std_msgs/msg/Header", distro=distro)(stamp=time_cls(sec=sec, nanosec=nanosec), frame_id=h.frame_id)


def _vec(v: Any, names: str) -> np.ndarray:
    return np.array([float(getattr(v, n)) for n in names], dtype=np.float64)


def decode_image(payload: bytes | memoryview, *, distro: str = DEFAULT_DISTRO) -> ImageMsg:
    m = deserialize(payload, "sensor_msgs/msg/Image", distro=distro)
    return ImageMsg(_header(m.header), int(m.height), int(m.width), str(m.encoding), bool(m.is_bigendian),
                    int(m.step), m.data)


def encode_image(msg: ImageMsg, *, distro: str = DEFAULT_DISTRO) -> bytes:
    cls = message_class("sensor_msgs/msg/Image", distro=distro)
    data = np.frombuffer(bytes(msg.data), dtype=np.uint8) if not isinstance(msg.data, np.ndarray) else msg.data
    return serialize(cls(header=ros_header(msg.header, distro=distro), height=msg.height, width=msg.width,
                         encoding=msg.encoding, is_bigendian=int(msg.is_bigendian), step=msg.step,
                         data=np.ascontiguousarray(data, dtype=np.uint8).ravel()), distro=distro)


def decode_compressed_image(payload: bytes | memoryview, *, distro: str = DEFAULT_DISTRO) -> CompressedImageMsg:
    m = deserialize(payload, "sensor_msgs/msg/CompressedImage", distro=distro)
    return CompressedImageMsg(_header(m.header), str(m.format), m.data)


def encode_compressed_image(msg: CompressedImageMsg, *, distro: str = DEFAULT_DISTRO) -> bytes:
    cls = message_class("sensor_msgs/msg/CompressedImage", distro=distro)
    data = np.frombuffer(bytes(msg.data), dtype=np.uint8)
    return serialize(cls(header=ros_header(msg.header, distro=distro), format=msg.format, data=data), distro=distro)


def decode_camera_info(payload: bytes | memoryview, *, distro: str = DEFAULT_DISTRO) -> CameraInfoMsg:
    m = deserialize(payload, "sensor_msgs/msg/CameraInfo", distro=distro)
    roi = m.roi
    return CameraInfoMsg(
        _header(m.header), int(m.height), int(m.width), str(m.distortion_model),
        np.asarray(m.d, dtype=np.float64), np.asarray(m.k, dtype=np.float64).reshape(3, 3),
        np.asarray(m.r, dtype=np.float64).reshape(3, 3), np.asarray(m.p, dtype=np.float64).reshape(3, 4),
        int(m.binning_x), int(m.binning_y),
        (int(roi.x_offset), int(roi.y_offset), int(roi.height), int(roi.width), bool(roi.do_rectify)),
    )


def encode_camera_info(msg: CameraInfoMsg, *, distro: str = DEFAULT_DISTRO) -> bytes:
    cls = message_class("sensor_msgs/msg/CameraInfo", distro=distro)
    roi_cls = message_class("sensor_msgs/msg/RegionOfInterest", distro=distro)
    x, y, h, w, rect = msg.roi
    f64 = lambda a: np.asarray(a, dtype=np.float64).ravel()  # noqa: E731 - local shorthand
    return serialize(cls(header=ros_header(msg.header, distro=distro), height=msg.height, width=msg.width,
                         distortion_model=msg.distortion_model, d=f64(msg.d), k=f64(msg.k), r=f64(msg.r), p=f64(msg.p),
                         binning_x=msg.binning_x, binning_y=msg.binning_y,
                         roi=roi_cls(x_offset=x, y_offset=y, height=h, width=w, do_rectify=bool(rect))), distro=distro)


def decode_odometry(payload: bytes | memoryview, *, distro: str = DEFAULT_DISTRO) -> OdometryMsg:
    m = deserialize(payload, "nav_msgs/msg/Odometry", distro=distro)
    pose, twist = m.pose, m.twist
    return OdometryMsg(_header(m.header), str(m.child_frame_id), _vec(pose.pose.position, "xyz"),
                       _vec(pose.pose.orientation, "xyzw"), np.asarray(pose.covariance, dtype=np.float64),
                       _vec(twist.twist.linear, "xyz"), _vec(twist.twist.angular, "xyz"),
                       np.asarray(twist.covariance, dtype=np.float64))


def encode_odometry(msg: OdometryMsg, *, distro: str = DEFAULT_DISTRO) -> bytes:
    c = lambda name: message_class(name, distro=distro)  # noqa: E731 - local shorthand
    p, q = np.asarray(msg.position, dtype=float), np.asarray(msg.orientation_xyzw, dtype=float)
    lin, ang = np.asarray(msg.linear, dtype=float), np.asarray(msg.angular, dtype=float)
    pose = c("geometry_msgs/msg/PoseWithCovariance")(
        pose=c("geometry_msgs/msg/Pose")(position=c("geometry_msgs/msg/Point")(x=p[0], y=p[1], z=p[2]),
                                         orientation=c("geometry_msgs/msg/Quaternion")(x=q[0], y=q[1], z=q[2], w=q[3])),
        covariance=np.asarray(msg.pose_covariance, dtype=np.float64).ravel())
    twist = c("geometry_msgs/msg/TwistWithCovariance")(
        twist=c("geometry_msgs/msg/Twist")(linear=c("geometry_msgs/msg/Vector3")(x=lin[0], y=lin[1], z=lin[2]),
                                           angular=c("geometry_msgs/msg/Vector3")(x=ang[0], y=ang[1], z=ang[2])),
        covariance=np.asarray(msg.twist_covariance, dtype=np.float64).ravel())
    return serialize(c("nav_msgs/msg/Odometry")(header=ros_header(msg.header, distro=distro),
                                                child_frame_id=msg.child_frame_id, pose=pose, twist=twist), distro=distro)


def decode_tf_message(payload: bytes | memoryview, *, distro: str = DEFAULT_DISTRO) -> list[TransformStampedMsg]:
    m = deserialize(payload, "tf2_msgs/msg/TFMessage", distro=distro)
    return [TransformStampedMsg(_header(t.header), str(t.child_frame_id), _vec(t.transform.translation, "xyz"),
                                _vec(t.transform.rotation, "xyzw")) for t in m.transforms]


def encode_tf_message(transforms: list[TransformStampedMsg], *, distro: str = DEFAULT_DISTRO) -> bytes:
    c = lambda name: message_class(name, distro=distro)  # noqa: E731 - local shorthand
    out = []
    for tf in transforms:
        t, q = np.asarray(tf.translation, dtype=float), np.asarray(tf.rotation_xyzw, dtype=float)
        out.append(c("geometry_msgs/msg/TransformStamped")(
            header=ros_header(tf.header, distro=distro), child_frame_id=tf.child_frame_id,
            transform=c("geometry_msgs/msg/Transform")(
                translation=c("geometry_msgs/msg/Vector3")(x=t[0], y=t[1], z=t[2]),
                rotation=c("geometry_msgs/msg/Quaternion")(x=q[0], y=q[1], z=q[2], w=q[3]))))
    return serialize(c("tf2_msgs/msg/TFMessage")(transforms=out), distro=distro)


def decode_string(payload: bytes | memoryview, *, distro: str = DEFAULT_DISTRO) -> str:
    return str(deserialize(payload, "std_msgs/msg/String", distro=distro).data)


def encode_string(text: str, *, distro: str = DEFAULT_DISTRO) -> bytes:
    return serialize(message_class("std_msgs/msg/String", distro=distro)(data=text), distro=distro)


# -------------------------------------------------------------------------------- image pixels

_ENCODINGS = {
    # encoding: (channels, numpy base dtype)
    "rgb8": (3, "u1"),
    "bgr8": (3, "u1"),
    "rgba8": (4, "u1"),
    "bgra8": (4, "u1"),
    "mono8": (1, "u1"),
    "16UC1": (1, "u2"),
    "mono16": (1, "u2"),
    "32FC1": (1, "f4"),
    "32SC1": (1, "i4"),
}
SUPPORTED_ENCODINGS: tuple[str, ...] = tuple(_ENCODINGS)


def image_to_array(msg: ImageMsg) -> np.ndarray:
    """Pixels as numpy: HxWx3 uint8 RGB for colour encodings (bgr/bgra/rgba converted), HxW uint16
    for ``16UC1``/``mono16``, HxW float32 for ``32FC1``, HxW int32 for ``32SC1``, HxW uint8 for
    ``mono8``. Honours ``step`` (row padding) and ``is_bigendian``. CdrError for an unsupported
    encoding or a data size that disagrees with height, width and step."""
    spec = _ENCODINGS.get(msg.encoding)
    if spec is None:
        raise CdrError(f"unsupported image encoding {msg.encoding!r}; supported: {', '.join(SUPPORTED_ENCODINGS)}")
    channels, base = spec
    dtype = np.dtype((">" if msg.is_bigendian else "<") + base)
    row_bytes = msg.width * channels * dtype.itemsize
    if msg.height == 0 or msg.width == 0:
        raise CdrError(f"image has an empty size {msg.width}x{msg.height}")
    if msg.step < row_bytes:
        raise CdrError(f"image step {msg.step} is shorter than a row of {row_bytes} bytes ({msg.encoding})")
    data = np.frombuffer(msg.data, dtype=np.uint8) if not isinstance(msg.data, np.ndarray) else msg.data.view(np.uint8)
    if data.size != msg.step * msg.height:
        raise CdrError(f"image data is {data.size} bytes, expected step*height = {msg.step * msg.height} "
                       f"({msg.width}x{msg.height} {msg.encoding}, step {msg.step})")
    rows = data.reshape(msg.height, msg.step)[:, :row_bytes]
    arr = np.ascontiguousarray(rows).view(dtype).reshape(msg.height, msg.width, channels)
    arr = arr.astype(dtype.newbyteorder("="), copy=False)
    if msg.encoding in ("rgb8", "rgba8"):
        return np.ascontiguousarray(arr[..., :3])
    if msg.encoding in ("bgr8", "bgra8"):
        return np.ascontiguousarray(arr[..., 2::-1])
    return arr[..., 0]


def array_to_image(arr: np.ndarray, encoding: str, *, stamp_ns: int, frame_id: str, row_padding: int = 0) -> ImageMsg:
    """An ``ImageMsg`` of a numpy image (``rgb8``/``bgr8`` take RGB input); for tests and tools."""
    if encoding not in _ENCODINGS:
        raise ValueError(f"unsupported encoding {encoding!r}")
    channels, base = _ENCODINGS[encoding]
    a = np.asarray(arr)
    if encoding in ("bgr8", "bgra8"):
        a = a[..., ::-1] if encoding == "bgr8" else a[..., [2, 1, 0, 3]]
    a = np.ascontiguousarray(a.astype("<" + base)).reshape(a.shape[0], a.shape[1], channels)
    h, w = a.shape[:2]
    row = w * channels * np.dtype(base).itemsize
    step = row + row_padding
    data = np.zeros((h, step), dtype=np.uint8)
    data[:, :row] = a.reshape(h, -1).view(np.uint8)
    return ImageMsg(Header(stamp_ns, frame_id), h, w, encoding, False, step, data.tobytes())


#: compressed_depth_image_transport's ConfigHeader: int32 format, float32 depthParam[2]
COMPRESSED_DEPTH_HEADER_BYTES = 12
_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def compressed_to_array(msg: CompressedImageMsg) -> np.ndarray:
    """Pixels of a ``CompressedImage``: JPEG/PNG colour -> HxWx3 uint8 RGB (grey and RGBA
    converted); ``compressedDepth`` (``16UC1; compressedDepth png``) -> HxW uint16 millimetres.
    CdrError for a format we do not read (e.g. ``32FC1`` compressedDepth, which is quantised
    inverse depth) or bytes that do not decode."""
    from PIL import Image, UnidentifiedImageError

    fmt = msg.format.lower()
    raw = bytes(msg.data)
    if "compresseddepth" in fmt:
        if not fmt.startswith("16uc1") and not fmt.startswith("mono16"):
            raise CdrError(f"compressedDepth format {msg.format!r}: only 16UC1 PNG depth is read")
        start = raw.find(_PNG_MAGIC, 0, COMPRESSED_DEPTH_HEADER_BYTES + len(_PNG_MAGIC))
        if start < 0:
            raise CdrError(f"compressedDepth image ({len(raw)} bytes) holds no PNG after its config header")
        raw = raw[start:]
    try:
        with Image.open(io.BytesIO(raw)) as img:
            img.load()
            if "compresseddepth" in fmt:
                if img.mode not in ("I;16", "I;16B", "I"):
                    raise CdrError(f"compressedDepth PNG has mode {img.mode}, expected 16-bit grey")
                return np.asarray(img, dtype=np.uint16)
            return np.asarray(img.convert("RGB"), dtype=np.uint8)
    except (UnidentifiedImageError, OSError, ValueError) as exc:
        raise CdrError(f"CompressedImage ({msg.format!r}, {len(raw)} bytes) does not decode: {exc}") from None


def array_to_compressed(arr: np.ndarray, fmt: str, *, stamp_ns: int, frame_id: str) -> CompressedImageMsg:
    """A ``CompressedImage`` of a numpy image: ``jpeg``/``png`` colour (RGB input) or
    ``16UC1; compressedDepth png`` (uint16 input, with the 12-byte config header); for tests and tools."""
    from PIL import Image

    buf = io.BytesIO()
    if "compresseddepth" in fmt.lower():
        buf.write(struct.pack("<iff", 0, 0.0, 0.0))  # format PNG, no depth quantisation parameters
        Image.fromarray(np.ascontiguousarray(arr, dtype=np.uint16)).save(buf, format="PNG")
    else:
        Image.fromarray(np.ascontiguousarray(arr, dtype=np.uint8)).save(buf, format="JPEG" if "jp" in fmt.lower() else "PNG",
                                                                         **({"quality": 95} if "jp" in fmt.lower() else {}))
    return CompressedImageMsg(Header(stamp_ns, frame_id), fmt, buf.getvalue())
