"""Messages of the geometry service: progress, render, points, regions, mesh."""

from __future__ import annotations

from typing import ClassVar

import numpy as np
from pydantic import Field, model_validator

from openfusion.poses import check_pose
from openfusion.wire.codec import ndarray
from openfusion.wire.message import Message
from openfusion.wire.schemas.base import (
    DEFAULT_ROBOT,
    Colors3u8,
    FloatMap,
    KeyList,
    KeyMap,
    PinholeMessage,
    Points3f,
    Pose4x4,
    RobotName,
)


class GeometryProgress(Message):
    """The geometry service took frame (``frame_id``, ``stamp_ns``) out of its queue (integrated
    it, or refused it for capacity), on ``…/geometry/progress``: the acknowledgement the bridge's
    flow control (:mod:`openfusion.bus.flow_control`) waits for during playback.

    v2, resume after a restart: ``incarnation`` names the geometry process (new at each start);
    ``holds_frame_id`` is the last frame of playback ``holds_playback`` it holds (its loaded
    checkpoint's, then the last one taken; -1 and ``""``: none). A message with ``resume > 0`` is an announcement (``frame_id = -1`` when it
    acknowledges no frame): this geometry wants the playback frames after ``holds_frame_id``; it
    sends one when it starts and when a frame comes whose predecessor it does not hold, repeats it
    every second until the next frame arrives in order, and numbers each new one, so the bridge
    goes back once per (``incarnation``, ``resume``).

    v3: ``robot`` names the robot whose frame this acknowledges or whose playback the announcement
    is about; chains, acknowledgements and announcements are per robot, and a bridge reads only
    its own robot's.

    v4: ``shard`` names the geometry shard that sends it (its service name, ``geometry`` for an
    unsharded map, ``geometry-0of2``...: :class:`~openfusion.wire.keys.ShardId`); a bridge keeps a
    flow-control window per shard (docs/SHARDS.md)."""

    schema_name: ClassVar[str] = "geometry.progress"
    schema_version: ClassVar[int] = 4

    frame_id: int = Field(ge=-1)
    stamp_ns: int = Field(ge=0)
    integrated: bool
    frames_integrated: int = Field(ge=0)
    queued: int = Field(ge=0)  # frames waiting in geometry's queue after this one
    incarnation: str = Field("", max_length=64)
    holds_playback: str = Field("", max_length=64)
    holds_frame_id: int = Field(-1, ge=-1)
    resume: int = Field(0, ge=0)
    robot: RobotName = DEFAULT_ROBOT
    shard: str = Field("geometry", min_length=1, max_length=64)


class RenderRequest(PinholeMessage):
    """Render the map's region keys from ``T_world_cam`` into a small ``width_px`` x ``height_px`` view.

    v2: ``T_world_cam`` is in ``robot``'s odometry frame, as its frames are; geometry renders from
    the map pose its join gives (a robot not joined yet is refused: ``robot_not_joined``).

    v3: ``after_update_source`` / ``after_update_seq``: render once the update numbered
    ``after_update_seq`` from that semantic service (:attr:`SemanticUpdate.seq`) is applied, so a
    frame is matched against the labels of the frame encoded before it (geometry waits at most
    ``render_update_wait_s``); 0: at once.

    v4: ``probe_depth_m``, the frame's own depth in metres at the request's size (0 = none):
    geometry answers with the map's surface near that depth instead of a ray cast
    (:mod:`openfusion.mapping.surface_probe`) when it holds more than ``probe_above_blocks`` blocks:
    the same reply, at a cost that does not grow with the map (a candidate's view: frame selection's
    ``select_view``; an encoded frame's: ``step_probe_blocks``). A request that names an update
    (``after_update_source``: a semantic step's) has its view kept for the update that follows."""

    schema_name: ClassVar[str] = "geometry.render_request"
    schema_version: ClassVar[int] = 4

    frame_id: int = Field(ge=0)
    T_world_cam: Pose4x4
    robot: RobotName = DEFAULT_ROBOT
    after_update_source: str = Field("", max_length=64)
    after_update_seq: int = Field(0, ge=0)
    probe_depth_m: FloatMap | None = None
    probe_above_blocks: int = Field(0, ge=0)

    @model_validator(mode="after")
    def _check(self) -> RenderRequest:
        check_pose(self.T_world_cam)
        if self.after_update_seq and not self.after_update_source:
            raise ValueError("after_update_seq > 0 must name after_update_source")
        if self.probe_depth_m is not None:
            if self.probe_depth_m.shape != (self.height_px, self.width_px):
                raise ValueError(f"probe_depth_m is {self.probe_depth_m.shape}, the view is "
                                 f"{(self.height_px, self.width_px)}")
            if not (np.isfinite(self.probe_depth_m).all() and (self.probe_depth_m >= 0).all()):
                raise ValueError("probe_depth_m must be finite and >= 0 (0 = no depth)")
        return self


