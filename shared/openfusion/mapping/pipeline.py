"""The mapping pipeline in one process (no bus): what the services do, as one loop.

Used by ``openfusion run --in-process``, the evaluation and notebooks::

    from openfusion.mapping.pipeline import map_scene
    from openfusion.encoders import make_region_encoder
    from openfusion.sources import open_source
    result = map_scene(open_source("synthetic:frames=60"), region_encoder=make_region_encoder("gt"))
    result.volume, result.dictionary, result.stats
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any

from openfusion.frame import Frame
from openfusion.mapping import RegionDictionary, SemanticMapper, SemanticVolume, VolumeParams

logger = logging.getLogger(__name__)


@dataclass
class PipelineStats:
    """Counts and times of one pipeline run; fps as defined in :mod:`openfusion.app.run`."""

    frames_read: int = 0
    frames_skipped: dict[str, int] = field(default_factory=dict)
    frames_integrated: int = 0
    semantic_frames: int = 0
    integrate_s: float = 0.0
    encode_s: float = 0.0
    semantic_step_s: float = 0.0

    @property
    def rec_fps(self) -> float | None:
        return self.frames_integrated / self.integrate_s if self.integrate_s > 0 else None

    @property
    def sem_rec_fps(self) -> float | None:
        if not self.semantic_frames or not self.frames_integrated:
            return None
        per_frame = self.integrate_s / self.frames_integrated
        per_sem = (self.encode_s + self.semantic_step_s) / self.semantic_frames
        return 1.0 / (per_frame + per_sem)

    def as_dict(self) -> dict[str, Any]:
        out = asdict(self)
        out["rec_fps"] = round(self.rec_fps, 2) if self.rec_fps else None
        out["sem_rec_fps"] = round(self.sem_rec_fps, 2) if self.sem_rec_fps else None
        return out


@dataclass
class MapResult:
    volume: SemanticVolume
    dictionary: RegionDictionary
    stats: PipelineStats


def map_scene(
    source: Any,
    *,
    region_encoder: Any,
    volume_params: VolumeParams | None = None,
    semantic_every: int = 1,
    max_frames: int | None = None,
    min_iou: float = 0.10,
    on_frame: Callable[[Frame, PipelineStats], None] | None = None,
) -> MapResult:
    """Integrate every frame of ``source``; run the semantic step on every ``semantic_every``-th
    frame id (0 = geometry only). Returns the map and its stats."""
    if semantic_every < 0:
        raise ValueError(f"semantic_every must be >= 0, got {semantic_every}")
    volume = SemanticVolume(volume_params or VolumeParams())
    dictionary = RegionDictionary(region_encoder.embedding_space, region_encoder.dim)
    mapper = SemanticMapper(volume, dictionary, min_iou=min_iou)
    stats = PipelineStats()
    for frame in source:
        if max_frames is not None and stats.frames_integrated >= max_frames:
            break
        t0 = time.perf_counter()
        volume.integrate(frame)
        t1 = time.perf_counter()
        stats.integrate_s += t1 - t0
        stats.frames_integrated += 1
        if semantic_every and frame.frame_id % semantic_every == 0:
            obs = region_encoder.encode(frame)
            t2 = time.perf_counter()
            mapper.step(obs, frame.T_world_cam, frame.intrinsics, depth_m=frame.depth_m())
            t3 = time.perf_counter()
            stats.encode_s += t2 - t1
            stats.semantic_step_s += t3 - t2
            stats.semantic_frames += 1
        if on_frame is not None:
            on_frame(frame, stats)
    source_stats = getattr(source, "stats", None)
    if source_stats is not None:
        stats.frames_read = int(source_stats.read)
        stats.frames_skipped = dict(source_stats.skipped)
    else:
        stats.frames_read = stats.frames_integrated
    return MapResult(volume, dictionary, stats)
