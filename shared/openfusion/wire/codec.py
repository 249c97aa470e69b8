"""The wire codec: pydantic messages <-> msgpack bytes, numpy arrays as raw bytes.

Wire format: ONE msgpack map, readable by any msgpack library::

    {"arraydata": <bin>, "schema": "sensor.rgbd", "version": 1, "body": {...fields...}}

Inside ``body`` every numpy array field is a map ``{"dtype": "uint16", "shape": [480, 640],
"offset": 1024}``: its C-contiguous, little-endian bytes are at ``offset`` in ``arraydata``
(each array starts at a multiple of :data:`ARRAY_ALIGN` bytes). ``dtype`` is one of
:data:`ALLOWED_DTYPES` (names; byte order always little-endian). Writers may instead inline the
bytes as ``{"dtype", "shape", "data": <bin>}`` and omit ``arraydata``; decoders accept both.
:func:`encode` writes ``arraydata`` first, so the array bytes start at offset 16 of the payload
and :func:`decode` hands out arrays that are views on the payload without copying them
(only the small rest of the map goes through msgpack). Dict keys travel as strings (msgpack
maps with ``strict_map_key``); int keys come back through pydantic.

Payloads come from the network, so decoding never runs code: msgpack with ``raw=False``,
``strict_map_key=True`` and an ``ext_hook`` that refuses every extension type; no pickle. Bytes
that are not a valid message raise :class:`DecodeError` (a ValueError) whose ``reason`` is one
of :data:`DECODE_REASONS`:

=====================  ======================================================================
``too_large``          payload over ``max_bytes``, or an array over ``max_array_elements``
``truncated``          empty or cut-off input
``not_msgpack``        not msgpack, trailing bytes, extension types, non-string map keys
``bad_envelope``       msgpack, but not a ``{schema, version, body}`` map
``unknown_schema``     no message class registered for that schema name
``unexpected_schema``  a valid message, but not the schema the caller expected
``version_mismatch``   the schema is known, in another version
``bad_dtype``          an array dtype outside the whitelist or not allowed for that field
``array_size_mismatch``  an array's byte count disagrees with its dtype and shape
``invalid_fields``     fields missing, unknown or of the wrong type/shape (pydantic's message)
=====================  ======================================================================

Decoded arrays are zero-copy views (``np.frombuffer``) on the payload: they are READ-ONLY and
keep the payload alive. Copy (``arr.copy()``) before writing into one.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Annotated, Any, TypeVar

import msgpack
import numpy as np
from pydantic import BaseModel, ValidationError
from pydantic_core import PydanticCustomError, core_schema

from openfusion.errors import OpenFusionError
from openfusion.wire.limits import MAX_MESSAGE_BYTES
from openfusion.wire.message import Message, message_class

DEFAULT_MAX_MESSAGE_BYTES = MAX_MESSAGE_BYTES
"""Largest payload :func:`encode` writes and :func:`decode` reads unless told otherwise
(:data:`openfusion.wire.limits.MAX_MESSAGE_BYTES`)."""

DEFAULT_MAX_ARRAY_ELEMENTS = 32 * 1024 * 1024
"""Most elements one array may have on the wire unless told otherwise (per array)."""

MAX_ARRAY_NDIM = 8

ARRAY_ALIGN = 16
"""Each array in ``arraydata`` starts at a multiple of this many bytes (as does ``arraydata``)."""

_ARRAYDATA = "arraydata"
# What encode() writes first: a map of 4 entries, key "arraydata", then a bin32 header; the
# 4-byte length follows, so the array bytes start at offset 16 of the payload.
_FAST_PREFIX = b"\x84\xa9" + _ARRAYDATA.encode() + b"\xc6"

ALLOWED_DTYPES: tuple[str, ...] = (
    "bool",
    "int8",
    "int16",
    "int32",
    "int64",
    "uint8",
    "uint16",
    "uint32",
    "uint64",
    "float16",
    "float32",
    "float64",
)
_WIRE_DTYPES: dict[str, np.dtype] = {name: np.dtype(name).newbyteorder("<") for name in ALLOWED_DTYPES}
# dtype -> name for native and little-endian dtypes (``dtype.name`` is slow on the hot path).
_DTYPE_NAMES: dict[np.dtype, str] = {
    **{np.dtype(name): name for name in ALLOWED_DTYPES},
    **{dt: name for name, dt in _WIRE_DTYPES.items()},
}


def _dtype_name(dtype: np.dtype) -> str:
    name = _DTYPE_NAMES.get(dtype)
    return name if name is not None else dtype.name

DECODE_REASONS: tuple[str, ...] = (
    "too_large",
    "truncated",
    "not_msgpack",
    "bad_envelope",
    "unknown_schema",
    "unexpected_schema",
    "version_mismatch",
    "bad_dtype",
    "array_size_mismatch",
    "invalid_fields",
)
# Error types raised inside array validation that name a decode reason of their own.
_ARRAY_REASONS = ("too_large", "bad_dtype", "array_size_mismatch")

M = TypeVar("M", bound=BaseModel)


class DecodeError(OpenFusionError, ValueError):
    """Bytes that are not a valid message. ``reason`` is one of :data:`DECODE_REASONS`."""

    def __init__(self, reason: str, detail: str, *, schema: str | None = None) -> None:
        assert reason in DECODE_REASONS, reason
        self.reason = reason
        self.detail = detail
        self.schema = schema
        where = f" ({schema})" if schema else ""
        super().__init__(f"{reason}{where}: {detail}")


class EncodeError(OpenFusionError, ValueError):
    """A message that cannot be put on the wire (too large, or an array of an unsupported dtype)."""


# --------------------------------------------------------------------------------------- arrays


@dataclass(frozen=True)
class ArraySpec:
    """Pydantic annotation for a numpy array field: allowed dtypes and shape.

    ``dtypes``: allowed dtype names (subset of :data:`ALLOWED_DTYPES`; empty = all of them).
    ``shape``: None for any shape, else a tuple with one entry per dimension: an int for a
    fixed size or None for any size. A field accepts a numpy array of an allowed dtype, the wire
    map ``{dtype, shape, data}``, or (when exactly one dtype is allowed) a nested list.
    Arrays are taken as they are (no dtype casting) so a wrong dtype is reported, not hidden.
    """

    dtypes: tuple[str, ...] = ()
    shape: tuple[int | None, ...] | None = None

    def __post_init__(self) -> None:
        unknown = [d for d in self.dtypes if d not in ALLOWED_DTYPES]
        if unknown:
            raise ValueError(f"ArraySpec dtypes {unknown} are not in the wire whitelist {ALLOWED_DTYPES}")

    def __get_pydantic_core_schema__(self, source: Any, handler: Any) -> core_schema.CoreSchema:
        return core_schema.with_info_plain_validator_function(self._validate)

    def describe(self) -> str:
        dt = "|".join(self.dtypes) if self.dtypes else "any dtype"
        if self.shape is None:
            return f"{dt} array"
        dims = ",".join("?" if d is None else str(d) for d in self.shape)
        return f"{dt} array of shape ({dims})"

    def _validate(self, value: Any, info: core_schema.ValidationInfo) -> np.ndarray:
        if isinstance(value, np.ndarray):
            arr = value
        elif isinstance(value, Mapping):
            context = info.context or {}
            arr = array_from_wire(
                value,
                max_elements=context.get("max_array_elements", DEFAULT_MAX_ARRAY_ELEMENTS),
                arraydata=context.get("arraydata"),
            )
        elif isinstance(value, (list, tuple)) and len(self.dtypes) == 1:
            try:
                arr = np.asarray(value, dtype=self.dtypes[0])
            except (ValueError, TypeError, OverflowError) as exc:
                raise PydanticCustomError(
                    "ndarray_type", "cannot make a {spec} from this list: {error}",
                    {"spec": self.describe(), "error": str(exc)},
                ) from None
        else:
            raise PydanticCustomError(
                "ndarray_type", "expected a numpy {spec}, got {type}",
                {"spec": self.describe(), "type": type(value).__name__},
            )
        name = _dtype_name(arr.dtype)
        if name not in _WIRE_DTYPES:
            raise PydanticCustomError(
                "bad_dtype", "array dtype {dtype} is not allowed on the wire", {"dtype": str(arr.dtype)}
            )
        if self.dtypes and name not in self.dtypes:
            raise PydanticCustomError(
                "bad_dtype", "expected a {spec}, got dtype {dtype}", {"spec": self.describe(), "dtype": name}
            )
        if self.shape is not None and (
            arr.ndim != len(self.shape) or any(w is not None and w != s for w, s in zip(self.shape, arr.shape, strict=True))
        ):
            raise PydanticCustomError(
                "ndarray_shape", "expected a {spec}, got shape {shape}",
                {"spec": self.describe(), "shape": str(tuple(arr.shape))},
            )
        return arr


def ndarray(*dtypes: str, shape: tuple[int | None, ...] | None = None) -> Any:
    """The annotated type of an array field: ``color: ndarray("uint8", shape=(None, None, 3))``."""
    return Annotated[np.ndarray, ArraySpec(tuple(dtypes), shape)]


class _Chunks:
    """Array bytes collected for the ``arraydata`` blob, each start aligned to :data:`ARRAY_ALIGN`."""

    def __init__(self) -> None:
        self.parts: list[Any] = []
        self.size = 0

    def add(self, data: Any, nbytes: int) -> int:
        pad = (-self.size) % ARRAY_ALIGN
        if pad:
            self.parts.append(bytes(pad))
            self.size += pad
        offset = self.size
        self.parts.append(data)
        self.size += nbytes
        return offset


def array_to_wire(arr: np.ndarray, chunks: _Chunks | None = None) -> dict[str, Any]:
    """The wire map of ``arr`` (little-endian, C-contiguous; copies only when it must): inline
    ``{dtype, shape, data}``, or ``{dtype, shape, offset}`` with the bytes added to ``chunks``."""
    name = _dtype_name(arr.dtype)
    if name not in _WIRE_DTYPES:
        raise EncodeError(f"array dtype {arr.dtype} cannot go on the wire (allowed: {', '.join(ALLOWED_DTYPES)})")
    wire_dtype = _WIRE_DTYPES[name]
    if arr.dtype != wire_dtype:
        arr = arr.astype(wire_dtype)
    shape = list(arr.shape)  # before ascontiguousarray, which makes 0-d arrays 1-d
    data = np.ascontiguousarray(arr).reshape(-1).view(np.uint8).data if arr.size else b""
    if chunks is None:
        return {"dtype": name, "shape": shape, "data": data}
    return {"dtype": name, "shape": shape, "offset": chunks.add(data, arr.nbytes)}


def array_from_wire(
    value: Mapping[str, Any],
    *,
    max_elements: int = DEFAULT_MAX_ARRAY_ELEMENTS,
    arraydata: memoryview | None = None,
) -> np.ndarray:
    """The (read-only, zero-copy) array of a wire map; PydanticCustomError naming the reason.

    ``{dtype, shape, data}`` carries its bytes inline; ``{dtype, shape, offset}`` points into
    the message's ``arraydata`` blob."""
    keys = set(value.keys())
    if keys not in ({"dtype", "shape", "data"}, {"dtype", "shape", "offset"}):
        raise PydanticCustomError(
            "ndarray_wire", "an array must be a map with keys dtype, shape and data or offset; got keys {keys}",
            {"keys": str(sorted(map(str, keys)))},
        )
    dtype_name, shape = value["dtype"], value["shape"]
    if not isinstance(dtype_name, str) or dtype_name not in _WIRE_DTYPES:
        raise PydanticCustomError(
            "bad_dtype", "array dtype {dtype!r} is not one of the allowed dtypes", {"dtype": str(dtype_name)[:40]}
        )
    if (
        not isinstance(shape, (list, tuple))
        or len(shape) > MAX_ARRAY_NDIM
        or not all(type(d) is int and d >= 0 for d in shape)
    ):
        raise PydanticCustomError(
            "ndarray_wire", "array shape must be a list of at most {n} non-negative ints, got {shape}",
            {"n": MAX_ARRAY_NDIM, "shape": str(shape)[:80]},
        )
    count = math.prod(shape)
    if count > max_elements or any(d > max_elements for d in shape):
        raise PydanticCustomError(
            "too_large", "array of shape {shape} has more than {limit} elements",
            {"shape": str(tuple(shape)), "limit": max_elements},
        )
    dtype = _WIRE_DTYPES[dtype_name]
    need = count * dtype.itemsize
    if "data" in value:
        data = value["data"]
        if not isinstance(data, (bytes, bytearray, memoryview)):
            raise PydanticCustomError("ndarray_wire", "array data must be bytes, got {type}", {"type": type(data).__name__})
        if len(data) != need:
            raise PydanticCustomError(
                "array_size_mismatch", "array {dtype} {shape} needs {need} bytes, got {got}",
                {"dtype": dtype_name, "shape": str(tuple(shape)), "need": need, "got": len(data)},
            )
        arr = np.frombuffer(data, dtype=dtype).reshape(shape)
    else:
        offset = value["offset"]
        if type(offset) is not int or offset < 0:
            raise PydanticCustomError("ndarray_wire", "array offset must be a non-negative int, got {offset}",
                                      {"offset": str(offset)[:40]})
        if arraydata is None:
            raise PydanticCustomError("ndarray_wire", "array points into arraydata but the message has none", {})
        if offset + need > len(arraydata):
            raise PydanticCustomError(
                "array_size_mismatch", "array {dtype} {shape} needs bytes {start}..{end} of arraydata, which has {got}",
                {"dtype": dtype_name, "shape": str(tuple(shape)), "start": offset, "end": offset + need,
                 "got": len(arraydata)},
            )
        arr = np.frombuffer(arraydata, dtype=dtype, count=count, offset=offset).reshape(shape)
    if sys.byteorder != "little":  # keep native dtypes for the rest of the code
        arr = arr.astype(dtype.newbyteorder("="))
    return arr