class RenderReply(Message):
    """Per-pixel region key (-1 = none), its confidence and the rendered depth in metres.

    v2: ``T_map_cam``, the pose geometry rendered from in the map's frame (the request's pose
    joined to the map by its robot's transform), so a reader that keeps its own world-frame record
    (frame selection's coverage) files every robot's views in the one frame."""

    schema_name: ClassVar[str] = "geometry.render_reply"
    schema_version: ClassVar[int] = 2

    frame_id: int = Field(ge=0)
    T_map_cam: Pose4x4 | None = None
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
    schema_version: ClassVar[int] = 2  # 2: optional centroid

    map_version: int = Field(ge=0)
    key_horizon: int = Field(ge=0)
    age_s: float = Field(default=0.0, ge=0)
    keys: KeyList
    bbox_min: Points3f
    bbox_max: Points3f
    num_points: ndarray("int64", shape=(None,))
    #: Mean of each region's surface points (None from a geometry that does not send it: the
    #: query service then reports the box centre).
    centroid: Points3f | None = None

    @model_validator(mode="after")
    def _check(self) -> RegionSummaryReply:
        n = len(self.keys)
        if self.centroid is not None and len(self.centroid) != n:
            raise ValueError(f"keys ({n}) and centroid ({len(self.centroid)}) differ in length")
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


class RegionContactsRequest(Message):
    """Ask geometry which regions' labelled voxels touch (what the semantic service decides merges
    on, :mod:`openfusion.mapping.merging`): voxels within ``radius_vox`` voxels per axis touch."""

    schema_name: ClassVar[str] = "geometry.contacts_request"
    schema_version: ClassVar[int] = 1

    radius_vox: int = Field(default=1, ge=1, le=3)


class RegionContactsReply(Message):
    """Region adjacency of the map at ``map_version``: every region with labelled voxels and how
    many (``keys``, ``surface_voxels``), and every touching pair ``pair_a`` < ``pair_b`` with the
    number of ``a``'s voxels touching ``b`` (``contact_a``) and of ``b``'s touching ``a``
    (``contact_b``)."""

    schema_name: ClassVar[str] = "geometry.contacts_reply"
    schema_version: ClassVar[int] = 1

    map_version: int = Field(ge=0)
    keys: KeyList
    surface_voxels: ndarray("int64", shape=(None,))
    pair_a: KeyList
    pair_b: KeyList
    contact_a: ndarray("int64", shape=(None,))
    contact_b: ndarray("int64", shape=(None,))

    @model_validator(mode="after")
    def _check(self) -> RegionContactsReply:
        if len(self.surface_voxels) != len(self.keys):
            raise ValueError(f"keys ({len(self.keys)}) and surface_voxels ({len(self.surface_voxels)}) differ in length")
        p = len(self.pair_a)
        if not (len(self.pair_b) == len(self.contact_a) == len(self.contact_b) == p):
            raise ValueError("pair_a, pair_b, contact_a and contact_b must have the same length")
        if len(self.keys) and (len(np.unique(self.keys)) != len(self.keys) or int(self.keys.min()) < 0):
            raise ValueError("keys must be unique and >= 0")
        if p and (int(self.pair_a.min()) < 0 or bool((self.pair_a >= self.pair_b).any())):
            raise ValueError("pairs must be 0 <= pair_a < pair_b")
        for name in ("surface_voxels", "contact_a", "contact_b"):
            arr = getattr(self, name)
            if arr.size and int(arr.min()) < 0:
                raise ValueError(f"{name} must be >= 0")
        return self
