"""The evaluation run: map each scene, score it with the protocol, measure geometry, speed, memory
and the baselines in the same run.

Mapping loop (one process, no bus; :func:`map_scene_for_eval`): for every frame
``volume.integrate(frame)`` (timed as geometry), and every ``semantic_every``-th frame
``obs = region_encoder.encode(frame)`` then ``mapper.step(obs, T_world_cam, intrinsics, depth_m=...)``
(the frame's depth enables the update's depth gate; timed as
semantics). The same loop records what the baselines and the completeness metric need (the
frame's depth for the observed-surface test and a compact copy of the encoder output). It is
written here rather than calling ``openfusion.mapping.pipeline.map_scene`` because those per-frame
hooks and the split timings are what the evaluation measures.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from openfusion.encoders import make_region_encoder, make_text_encoder
from openfusion.eval.baselines import (
    FrameRecord,
    RawOpen3DIntegrator,
    block_sampled_keys,
    fuse_point_features,
    record_frame,
    time_call,
)
from openfusion.eval.classes import DEFAULT_BACKGROUND_CLASSES
from openfusion.eval.geometry import ObservedSurface, geometry_metrics, mesh_distances
from openfusion.eval.ground_truth import GroundTruth
from openfusion.eval.metrics import ConfusionMatrix, compute_metrics, sum_confusions
from openfusion.eval.point_labels import (
    dictionary_arrays,
    nearest_labelled_fill,
    region_counts,
    segment_with_library,
)
from openfusion.eval.protocol import (
    class_scores_mask,
    classify_embeddings,
    confusion_for_points,
    ground_truth_labels_for,
    labels_from_region_keys,
)
from openfusion.eval.scenes import SceneSpec, check_scene_inputs, open_scene
from openfusion.mapping import RegionDictionary, SemanticMapper, SemanticVolume
from openfusion.mapping.merging import EmptyRegions, MergeSchedule, merge_regions
from openfusion.mapping.params import MatchParams, MergeParams, SelectParams, VolumeParams
from openfusion.mapping.selection import FrameSelector
from openfusion.mapping.storage import SEMANTIC_BYTES_PER_VOXEL

logger = logging.getLogger(__name__)

#: Maps compared in every run, in table order.
MAP_NAMES = ("region_map", "region_map_nn_fill", "point_features", "block_samples_16")
MAP_TITLES = {
    "region_map": "region map (ours: per-voxel key + region dictionary)",
    "region_map_nn_fill": "region map + nearest-labelled fill (diagnostic)",
    "point_features": "per-point features (ConceptFusion-style)",
    "block_samples_16": "16 samples per block (reference storage)",
}


@dataclass(frozen=True)
class EvalConfig:
    """Everything that decides what one evaluation run measures."""

    encoder: str = "gt"
    noise: str = "off"
    text_encoder: str = "minilm"
    region_text: str = "caption"  # the gt encoder's region embeddings: "caption" or "name"
    frames: int = 24
    width_px: int = 640
    height_px: int = 480
    # The map's parameters: the same models (and defaults) as the geometry and semantic services.
    volume: VolumeParams = field(default_factory=VolumeParams)
    match: MatchParams = field(default_factory=MatchParams)
    merge: MergeParams = field(default_factory=MergeParams)
    select: SelectParams = field(default_factory=SelectParams)  # which frames are encoded (coverage)
    semantic_every: int = 1
    exclude_background: bool = False
    background_classes: tuple[str, ...] = DEFAULT_BACKGROUND_CLASSES
    unlabelled: str = "miss"
    gt_spacing_m: float = 0.03
    completeness_voxels: float = 2.0
    baselines: bool = True
    raw_open3d_baseline: bool = True
    samples_per_block: int = 16
    encoder_seed: int = 0
    query_repeats: int = 5

    def __post_init__(self) -> None:
        if self.frames < 1:
            raise ValueError(f"frames must be >= 1, got {self.frames}")
        if self.semantic_every < 1:
            raise ValueError(f"semantic_every must be >= 1, got {self.semantic_every}")
        for name in ("gt_spacing_m", "completeness_voxels"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        if self.unlabelled not in ("miss", "ignore"):
            raise ValueError(f"unlabelled must be 'miss' or 'ignore', got {self.unlabelled!r}")

    @property
    def excluded_classes(self) -> tuple[str, ...]:
        return tuple(self.background_classes) if self.exclude_background else ()

    @property
    def voxel_size_m(self) -> float:
        return self.volume.voxel_size_m

    def to_dict(self) -> dict:
        """Plain JSON (results.json): the volume's and matching parameters flattened into the top level."""
        d = {k: v for k, v in self.__dict__.items() if k not in ("volume", "match", "merge", "select")}
        d.update(self.volume.to_dict())
        d.update(self.match.model_dump())
        d.update(self.merge.model_dump())
        d.update(self.select.model_dump())
        d["background_classes"] = list(self.background_classes)
        return d


