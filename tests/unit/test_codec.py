"""The wire codec: round trips for every allowed dtype/shape, and every malformed input refused
with a DecodeError carrying the right reason (payloads come from the network)."""

from __future__ import annotations

from pathlib import Path
from typing import Any, ClassVar

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from openfusion.wire import codec
from openfusion.wire.codec import ALLOWED_DTYPES, DecodeError, EncodeError, decode, encode, ndarray
from openfusion.wire.schemas import Message, RgbdFrame, TextQuery

#: The repository root (deploy files, docs, the README's commands).
ROOT = next(p for p in Path(__file__).resolve().parents if (p / "pyproject.toml").is_file())



class AnyArrayMessage(Message):
    """Test-only message: one array of any allowed dtype/shape and an optional second one."""

    schema_name: ClassVar[str] = "test.codec.any_array"
    schema_version: ClassVar[int] = 3

    name: str
    values: ndarray()
    extra: ndarray("float32", shape=(None, 3)) | None = None


def _wire(msg: Message) -> dict[str, Any]:
    return msgpack.unpackb(encode(msg), raw=False)


def _pack(obj: Any) -> bytes:
    return msgpack.packb(obj, use_bin_type=True)


def _reason(data: bytes, **kwargs: Any) -> str:
    with pytest.raises(DecodeError) as info:
        decode(data, **kwargs)
    assert isinstance(info.value, ValueError)
    return info.value.reason


def _frame_msg(h: int = 6, w: int = 8) -> RgbdFrame:
    rng = np.random.default_rng(0)
    return RgbdFrame(
        frame_id=3,
        stamp_ns=123,
        width_px=w,
        height_px=h,
        fx=10.0,
        fy=10.0,
        cx=w / 2,
        cy=h / 2,
        T_world_cam=np.eye(4),
        depth_scale=1000.0,
        color=rng.integers(0, 255, (h, w, 3), dtype=np.uint8),
        depth=rng.integers(0, 5000, (h, w), dtype=np.uint16),
        instance_categories={1: "chair"},
    )


# ----------------------------------------------------------------------------- round trips

_dtypes = st.sampled_from(ALLOWED_DTYPES)


@st.composite
def _arrays(draw: st.DrawFn) -> np.ndarray:
    dtype = np.dtype(draw(_dtypes))
    shape = draw(hnp.array_shapes(min_dims=0, max_dims=4, min_side=0, max_side=5))
    arr = draw(hnp.arrays(dtype, shape))
    order = draw(st.sampled_from(["native", "big", "fortran", "strided"]))
    if order == "big" and dtype.itemsize > 1:
        arr = arr.astype(dtype.newbyteorder(">"))
    elif order == "fortran":
        arr = np.asfortranarray(arr)
    elif order == "strided" and arr.ndim >= 1:
        arr = np.concatenate([arr, arr], axis=0)[::2]
    return arr


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(arr=_arrays(), name=st.text(max_size=20))
def test_arrays_of_every_dtype_and_shape_round_trip_exactly(arr: np.ndarray, name: str) -> None:
    """Arrays of each whitelisted dtype, any shape (incl. 0-d and empty), big-endian, Fortran-order
    and strided inputs come back with the same values, dtype and shape."""
    out = decode(encode(AnyArrayMessage(name=name, values=arr)), expected=AnyArrayMessage)
    assert out.name == name
    assert out.values.dtype == arr.dtype.newbyteorder("=")
    assert out.values.shape == arr.shape
    np.testing.assert_array_equal(out.values, arr)  # NaN == NaN positions compared by numpy


def test_decoded_arrays_are_zero_copy_read_only_views() -> None:
    """Decoding does not copy arrays a second time: they are read-only views on the payload."""
    out = decode(encode(_frame_msg()), expected=RgbdFrame)
    assert not out.depth.flags.writeable and not out.depth.flags.owndata
    with pytest.raises(ValueError):
        out.depth[0, 0] = 1


def test_rgbd_frame_round_trips_through_frame() -> None:
    """RgbdFrame.from_frame -> wire -> to_frame keeps pixels, pose, intrinsics and categories."""
    msg = _frame_msg()
    frame = decode(encode(RgbdFrame.from_frame(msg.to_frame())), expected=RgbdFrame).to_frame()
    np.testing.assert_array_equal(frame.color, msg.color)
    np.testing.assert_array_equal(frame.depth, msg.depth)
    assert frame.intrinsics == msg.intrinsics
    assert frame.instance_categories == {1: "chair"}  # int keys survive the str-keyed wire map


def test_encode_refuses_unsupported_dtypes_and_oversize() -> None:
    """Object/complex arrays cannot be put on the wire; a payload over max_bytes is refused."""
    with pytest.raises(Exception) as info:
        AnyArrayMessage(name="x", values=np.array([1 + 2j]))
    assert "complex" in str(info.value)
    with pytest.raises(EncodeError, match="over the limit"):
        encode(_frame_msg(), max_bytes=100)
    with pytest.raises(TypeError):
        encode({"schema": "x"})  # type: ignore[arg-type]


