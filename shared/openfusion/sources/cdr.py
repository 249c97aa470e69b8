"""Minimal OMG CDR (XCDR1, as ROS 2 uses it) decoder and encoder for the few messages we read.

zenoh-bridge-ros2dds republishes each DDS sample's serialized payload unchanged: a 4-byte
encapsulation header (``00 01 00 00`` little-endian CDR, ``00 00 00 00`` big-endian) followed by
the CDR body. Alignment of every primitive is to its own size (8 at most), counted from the
start of the body (after the header). Strings are a uint32 length that includes the trailing
NUL, the bytes and the NUL; sequences a uint32 count and the elements; fixed arrays just the
elements.

Message types (field order as in the .msg files):

- ``builtin_interfaces/Time``: int32 sec, uint32 nanosec
- ``std_msgs/Header``: Time stamp, string frame_id
- ``sensor_msgs/Image``: Header, uint32 height, uint32 width, string encoding, uint8
  is_bigendian, uint32 step, uint8[] data
- ``sensor_msgs/CameraInfo``: Header, uint32 height, width, string distortion_model,
  float64[] d, float64[9] k, float64[9] r, float64[12] p, uint32 binning_x, binning_y,
  RegionOfInterest roi (uint32 x_offset, y_offset, height, width, bool do_rectify)
- ``nav_msgs/Odometry``: Header, string child_frame_id, PoseWithCovariance (Pose (Point
  position, Quaternion orientation), float64[36]), TwistWithCovariance (Twist (Vector3 linear,
  Vector3 angular), float64[36])
- ``tf2_msgs/TFMessage``: TransformStamped[] (Header, string child_frame_id, Transform
  (Vector3 translation, Quaternion rotation))

Every length read from a payload is checked against the bytes left, so a malformed or hostile
payload raises ``CdrError`` instead of allocating or reading past the end.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field

import numpy as np

from openfusion.errors import OpenFusionError

ENCAPSULATION_LE = b"\x00\x01\x00\x00"
ENCAPSULATION_BE = b"\x00\x00\x00\x00"
MAX_STRING_BYTES = 1 << 16


class CdrError(OpenFusionError, ValueError):
    """A payload that is not a valid CDR encoding of the expected message."""


class CdrReader:
    """Sequential reader over one CDR payload (header included)."""

    def __init__(self, data: bytes | bytearray | memoryview) -> None:
        buf = memoryview(data).cast("B") if not isinstance(data, bytes) else memoryview(data)
        if len(buf) < 4:
            raise CdrError(f"payload of {len(buf)} bytes is shorter than the 4-byte encapsulation header")
        header = bytes(buf[:4])
        if header[:2] == ENCAPSULATION_LE[:2]:
            self.endian = "<"
        elif header[:2] == ENCAPSULATION_BE[:2]:
            self.endian = ">"
        else:
            raise CdrError(f"unsupported CDR encapsulation {header[:2].hex()} (expected plain CDR, 0000 or 0001)")
        self._buf = buf
        self._base = 4
        self._pos = 4

    @property
    def remaining(self) -> int:
        return len(self._buf) - self._pos

    def _align(self, n: int) -> None:
        rel = (self._pos - self._base) % n
        if rel:
            self._pos += n - rel

    def _take(self, size: int, what: str) -> memoryview:
        if size < 0 or self._pos + size > len(self._buf):
            raise CdrError(f"payload ends inside {what} (needs {size} bytes at offset {self._pos}, has {len(self._buf)})")
        out = self._buf[self._pos : self._pos + size]
        self._pos += size
        return out

    def _prim(self, fmt: str, size: int, what: str):
        self._align(size)
        return struct.unpack(self.endian + fmt, self._take(size, what))[0]

    def u8(self, what: str = "uint8") -> int:
        return self._prim("B", 1, what)

    def boolean(self, what: str = "bool") -> bool:
        return bool(self._prim("B", 1, what))

    def i32(self, what: str = "int32") -> int:
        return self._prim("i", 4, what)

    def u32(self, what: str = "uint32") -> int:
        return self._prim("I", 4, what)

    def f64(self, what: str = "float64") -> float:
        return self._prim("d", 8, what)

    def string(self, what: str = "string") -> str:
        n = self.u32(f"{what} length")
        if n == 0:
            return ""  # some writers send 0 for an empty string
        if n > MAX_STRING_BYTES:
            raise CdrError(f"{what} claims {n} bytes (limit {MAX_STRING_BYTES})")
        raw = bytes(self._take(n, what))
        if raw[-1:] != b"\x00":
            raise CdrError(f"{what} is not NUL-terminated")
        try:
            return raw[:-1].decode("utf-8")
        except UnicodeDecodeError as exc:
            raise CdrError(f"{what} is not UTF-8: {exc}") from exc

    def f64_array(self, n: int, what: str = "float64[]") -> np.ndarray:
        self._align(8)
        raw = self._take(8 * n, what)
        return np.frombuffer(raw, dtype=np.dtype(self.endian + "f8")).astype(np.float64)

    def f64_seq(self, what: str = "float64[]") -> np.ndarray:
        n = self.u32(f"{what} length")
        if 8 * n > self.remaining:
            raise CdrError(f"{what} claims {n} elements, only {self.remaining} bytes left")
        return self.f64_array(n, what)

    def u8_seq(self, what: str = "uint8[]") -> memoryview:
        n = self.u32(f"{what} length")
        return self._take(n, what)

    def time_ns(self, what: str = "stamp") -> int:
        sec = self.i32(f"{what}.sec")
        nanosec = self.u32(f"{what}.nanosec")
        if nanosec >= 1_000_000_000:
            raise CdrError(f"{what}.nanosec {nanosec} is not below 1e9")
        return sec * 1_000_000_000 + nanosec


class CdrWriter:
    """Builds a little-endian CDR payload (header included); used by tests and simulators."""

    def __init__(self) -> None:
        self._body = bytearray()

    def _align(self, n: int) -> None:
        rel = len(self._body) % n
        if rel:
            self._body += b"\x00" * (n - rel)

    def _prim(self, fmt: str, size: int, value) -> None:  # noqa: ANN001 - any packable value
        self._align(size)
        self._body += struct.pack("<" + fmt, value)

    def u8(self, v: int) -> None:
        self._prim("B", 1, v)

    def boolean(self, v: bool) -> None:
        self._prim("B", 1, 1 if v else 0)

    def i32(self, v: int) -> None:
        self._prim("i", 4, v)

    def u32(self, v: int) -> None:
        self._prim("I", 4, v)

    def f64(self, v: float) -> None:
        self._prim("d", 8, v)

    def string(self, s: str) -> None:
        raw = s.encode("utf-8") + b"\x00"
        self.u32(len(raw))
        self._body += raw

    def f64_array(self, values) -> None:  # noqa: ANN001 - array-like
        self._align(8)
        self._body += np.asarray(values, dtype="<f8").tobytes()

    def f64_seq(self, values) -> None:  # noqa: ANN001 - array-like
        arr = np.asarray(values, dtype="<f8").ravel()
        self.u32(arr.size)
        self.f64_array(arr)

    def u8_seq(self, data: bytes) -> None:
        self.u32(len(data))
        self._body += data

    def time_ns(self, stamp_ns: int) -> None:
        sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
        self.i32(sec)
        self.u32(nanosec)

    def getvalue(self) -> bytes:
        return ENCAPSULATION_LE + bytes(self._body)


# ------------------------------------------------------------------------------------ messages


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
    data: bytes | memoryview


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


def _read_header(r: CdrReader) -> Header:
    stamp = r.time_ns("header.stamp")
    return Header(stamp, r.string("header.frame_id"))


def _write_header(w: CdrWriter, h: Header) -> None:
    w.time_ns(h.stamp_ns)
    w.string(h.frame_id)


def _done(r: CdrReader, what: str) -> None:
    # DDS may pad the sample to a multiple of 4 bytes; more than that is not this message
    if r.remaining > 3:
        raise CdrError(f"{r.remaining} unexpected bytes after the {what} message (wrong message type?)")


def decode_image(payload: bytes | memoryview) -> ImageMsg:
    r = CdrReader(payload)
    header = _read_header(r)
    height, width = r.u32("height"), r.u32("width")
    encoding = r.string("encoding")
    is_be = r.boolean("is_bigendian")
    step = r.u32("step")
    data = r.u8_seq("data")
    _done(r, "Image")
    return ImageMsg(header, height, width, encoding, is_be, step, data)


def encode_image(msg: ImageMsg) -> bytes:
    w = CdrWriter()
    _write_header(w, msg.header)
    w.u32(msg.height)
    w.u32(msg.width)
    w.string(msg.encoding)
    w.boolean(msg.is_bigendian)
    w.u32(msg.step)
    w.u8_seq(bytes(msg.data))
    return w.getvalue()


def decode_camera_info(payload: bytes | memoryview) -> CameraInfoMsg:
    r = CdrReader(payload)
    header = _read_header(r)
    height, width = r.u32("height"), r.u32("width")
    model = r.string("distortion_model")
    d = r.f64_seq("d")
    k = r.f64_array(9, "k").reshape(3, 3)
    rr = r.f64_array(9, "r").reshape(3, 3)
    p = r.f64_array(12, "p").reshape(3, 4)
    bx, by = r.u32("binning_x"), r.u32("binning_y")
    roi = (r.u32("roi.x_offset"), r.u32("roi.y_offset"), r.u32("roi.height"), r.u32("roi.width"), r.boolean("roi.do_rectify"))
    _done(r, "CameraInfo")
    return CameraInfoMsg(header, height, width, model, d, k, rr, p, bx, by, roi)


def encode_camera_info(msg: CameraInfoMsg) -> bytes:
    w = CdrWriter()
    _write_header(w, msg.header)
    w.u32(msg.height)
    w.u32(msg.width)
    w.string(msg.distortion_model)
    w.f64_seq(msg.d)
    w.f64_array(np.asarray(msg.k).ravel())
    w.f64_array(np.asarray(msg.r).ravel())
    w.f64_array(np.asarray(msg.p).ravel())
    w.u32(msg.binning_x)
    w.u32(msg.binning_y)
    for v in msg.roi[:4]:
        w.u32(v)
    w.boolean(msg.roi[4])
    return w.getvalue()


def decode_odometry(payload: bytes | memoryview) -> OdometryMsg:
    r = CdrReader(payload)
    header = _read_header(r)
    child = r.string("child_frame_id")
    position = r.f64_array(3, "pose.position")
    orientation = r.f64_array(4, "pose.orientation")
    pose_cov = r.f64_array(36, "pose.covariance")
    linear = r.f64_array(3, "twist.linear")
    angular = r.f64_array(3, "twist.angular")
    twist_cov = r.f64_array(36, "twist.covariance")
    _done(r, "Odometry")
    return OdometryMsg(header, child, position, orientation, pose_cov, linear, angular, twist_cov)


def encode_odometry(msg: OdometryMsg) -> bytes:
    w = CdrWriter()
    _write_header(w, msg.header)
    w.string(msg.child_frame_id)
    for arr in (msg.position, msg.orientation_xyzw, msg.pose_covariance, msg.linear, msg.angular, msg.twist_covariance):
        w.f64_array(np.asarray(arr, dtype=np.float64).ravel())
    return w.getvalue()


def decode_tf_message(payload: bytes | memoryview) -> list[TransformStampedMsg]:
    r = CdrReader(payload)
    n = r.u32("transforms length")
    # each TransformStamped takes at least 8 + 4 + 4 + 56 bytes
    if n * 72 > r.remaining:
        raise CdrError(f"TFMessage claims {n} transforms, only {r.remaining} bytes left")
    out = []
    for i in range(n):
        header = _read_header(r)
        child = r.string(f"transforms[{i}].child_frame_id")
        t = r.f64_array(3, f"transforms[{i}].translation")
        q = r.f64_array(4, f"transforms[{i}].rotation")
        out.append(TransformStampedMsg(header, child, t, q))
    _done(r, "TFMessage")
    return out


def encode_tf_message(transforms: list[TransformStampedMsg]) -> bytes:
    w = CdrWriter()
    w.u32(len(transforms))
    for tf in transforms:
        _write_header(w, tf.header)
        w.string(tf.child_frame_id)
        w.f64_array(np.asarray(tf.translation, dtype=np.float64))
        w.f64_array(np.asarray(tf.rotation_xyzw, dtype=np.float64))
    return w.getvalue()


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
}
SUPPORTED_ENCODINGS: tuple[str, ...] = tuple(_ENCODINGS)


def image_to_array(msg: ImageMsg) -> np.ndarray:
    """Pixels as numpy: HxWx3 uint8 RGB for color encodings (bgr/bgra/rgba converted), HxW
    uint16 for ``16UC1``/``mono16``, HxW float32 for ``32FC1``, HxW uint8 for ``mono8``.

    Honors ``step`` (row padding) and ``is_bigendian``. Raises CdrError for an unsupported
    encoding or a data size that disagrees with height, width and step.
    """
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
    if len(msg.data) != msg.step * msg.height:
        raise CdrError(f"image data is {len(msg.data)} bytes, expected step*height = {msg.step * msg.height}")
    rows = np.frombuffer(msg.data, dtype=np.uint8).reshape(msg.height, msg.step)[:, :row_bytes]
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