#: CI-sized run: a 24-frame lap of 640x480 frames per scene (about a minute per scene on a
#: 2-core CPU). Smaller images are not used to save time: the encoder works at a quarter of the
#: input size, and at 320x240 (80x60 regions) boundaries are too coarse for the quality targets.
QUICK = EvalConfig()
#: Full size: a 150-frame lap of 640x480 frames, 2 cm ground-truth sampling.
FULL = replace(QUICK, frames=150, gt_spacing_m=0.02)


# --------------------------------------------------------------------------- mapping loop


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
    encoder_regions: int = 0  # regions it returned over those calls
    frames_scored: int = 0
    skipped_no_gain: int = 0
    select_s: float = 0.0


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
    selector = FrameSelector(select_params, volume.render)

    def merge_pass() -> None:  # timed with the semantic step (it is part of it in the services)
        result = merge_regions(volume, dictionary, merge_p, empty=empty)
        selector.merged(result.plan.merged_into, result.removed)
        run.merge_passes += 1
        run.regions_merged += result.merged
        run.merge_s += result.total_ms / 1e3
        run.semantic_step_s += result.total_ms / 1e3
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
        if i % semantic_every or not selector.wants(frame):
            continue
        t1 = time.perf_counter()
        obs = region_encoder.encode(frame)
        run.encoder_calls += 1
        run.encoder_regions += len(obs.conf_maps)
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
            rec = record_frame(
                obs.conf_maps,
                obs.embeddings,
                depth_m=depth_m,
                intrinsics=frame.intrinsics,
                T_world_cam=frame.T_world_cam,
            )
            run.records.append(rec)
            run.record_bytes += rec.nbytes
    if run.frames == 0:
        raise ValueError(f"source {getattr(source, 'name', source)!r} produced no frames")
    if merge_p.merge_every > 0 and run.semantic_frames:
        merge_pass()
    run.frames_scored = selector.stats.frames_scored
    run.skipped_no_gain = selector.stats.skipped_no_gain
    run.select_s = selector.stats.score_s
    if raw is not None:
        run.raw_integrate_s = raw.seconds
        del raw  # free its grid before the evaluation allocates
    return run


# --------------------------------------------------------------------------- one scene


def encoder_calls_per_region(encoder_regions: int, dictionary_regions: int, gt_objects: int | None) -> dict:
    """Region encodes (regions the encoder returned, summed over its calls) per region of the final
    map and per ground-truth object (OVI-MAP's VLM calls per instance)."""
    return {
        "encoder_regions": int(encoder_regions),
        "dictionary_regions": int(dictionary_regions),
        "calls_per_region": encoder_regions / dictionary_regions if dictionary_regions else None,
        "calls_per_object": encoder_regions / gt_objects if gt_objects else None,
    }


def _quality(pred: np.ndarray, gt_of_points: np.ndarray, gt: GroundTruth, config: EvalConfig) -> dict:
    cm = confusion_for_points(pred, gt_of_points, gt.class_names)
    m = compute_metrics(cm, exclude_classes=config.excluded_classes, unlabelled=config.unlabelled)
    return {"metrics": m.to_dict(), "confusion": cm.to_dict()}