# ---------------------------------------------------------------------------- malformed input


def test_empty_and_cut_off_payloads_are_truncated() -> None:
    """Every prefix of a valid payload is refused as truncated, never half-decoded."""
    data = encode(TextQuery(text="chair"))
    assert _reason(b"") == "truncated"
    for cut in range(1, len(data)):
        assert _reason(data[:cut]) == "truncated", cut


@pytest.mark.parametrize(
    "data",
    [
        b"\xc1",  # never-used msgpack byte
        encode(TextQuery(text="chair")) + b"\x00",  # trailing bytes
        _pack({"schema": "query.text", "version": 1, "body": {"text": msgpack.ExtType(5, b"x")}}),
        _pack({1: 2}),  # int map key (strict_map_key)
        b"\xa3\xff\xfe\xfd",  # str with invalid UTF-8
    ],
    ids=["reserved-byte", "trailing", "ext-type", "int-key", "bad-utf8"],
)
def test_non_msgpack_is_refused(data: bytes) -> None:
    """Garbage, trailing bytes, extension types and non-string keys are not_msgpack."""
    assert _reason(data) == "not_msgpack"


@pytest.mark.parametrize(
    "obj",
    [[1, 2], {"schema": "query.text", "version": 1}, {"schema": 1, "version": 1, "body": {}},
     {"schema": "query.text", "version": "1", "body": {}}],
)
def test_bad_envelopes_are_refused(obj: Any) -> None:
    """A msgpack value that is not a {schema, version, body} map is bad_envelope."""
    assert _reason(_pack(obj)) == "bad_envelope"


def test_unknown_unexpected_and_version_mismatched_schemas() -> None:
    """Unknown names, another schema than expected, and another version are each named."""
    assert _reason(_pack({"schema": "no.such", "version": 1, "body": {}})) == "unknown_schema"
    assert _reason(encode(TextQuery(text="x")), expected=RgbdFrame) == "unexpected_schema"
    wire = _wire(TextQuery(text="x"))
    wire["version"] = 2
    assert _reason(_pack(wire)) == "version_mismatch"


def test_array_byte_count_disagreeing_with_shape_is_array_size_mismatch() -> None:
    """A depth image whose inline data is shorter/longer than dtype x shape, or whose offset and
    size run past the end of arraydata, is refused."""
    wire = _wire(_frame_msg())
    depth = np.zeros((6, 8), np.uint16).tobytes()
    for bad_data in (depth[:-2], depth + b"\x00\x00", depth[:-1], b""):
        wire["body"]["depth"] = {"dtype": "uint16", "shape": [6, 8], "data": bad_data}
        assert _reason(_pack(wire)) == "array_size_mismatch"
    blob_len = len(wire["arraydata"])
    for offset, shape in ((blob_len - 2, [2]), (0, [blob_len]), (blob_len, [1, 1])):
        wire["body"]["depth"] = {"dtype": "uint16", "shape": shape, "offset": offset}
        assert _reason(_pack(wire)) == "array_size_mismatch"


def test_array_offsets_need_valid_arraydata() -> None:
    """Offsets that are negative or not ints, offsets without arraydata, and an arraydata that is
    not bytes are refused."""
    wire = _wire(_frame_msg())
    for offset in (-16, "0", 1.5):
        bad = {**wire, "body": {**wire["body"], "depth": {**wire["body"]["depth"], "offset": offset}}}
        assert _reason(_pack(bad)) == "invalid_fields"
    no_blob = {k: v for k, v in wire.items() if k != "arraydata"}
    assert _reason(_pack(no_blob)) == "invalid_fields"
    assert _reason(_pack({**wire, "arraydata": "text"})) == "bad_envelope"


def test_generic_msgpack_writers_are_understood() -> None:
    """Another writer's key order (arraydata last) and inline array data decode to the same
    message as encode()'s own layout."""
    msg = _frame_msg()
    wire = _wire(msg)
    reordered = {"schema": wire["schema"], "version": wire["version"], "body": wire["body"], "arraydata": wire["arraydata"]}
    inline = {k: v for k, v in wire.items() if k != "arraydata"}
    inline["body"] = {
        name: codec.array_to_wire(getattr(msg, name)) if isinstance(v, dict) and "offset" in v else v
        for name, v in wire["body"].items()
    }
    assert "offset" not in str(inline)
    for data in (_pack(reordered), _pack(inline)):
        out = decode(data, expected=RgbdFrame)
        np.testing.assert_array_equal(out.color, msg.color)
        np.testing.assert_array_equal(out.depth, msg.depth)


