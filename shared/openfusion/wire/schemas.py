"""Every message schema that travels over the bus, and the schema registry.

Each message is a pydantic model with a class-level ``schema_name`` and integer
``schema_version``; :mod:`openfusion.wire.codec` puts them on the wire. Units and frames are in the
field names (``stamp_ns``, ``T_world_cam``, ``depth_m``, ``radius_m``). Array fields declare
their dtype and shape (:func:`openfusion.wire.codec.ndarray`); sizes that must agree across fields
are checked by the model, so a decoded message is always self-consistent.

Changing a message's fields means bumping its ``schema_version``: peers of another version
refuse it with ``DecodeError(reason="version_mismatch")`` instead of misreading it.

Define a new message by subclassing :class:`Message` with ``schema_name`` and
``schema_version`` set; it registers itself (:func:`message_class`, :func:`registered_schemas`).
"""

from __future__ import annotations

import logging
from typing import Any, ClassVar, Literal

import numpy as np
from pydantic import Field, model_validator

from openfusion.frame import CameraIntrinsics, Frame
from openfusion.poses import check_pose
from openfusion.wire.codec import ndarray
from openfusion.wire.message import Message, Record

logger = logging.getLogger(__name__)

# Array field types used below.
Pose4x4 = ndarray("float64", shape=(4, 4))
Vec3f64 = ndarray("float64", shape=(3,))
Vec3f32 = ndarray("float32", shape=(3,))
ImageRGB8 = ndarray("uint8", shape=(None, None, 3))
DepthImage = ndarray("uint16", "float32", shape=(None, None))
KeyMap = ndarray("int32", shape=(None, None))
FloatMap = ndarray("float32", shape=(None, None))
KeyList = ndarray("int32", shape=(None,))
Points3f = ndarray("float32", shape=(None, 3))
Colors3u8 = ndarray("uint8", shape=(None, 3))


class PinholeMessage(Message):
    """Base of messages that carry pinhole intrinsics of an image of ``width_px`` x ``height_px``."""

    width_px: int = Field(gt=0)
    height_px: int = Field(gt=0)
    fx: float = Field(gt=0)
    fy: float = Field(gt=0)
    cx: float
    cy: float

    @property
    def intrinsics(self) -> CameraIntrinsics:
        return CameraIntrinsics(self.width_px, self.height_px, self.fx, self.fy, self.cx, self.cy)

    @staticmethod
    def intrinsics_fields(intrinsics: CameraIntrinsics) -> dict[str, Any]:
        """Keyword arguments for the intrinsics fields: ``RenderRequest(**intrinsics_fields(K), ...)``."""
        return {
            "width_px": intrinsics.width_px,
            "height_px": intrinsics.height_px,
            "fx": intrinsics.fx,
            "fy": intrinsics.fy,
            "cx": intrinsics.cx,
            "cy": intrinsics.cy,
        }

    def _check_image(self, name: str, arr: np.ndarray) -> None:
        if arr.shape[:2] != (self.height_px, self.width_px):
            raise ValueError(
                f"{name} is {arr.shape[1]}x{arr.shape[0]} but the intrinsics are for {self.width_px}x{self.height_px}"
            )


# ----------------------------------------------------------------------------------- sensor