def evaluate_scene(
    spec: SceneSpec,
    config: EvalConfig,
    *,
    region_encoder: object,
    text_encoder: object,
) -> dict:
    """Map one scene and measure it; returns the scene's results (JSON-ready dict)."""

    t_start = time.perf_counter()
    scene = open_scene(
        spec,
        frames=config.frames,
        width_px=config.width_px,
        height_px=config.height_px,
        gt_spacing_m=config.gt_spacing_m,
    )
    gt = scene.ground_truth
    t_gt = time.perf_counter() - t_start
    if not gt.class_names:
        raise ValueError(f"{spec.name}: the ground truth has no labelled class")
    voxel = config.volume.voxel_size_m
    params = config.volume
    observed = ObservedSurface(
        gt.points,
        depth_tolerance_m=config.completeness_voxels * voxel,
        depth_min_m=scene.depth_min_m,
        depth_max_m=config.volume.depth_max_m,
    )
    logger.info("%s: mapping %s frames", spec.name, config.frames)
    run = map_scene_for_eval(
        scene.source,
        region_encoder=region_encoder,
        volume_params=params,
        match_params=config.match,
        merge_params=config.merge,
        select_params=config.select,
        semantic_every=config.semantic_every,
        observed=observed,
        record_for_baselines=config.baselines,
        raw_open3d_baseline=config.raw_open3d_baseline,
    )
    volume = run.volume
    surface = volume.extract_points()
    points = np.asarray(surface.points, dtype=np.float64)
    keys = np.asarray(surface.keys, dtype=np.int64)

    # ---- protocol: class queries -> per-point labels -> nearest GT label -> confusion
    class_emb = np.asarray(text_encoder.encode(list(gt.class_names)), dtype=np.float32)
    allowed = class_scores_mask(gt.class_names, config.excluded_classes)
    region_keys, region_emb = dictionary_arrays(run.dictionary)
    gt_of_points, _ = ground_truth_labels_for(points, gt)

    def segment_regions() -> np.ndarray:
        region_cls = classify_embeddings(region_emb, class_emb, allowed=allowed)
        return labels_from_region_keys(keys, region_keys, region_cls)

    pred = segment_with_library(volume, run.dictionary, class_emb, allowed, points)
    if pred is None:
        pred = segment_regions()
    quality = {"region_map": _quality(pred, gt_of_points, gt, config)}
    # Diagnostic: what the region map would score if extraction gave every unlabelled surface
    # point the label of its nearest labelled point (isolates the "never labelled" share).
    quality["region_map_nn_fill"] = _quality(nearest_labelled_fill(points, pred), gt_of_points, gt, config)

    # ---- geometry
    acc_d = mesh_distances(points, gt.mesh_vertices, gt.mesh_triangles) if gt.has_mesh else None
    geo = geometry_metrics(
        points,
        gt.points,
        voxel_size_m=voxel,
        observed_mask=observed.mask,
        completeness_voxels=config.completeness_voxels,
        accuracy_distances_m=acc_d,
    )

    # ---- memory + query time of the region map
    n_blocks = int(volume.num_blocks_total)
    d = region_emb.shape[1] if region_emb.ndim == 2 else 0
    # key slot uint16 + conf uint16 (compact voxels, openfusion.mapping.storage)
    voxel_sem_bytes = n_blocks * config.volume.block_resolution**3 * SEMANTIC_BYTES_PER_VOXEL
    dict_bytes = len(region_keys) * (d * 4 + 4 + 8)  # embedding + count + key
    q = class_emb[:1]
    memory = {
        "region_map": {
            "semantic_bytes": voxel_sem_bytes + dict_bytes,
            "voxel_semantic_bytes": voxel_sem_bytes,
            "dictionary_bytes": dict_bytes,
            "regions": len(region_keys),
            "blocks": n_blocks,
        }
    }
    query = {
        "region_map": {
            "segment_ms": 1e3 * time_call(segment_regions, repeats=config.query_repeats),
            "rank_one_ms": 1e3
            * time_call(lambda: np.argsort(-(region_emb @ q[0])), repeats=config.query_repeats),
            "entries": len(region_keys),
        }
    }

    # ---- baselines fed with the same encoder outputs
    if config.baselines and run.records:
        pf = fuse_point_features(points, run.records, depth_tolerance_m=config.completeness_voxels * voxel)
        feats = pf.features

        def segment_points_baseline() -> np.ndarray:
            scores = feats @ class_emb.T
            scores[:, ~allowed] = -np.inf
            lab = scores.argmax(axis=1)
            lab[pf.weights <= 0] = -1
            return lab

        quality["point_features"] = _quality(segment_points_baseline(), gt_of_points, gt, config)
        memory["point_features"] = {
            "semantic_bytes": pf.nbytes,
            "points": len(points),
            "fuse_s": pf.fuse_seconds,
        }
        query["point_features"] = {
            "segment_ms": 1e3 * time_call(segment_points_baseline, repeats=config.query_repeats),
            "rank_one_ms": 1e3 * time_call(lambda: np.argsort(-(feats @ q[0])), repeats=config.query_repeats),
            "entries": len(points),
        }
        bs = block_sampled_keys(
            points,
            keys,
            voxel_size_m=voxel,
            block_resolution=config.volume.block_resolution,
            samples_per_block=config.samples_per_block,
            seed=config.encoder_seed,
        )
        region_cls = classify_embeddings(region_emb, class_emb, allowed=allowed)
        pred_b = labels_from_region_keys(bs.keys, region_keys, region_cls)
        quality["block_samples_16"] = _quality(pred_b, gt_of_points, gt, config)
        memory["block_samples_16"] = {
            "semantic_bytes": bs.nbytes + dict_bytes,
            "samples": bs.num_samples,
            "blocks": n_blocks,
        }

    sem_s = run.integrate_s + run.encode_s + run.semantic_step_s
    speed = {
        "frames": run.frames,
        "semantic_frames": run.semantic_frames,
        "integrate_s": run.integrate_s,
        "encode_s": run.encode_s,
        "semantic_step_s": run.semantic_step_s,
        "rec3d_fps": run.frames / run.integrate_s if run.integrate_s > 0 else None,
        "raw_open3d_integrate_s": run.raw_integrate_s,
        "raw_open3d_fps": run.frames / run.raw_integrate_s if run.raw_integrate_s else None,
        "sem_rec3d_fps": run.frames / sem_s if sem_s > 0 else None,
        "semantic_step_ms": 1e3 * run.semantic_step_s / max(run.semantic_frames, 1),
        "encode_ms": 1e3 * run.encode_s / max(run.semantic_frames, 1),
        # frame selection: calls of the region encoder (frames, and regions over them), frames left out
        "select": config.select.select,
        "encoder_calls": run.encoder_calls,
        "encoder_regions": run.encoder_regions,
        "frames_scored": run.frames_scored,
        "skipped_no_gain": run.skipped_no_gain,
        "select_s": run.select_s,
        "select_ms": 1e3 * run.select_s / run.frames_scored if run.frames_scored else None,
    }
    regions = region_counts(keys, gt, observed.mask)
    regions.update(merge_passes=run.merge_passes, regions_merged=run.regions_merged, merge_s=run.merge_s)
    regions.update(encoder_calls_per_region(run.encoder_regions, len(run.dictionary), regions.get("gt_objects")))
    return {
        "scene": spec.name,
        "regions": regions,
        "ground_truth": {
            "source": gt.source,
            "points": int(len(gt.points)),
            "classes": list(gt.class_names),
            "class_counts": gt.class_counts(),
            "accuracy_reference": "mesh" if gt.has_mesh else "points",
            "load_s": t_gt,
        },
        "surface_points": int(len(points)),
        "surface_points_with_key": int((keys >= 0).sum()),
        "quality": quality,
        "geometry": geo.to_dict(),
        "speed": speed,
        "memory": memory,
        "query": query,
        "wall_s": time.perf_counter() - t_start,
    }