# -------------------------------------------------------------------------------- encode/decode


def _to_wire(value: Any, chunks: _Chunks) -> Any:
    if isinstance(value, np.ndarray):
        return array_to_wire(value, chunks)
    if isinstance(value, BaseModel):
        return {name: _to_wire(getattr(value, name), chunks) for name in type(value).model_fields}
    if isinstance(value, (list, tuple)):
        return [_to_wire(v, chunks) for v in value]
    if isinstance(value, dict):
        return {(k if isinstance(k, str) else str(k)): _to_wire(v, chunks) for k, v in value.items()}
    if isinstance(value, np.generic):
        return value.item()
    return value


def encode(msg: Message, *, max_bytes: int = DEFAULT_MAX_MESSAGE_BYTES) -> bytes:
    """The wire bytes of ``msg`` (a registered :class:`openfusion.wire.schemas.Message`)."""
    schema = getattr(type(msg), "schema_name", None)
    version = getattr(type(msg), "schema_version", None)
    if not isinstance(msg, BaseModel) or not isinstance(schema, str) or not isinstance(version, int):
        raise TypeError(f"encode needs an openfusion.wire.schemas.Message with a schema name, got {type(msg).__name__}")
    chunks = _Chunks()
    try:
        body = _to_wire(msg, chunks)
        tail = msgpack.packb({"schema": schema, "version": version, "body": body}, use_bin_type=True)
    except EncodeError:
        raise
    except (TypeError, ValueError, OverflowError) as exc:
        raise EncodeError(f"cannot encode {schema}: {exc}") from exc
    size = len(_FAST_PREFIX) + 4 + chunks.size + len(tail) - 1
    if size > max_bytes or chunks.size >= 2**32:
        raise EncodeError(f"{schema} message is {size} bytes, over the limit of {max_bytes} bytes")
    # One map of 4: "arraydata" (bin32, first so its bytes start at offset 16) + the 3 entries of tail.
    return b"".join((_FAST_PREFIX, chunks.size.to_bytes(4, "big"), *chunks.parts, memoryview(tail)[1:]))


