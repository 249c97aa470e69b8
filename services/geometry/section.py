"""The geometry service's settings (:class:`GeometrySection`, every volume parameter plus the
service's own) and its cache of region summaries (:class:`SummaryCache`), apart from the service's
message handling in :mod:`.service`."""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import Field, field_validator, model_validator

from openfusion.config import ServiceConfig
from openfusion.mapping import VolumeParams
from openfusion.mapping.params import JoinParams
from openfusion.mapping.queries import RegionTable
from openfusion.wire.keys import ShardId
from openfusion.wire.limits import MAX_SURFACE_POINTS
from openfusion.wire.schemas import RegionSummaryReply

logger = logging.getLogger("openfusion.services.geometry.service")


class GeometrySection(VolumeParams, JoinParams):
    """The geometry service's settings: every volume parameter (:class:`VolumeParams`, declared
    there once), how robots' frames join the map's (:class:`JoinParams`) plus the service's own."""

    map_dir: Path | None = Field(None, description="checkpoint folder (the map is saved to MAP_DIR/MAP_ID)")
    checkpoint_period_s: float = Field(30.0, ge=0, description="seconds between checkpoints (0 = only on control/save)")
    load_on_start: bool = Field(True, description="load the checkpoint in MAP_DIR/MAP_ID at start when there is one")
    frame_queue_size: int = Field(
        64, gt=0, description="frames waiting for integration; when full the oldest is dropped and counted"
    )
    max_points_reply: int = Field(MAX_SURFACE_POINTS, gt=0, le=MAX_SURFACE_POINTS,
                                  description="most surface points or mesh vertices in one reply")
    max_render_pixels: int = Field(640 * 480, gt=0, description="largest render request (width x height)")
    render_update_wait_s: float = Field(
        0.5, ge=0, le=5, description="a render asked for after a semantic update (the next frame's) waits at most "
        "this long for that update to be applied here (then renders without it, counted)"
    )
    merge_on_save: bool = Field(
        True, description="before a save on control/save, ask the semantic service for a merge pass"
    )
    merge_on_save_timeout_s: float = Field(
        20.0, gt=0, description="how long a save waits for that merge pass (then it saves without it)"
    )
    replica: int = Field(
        0, ge=0, le=9, description="replica of this shard (docs/SHARDS.md): 0 = the shard; 1.. = the same shard run "
        "again (another host): same frames, same tiles, the same keys; named geometry[-IofN]-rR"
    )
    copy_from_peer: bool | None = Field(
        None, description="with no checkpoint of its own at start, copy the checkpoint of a live peer of its shard "
        "(same shard, another replica) and follow from there (docs/SHARDS.md); none = on for a replica (replica >= 1)")
    peer_copy_checkpoint_first: bool = Field(
        True, description="ask the peer to checkpoint what it holds before it serves its checkpoint (a live source's "
        "frames between the peer's checkpoint and this start are not in the copy)")
    peer_copy_buffer_frames: int = Field(
        128, ge=0, le=4096, description="frames held while a peer's checkpoint is copied, taken after it (a live "
        "source's frames of that time; about 1.5 MB per 640x480 frame); more are counted as peer_copy_frames_lost; "
        "0 = subscribe after the copy")
    peer_copy_timeout_s: float = Field(
        60.0, gt=0, description="how long a peer may take to list its checkpoint (it checkpoints and copies its store "
        "first; each chunk: a quarter of this, at least 5 s); then the next peer is tried")
    regions_min_interval_s: float = Field(
        0.5, ge=0, description="a changed map's region summaries are recomputed at most this often (unless fresh)"
    )
    robot_frames: str = Field(
        "", description="how each robot's odometry frame joins the map's: 'ROBOT=fixed|guess|search[:x,y,z,yaw_deg]' "
        "entries separated by ';' (metres, degrees; fixed: joined at once; guess: ICP from it; search: global "
        "registration). Robots not named: search. Robots given as fixed define the map's frame; without one, the first "
        "robot on an empty map anchors it")

    @field_validator("robot_frames")
    @classmethod
    def _robot_frames(cls, value: str) -> str:
        from openfusion.mapping.robot_streams import parse_robot_frames

        parse_robot_frames(value)  # a clear error at start-up, naming the entry
        return value

    @model_validator(mode="before")
    @classmethod
    def _renamed(cls, data: Any) -> Any:
        # ``initial_blocks`` was this section's name of VolumeParams.initial_block_count.
        if isinstance(data, dict) and "initial_blocks" in data:
            data = dict(data)
            value = data.pop("initial_blocks")
            data.setdefault("initial_block_count", value)
            logger.warning("geometry.initial_blocks is deprecated; use geometry.initial_block_count")
        return data

    @property
    def shard_service(self) -> ShardId:
        """This geometry's shard and replica (:class:`~openfusion.wire.keys.ShardId`)."""
        return self.shard_id.with_replica(self.replica)

    def volume_params(self) -> VolumeParams:
        return VolumeParams.from_section(self)

    def join_params(self) -> JoinParams:
        return JoinParams.from_section(self)


class GeometryConfig(ServiceConfig):
    geometry: GeometrySection = Field(default_factory=GeometrySection)


class SummaryCache:
    """The region table (:class:`RegionTable`) of one map version: what ``geometry/regions``
    answers, and what a checkpoint of that version stores without reading the surface again."""

    def __init__(self, map_version: int, key_horizon: int, table: RegionTable) -> None:
        self.map_version = map_version
        self.key_horizon = key_horizon
        self.table = table
        self.computed_at = time.monotonic()

    def reply(self, keys: list[int] | None) -> RegionSummaryReply:
        t = self.table
        sel = slice(None) if keys is None else np.isin(t.keys, np.asarray(keys, np.int64))
        return RegionSummaryReply(
            map_version=self.map_version,
            key_horizon=self.key_horizon,
            age_s=max(0.0, time.monotonic() - self.computed_at),
            keys=t.keys[sel],
            bbox_min=t.bbox_min[sel],
            bbox_max=t.bbox_max[sel],
            num_points=t.num_points[sel],
            centroid=np.asarray(t.centroid[sel], np.float32),
        )