class RgbdFrame(PinholeMessage):
    """One registered RGB-D frame with its camera-to-world pose (see :class:`openfusion.frame.Frame`)."""

    schema_name: ClassVar[str] = "sensor.rgbd"
    schema_version: ClassVar[int] = 1

    frame_id: int = Field(ge=0)
    stamp_ns: int = Field(ge=0)
    T_world_cam: Pose4x4
    depth_scale: float = Field(gt=0)
    color: ImageRGB8
    depth: DepthImage
    instance: KeyMap | None = None
    instance_categories: dict[int, str] = Field(default_factory=dict)
    source: str = ""

    @model_validator(mode="after")
    def _check_frame(self) -> RgbdFrame:
        with np.errstate(all="ignore"):  # a garbage pose must fail validation, not overflow-warn
            self.to_frame().validate()
        return self

    @classmethod
    def from_frame(cls, frame: Frame, *, with_instance: bool = True) -> RgbdFrame:
        """The message of a frame (arrays are not copied). ``with_instance=False`` leaves the
        ground-truth instance image out: the bridge sends it on its own key
        (:class:`InstanceFrame`), so geometry never receives those bytes."""
        frame.validate()
        return cls(
            frame_id=frame.frame_id,
            stamp_ns=frame.stamp_ns,
            **cls.intrinsics_fields(frame.intrinsics),
            T_world_cam=np.asarray(frame.T_world_cam, dtype=np.float64),
            depth_scale=frame.depth_scale,
            color=frame.color,
            depth=frame.depth,
            instance=frame.instance if with_instance else None,
            instance_categories=dict(frame.instance_categories) if with_instance else {},
            source=frame.source,
        )

    def to_frame(self, instance: InstanceFrame | None = None) -> Frame:
        """The in-memory frame (arrays are shared, so read-only after :func:`codec.decode`).

        ``instance``: the frame's :class:`InstanceFrame` from ``…/sensor/instance``, joined in
        place of this message's own (usually absent) instance image. Raises ValueError when it
        belongs to another frame or its image size differs."""
        inst, categories = self.instance, dict(self.instance_categories)
        if instance is not None:
            if not instance.belongs_to(self):
                raise ValueError(
                    f"instance image of frame {instance.frame_id} (stamp {instance.stamp_ns} ns) joined to "
                    f"frame {self.frame_id} (stamp {self.stamp_ns} ns)"
                )
            self._check_image("instance", instance.instance)
            inst, categories = instance.instance, dict(instance.instance_categories)
        return Frame(
            frame_id=self.frame_id,
            stamp_ns=self.stamp_ns,
            color=self.color,
            depth=self.depth,
            depth_scale=self.depth_scale,
            intrinsics=self.intrinsics,
            T_world_cam=self.T_world_cam,
            instance=inst,
            instance_categories=categories,
            source=self.source,
        )


class InstanceFrame(Message):
    """Ground-truth instance ids of one frame, on ``…/sensor/instance`` next to its
    :class:`RgbdFrame` (same ``frame_id`` and ``stamp_ns``).

    Sources with labels (synthetic scene, ScanNet ``instance-filt``, Replica) have them; only the
    gt encoder of the semantic service reads them. Keeping them off ``…/sensor/rgbd`` saves
    geometry 45 % of each 640x480 frame's bytes (the int32 image is larger than color and depth
    together). ``instance`` is HxW int32 (0 = no instance); ``instance_categories`` maps ids to
    raw category names.
    """

    schema_name: ClassVar[str] = "sensor.instance"
    schema_version: ClassVar[int] = 1

    frame_id: int = Field(ge=0)
    stamp_ns: int = Field(ge=0)
    instance: KeyMap
    instance_categories: dict[int, str] = Field(default_factory=dict)
    source: str = ""

    @model_validator(mode="after")
    def _check_not_empty(self) -> InstanceFrame:
        if self.instance.size == 0:
            raise ValueError(f"instance image is empty ({self.instance.shape})")
        return self

    @classmethod
    def from_frame(cls, frame: Frame) -> InstanceFrame | None:
        """The instance message of a frame, or None when the frame has no instance image."""
        if frame.instance is None:
            return None
        return cls(
            frame_id=frame.frame_id,
            stamp_ns=frame.stamp_ns,
            instance=frame.instance,
            instance_categories=dict(frame.instance_categories),
            source=frame.source,
        )

    def belongs_to(self, msg: RgbdFrame) -> bool:
        """Same frame id and time stamp as ``msg``."""
        return self.frame_id == msg.frame_id and self.stamp_ns == msg.stamp_ns


# --------------------------------------------------------------------------------- geometry


class GeometryProgress(Message):
    """The geometry service took frame (``frame_id``, ``stamp_ns``) out of its queue (integrated
    it, or refused it for capacity), on ``…/geometry/progress``: the acknowledgement the bridge's
    flow control (:mod:`openfusion.bus.flow_control`) waits for during playback."""

    schema_name: ClassVar[str] = "geometry.progress"
    schema_version: ClassVar[int] = 1

    frame_id: int = Field(ge=0)
    stamp_ns: int = Field(ge=0)
    integrated: bool
    frames_integrated: int = Field(ge=0)
    queued: int = Field(ge=0)  # frames waiting in geometry's queue after this one


