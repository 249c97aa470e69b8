"""How ROS 2 topics map onto Zenoh keys, in the two layouts a robot uses, and rmw_zenoh's attachment.

``bridge`` (zenoh-bridge-ros2dds, any ROS 2 distribution on DDS)
    topic ``/ns/topic`` -> key ``ns/topic``, prefixed by the bridge's ``--namespace`` if set. The
    payload is the CDR sample; the type is not in the key (the source is told, or guesses it).

``rmw_zenoh`` (ROS 2 with ``RMW_IMPLEMENTATION=rmw_zenoh_cpp``, shipped from Jazzy on)
    ``<domain_id>/<fully_qualified_name>/<type_name>/<type_hash>``, as rmw_zenoh's
    ``docs/design.md`` ("Topic and Service name mapping to Zenoh key expressions") gives it: the
    domain id (``ROS_DOMAIN_ID``, 0 by default), the topic name without its leading ``/``, the DDS
    type name (``sensor_msgs::msg::dds_::Image_``) and the REP-2016 type hash
    (``RIHS01_<sha256 hex>``; ``rosbags`` computes it). A subscriber here uses ``*`` for type and
    hash, so it hears a topic whatever its type, and reads the type from the sample's key.

    Each sample carries an attachment: int64 sequence number, int64 source timestamp (ns since the
    UNIX epoch), the publisher GID (16 bytes) - encoded with Zenoh's serializer as rmw_zenoh does
    since its PR #601 (backported to Humble in rmw_zenoh 0.1.2, 2025-06; Jazzy 0.2.x and later):
    8 bytes little-endian, 8 bytes little-endian, a 1-byte length (16), the 16 bytes. Releases
    before that put the key strings ``sequence_number``, ``source_timestamp``, ``source_gid``
    (each a varint length + UTF-8) before each value; :func:`parse_attachment` reads both forms and
    :func:`make_attachment` writes either (``keyed=True`` for the older releases).

Nothing here imports Zenoh: these are names and bytes, tested without a session.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Literal

from openfusion.sources.cdr import CdrError, dds_type_name, full_type_name, type_hash

Layout = Literal["bridge", "rmw_zenoh"]
LAYOUTS: tuple[str, ...] = ("bridge", "rmw_zenoh")
GID_BYTES = 16


def topic_key(topic: str, *, layout: str, namespace: str = "", domain_id: int = 0, typename: str | None = None,
              distro: str = "jazzy") -> str:
    """The Zenoh key of a ROS 2 topic. ``typename=None`` in the rmw_zenoh layout gives the
    subscription key with ``*`` for type name and hash (any type)."""
    ns = namespace.strip("/")
    name = topic.strip("/")
    name = f"{ns}/{name}" if ns else name
    if not name:
        raise ValueError("empty ROS 2 topic name")
    if layout == "bridge":
        return name
    if layout != "rmw_zenoh":
        raise ValueError(f"unknown key layout {layout!r}; known: {', '.join(LAYOUTS)}")
    if domain_id < 0:
        raise ValueError(f"domain_id must be >= 0, got {domain_id}")
    if typename is None:
        return f"{domain_id}/{name}/*/*"
    return f"{domain_id}/{name}/{dds_type_name(typename)}/{type_hash(typename, distro=distro)}"


def type_from_key(key: str) -> str | None:
    """The ROS type name (``sensor_msgs/msg/Image``) in an rmw_zenoh key, None when it has none."""
    parts = str(key).split("/")
    if len(parts) < 4:
        return None
    dds = parts[-2]
    pieces = dds.split("::")
    if len(pieces) != 4 or pieces[2] != "dds_" or not pieces[3].endswith("_"):
        return None
    return full_type_name(f"{pieces[0]}/{pieces[1]}/{pieces[3][:-1]}")


@dataclass(frozen=True)
class Attachment:
    sequence_number: int
    source_timestamp_ns: int
    source_gid: bytes


def _varint(n: int) -> bytes:
    out = bytearray()
    while True:
        b = n & 0x7F
        n >>= 7
        out.append(b | (0x80 if n else 0))
        if not n:
            return bytes(out)


def _read_varint(buf: bytes, pos: int) -> tuple[int, int]:
    value = shift = 0
    while True:
        if pos >= len(buf) or shift > 63:
            raise CdrError("rmw_zenoh attachment: truncated length")
        b = buf[pos]
        pos += 1
        value |= (b & 0x7F) << shift
        shift += 7
        if not b & 0x80:
            return value, pos


def make_attachment(sequence_number: int, source_timestamp_ns: int, source_gid: bytes, *, keyed: bool = False) -> bytes:
    """rmw_zenoh's publication attachment (module docstring); ``keyed`` for releases before PR #601."""
    if len(source_gid) != GID_BYTES:
        raise ValueError(f"source_gid must be {GID_BYTES} bytes, got {len(source_gid)}")

    def key(name: str) -> bytes:
        raw = name.encode()
        return _varint(len(raw)) + raw if keyed else b""

    return (key("sequence_number") + struct.pack("<q", sequence_number) + key("source_timestamp")
            + struct.pack("<q", source_timestamp_ns) + key("source_gid") + _varint(GID_BYTES) + bytes(source_gid))


def parse_attachment(raw: bytes | None) -> Attachment:
    """Read either attachment form (module docstring); CdrError for anything else."""
    if raw is None:
        raise CdrError("rmw_zenoh sample without an attachment")
    buf = bytes(raw)
    pos = 0
    keyed = len(buf) > 0 and buf[0] == len("sequence_number") and buf[1:16] == b"sequence_number"

    def expect(name: str) -> None:
        nonlocal pos
        if not keyed:
            return
        n, pos = _read_varint(buf, pos)
        if buf[pos:pos + n] != name.encode():
            raise CdrError(f"rmw_zenoh attachment: expected key {name!r}")
        pos += n

    def i64(what: str) -> int:
        nonlocal pos
        if pos + 8 > len(buf):
            raise CdrError(f"rmw_zenoh attachment ends inside {what}")
        (v,) = struct.unpack_from("<q", buf, pos)
        pos += 8
        return v

    expect("sequence_number")
    seq = i64("sequence_number")
    expect("source_timestamp")
    stamp = i64("source_timestamp")
    expect("source_gid")
    n, pos = _read_varint(buf, pos)
    if n != GID_BYTES or pos + n != len(buf):
        raise CdrError(f"rmw_zenoh attachment: source_gid of {n} bytes ({len(buf) - pos} left), expected {GID_BYTES}")
    return Attachment(seq, stamp, buf[pos:pos + n])
