"""The evaluation's summary over its scenes: quality from the summed confusion matrices, geometry
averaged, speed pooled over frames (:func:`summarize`), and the acceptance targets checked
against it (:func:`check_targets`, docs/EVAL.md)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from openfusion.eval.config import MAP_NAMES, EvalConfig
from openfusion.eval.metrics import ConfusionMatrix, compute_metrics, sum_confusions


def encoder_calls_per_region(encoder_regions: int, dictionary_regions: int, gt_objects: int | None) -> dict:
    """Region encodes (regions the encoder embedded, summed over its calls) per region of the final
    map and per ground-truth object (OVI-MAP's VLM calls per instance)."""
    return {
        "encoder_regions": int(encoder_regions),
        "dictionary_regions": int(dictionary_regions),
        "calls_per_region": encoder_regions / dictionary_regions if dictionary_regions else None,
        "calls_per_object": encoder_regions / gt_objects if gt_objects else None,
    }


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
        "regions_not_embedded": sum(s["speed"].get("regions_not_embedded", 0) for s in scenes),
        "skipped_no_gain": sum(s["speed"].get("skipped_no_gain", 0) for s in scenes),
        "skipped_switch": sum(s["speed"].get("skipped_switch", 0) for s in scenes),
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