def _refuse_ext(code: int, data: bytes) -> Any:
    raise ValueError(f"msgpack extension type {code} is not allowed")


def _as_buffer(data: Any) -> bytes | bytearray | memoryview:
    if isinstance(data, (bytes, bytearray, memoryview)):
        return data
    to_bytes = getattr(data, "to_bytes", None)  # zenoh.ZBytes
    if callable(to_bytes):
        return to_bytes()
    raise TypeError(f"decode needs bytes (or zenoh.ZBytes), got {type(data).__name__}")


def _unpackb(buf: Any, total: int) -> Any:
    try:
        return msgpack.unpackb(buf, raw=False, strict_map_key=True, ext_hook=_refuse_ext)
    except msgpack.ExtraData:
        raise DecodeError("not_msgpack", "trailing bytes after the msgpack message") from None
    except (ValueError, TypeError, msgpack.UnpackException) as exc:
        text = str(exc)
        # msgpack bounds declared lengths by the buffer size ("3 exceeds max_map_len(0)"):
        # a length the rest of the buffer cannot hold means the payload was cut off.
        if "incomplete input" in text or "exceeds max_" in text:
            raise DecodeError("truncated", f"payload of {total} bytes is cut off") from None
        raise DecodeError("not_msgpack", f"payload is not valid msgpack ({type(exc).__name__}: {text})") from None


