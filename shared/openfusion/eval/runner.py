"""The evaluation run: map each scene, score it with the protocol, measure geometry, speed, memory
and the baselines in the same run (:func:`run_eval`; one scene: :func:`evaluate_scene`).

What a run measures: :mod:`openfusion.eval.config`; the mapping loop it times:
:mod:`openfusion.eval.mapping_loop`; the summary over scenes and the targets:
:mod:`openfusion.eval.summary` (their names are re-exported here).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence

import numpy as np

from openfusion.encoders import make_region_encoder, make_text_encoder
from openfusion.eval.baselines import block_sampled_keys, fuse_point_features, time_call
from openfusion.eval.config import FULL, MAP_NAMES, MAP_TITLES, QUICK, EvalConfig
from openfusion.eval.geometry import ObservedSurface, geometry_metrics, mesh_distances
from openfusion.eval.ground_truth import GroundTruth
from openfusion.eval.mapping_loop import MappingRun, map_scene_for_eval
from openfusion.eval.metrics import compute_metrics
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
from openfusion.eval.summary import (
    GEOMETRY_TARGETS,
    TARGETS,
    check_targets,
    encoder_calls_per_region,
    summarize,
)
from openfusion.eval.wrong_regions import wrong_regions
from openfusion.mapping.storage import SEMANTIC_BYTES_PER_VOXEL

__all__ = [
    "FULL",
    "GEOMETRY_TARGETS",
    "MAP_NAMES",
    "MAP_TITLES",
    "QUICK",
    "TARGETS",
    "EvalConfig",
    "MappingRun",
    "check_targets",
    "encoder_calls_per_region",
    "evaluate_scene",
    "make_encoders",
    "map_scene_for_eval",
    "run_eval",
    "summarize",
]

logger = logging.getLogger(__name__)


# --------------------------------------------------------------------------- one scene


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
    t_readout = time.perf_counter()
    surface = volume.extract_points()
    readout_s = time.perf_counter() - t_readout
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
    wrong = wrong_regions(keys, pred, gt_of_points, gt.class_names, run.dictionary, scored=allowed)

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
        "regions_not_embedded": run.regions_not_embedded,
        "frames_scored": run.frames_scored,
        "skipped_no_gain": run.skipped_no_gain,
        "skipped_switch": run.skipped_switch,
        "select_s": run.select_s,
        "renders_reused": run.renders_reused,
        "select_ms": 1e3 * run.select_s / run.frames_scored if run.frames_scored else None,
        "readout_s": readout_s,  # the map's surface points with keys (fill and vote included)
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
        "wrong_regions": wrong,
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
