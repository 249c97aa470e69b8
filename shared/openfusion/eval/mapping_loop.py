"""The evaluation's mapping loop (one process, no bus; :func:`map_scene_for_eval`): for every frame
``volume.integrate(frame)`` (timed as geometry), and every ``semantic_every``-th frame
``obs = encode_where(region_encoder, frame, ...)`` then ``mapper.step(obs, T_world_cam, intrinsics, depth_m=...)``
(the frame's depth enables the update's depth gate; timed as
semantics). The same loop records what the baselines and the completeness metric need (the
frame's depth for the observed-surface test and a compact copy of the encoder output). It is
written here rather than calling ``openfusion.mapping.pipeline.map_scene`` because those per-frame
hooks and the split timings are what the evaluation measures.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

from openfusion.eval.baselines import FrameRecord, RawOpen3DIntegrator, record_frame
from openfusion.eval.geometry import ObservedSurface
from openfusion.mapping import RegionDictionary, SemanticMapper, SemanticVolume
from openfusion.mapping.merging import EmptyRegions, MergeSchedule, merge_regions
from openfusion.mapping.params import MatchParams, MergeParams, SelectParams, VolumeParams
from openfusion.mapping.region_gate import encode_where
from openfusion.mapping.selection import FrameSelector


@dataclass
class MappingRun:
    """What the mapping loop produced and measured."""

    volume: object
    dictionary: object
    frames: int = 0
    semantic_frames: int = 0
    integrate_s: float = 0.0
    encode_s: float = 0.0
    semantic_step_s: float = 0.0
    records: list[FrameRecord] = field(default_factory=list)
    record_bytes: int = 0
    raw_integrate_s: float | None = None
    merge_passes: int = 0
    regions_merged: int = 0
    merge_s: float = 0.0
    encoder_calls: int = 0  # frames given to the region encoder
    encoder_regions: int = 0  # regions it embedded over those calls
    regions_not_embedded: int = 0  # regions of chosen frames that added nothing: masks fused, no embedding
    frames_scored: int = 0
    skipped_no_gain: int = 0
    skipped_switch: int = 0  # frames left out by semantic_every (never offered to the selection)
    select_s: float = 0.0
    renders_reused: int = 0  # frames scored on a still camera's last render (select_still_s)


def map_scene_for_eval(
    source: object,
    *,
    region_encoder: object,
    volume_params: VolumeParams,
    match_params: MatchParams | None = None,
    merge_params: MergeParams | None = None,
    select_params: SelectParams | None = None,
    semantic_every: int = 1,
    observed: ObservedSurface | None = None,
    record_for_baselines: bool = True,
    raw_open3d_baseline: bool = False,
) -> MappingRun:
    """Integrate every frame and run the semantic step on the frames the selection picks
    (``select_params``, :class:`~openfusion.mapping.selection.FrameSelector`, as the pipeline) of
    every ``semantic_every``-th frame.

    ``raw_open3d_baseline`` also integrates every frame into a plain Open3D grid (timed
    separately, interleaved with ours, first on every other frame, so both see the same machine
    load and cache state).
    """

    volume = SemanticVolume(volume_params)
    dictionary = RegionDictionary(region_encoder.embedding_space, region_encoder.dim)
    mapper = SemanticMapper(volume, dictionary, params=match_params)
    run = MappingRun(volume=volume, dictionary=dictionary)
    merge_p = merge_params if merge_params is not None else MergeParams()
    schedule = MergeSchedule(merge_p)
    empty = EmptyRegions(passes=1)  # updates are written before the next pass
    selector = FrameSelector(select_params, volume.render, volume.candidate_view)
    selector.scorer.embedding_support = dictionary.support_of

    def merge_pass() -> None:  # timed with the semantic step (it is part of it in the services)
        result = merge_regions(volume, dictionary, merge_p, empty=empty)
        selector.merged(result.plan.merged_into, result.removed)
        run.merge_passes += 1
        run.regions_merged += result.merged
        run.merge_s += result.total_ms / 1e3
        run.semantic_step_s += result.total_ms / 1e3

    def semantic(frame: object, depth_m: object) -> None:  # one chosen frame: encode, step, record
        t1 = time.perf_counter()
        obs = encode_where(region_encoder, frame, *selector.embed_where(frame))
        run.encoder_calls += 1
        run.encoder_regions += obs.num_embedded
        run.regions_not_embedded += obs.num_regions - obs.num_embedded
        t2 = time.perf_counter()
        mapper.step(obs, frame.T_world_cam, frame.intrinsics, depth_m=depth_m)
        if mapper.last_plan is not None:
            selector.encoded(frame, mapper.last_plan.key_map)
        t3 = time.perf_counter()
        run.encode_s += t2 - t1
        run.semantic_step_s += t3 - t2
        run.semantic_frames += 1
        if schedule.due():
            merge_pass()
        if record_for_baselines:
            kept = obs.embedded_mask  # the baselines fuse what the encoder embedded
            rec = record_frame(
                obs.conf_maps[kept],
                obs.embeddings[kept],
                depth_m=depth_m,
                intrinsics=frame.intrinsics,
                T_world_cam=frame.T_world_cam,
            )
            run.records.append(rec)
            run.record_bytes += rec.nbytes

    raw = None
    if raw_open3d_baseline:
        p = volume_params
        raw = RawOpen3DIntegrator(
            voxel_size_m=p.voxel_size_m,
            block_resolution=p.block_resolution,
            trunc_voxels=p.trunc_voxels,
            depth_max_m=p.depth_max_m,
            initial_block_count=p.initial_block_count,
        )
    for i, frame in enumerate(source):
        # With the raw baseline, the two integrations alternate which goes first: the one right after
        # the source produced the frame (a synthetic render, a decode) runs with colder caches and
        # measured 0.70x of the other when it was always ours.
        raw_first = raw is not None and i % 2 == 1
        if raw_first:
            raw.integrate(frame.depth, frame.depth_scale, frame.color, frame.intrinsics, frame.T_world_cam)
        t0 = time.perf_counter()
        volume.integrate(frame)
        run.integrate_s += time.perf_counter() - t0
        run.frames += 1
        if raw is not None and not raw_first:
            raw.integrate(frame.depth, frame.depth_scale, frame.color, frame.intrinsics, frame.T_world_cam)
        depth_m = frame.depth_m()
        if observed is not None:
            observed.add_view(depth_m, frame.intrinsics, frame.T_world_cam)
        if i % semantic_every != 0:
            run.skipped_switch += 1
        else:
            for chosen in selector.offer(frame):
                semantic(chosen, depth_m if chosen is frame else chosen.depth_m())
    for chosen in selector.flush():
        semantic(chosen, chosen.depth_m())
    if run.frames == 0:
        raise ValueError(f"source {getattr(source, 'name', source)!r} produced no frames")
    if merge_p.merge_every > 0 and run.semantic_frames:
        merge_pass()
    run.frames_scored = selector.stats.frames_scored
    run.skipped_no_gain = selector.stats.skipped_no_gain
    run.select_s = selector.stats.score_s
    run.renders_reused = selector.stats.renders_reused
    if raw is not None:
        run.raw_integrate_s = raw.seconds
        del raw  # free its grid before the evaluation allocates
    return run
