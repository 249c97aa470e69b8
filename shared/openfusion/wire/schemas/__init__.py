"""Every message schema that travels over the bus (one package, one module per service's messages).

Each message is a pydantic model with a class-level ``schema_name`` and integer
``schema_version``; :mod:`openfusion.wire.codec` puts them on the wire. Units and frames are in the
field names (``stamp_ns``, ``T_world_cam``, ``depth_m``, ``radius_m``). Array fields declare
their dtype and shape (:func:`openfusion.wire.codec.ndarray`); sizes that must agree across fields
are checked by the model, so a decoded message is always self-consistent.

Changing a message's fields means bumping its ``schema_version``: peers of another version
refuse it with ``DecodeError(reason="version_mismatch")`` instead of misreading it.

Define a new message by subclassing :class:`~openfusion.wire.message.Message` with ``schema_name``
and ``schema_version`` set; it registers itself (:mod:`openfusion.wire.message`). Import from
this package (``from openfusion.wire.schemas import RgbdFrame``); the modules split it by service.
"""

from openfusion.wire.message import Message, Record
from openfusion.wire.schemas.admin import ControlReply, ControlRequest, ErrorReply, HealthStats
from openfusion.wire.schemas.base import (
    Colors3u8,
    DepthImage,
    FloatMap,
    ImageRGB8,
    KeyList,
    KeyMap,
    PinholeMessage,
    Points3f,
    Pose4x4,
    Vec3f32,
    Vec3f64,
)
from openfusion.wire.schemas.checkpoint import (
    CheckpointChunk,
    CheckpointChunkRequest,
    CheckpointFile,
    CheckpointListing,
    CheckpointListRequest,
    CheckpointRelease,
)
from openfusion.wire.schemas.geometry import (
    GeometryProgress,
    MeshReply,
    MeshRequest,
    PointsReply,
    PointsRequest,
    RegionContactsReply,
    RegionContactsRequest,
    RegionSummaryReply,
    RegionSummaryRequest,
    RenderReply,
    RenderRequest,
)
from openfusion.wire.schemas.pool import EncodeReply, EncodeRequest, WorkerInfo, WorkerInfoRequest
from openfusion.wire.schemas.query import (
    MAX_BATCH_TEXTS,
    ImageQuery,
    NearbyRegion,
    PointQuery,
    QueryBatchReply,
    QueryReply,
    RegionHit,
    RelationQueryInfo,
    TextQuery,
    TextQueryBatch,
)
from openfusion.wire.schemas.semantic import (
    DictionaryDelta,
    DictionaryRequest,
    DictionarySnapshot,
    MergeReply,
    MergeRequest,
    SemanticUpdate,
)
from openfusion.wire.schemas.sensor import InstanceFrame, RgbdFrame

__all__ = [
    "CheckpointChunk",
    "CheckpointChunkRequest",
    "CheckpointFile",
    "CheckpointListRequest",
    "CheckpointListing",
    "CheckpointRelease",
    "MergeReply",
    "MergeRequest",
    "WorkerInfo",
    "WorkerInfoRequest",
    "MAX_BATCH_TEXTS",
    "Colors3u8",
    "ControlReply",
    "ControlRequest",
    "DepthImage",
    "DictionaryDelta",
    "DictionaryRequest",
    "DictionarySnapshot",
    "EncodeReply",
    "EncodeRequest",
    "ErrorReply",
    "FloatMap",
    "GeometryProgress",
    "HealthStats",
    "ImageQuery",
    "ImageRGB8",
    "InstanceFrame",
    "KeyList",
    "KeyMap",
    "MeshReply",
    "MeshRequest",
    "Message",
    "PinholeMessage",
    "PointQuery",
    "Points3f",
    "PointsReply",
    "PointsRequest",
    "Pose4x4",
    "QueryBatchReply",
    "NearbyRegion",
    "QueryReply",
    "RelationQueryInfo",
    "Record",
    "RegionContactsReply",
    "RegionContactsRequest",
    "RegionHit",
    "RegionSummaryReply",
    "RegionSummaryRequest",
    "RenderReply",
    "RenderRequest",
    "RgbdFrame",
    "SemanticUpdate",
    "TextQuery",
    "TextQueryBatch",
    "Vec3f32",
    "Vec3f64",
]
