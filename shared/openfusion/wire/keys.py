"""The key grammar of OpenFusion-Z: every Zenoh key expression is built here.

Key space: ``{prefix}/{map_id}/{service}/{...}``; the default prefix is ``openfusion``.
``map_id`` names one map (a robot, a site, a session) and must be ONE key segment. The prefix
may have several segments (``fleet/openfusion``), each of which must be a valid segment.

A valid segment is non-empty, at most 128 characters, made only of ASCII letters, digits,
``_``, ``-`` and ``.``, and does not start with ``.``. This refuses everything with a meaning
in Zenoh key expressions (``/``, ``*``, ``$``, ``?``, ``#``, ``@``) and whitespace, so a user id
can never widen a subscription or escape its map.

Use :class:`KeySpace`::

    keys = KeySpace("openfusion", "lab")
    keys.key("sensor", "rgbd")  # "openfusion/lab/sensor/rgbd"
    keys.health("geometry")     # "openfusion/lab/health/geometry"
    keys.health_all             # "openfusion/lab/health/*"

The topics and queryables of a map (key parts, message types, owners) are declared once in
:mod:`openfusion.wire.endpoints` (``SENSOR_RGBD.key(keys)``); :func:`key_for` builds any key.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Literal

from openfusion.errors import UserError

DEFAULT_PREFIX = "openfusion"
MAX_SEGMENT_CHARS = 128

#: A single-segment wildcard part, allowed in the ``parts`` of :func:`key_for` only.
ANY = "*"
#: A multi-segment wildcard part, allowed in the ``parts`` of :func:`key_for` only.
ANY_DEEP = "**"

CONTROL_ACTIONS: tuple[str, ...] = ("save", "load", "reset")
ControlAction = Literal["save", "load", "reset"]



class InvalidKeyError(UserError, ValueError):
    """A map id, prefix, service name or key part that is not a valid key segment (the message
    names the value and why)."""


_VALID_SEGMENT = re.compile(r"^[A-Za-z0-9_\-][A-Za-z0-9_.\-]*$")
_SPECIAL_CHARS = {
    "/": "'/' separates key segments",
    "*": "'*' is a Zenoh wildcard",
    "$": "'$' is a Zenoh wildcard marker",
    "?": "'?' starts Zenoh selector parameters",
    "#": "'#' is reserved in Zenoh key expressions",
    "@": "'@' marks Zenoh verbatim/admin chunks",
}


def segment_error(value: object) -> str | None:
    """Why ``value`` is not a valid single key segment, or None when it is."""
    if not isinstance(value, str):
        return f"must be a string, got {type(value).__name__}"
    if value == "":
        return "is empty"
    if len(value) > MAX_SEGMENT_CHARS:
        return f"is {len(value)} characters long (at most {MAX_SEGMENT_CHARS})"
    for ch in value:
        if ch.isspace():
            return f"contains whitespace ({ch!r})"
        if ch in _SPECIAL_CHARS:
            return f"contains {ch!r} ({_SPECIAL_CHARS[ch]})"
    if value.startswith("."):
        return "starts with '.'"
    if not _VALID_SEGMENT.match(value):
        bad = next(ch for ch in value if not re.match(r"[A-Za-z0-9_.\-]", ch))
        return f"contains {bad!r} (allowed: ASCII letters, digits, '_', '-', '.')"
    return None


def validate_segment(value: str, *, what: str = "map id") -> str:
    """Return ``value`` if it is one valid key segment, else raise InvalidKeyError naming it and why."""
    why = segment_error(value)
    if why is not None:
        raise InvalidKeyError(f"{what} {value!r} is not a valid key segment: it {why}")
    return value


def validate_map_id(map_id: str) -> str:
    """Return ``map_id`` if it is one valid key segment, else raise InvalidKeyError naming it and why."""
    return validate_segment(map_id, what="map id")


def validate_prefix(prefix: str) -> str:
    """Return ``prefix`` if each of its '/'-separated segments is valid, else raise ValueError."""
    if not isinstance(prefix, str) or prefix == "":
        raise InvalidKeyError(f"key prefix {prefix!r} is not valid: it is empty")
    for segment in prefix.split("/"):
        why = segment_error(segment)
        if why is not None:
            raise InvalidKeyError(f"key prefix {prefix!r} is not valid: segment {segment!r} {why}")
    return prefix


def key_for(map_id: str, *parts: str, prefix: str = DEFAULT_PREFIX) -> str:
    """The key expression ``{prefix}/{map_id}/{part}/...``.

    Every part must be a valid segment, or exactly :data:`ANY` (``*``) / :data:`ANY_DEEP`
    (``**``) for wildcard subscriptions and queries. ``map_id`` and ``prefix`` are never
    wildcards. Raises InvalidKeyError naming the offending id and why.
    """
    validate_prefix(prefix)
    validate_map_id(map_id)
    if not parts:
        raise InvalidKeyError("key_for needs at least one part after the map id (e.g. 'sensor', 'rgbd')")
    for part in parts:
        if part in (ANY, ANY_DEEP):
            continue
        validate_segment(part, what="key part")
    return "/".join((prefix, map_id, *parts))


@dataclass(frozen=True)
class KeySpace:
    """All keys of one map: ``KeySpace(prefix, map_id)``; validated on construction."""

    prefix: str = DEFAULT_PREFIX
    map_id: str = "default"

    def __post_init__(self) -> None:
        validate_prefix(self.prefix)
        validate_map_id(self.map_id)

    def key(self, *parts: str) -> str:
        """Any key of this map (see :func:`key_for`)."""
        return key_for(self.map_id, *parts, prefix=self.prefix)

    @property
    def base(self) -> str:
        """``{prefix}/{map_id}`` (not itself a key anything is declared on)."""
        return f"{self.prefix}/{self.map_id}"

    @property
    def all(self) -> str:
        """Every key of this map: ``{prefix}/{map_id}/**``."""
        return self.key(ANY_DEEP)

    # presence and stats
    def health(self, service: str) -> str:
        """HealthStats pub + health queryable of one service instance."""
        return self.key("health", validate_segment(service, what="service name"))

    def liveliness(self, service: str) -> str:
        """Liveliness token key of one service instance (same key as its health, in the
        separate liveliness namespace of Zenoh)."""
        return self.health(service)

    @property
    def health_all(self) -> str:
        """Health / liveliness of every service of this map: ``{prefix}/{map_id}/health/*``."""
        return self.key("health", ANY)

    def service_from_health_key(self, key: str) -> str:
        """The service name of a key matched by :attr:`health_all`; ValueError otherwise."""
        head = f"{self.base}/health/"
        key = str(key)
        rest = key[len(head) :] if key.startswith(head) else ""
        if segment_error(rest) is not None:
            raise InvalidKeyError(f"{key!r} is not a health key of map {self.map_id!r} (expected {head}<service>)")
        return rest


def health_all_maps(prefix: str = DEFAULT_PREFIX) -> str:
    """Health / liveliness of every service of every map under ``prefix``."""
    validate_prefix(prefix)
    return f"{prefix}/{ANY}/health/{ANY}"


#: The verbatim chunk under which the encoder pool lives, outside every map (one pool may serve
#: several maps). Zenoh never matches a verbatim (``@``) chunk with ``*`` or ``**``, so a map's
#: ``openfusion/**`` subscription does not see pool traffic and the pool's keys stay apart.
POOL_CHUNK = "@pool"


@dataclass(frozen=True)
class PoolKeys:
    """Keys of the encoder pool of ``prefix``: ``{prefix}/@pool/encoder/{worker_id}`` (the worker's
    liveliness token), ``…/{worker_id}/info`` (WorkerInfo) and ``…/{worker_id}/encode``
    (EncodeRequest -> EncodeReply)."""

    prefix: str = DEFAULT_PREFIX

    def __post_init__(self) -> None:
        validate_prefix(self.prefix)

    def worker(self, worker_id: str) -> str:
        return f"{self.prefix}/{POOL_CHUNK}/encoder/{validate_segment(worker_id, what='worker id')}"

    def info(self, worker_id: str) -> str:
        return f"{self.worker(worker_id)}/info"

    def encode(self, worker_id: str) -> str:
        return f"{self.worker(worker_id)}/encode"

    @property
    def workers(self) -> str:
        """Every worker's liveliness token: ``{prefix}/@pool/encoder/*``."""
        return f"{self.prefix}/{POOL_CHUNK}/encoder/{ANY}"

    def worker_id_of(self, key: str) -> str:
        """The worker id of a key matched by :attr:`workers`; InvalidKeyError otherwise."""
        head = f"{self.prefix}/{POOL_CHUNK}/encoder/"
        rest = str(key)[len(head):] if str(key).startswith(head) else ""
        if segment_error(rest) is not None:
            raise InvalidKeyError(f"{key!r} is not an encoder worker key (expected {head}<worker id>)")
        return rest


# ----------------------------------------------------------------------------- geometry shards
#: The service name of the one geometry service of an unsharded map (and the prefix of a shard's).
GEOMETRY_SERVICE = "geometry"
_SHARD_SPEC = re.compile(r"^\s*([0-9]+)\s*/\s*([0-9]+)\s*$")
_SHARD_SERVICE = re.compile(r"^geometry(?:-([0-9]+)of([0-9]+))?(?:-r([0-9]+))?$")
#: Replicas of one shard (the same tiles, on other hosts); more is a typo.
MAX_REPLICAS = 9
#: More shards than this is a typo, not a deployment (each shard receives every frame).
MAX_SHARDS = 64


