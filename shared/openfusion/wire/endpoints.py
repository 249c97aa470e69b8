"""Every topic and queryable of a map, declared once: key, message types and owner.

A :class:`Topic` is a pub/sub key: the message that travels on it and the service that
publishes it. An :class:`Endpoint` is a queryable: request type, reply type and the service
that answers. Publishers, subscribers, queryables and every ``get`` use these declarations
(``openfusion.bus``: ``runner.publisher(SENSOR_RGBD)``, ``runner.queryable(GEOMETRY_RENDER,
handler)``, ``call(session, keys, GEOMETRY_RENDER, request)``), so a key, its types and its
owner are never restated at a call site. The key grammar (prefix, map id, segment rules) is
:mod:`openfusion.wire.keys`; health and liveliness keys, which carry a service name, are there
too (:meth:`~openfusion.wire.keys.KeySpace.health`).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Generic, TypeVar

from openfusion.wire.keys import CONTROL_ACTIONS, KeySpace, ShardId, validate_segment
from openfusion.wire.message import Message
from openfusion.wire.schemas import (
    CheckpointChunk,
    CheckpointChunkRequest,
    CheckpointListing,
    CheckpointListRequest,
    CheckpointRelease,
    ControlReply,
    ControlRequest,
    DictionaryDelta,
    DictionaryRequest,
    DictionarySnapshot,
    GeometryProgress,
    ImageQuery,
    InstanceFrame,
    MergeReply,
    MergeRequest,
    MeshReply,
    MeshRequest,
    PointQuery,
    PointsReply,
    PointsRequest,
    QueryBatchReply,
    QueryReply,
    RegionContactsReply,
    RegionContactsRequest,
    RegionSummaryReply,
    RegionSummaryRequest,
    RenderReply,
    RenderRequest,
    RgbdFrame,
    SemanticUpdate,
    TextQuery,
    TextQueryBatch,
)

M = TypeVar("M", bound=Message)
Q = TypeVar("Q", bound=Message)
R = TypeVar("R", bound=Message)


@dataclass(frozen=True)
class Topic(Generic[M]):
    """A pub/sub key of one map: ``{prefix}/{map}/{parts...}`` carrying ``message``, published by
    the ``publisher`` service."""

    parts: tuple[str, ...]
    message: type[M]
    publisher: str

    def key(self, keys: KeySpace) -> str:
        return keys.key(*self.parts)

    @property
    def path(self) -> str:
        """The key below ``{prefix}/{map}`` (``sensor/rgbd``), as the docs' key tables write it."""
        return "/".join(self.parts)


@dataclass(frozen=True)
class Endpoint(Generic[Q, R]):
    """A queryable of one map: ``request`` in, ``reply`` out, answered by the ``owner`` service."""

    parts: tuple[str, ...]
    request: type[Q]
    reply: type[R]
    owner: str

    def key(self, keys: KeySpace) -> str:
        return keys.key(*self.parts)

    def instance_key(self, keys: KeySpace, service: str) -> str:
        """The key of this endpoint at ONE of several services that all answer :meth:`key`
        (``…/query/text/query-2``): a client that spreads its requests asks one by name."""
        return keys.key(*self.parts, validate_segment(service, what="service name"))

    def shard_key(self, keys: KeySpace, shard: ShardId) -> str:
        """The key of this (geometry) endpoint at one shard: the plain key for an unsharded map
        (today's), else ``…/geometry/render/geometry-0of2`` (docs/SHARDS.md). A shard answers only
        its own key, so a reader that asks one key gets one shard's part of the map, never a
        partial answer it mistakes for the whole."""
        return self.key(keys) if not shard.sharded else self.instance_key(keys, shard.part.service)

    def at_process(self, shard: ShardId) -> Endpoint[Q, R]:
        """This endpoint at ONE geometry process, replica included
        (``…/geometry/checkpoint/list/geometry-0of2-r1``): what a replica asks its peer on, so the
        listing and every chunk of one snapshot go to the process that holds it."""
        return Endpoint((*self.parts, validate_segment(shard.service, what="service name")), self.request,
                        self.reply, self.owner)

    def peer_key(self, keys: KeySpace, shard: ShardId) -> str:
        """The key of :meth:`at_process` in the map ``keys``."""
        return self.at_process(shard).key(keys)

    @property
    def path(self) -> str:
        return "/".join(self.parts)


# ----------------------------------------------------------------------------------- topics
SENSOR_RGBD = Topic(("sensor", "rgbd"), RgbdFrame, publisher="bridge")
#: Ground-truth instance images, next to their frame (read by the gt encoder only).
SENSOR_INSTANCE = Topic(("sensor", "instance"), InstanceFrame, publisher="bridge")
#: One acknowledgement per frame geometry took from its queue (the bridge's flow control).
GEOMETRY_PROGRESS = Topic(("geometry", "progress"), GeometryProgress, publisher="geometry")
SEMANTIC_UPDATE = Topic(("semantic", "update"), SemanticUpdate, publisher="semantic")
DICTIONARY_DELTA = Topic(("semantic", "dictionary", "delta"), DictionaryDelta, publisher="semantic")

