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
from dataclasses import dataclass, field
from typing import Any

from openfusion.frame import Frame
from openfusion.mapping.dictionary import RegionDictionary
from openfusion.mapping.errors import CapacityError
from openfusion.mapping.mapper import SemanticMapper
from openfusion.mapping.merging import EmptyRegions, MergeSchedule, merge_regions
from openfusion.mapping.params import MatchParams, MergeParams, SelectParams, VolumeParams
from openfusion.mapping.region_gate import encode_where
from openfusion.mapping.selection import FrameSelector
from openfusion.mapping.volume import SemanticVolume

logger = logging.getLogger(__name__)


def reconstruction_rates(
    *, frames_integrated: float, integrate_s: float, semantic_frames: float, semantic_s: float
) -> tuple[float | None, float | None]:
    """(3D-Rec fps, Sem-3D-Rec fps) from counts and busy times, the one definition every report uses.

    3D-Rec = frames integrated / time spent integrating them. Sem-3D-Rec = 1 / (integration time
    per frame + semantic time per semantic frame): the rate of a pipeline that runs semantics
    (encode + render + match + update) on every frame, from the same measurements. None when a
    count or time is 0.
    """
    per_frame = integrate_s / frames_integrated if frames_integrated and integrate_s > 0 else None
    per_sem = semantic_s / semantic_frames if semantic_frames and semantic_s > 0 else None
    rec = 1.0 / per_frame if per_frame else None
    sem = 1.0 / (per_frame + per_sem) if per_frame and per_sem else None
    return rec, sem