class RenderRequest(PinholeMessage):
    """Render the map's region keys from ``T_world_cam`` into a small ``width_px`` x ``height_px`` view."""

    schema_name: ClassVar[str] = "geometry.render_request"
    schema_version: ClassVar[int] = 1

    frame_id: int = Field(ge=0)
    T_world_cam: Pose4x4

    @model_validator(mode="after")
    def _check(self) -> RenderRequest:
        check_pose(self.T_world_cam)
        return self


class RenderReply(Message):
    """Per-pixel region key (-1 = none), its confidence and the rendered depth in metres."""

    schema_name: ClassVar[str] = "geometry.render_reply"
    schema_version: ClassVar[int] = 1

    frame_id: int = Field(ge=0)
    key_map: KeyMap
    conf_map: FloatMap
    depth_m: FloatMap

    @model_validator(mode="after")
    def _check(self) -> RenderReply:
        if not (self.key_map.shape == self.conf_map.shape == self.depth_m.shape):
            raise ValueError(
                f"key_map {self.key_map.shape}, conf_map {self.conf_map.shape} and depth_m "
                f"{self.depth_m.shape} must have the same shape"
            )
        return self


class PointsRequest(Message):
    """Surface points of the map, optionally only those of region ``keys``, at most ``max_points``."""

    schema_name: ClassVar[str] = "geometry.points_request"
    schema_version: ClassVar[int] = 1

    keys: list[int] | None = None
    max_points: int | None = Field(default=None, gt=0)


class PointsReply(Message):
    """Surface points (world frame, metres), their colors and region keys (-1 = none)."""

    schema_name: ClassVar[str] = "geometry.points_reply"
    schema_version: ClassVar[int] = 1

    points: Points3f
    colors: Colors3u8
    keys: KeyList
    truncated: bool = False

    @model_validator(mode="after")
    def _check(self) -> PointsReply:
        n = len(self.points)
        if len(self.colors) != n or len(self.keys) != n:
            raise ValueError(
                f"points ({n}), colors ({len(self.colors)}) and keys ({len(self.keys)}) differ in length"
            )
        return self


class RegionSummaryRequest(Message):
    """Ask geometry for per-region summaries (bounding box, surface point count) of the map.

    ``keys``: only these regions (None = all). ``fresh``: recompute from the current map even
    when the service's cached summary is of an older map version (without it the service may
    answer its cached summary; its ``map_version`` and ``age_s`` say how old it is)."""

    schema_name: ClassVar[str] = "geometry.regions_request"
    schema_version: ClassVar[int] = 1

    keys: list[int] | None = None
    fresh: bool = False


class RegionSummaryReply(Message):
    """Per-region summaries of the surface points of the map at ``map_version``: for each key,
    the axis-aligned bounding box (world, metres) and the number of surface points (the same
    points ``geometry/points`` serves). ``key_horizon``: every region key below it is covered,
    so a key under the horizon that is not listed has no surface points in that map version; a
    key at or above it is newer than the summary (unknown). ``age_s``: seconds between the
    computation of the summary and the reply."""

    schema_name: ClassVar[str] = "geometry.regions_reply"
    schema_version: ClassVar[int] = 1

    map_version: int = Field(ge=0)
    key_horizon: int = Field(ge=0)
    age_s: float = Field(default=0.0, ge=0)
    keys: KeyList
    bbox_min: Points3f
    bbox_max: Points3f
    num_points: ndarray("int64", shape=(None,))

    @model_validator(mode="after")
    def _check(self) -> RegionSummaryReply:
        n = len(self.keys)
        if len(self.bbox_min) != n or len(self.bbox_max) != n or len(self.num_points) != n:
            raise ValueError(
                f"keys ({n}), bbox_min ({len(self.bbox_min)}), bbox_max ({len(self.bbox_max)}) and num_points "
                f"({len(self.num_points)}) differ in length"
            )
        if n and len(np.unique(self.keys)) != n:
            raise ValueError("keys must be unique")
        if n and int(self.num_points.min()) < 0:
            raise ValueError("num_points must be >= 0")
        return self


class MeshRequest(Message):
    """The surface mesh, optionally only the vertices of region ``keys``."""

    schema_name: ClassVar[str] = "geometry.mesh_request"
    schema_version: ClassVar[int] = 1

    keys: list[int] | None = None