def test_arrays_are_views_on_the_payload_and_aligned() -> None:
    """Decoding does not copy array bytes: changing the payload buffer changes the array; every
    array starts 16-byte aligned inside the payload."""
    msg = _frame_msg()
    payload = bytearray(encode(msg))
    out = decode(payload, expected=RgbdFrame)
    offset = _wire(msg)["body"]["depth"]["offset"]
    assert offset % codec.ARRAY_ALIGN == 0 and _wire(msg)["body"]["color"]["offset"] % codec.ARRAY_ALIGN == 0
    payload[16 + offset : 16 + offset + 2] = (4242).to_bytes(2, "little")
    assert out.depth[0, 0] == 4242


@pytest.mark.parametrize("dtype", ["object", "complex64", ">u2", "<u2", "int64", "", 7])
def test_dtypes_outside_the_whitelist_or_field_are_bad_dtype(dtype: Any) -> None:
    """Non-whitelisted dtype strings, and whitelisted ones a field does not allow (depth as int64),
    are bad_dtype (numpy is never asked to interpret an arbitrary dtype string)."""
    wire = _wire(_frame_msg())
    depth = dict(wire["body"]["depth"])
    depth["dtype"] = dtype
    if dtype == "int64":  # a whitelisted dtype, with the right number of bytes, on the wrong field
        depth = {"dtype": dtype, "shape": [6, 8], "data": np.zeros((6, 8), np.int64).tobytes()}
    wire["body"]["depth"] = depth
    assert _reason(_pack(wire)) == "bad_dtype"


def test_size_limits_are_configurable_per_call() -> None:
    """Payloads over max_bytes and arrays over max_array_elements are too_large; defaults accept them."""
    data = encode(_frame_msg(6, 8))
    assert _reason(data, max_bytes=len(data) - 1) == "too_large"
    assert decode(data, max_bytes=len(data)).frame_id == 3
    assert _reason(data, max_array_elements=6 * 8 - 1) == "too_large"
    wire = _wire(_frame_msg())
    wire["body"]["depth"]["shape"] = [2**40, 2**40]  # claimed size, no data
    assert _reason(_pack(wire)) == "too_large"


@pytest.mark.parametrize(
    "edit",
    [
        lambda b: b.pop("frame_id"),
        lambda b: b.update(frame_id="three"),
        lambda b: b.update(unexpected_field=1),
        lambda b: b.update(fx=float("nan")),
        lambda b: b.update(width_px=9),  # intrinsics disagree with image size (Frame.validate)
        lambda b: b.update(T_world_cam=codec.array_to_wire(np.zeros((4, 4)))),  # not a pose
        lambda b: b.update(color=codec.array_to_wire(np.zeros((6, 8, 4), np.uint8))),  # 4 channels
        lambda b: b.update(color=[1, 2, 3]),
        lambda b: b.update(depth={"dtype": "uint16", "shape": [6, 8]}),  # no data key
    ],
    ids=["missing", "wrong-type", "extra", "nan", "size-mismatch", "bad-pose", "bad-shape", "list", "array-keys"],
)
def test_invalid_fields_are_refused_with_pydantic_message(edit: Any) -> None:
    """Missing, unknown, mistyped, non-finite and mutually inconsistent fields are invalid_fields."""
    wire = _wire(_frame_msg())
    edit(wire["body"])
    with pytest.raises(DecodeError) as info:
        decode(_pack(wire))
    assert info.value.reason == "invalid_fields"
    assert info.value.schema == "sensor.rgbd"


def test_body_that_is_not_a_map_is_invalid_fields() -> None:
    """A list body is refused with a clear message."""
    assert _reason(_pack({"schema": "error", "version": 1, "body": [1, 2]})) == "invalid_fields"


@settings(max_examples=150, deadline=None)
@given(data=st.binary(max_size=200))
def test_random_bytes_never_escape_decode_error(data: bytes) -> None:
    """Arbitrary bytes either decode to a valid message or raise DecodeError, nothing else."""
    try:
        msg = decode(data)
    except DecodeError as exc:
        assert exc.reason in codec.DECODE_REASONS
    else:
        assert isinstance(msg, Message)


@settings(max_examples=150, deadline=None)
@given(pos=st.integers(min_value=0), byte=st.integers(min_value=0, max_value=255))
def test_corrupted_valid_payloads_never_escape_decode_error(pos: int, byte: int) -> None:
    """A valid payload with one byte changed decodes to a valid message or raises DecodeError."""
    data = bytearray(encode(_frame_msg(2, 3)))
    data[pos % len(data)] = byte
    try:
        msg = decode(bytes(data))
    except DecodeError:
        return
    assert isinstance(msg, RgbdFrame)
    msg.to_frame().validate()


def test_no_pickle_anywhere_in_the_library() -> None:
    """No library module imports pickle or enables allow_pickle (payloads are untrusted)."""
    offenders = []
    for path in (ROOT / "shared" / "openfusion").rglob("*.py"):
        text = path.read_text()
        if "import pickle" in text or "allow_pickle=True" in text or "from pickle" in text:
            offenders.append(str(path.relative_to(ROOT)))
    assert not offenders, offenders