@dataclass(frozen=True)
class ShardId:
    """Geometry shard ``index`` of ``count`` (docs/SHARDS.md): the tiles it owns are those
    :func:`openfusion.mapping.shards.shard_of_tiles` maps to ``index``.

    Its name on the bus (health, liveliness and the segment its queryables are declared under,
    :meth:`openfusion.wire.endpoints.Endpoint.shard_key`) is ``geometry`` for the one shard of an
    unsharded map (today's service, today's keys) and ``geometry-{index}of{count}`` otherwise, so a
    reader learns the shard count from any shard's liveliness token. A *replica* ``r > 0`` of a
    shard (the same shard run again, on another host) is named ``…-r{r}`` in health, liveliness and
    its acknowledgements, and answers the same keys as the shard (:attr:`part`): Zenoh gives a
    reader's query to one of them."""

    index: int = 0
    count: int = 1
    replica: int = 0

    def __post_init__(self) -> None:
        if not 1 <= self.count <= MAX_SHARDS:
            raise InvalidKeyError(f"shard count must be 1..{MAX_SHARDS}, got {self.count}")
        if not 0 <= self.index < self.count:
            raise InvalidKeyError(f"shard index must be 0..{self.count - 1} for {self.count} shards, got {self.index}")
        if not 0 <= self.replica <= MAX_REPLICAS:
            raise InvalidKeyError(f"replica must be 0..{MAX_REPLICAS}, got {self.replica}")

    @classmethod
    def parse(cls, text: str) -> ShardId:
        """``"I/N"`` (shard I of N, counted from 0); InvalidKeyError naming the value otherwise."""
        m = _SHARD_SPEC.match(str(text))
        if m is None:
            raise InvalidKeyError(f"shard {text!r} is not of the form I/N (e.g. 0/2: the first of two shards)")
        return cls(int(m.group(1)), int(m.group(2)))

    @classmethod
    def of_service(cls, name: str) -> ShardId | None:
        """The shard a geometry service name names (``geometry`` -> 0/1), None for another service."""
        m = _SHARD_SERVICE.match(str(name))
        if m is None:
            return None
        try:
            shard = cls(int(m.group(1)), int(m.group(2))) if m.group(1) is not None else cls()
            if m.group(1) is not None and not shard.sharded:
                return None  # geometry-0of1 is not a name any service takes
            return shard.with_replica(int(m.group(3) or 0))
        except InvalidKeyError:
            return None

    def with_replica(self, replica: int) -> ShardId:
        return ShardId(self.index, self.count, int(replica))

    @property
    def part(self) -> ShardId:
        """The shard itself (replica 0's id): what keys, flow-control windows and map parts are of."""
        return ShardId(self.index, self.count)

    @classmethod
    def all(cls, count: int) -> list[ShardId]:
        """Every shard of a map split ``count`` ways."""
        return [cls(i, count) for i in range(count)]

    @property
    def sharded(self) -> bool:
        return self.count > 1

    @property
    def service(self) -> str:
        """Service name (health, liveliness, acknowledgements): ``geometry`` or ``geometry-{I}of{N}``,
        with ``-r{R}`` for replica R > 0."""
        name = GEOMETRY_SERVICE if self.count == 1 else f"{GEOMETRY_SERVICE}-{self.index}of{self.count}"
        return name if self.replica == 0 else f"{name}-r{self.replica}"

    def __str__(self) -> str:
        return f"{self.index}/{self.count}"