@dataclass
class PipelineStats:
    """Counts and times of one pipeline run; fps by :func:`reconstruction_rates`."""

    frames_read: int = 0
    frames_skipped: dict[str, int] = field(default_factory=dict)
    frames_integrated: int = 0
    semantic_frames: int = 0
    semantic_failed: int = 0  # frames whose encoder or semantic step raised (logged, geometry kept)
    integrate_s: float = 0.0
    encode_s: float = 0.0
    semantic_step_s: float = 0.0
    merge_passes: int = 0  # region merge passes run (every MergeParams.merge_every semantic frames, and at the end)
    regions_merged: int = 0  # regions folded into another (dictionary entries removed by merges)
    regions_pruned: int = 0  # regions removed for holding no voxel in two merge passes in a row
    merge_s: float = 0.0
    # frame selection (openfusion.mapping.selection): what went to the encoder and what was left out
    select: str = "coverage"
    encoder_calls: int = 0  # frames given to the region encoder
    encoder_regions: int = 0  # regions it embedded, summed over those calls
    regions_not_embedded: int = 0  # regions of chosen frames that added nothing: masks fused, no embedding
    frames_scored: int = 0  # frames scored by the coverage scorer
    skipped_no_gain: int = 0  # frames not encoded: they added too little (select_min_gain)
    select_s: float = 0.0  # time spent scoring (render at the scored size + numpy)
    renders_reused: int = 0  # frames scored on a still camera's last render, not rendered (select_still_s)

    def _rates(self) -> tuple[float | None, float | None]:
        return reconstruction_rates(frames_integrated=self.frames_integrated, integrate_s=self.integrate_s,
                                    semantic_frames=self.semantic_frames,
                                    semantic_s=self.encode_s + self.semantic_step_s)

    @property
    def rec_fps(self) -> float | None:
        return self._rates()[0]

    @property
    def sem_rec_fps(self) -> float | None:
        return self._rates()[1]


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
    match_params: MatchParams | None = None,
    merge_params: MergeParams | None = None,
    semantic_every: int = 1,
    select_params: SelectParams | None = None,
    max_frames: int | None = None,
    on_frame: Callable[[Frame, PipelineStats], None] | None = None,
) -> MapResult:
    """Integrate every frame of ``source``; of every ``semantic_every``-th frame id (0 = geometry
    only), run the semantic step on the frames the selection picks (``select_params``, default
    :class:`SelectParams`: coverage, the frames that add something; ``select="every"``: all of
    them; :class:`~openfusion.mapping.selection.FrameSelector`). Returns the map and its stats.

    Regions that are one object merge (:mod:`openfusion.mapping.merging`, ``merge_params``) every
    ``merge_every`` semantic frames and once at the end, so the returned (and saved) map holds the
    merged regions.

    One bad frame never ends the run, as in the services: a frame the volume refuses for its
    block budget is skipped (``frames_skipped["capacity_refused"]``), and a frame whose encoder or
    semantic step raises is logged with its frame id and counted (``semantic_failed``) while its
    geometry stays integrated. An observation with no regions is a normal frame.
    """
    if semantic_every < 0:
        raise ValueError(f"semantic_every must be >= 0, got {semantic_every}")
    volume = SemanticVolume(volume_params or VolumeParams())
    dictionary = RegionDictionary(region_encoder.embedding_space, region_encoder.dim)
    mapper = SemanticMapper(volume, dictionary, params=match_params)
    merge_p = merge_params if merge_params is not None else MergeParams()
    schedule = MergeSchedule(merge_p)
    empty = EmptyRegions(passes=1)  # updates are written before the next pass
    selector = FrameSelector(select_params, volume.render, volume.candidate_view)
    selector.scorer.embedding_support = dictionary.support_of
    stats = PipelineStats(select=selector.params.select)

    def merge_pass() -> None:
        result = merge_regions(volume, dictionary, merge_p, empty=empty)
        selector.merged(result.plan.merged_into, result.removed)
        stats.merge_passes += 1
        stats.regions_merged += result.merged
        stats.regions_pruned += len(result.removed)
        stats.merge_s += result.total_ms / 1e3
        if result.merged:
            logger.debug("merged %d regions in %.0f ms: %s", result.merged, result.total_ms, result.plan.groups)

    def semantic(frame: Frame) -> None:  # one chosen frame: encode and step, a failure counted
        t1 = time.perf_counter()
        try:
            stats.encoder_calls += 1
            obs = encode_where(region_encoder, frame, *selector.embed_where(frame))
            stats.encoder_regions += obs.num_embedded
            stats.regions_not_embedded += obs.num_regions - obs.num_embedded
            t2 = time.perf_counter()
            mapper.step(obs, frame.T_world_cam, frame.intrinsics, depth_m=frame.depth_m())
            if mapper.last_plan is not None:
                selector.encoded(frame, mapper.last_plan.key_map)
        except Exception:  # one frame's encoder or step failure is logged and counted, never fatal
            logger.exception("frame %d: the semantic step failed; the frame keeps its geometry", frame.frame_id)
            stats.semantic_failed += 1
        else:
            t3 = time.perf_counter()
            stats.encode_s += t2 - t1
            stats.semantic_step_s += t3 - t2
            stats.semantic_frames += 1
            if schedule.due():
                merge_pass()

    refused: dict[str, int] = {}
    for frame in source:
        if max_frames is not None and stats.frames_integrated >= max_frames:
            break
        t0 = time.perf_counter()
        try:
            volume.integrate(frame)
        except CapacityError as exc:
            logger.warning("frame %d refused: %s", frame.frame_id, exc)
            refused["capacity_refused"] = refused.get("capacity_refused", 0) + 1
            continue
        t1 = time.perf_counter()
        stats.integrate_s += t1 - t0
        stats.frames_integrated += 1
        if semantic_every and frame.frame_id % semantic_every == 0:
            for chosen in _offered(selector, frame, stats):
                semantic(chosen)
        if on_frame is not None:
            on_frame(frame, stats)
    for chosen in _offered(selector, None, stats):
        semantic(chosen)
    if merge_p.merge_every > 0 and stats.semantic_frames:
        merge_pass()
    source_stats = getattr(source, "stats", None)
    if source_stats is not None:
        stats.frames_read = int(source_stats.read)
        stats.frames_skipped = dict(source_stats.skipped)
    else:
        stats.frames_read = stats.frames_integrated + sum(refused.values())
    for reason, n in refused.items():
        stats.frames_skipped[reason] = stats.frames_skipped.get(reason, 0) + n
    return MapResult(volume, dictionary, stats)


def _offered(selector: FrameSelector, frame: Frame | None, stats: PipelineStats) -> list[Frame]:
    """The frames the selection sends to the encoder now (``frame`` None: the end of the source);
    its counts and time go into ``stats``."""
    chosen = selector.offer(frame) if frame is not None else selector.flush()
    stats.frames_scored = selector.stats.frames_scored
    stats.skipped_no_gain = selector.stats.skipped_no_gain
    stats.select_s = selector.stats.score_s
    stats.renders_reused = selector.stats.renders_reused
    return chosen
