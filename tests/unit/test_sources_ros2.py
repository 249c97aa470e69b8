"""ROS 2 CDR through the rosbags adapter (golden bytes computed by hand, alignment, endianness, hostile payloads) and frame assembly
from bridged topics, plus one loopback Zenoh test."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from ros2_support import MS, K, _info, _odom, _stream, body_pose

from openfusion.sources.cdr import (
    CameraInfoMsg,
    CdrError,
    Header,
    ImageMsg,
    OdometryMsg,
    TransformStampedMsg,
    array_to_image,
    decode_camera_info,
    decode_image,
    decode_odometry,
    decode_tf_message,
    encode_camera_info,
    encode_image,
    encode_odometry,
    encode_tf_message,
    image_to_array,
)
from openfusion.sources.ros2 import T_BODY_OPTICAL, Ros2Config, Ros2FrameAssembler, Ros2Topics


def test_golden_header_and_odometry_alignment() -> None:
    """Bytes computed by hand from the CDR rules: encapsulation 00 01 00 00, int32 sec, uint32
    nanosec, string = uint32 length with NUL + bytes; float64 aligned to 8 from the body start."""
    odo = OdometryMsg(Header(1_000_000_002, "cam"), "base_link", np.array([1.5, -2.0, 3.25]), np.array([0, 0, 0, 1.0]))
    payload = encode_odometry(odo)
    assert payload[:4] == b"\x00\x01\x00\x00"
    assert payload[4:20] == struct.pack("<iiI", 1, 2, 4) + b"cam\x00"
    assert payload[20:34] == struct.pack("<I", 10) + b"base_link\x00"
    # body offset 30 -> padded to 32 -> payload offset 36
    assert payload[34:36] == b"\x00\x00"
    assert struct.unpack_from("<3d", payload, 36) == (1.5, -2.0, 3.25)
    back = decode_odometry(payload)
    assert back.header == odo.header and back.child_frame_id == "base_link"
    np.testing.assert_array_equal(back.position, odo.position)
    np.testing.assert_array_equal(back.orientation_xyzw, odo.orientation_xyzw)


def _be_image_payload(values: np.ndarray) -> bytes:
    """A big-endian (encapsulation 00 00) 16UC1 Image with is_bigendian=1, built by hand."""
    h, w = values.shape
    body = struct.pack(">iI", 7, 8) + struct.pack(">I", 2) + b"d\x00"
    body += b"\x00\x00"  # align uint32 height to 4 (body offset 14 -> 16)
    body += struct.pack(">II", h, w) + struct.pack(">I", 6) + b"16UC1\x00"
    body += b"\x01"  # is_bigendian at body offset 34
    body += b"\x00"  # align step to 4 (35 -> 36)
    data = values.astype(">u2").tobytes()
    body += struct.pack(">I", 2 * w) + struct.pack(">I", len(data)) + data
    return b"\x00\x00\x00\x00" + body


def test_big_endian_payload_and_big_endian_pixels() -> None:
    values = np.array([[1, 2, 300], [65535, 0, 4096]], dtype=np.uint16)
    msg = decode_image(_be_image_payload(values))
    assert msg.header == Header(7_000_000_008, "d") and msg.encoding == "16UC1" and msg.is_bigendian
    out = image_to_array(msg)
    assert out.dtype == np.uint16
    np.testing.assert_array_equal(out, values)


@pytest.mark.parametrize("encoding", ["rgb8", "bgr8", "rgba8", "16UC1", "32FC1", "mono8"])
def test_image_encodings_round_trip_with_row_padding(encoding: str) -> None:
    """Rows padded beyond width*bpp (step > row) are cut; bgr/rgba come back as RGB."""
    rng = np.random.default_rng(0)
    if encoding in ("rgb8", "bgr8"):
        arr = rng.integers(0, 255, (5, 7, 3), dtype=np.uint8)
    elif encoding == "rgba8":
        arr = rng.integers(0, 255, (5, 7, 4), dtype=np.uint8)
    elif encoding == "16UC1":
        arr = rng.integers(0, 65535, (5, 7), dtype=np.uint16)
    elif encoding == "32FC1":
        arr = rng.random((5, 7), dtype=np.float32)
        arr[0, 0] = np.nan  # no measurement
    else:
        arr = rng.integers(0, 255, (5, 7), dtype=np.uint8)
    msg = decode_image(encode_image(array_to_image(arr, encoding, stamp_ns=5, frame_id="f", row_padding=3)))
    assert msg.step > msg.width
    out = image_to_array(msg)
    expected = arr[..., :3] if encoding == "rgba8" else arr
    np.testing.assert_array_equal(out, expected)


def test_camera_info_and_tf_round_trip() -> None:
    K = np.array([[600.0, 0, 319.5], [0, 601.0, 239.5], [0, 0, 1]])
    P = np.hstack([K, np.zeros((3, 1))])
    info = CameraInfoMsg(Header(3, "color_optical"), 480, 640, "plumb_bob", np.arange(5.0), K, np.eye(3), P, 0, 0, (0, 0, 0, 0, False))
    back = decode_camera_info(encode_camera_info(info))
    np.testing.assert_array_equal(back.k, K)
    np.testing.assert_array_equal(back.d, np.arange(5.0))
    np.testing.assert_array_equal(back.p, P)
    assert (back.width, back.height, back.distortion_model) == (640, 480, "plumb_bob")
    tfs = [
        TransformStampedMsg(Header(9, "map"), "odom", np.array([1.0, 2, 3]), np.array([0, 0, 0, 1.0])),
        TransformStampedMsg(Header(10, "odom"), "base_link", np.array([4.0, 5, 6]), np.array([0, 0, 1.0, 0])),
    ]
    out = decode_tf_message(encode_tf_message(tfs))
    assert [(t.header.frame_id, t.child_frame_id) for t in out] == [("map", "odom"), ("odom", "base_link")]
    np.testing.assert_array_equal(out[1].rotation_xyzw, [0, 0, 1, 0])


def test_hostile_and_truncated_payloads_raise_cdr_error() -> None:
    """Bad input: every truncation of a valid Image payload, a sequence length of 4 GiB, an
    unknown encapsulation, the wrong message type, an unsupported encoding, a data size that
    disagrees with step*height. Each raises CdrError (a ValueError), nothing else."""
    good = encode_image(array_to_image(np.zeros((4, 6), np.uint16), "16UC1", stamp_ns=1, frame_id="depth"))
    for cut in range(len(good) - 4):
        with pytest.raises(CdrError):
            image_to_array(decode_image(good[:cut]))
    huge = bytearray(good)
    huge[-4 * 6 * 2 - 4 : -4 * 6 * 2] = struct.pack("<I", 0xFFFFFFFF)
    with pytest.raises(CdrError, match="sequence length"):
        decode_image(bytes(huge))
    with pytest.raises(CdrError, match="(?i)encapsulation"):
        decode_image(b"\x00\x07\x00\x00" + good[4:])
    odo = encode_odometry(OdometryMsg(Header(1, "odom"), "base", np.zeros(3), np.array([0, 0, 0, 1.0])))
    with pytest.raises(CdrError):
        decode_image(odo)
    with pytest.raises(CdrError, match="unsupported image encoding 'yuv422'"):
        image_to_array(ImageMsg(Header(0, ""), 2, 2, "yuv422", False, 4, b"\x00" * 8))
    with pytest.raises(CdrError, match="step\\*height"):
        image_to_array(ImageMsg(Header(0, ""), 2, 2, "16UC1", False, 4, b"\x00" * 7))
    with pytest.raises(CdrError, match="TFMessage"):
        decode_tf_message(b"\x00\x01\x00\x00" + struct.pack("<I", 10**6))


# ------------------------------------------------------------------------------- assembling


def test_assembler_builds_frames_with_camera_pose() -> None:
    """Color (bgr8) + aligned depth (16UC1 mm) + CameraInfo + odometry -> frames with the
    CameraInfo K, RGB color, depth_scale 1000 and T_world_cam = T_odom_base @ T_body_optical
    interpolated at the image stamp."""
    asm = Ros2FrameAssembler(Ros2Config())
    out = []
    for kind, payload in _stream():
        out += asm.feed(kind, payload)
    out += asm.flush()
    frames = [f for f in out if not hasattr(f, "reason")]
    assert [f.stamp_ns for f in frames] == [k * 100 * MS + 3 * MS for k in range(1, 6)]
    for f in frames:
        f.validate()
        np.testing.assert_allclose(f.intrinsics.K, K)
        assert f.depth.dtype == np.uint16 and f.depth_scale == 1000.0
        expected = body_pose(f.stamp_ns) @ T_BODY_OPTICAL
        np.testing.assert_allclose(f.T_world_cam, expected, atol=2e-4)
    # the camera looks along the body's forward (x) axis
    np.testing.assert_allclose(frames[0].T_world_cam[:3, 2], body_pose(frames[0].stamp_ns)[:3, 0], atol=1e-3)


def test_assembler_float_depth_tf_and_bad_messages() -> None:
    """32FC1 depth stays metres (scale 1); poses from a TFMessage with the right frame pair
    (others ignored); bad input: a corrupt image payload, odometry in another frame, an image
    before CameraInfo, a depth of the wrong size. Each is skipped with its reason."""
    cfg = Ros2Config(topics=Ros2Topics(odometry=None, tf="tf"))
    asm = Ros2FrameAssembler(cfg)
    # an image pair before CameraInfo
    early = []
    c = array_to_image(np.zeros((24, 32, 3), np.uint8), "rgb8", stamp_ns=1, frame_id="cam")
    d = array_to_image(np.zeros((24, 32), np.float32), "32FC1", stamp_ns=1, frame_id="cam")
    early += asm.feed("color", encode_image(c)) + asm.feed("depth", encode_image(d))
    assert [s.reason for s in early] == ["no_camera_info"]
    frames = []
    for kind, payload in _stream("32FC1"):
        if kind == "odometry":
            odo = decode_odometry(payload)
            tf_ok = TransformStampedMsg(odo.header, "base_link", odo.position, odo.orientation_xyzw)
            tf_other = TransformStampedMsg(Header(odo.header.stamp_ns, "map"), "odom", np.ones(3), np.array([0, 0, 0, 1.0]))
            kind, payload = "tf", encode_tf_message([tf_other, tf_ok])
        frames += asm.feed(kind, payload)
    bad = asm.feed("color", b"\x00\x01\x00\x00garbage")
    assert [s.reason for s in bad] == ["bad_color"]
    small = array_to_image(np.zeros((12, 16), np.float32), "32FC1", stamp_ns=900 * MS, frame_id="cam")
    asm.feed("color", encode_image(array_to_image(np.zeros((24, 32, 3), np.uint8), "rgb8", stamp_ns=900 * MS, frame_id="cam")))
    mismatch = asm.feed("depth", encode_image(small))
    assert [s.reason for s in mismatch] == ["size_mismatch"]
    good = [f for f in frames if not hasattr(f, "reason")]
    assert len(good) == 5
    for f in good:
        assert f.depth.dtype == np.float32 and f.depth_scale == 1.0
        np.testing.assert_allclose(f.T_world_cam, body_pose(f.stamp_ns) @ T_BODY_OPTICAL, atol=2e-4)
    odo_cfg = Ros2FrameAssembler(Ros2Config())
    odo_cfg.feed("camera_info", _info())
    assert [s.reason for s in odo_cfg.feed("odometry", _odom(0, frame="map"))] == ["pose_wrong_frame"]