class MeshReply(Message):
    """A triangle mesh in the world frame (metres) with per-vertex colors and region keys."""

    schema_name: ClassVar[str] = "geometry.mesh_reply"
    schema_version: ClassVar[int] = 1

    vertices: Points3f
    triangles: ndarray("int32", shape=(None, 3))
    vertex_colors: Colors3u8
    vertex_keys: KeyList

    @model_validator(mode="after")
    def _check(self) -> MeshReply:
        v = len(self.vertices)
        if len(self.vertex_colors) != v or len(self.vertex_keys) != v:
            raise ValueError(
                f"vertices ({v}), vertex_colors ({len(self.vertex_colors)}) and vertex_keys "
                f"({len(self.vertex_keys)}) differ in length"
            )
        if self.triangles.size and (self.triangles.min() < 0 or self.triangles.max() >= v):
            raise ValueError(f"triangles index vertices outside 0..{v - 1}")
        return self


# --------------------------------------------------------------------------------- semantic


class SemanticUpdate(PinholeMessage):
    """Per-pixel region keys and confidences to fuse into the volume, seen from ``T_world_cam``."""

    schema_name: ClassVar[str] = "semantic.update"
    schema_version: ClassVar[int] = 1

    frame_id: int = Field(ge=0)
    T_world_cam: Pose4x4
    key_map: KeyMap
    conf_map: FloatMap
    new_keys: KeyList
    # The frame's depth resampled to the key map (metres, 0 = none): enables the update's depth
    # gate, so labels of an object's outline do not land on the background behind it.
    depth_m: FloatMap | None = None

    @model_validator(mode="after")
    def _check(self) -> SemanticUpdate:
        check_pose(self.T_world_cam)
        self._check_image("key_map", self.key_map)
        self._check_image("conf_map", self.conf_map)
        if self.depth_m is not None:
            self._check_image("depth_m", self.depth_m)
        return self


def _check_dictionary_rows(
    *, dim: int, keys: np.ndarray, embeddings: np.ndarray, counts: np.ndarray, labels: list[str]
) -> None:
    m = len(keys)
    if embeddings.shape != (m, dim):
        raise ValueError(f"embeddings must be ({m}, {dim}) for {m} keys of dim {dim}, got {embeddings.shape}")
    if len(counts) != m or len(labels) != m:
        raise ValueError(f"keys ({m}), counts ({len(counts)}) and labels ({len(labels)}) differ in length")
    if len(np.unique(keys)) != m:
        raise ValueError("keys must be unique")


class DictionaryRequest(Message):
    """Ask the semantic service for a full :class:`DictionarySnapshot`."""

    schema_name: ClassVar[str] = "semantic.dictionary_request"
    schema_version: ClassVar[int] = 1


class DictionarySnapshot(Message):
    """The whole region dictionary: key -> running-mean embedding (not normalised), observation
    count, label ("" = none); ``next_key`` is the key the owner allocates next."""

    schema_name: ClassVar[str] = "semantic.dictionary"
    schema_version: ClassVar[int] = 1

    embedding_space: str = Field(min_length=1)
    dim: int = Field(gt=0)
    version: int = Field(ge=0)
    next_key: int = Field(ge=0)
    keys: KeyList
    embeddings: ndarray("float32", shape=(None, None))
    counts: ndarray("int64", shape=(None,))
    labels: list[str]

    @model_validator(mode="after")
    def _check(self) -> DictionarySnapshot:
        _check_dictionary_rows(
            dim=self.dim, keys=self.keys, embeddings=self.embeddings, counts=self.counts, labels=self.labels
        )
        return self


class DictionaryDelta(Message):
    """Changes from dictionary ``prev_version`` to ``version``: upserted rows, removed keys and
    what each removed key was merged into (-1 = deleted)."""

    schema_name: ClassVar[str] = "semantic.dictionary_delta"
    schema_version: ClassVar[int] = 1

    embedding_space: str = Field(min_length=1)
    dim: int = Field(gt=0)
    version: int = Field(ge=0)
    prev_version: int = Field(ge=0)
    next_key: int = Field(ge=0)
    keys: KeyList
    embeddings: ndarray("float32", shape=(None, None))
    counts: ndarray("int64", shape=(None,))
    labels: list[str]
    removed_keys: KeyList
    merged_into: KeyList

    @model_validator(mode="after")
    def _check(self) -> DictionaryDelta:
        if self.version <= self.prev_version:
            raise ValueError(
                f"version ({self.version}) must be greater than prev_version ({self.prev_version})"
            )
        _check_dictionary_rows(
            dim=self.dim, keys=self.keys, embeddings=self.embeddings, counts=self.counts, labels=self.labels
        )
        if len(self.merged_into) != len(self.removed_keys):
            raise ValueError(
                f"merged_into ({len(self.merged_into)}) must have one entry per removed key ({len(self.removed_keys)})"
            )
        return self