# --------------------------------------------------------------------------- whole run


def make_encoders(config: EvalConfig) -> tuple[object, object]:
    """(region encoder, matching text encoder) for the run."""

    if config.encoder == "gt":
        text = make_text_encoder(config.text_encoder)
        region = make_region_encoder("gt", text_encoder=text, noise=config.noise, seed=config.encoder_seed,
                                     region_text=config.region_text)
        return region, text
    if config.noise != "off":
        raise ValueError(f"--noise applies to the gt encoder only, not {config.encoder!r}")
    region = make_region_encoder(config.encoder)
    text = make_text_encoder(config.encoder)
    if text.embedding_space != region.embedding_space:
        raise ValueError(
            f"text encoder space {text.embedding_space!r} differs from region encoder space {region.embedding_space!r}"
        )
    return region, text


def run_eval(specs: Sequence[SceneSpec], config: EvalConfig) -> dict:
    """Evaluate every scene and sum the confusion matrices; returns the full results dict."""
    check_scene_inputs(specs)
    region, text = make_encoders(config)
    scenes = [evaluate_scene(s, config, region_encoder=region, text_encoder=text) for s in specs]
    return {"config": config.to_dict(), "scenes": scenes, "summary": summarize(scenes, config)}


def summarize(scenes: Sequence[dict], config: EvalConfig) -> dict:
    """Quality from the summed confusion matrices; geometry averaged; speed pooled over frames."""
    quality = {}
    for name in MAP_NAMES:
        mats = [
            ConfusionMatrix.from_dict(s["quality"][name]["confusion"]) for s in scenes if name in s["quality"]
        ]
        if len(mats) == len(scenes):
            cm = sum_confusions(mats)
            quality[name] = {
                "metrics": compute_metrics(
                    cm, exclude_classes=config.excluded_classes, unlabelled=config.unlabelled
                ).to_dict(),
                "confusion": cm.to_dict(),
            }

    def mean(path: tuple[str, ...]) -> float | None:
        vals = []
        for s in scenes:
            v = s
            for p in path:
                v = v.get(p) if isinstance(v, dict) else None
            if v is not None:
                vals.append(float(v))
        return float(np.mean(vals)) if vals else None

    frames = sum(s["speed"]["frames"] for s in scenes)
    integ = sum(s["speed"]["integrate_s"] for s in scenes)
    raws = [s["speed"].get("raw_open3d_integrate_s") for s in scenes]
    raw = sum(raws) if all(r is not None for r in raws) else None
    sem = integ + sum(s["speed"]["encode_s"] + s["speed"]["semantic_step_s"] for s in scenes)
    memory = {
        name: mean(("memory", name, "semantic_bytes"))
        for name in MAP_NAMES
        if all(name in s["memory"] for s in scenes)
    }
    query = {
        name: {
            "segment_ms": mean(("query", name, "segment_ms")),
            "rank_one_ms": mean(("query", name, "rank_one_ms")),
        }
        for name in ("region_map", "point_features")
        if all(name in s["query"] for s in scenes)
    }
    geometry = {
        k: mean(("geometry", k)) for k in ("accuracy_m", "accuracy_vox", "accuracy_median_m", "completeness")
    }
    objects = [s.get("regions", {}).get("gt_objects") for s in scenes]
    regions_100 = sum(s.get("regions", {}).get("regions_100", 0) for s in scenes)
    regions = {
        "regions_100": regions_100,
        "gt_objects": sum(objects) if all(o is not None for o in objects) else None,
        "regions_merged": sum(s.get("regions", {}).get("regions_merged", 0) for s in scenes),
    }
    regions["regions_100_per_object"] = regions_100 / regions["gt_objects"] if regions["gt_objects"] else None
    encoder_regions = sum(s["speed"].get("encoder_regions", 0) for s in scenes)
    regions.update(encoder_calls_per_region(encoder_regions, sum(s["regions"].get("dictionary_regions", 0)
                                                                 for s in scenes), regions["gt_objects"]))
    select_s = sum(s["speed"].get("select_s", 0.0) for s in scenes)
    scored = sum(s["speed"].get("frames_scored", 0) for s in scenes)
    step_s = sum(s["speed"]["encode_s"] + s["speed"]["semantic_step_s"] for s in scenes)
    sem_frames = sum(s["speed"]["semantic_frames"] for s in scenes)
    selection = {
        "select": config.select.select,
        "frames": frames,
        "encoder_calls": sum(s["speed"].get("encoder_calls", 0) for s in scenes),
        "encoder_regions": encoder_regions,
        "skipped_no_gain": sum(s["speed"].get("skipped_no_gain", 0) for s in scenes),
        "select_ms": 1e3 * select_s / scored if scored else None,
        "semantic_step_ms": 1e3 * step_s / sem_frames if sem_frames else None,
    }
    return {
        "scenes": [s["scene"] for s in scenes],
        "regions": regions,
        "quality": quality,
        "geometry": geometry,
        "speed": {
            "frames": frames,
            "rec3d_fps": frames / integ if integ > 0 else None,
            "raw_open3d_fps": frames / raw if raw else None,
            "sem_rec3d_fps": frames / sem if sem > 0 else None,
        },
        "selection": selection,
        "memory_bytes": memory,
        "query_ms": query,
        "targets": check_targets(quality, geometry, config),
    }