def unpack_envelope(data: Any, *, max_bytes: int = DEFAULT_MAX_MESSAGE_BYTES) -> tuple[str, int, dict[str, Any]]:
    """``(schema, version, body)`` of wire bytes, without validating the body (a cheap peek at
    the schema; array fields are left as their wire maps)."""
    schema, version, body, _ = _unpack(data, max_bytes=max_bytes)
    return schema, version, body


def _unpack(
    data: Any, *, max_bytes: int = DEFAULT_MAX_MESSAGE_BYTES
) -> tuple[str, int, dict[str, Any], memoryview | None]:
    """``(schema, version, body, arraydata)`` of wire bytes, without validating the body.

    Fast path for what :func:`encode` writes (``arraydata`` first): only the small rest of the
    map goes through msgpack and ``arraydata`` is a view on ``data``. Any other key order (other
    msgpack writers) is decoded generically.
    """
    buf = _as_buffer(data)
    total = len(buf)
    if total > max_bytes:
        raise DecodeError("too_large", f"payload is {total} bytes, over the limit of {max_bytes} bytes")
    if total == 0:
        raise DecodeError("truncated", "payload is empty")
    arraydata: memoryview | None = None
    head = len(_FAST_PREFIX) + 4
    if total >= head and buf[: len(_FAST_PREFIX)] == _FAST_PREFIX:
        view = memoryview(buf)
        n = int.from_bytes(view[len(_FAST_PREFIX) : head], "big")
        if head + n > total:
            raise DecodeError("truncated", f"payload of {total} bytes is cut off (arraydata needs {n} bytes)")
        arraydata = view[head : head + n]
        envelope = _unpackb(b"\x83" + view[head + n :].tobytes(), total)
    else:
        envelope = _unpackb(buf, total)
        if isinstance(envelope, dict) and _ARRAYDATA in envelope:
            blob = envelope.pop(_ARRAYDATA)
            if not isinstance(blob, bytes):
                raise DecodeError("bad_envelope", f"{_ARRAYDATA} must be bytes, got {type(blob).__name__}")
            arraydata = memoryview(blob)
    if not isinstance(envelope, dict) or set(envelope.keys()) != {"schema", "version", "body"}:
        got = sorted(map(str, envelope.keys())) if isinstance(envelope, dict) else type(envelope).__name__
        raise DecodeError("bad_envelope", f"expected a map with keys schema, version, body (and {_ARRAYDATA}); got {got}")
    schema, version, body = envelope["schema"], envelope["version"], envelope["body"]
    if not isinstance(schema, str) or type(version) is not int:
        raise DecodeError("bad_envelope", "schema must be a string and version an int")
    if not isinstance(body, dict):
        raise DecodeError("invalid_fields", f"body must be a map, got {type(body).__name__}", schema=schema)
    return schema, version, body, arraydata