# -------------------------------------------------------------------------------- queryables
GEOMETRY_RENDER = Endpoint(("geometry", "render"), RenderRequest, RenderReply, owner="geometry")
GEOMETRY_POINTS = Endpoint(("geometry", "points"), PointsRequest, PointsReply, owner="geometry")
GEOMETRY_MESH = Endpoint(("geometry", "mesh"), MeshRequest, MeshReply, owner="geometry")
#: Per-region bounding box and surface point count (what the query service ranks with).
GEOMETRY_REGIONS = Endpoint(("geometry", "regions"), RegionSummaryRequest, RegionSummaryReply, owner="geometry")
#: The dictionary geometry checkpoints with the volume (a restarted semantic service recovers it).
GEOMETRY_DICTIONARY = Endpoint(("geometry", "dictionary"), DictionaryRequest, DictionarySnapshot, owner="geometry")
#: Which regions' labelled voxels touch, and how much (the semantic service decides merges on it).
GEOMETRY_CONTACTS = Endpoint(("geometry", "contacts"), RegionContactsRequest, RegionContactsReply, owner="geometry")
#: A replica with no checkpoint of its own copies its peer's (docs/SHARDS.md): the listing of a
#: snapshot of the peer's newest checkpoint, its files in chunks, and letting the snapshot go. Each
#: geometry process answers them only at its own :meth:`Endpoint.peer_key`.
GEOMETRY_CHECKPOINT_LIST = Endpoint(("geometry", "checkpoint", "list"), CheckpointListRequest, CheckpointListing,
                                    owner="geometry")
GEOMETRY_CHECKPOINT_CHUNK = Endpoint(("geometry", "checkpoint", "chunk"), CheckpointChunkRequest, CheckpointChunk,
                                     owner="geometry")
GEOMETRY_CHECKPOINT_RELEASE = Endpoint(("geometry", "checkpoint", "release"), CheckpointRelease, ControlReply,
                                       owner="geometry")
SEMANTIC_DICTIONARY = Endpoint(("semantic", "dictionary"), DictionaryRequest, DictionarySnapshot, owner="semantic")
#: A merge pass now (geometry asks before it saves a map, so a saved map holds objects, not fragments).
SEMANTIC_MERGE = Endpoint(("semantic", "merge"), MergeRequest, MergeReply, owner="semantic")
QUERY_TEXT = Endpoint(("query", "text"), TextQuery, QueryReply, owner="query")
#: Several texts in one round trip (embedded in one encoder call): one QueryReply per text, in order.
QUERY_TEXT_BATCH = Endpoint(("query", "text_batch"), TextQueryBatch, QueryBatchReply, owner="query")
QUERY_IMAGE = Endpoint(("query", "image"), ImageQuery, QueryReply, owner="query")
QUERY_POINT = Endpoint(("query", "point"), PointQuery, QueryReply, owner="query")
#: The query service's endpoints: several query services may answer them on one map, each also on
#: its own :meth:`Endpoint.instance_key` (services/query/instances.py).
QUERY_ENDPOINTS = (QUERY_TEXT, QUERY_TEXT_BATCH, QUERY_IMAGE, QUERY_POINT)
_QUERY_SERVICE = re.compile(r"query(-[1-9][0-9]*)?")


def query_service_name(instance: int | None) -> str:
    """The service name (health, liveliness, instance keys) of query service ``instance``:
    ``query`` for none or 1, else ``query-N``."""
    return "query" if instance is None or int(instance) <= 1 else f"query-{int(instance)}"


def is_query_service(name: str) -> bool:
    """Whether ``name`` is one of :func:`query_service_name`'s names."""
    return _QUERY_SERVICE.fullmatch(name) is not None
#: Admin actions (access-controlled in production): save, load, reset.
CONTROL: dict[str, Endpoint[ControlRequest, ControlReply]] = {
    action: Endpoint(("control", action), ControlRequest, ControlReply, owner="geometry") for action in CONTROL_ACTIONS
}

TOPICS: tuple[Topic, ...] = (SENSOR_RGBD, SENSOR_INSTANCE, GEOMETRY_PROGRESS, SEMANTIC_UPDATE, DICTIONARY_DELTA)
ENDPOINTS: tuple[Endpoint, ...] = (
    GEOMETRY_RENDER, GEOMETRY_POINTS, GEOMETRY_MESH, GEOMETRY_REGIONS, GEOMETRY_DICTIONARY, GEOMETRY_CONTACTS,
    GEOMETRY_CHECKPOINT_LIST, GEOMETRY_CHECKPOINT_CHUNK, GEOMETRY_CHECKPOINT_RELEASE, SEMANTIC_DICTIONARY, SEMANTIC_MERGE, QUERY_TEXT, QUERY_TEXT_BATCH, QUERY_IMAGE, QUERY_POINT, *CONTROL.values(),
)