#: Acceptance targets with the gt encoder on synthetic scenes (docs/EVAL.md).
TARGETS = {
    "off": {"f_mIoU": 0.90, "mAcc": 0.90},
    "standard": {"f_mIoU": 0.75},
}
GEOMETRY_TARGETS = {"accuracy_vox_max": 1.0, "completeness_min": 0.90}


def check_targets(quality: dict, geometry: dict, config: EvalConfig) -> list[dict]:
    """Each target with the measured value and pass/fail (only for the gt encoder)."""
    out: list[dict] = []
    if config.encoder == "gt" and config.noise in TARGETS and "region_map" in quality:
        m = quality["region_map"]["metrics"]
        for key, thr in TARGETS[config.noise].items():
            v = m.get(key)
            out.append(
                {
                    "name": f"{key} >= {thr} (noise {config.noise})",
                    "value": v,
                    "passed": v is not None and v >= thr,
                }
            )
    acc = geometry.get("accuracy_vox")
    comp = geometry.get("completeness")
    out.append(
        {
            "name": f"accuracy <= {GEOMETRY_TARGETS['accuracy_vox_max']} voxel",
            "value": acc,
            "passed": acc is not None and acc <= GEOMETRY_TARGETS["accuracy_vox_max"],
        }
    )
    out.append(
        {
            "name": f"completeness >= {GEOMETRY_TARGETS['completeness_min']}",
            "value": comp,
            "passed": comp is not None and comp >= GEOMETRY_TARGETS["completeness_min"],
        }
    )
    return out