def decode(
    data: Any,
    *,
    expected: type[M] | None = None,
    max_bytes: int = DEFAULT_MAX_MESSAGE_BYTES,
    max_array_elements: int = DEFAULT_MAX_ARRAY_ELEMENTS,
    accept_older: bool = False,
) -> M:
    """The validated message in ``data``; :class:`DecodeError` for anything else.

    ``expected``: refuse any other schema (reason ``unexpected_schema``).
    ``max_bytes`` / ``max_array_elements``: size limits for this call.
    ``accept_older``: also read the older versions the message class lists in ``reads_versions``
    (its later fields have defaults): files written by an earlier build (recordings). On the bus
    a peer of another version is always refused.
    """
    schema, version, body, arraydata = _unpack(data, max_bytes=max_bytes)
    if expected is not None and schema != expected.schema_name:
        raise DecodeError(
            "unexpected_schema", f"expected {expected.schema_name} v{expected.schema_version}, got {schema}",
            schema=schema,
        )
    cls = message_class(schema)
    if cls is None:
        raise DecodeError("unknown_schema", f"no message type is registered as {schema!r}", schema=schema)
    if version != cls.schema_version and not (accept_older and version in getattr(cls, "reads_versions", ())):
        raise DecodeError(
            "version_mismatch", f"got version {version}, this build speaks version {cls.schema_version}",
            schema=schema,
        )
    try:
        context = {"max_array_elements": max_array_elements, "arraydata": arraydata}
        return cls.model_validate(body, context=context)  # type: ignore[return-value]
    except ValidationError as exc:
        errors = exc.errors(include_url=False, include_input=False)
        for err in errors:
            if err["type"] in _ARRAY_REASONS:
                loc = ".".join(map(str, err["loc"]))
                raise DecodeError(err["type"], f"{loc}: {err['msg']}", schema=schema) from None
        raise DecodeError("invalid_fields", _summarize(errors), schema=schema) from None
    except RecursionError:
        raise DecodeError("invalid_fields", "body is nested too deeply", schema=schema) from None


def _summarize(errors: list[Any], limit: int = 5) -> str:
    parts = [f"{'.'.join(map(str, e['loc'])) or '<body>'}: {e['msg']}" for e in errors[:limit]]
    more = f" (+{len(errors) - limit} more)" if len(errors) > limit else ""
    return "; ".join(parts) + more