# ------------------------------------------------------------------------------------ query


class _QueryOptions(Message):
    top_k: int = Field(default=5, gt=0, le=10_000)
    with_points: bool = False
    max_points: int = Field(default=20_000, gt=0)
    embedding_space: str | None = None


class TextQuery(_QueryOptions):
    """Rank the map's regions against ``text``. ``embedding_space``: refuse a map of another space."""

    schema_name: ClassVar[str] = "query.text"
    schema_version: ClassVar[int] = 1

    text: str = Field(min_length=1, max_length=4096)


class ImageQuery(_QueryOptions):
    """Rank the map's regions against an RGB image."""

    schema_name: ClassVar[str] = "query.image"
    schema_version: ClassVar[int] = 1

    image: ImageRGB8

    @model_validator(mode="after")
    def _check(self) -> ImageQuery:
        if self.image.shape[0] == 0 or self.image.shape[1] == 0:
            raise ValueError(f"image must not be empty, got shape {self.image.shape}")
        return self


class PointQuery(Message):
    """Regions within ``radius_m`` of a world point (metres), best ``top_k``."""

    schema_name: ClassVar[str] = "query.point"
    schema_version: ClassVar[int] = 1

    point_world: Vec3f64
    radius_m: float = Field(default=0.1, gt=0)
    top_k: int = Field(default=5, gt=0, le=10_000)
    with_points: bool = False
    max_points: int = Field(default=20_000, gt=0)

    @model_validator(mode="after")
    def _check(self) -> PointQuery:
        if not np.isfinite(self.point_world).all():
            raise ValueError("point_world must be finite")
        return self


class RegionHit(Record):
    """One ranked region: key, similarity score, label, axis-aligned bbox (world, metres)."""

    key: int
    score: float
    label: str | None = None
    bbox_min: Vec3f32
    bbox_max: Vec3f32
    num_points: int = Field(ge=0)
    points: Points3f | None = None


class QueryReply(Message):
    """Regions ranked best first for the ``query`` (text, or a description of the image/point query)."""

    schema_name: ClassVar[str] = "query.reply"
    schema_version: ClassVar[int] = 1

    embedding_space: str
    query: str
    regions: list[RegionHit] = Field(default_factory=list)


# ------------------------------------------------------------------------------ admin/health


class ControlRequest(Message):
    """Admin action on a map: save to / load from ``path`` (service default when None), or reset."""

    schema_name: ClassVar[str] = "control.request"
    schema_version: ClassVar[int] = 1

    action: Literal["save", "load", "reset"]
    path: str | None = None


class ControlReply(Message):
    """Outcome of a :class:`ControlRequest`."""

    schema_name: ClassVar[str] = "control.reply"
    schema_version: ClassVar[int] = 1

    ok: bool
    message: str = ""


class HealthStats(Message):
    """Periodic stats of one service instance (published on ``…/health/{service}``)."""

    schema_name: ClassVar[str] = "health.stats"
    schema_version: ClassVar[int] = 1

    service: str
    map_id: str
    pid: int
    stamp_ns: int = Field(default=0, ge=0)
    uptime_s: float = Field(ge=0)
    fps: float = Field(ge=0)
    latency_ms_p50: float = Field(ge=0)
    latency_ms_p99: float = Field(ge=0)
    drops: int = Field(ge=0)
    errors: int = Field(ge=0)
    counters: dict[str, float] = Field(default_factory=dict)

    def counter(self, name: str, default: float = 0.0) -> float:
        """One named counter (names: :mod:`openfusion.wire.counters`), ``default`` when absent."""
        return float(self.counters.get(str(name), default))


class ErrorReply(Message):
    """The payload of every ``reply_err``: a machine-readable ``code`` and a human ``reason``.

    Codes used by :mod:`openfusion.bus`: ``bad_request:<decode reason>`` (the request did not
    decode), ``handler_error`` (the service failed on a valid request), or a code the handler
    chose by raising :class:`openfusion.bus.RequestError`.
    """

    schema_name: ClassVar[str] = "error"
    schema_version: ClassVar[int] = 1

    reason: str
    code: str
