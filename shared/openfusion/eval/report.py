"""Write evaluation results: ``results.json`` (everything) and ``results.md`` (the tables).

Both files are written atomically (temporary file + rename), so a crashed run never leaves a
half-written result that looks complete.
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Sequence
from pathlib import Path

from openfusion.eval.config import MAP_NAMES, MAP_TITLES

logger = logging.getLogger(__name__)

RESULTS_JSON = "results.json"
RESULTS_MD = "results.md"


def _atomic_write(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        tmp.write_text(text, encoding="utf-8")
        tmp.replace(path)
    finally:
        if tmp.exists():
            tmp.unlink()


def write_results(results: dict, out_dir: str | Path) -> tuple[Path, Path]:
    """Write ``results.json`` and ``results.md`` into ``out_dir`` (created if needed)."""
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ValueError(f"cannot create output folder {out}: {exc}") from exc
    json_path, md_path = out / RESULTS_JSON, out / RESULTS_MD
    _atomic_write(json_path, json.dumps(results, indent=2, allow_nan=False) + "\n")
    _atomic_write(md_path, render_markdown(results))
    logger.info("wrote %s and %s", json_path, md_path)
    return json_path, md_path


def _f(v: float | None, fmt: str = "{:.3f}") -> str:
    return "n/a" if v is None else fmt.format(v)


def _ratio(v: float | None, base: float | None) -> str:
    if v is None or base is None or base == 0:
        return "n/a"
    return f"{v / base:.2f}x"


def _table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> list[str]:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return lines


def render_markdown(results: dict) -> str:
    """The human-readable report: summary, per-scene quality, per-class table, geometry, speed,
    memory and query time with the baselines and their ratios to the region map."""
    cfg = results["config"]
    summary = results["summary"]
    scenes = results["scenes"]
    lines: list[str] = ["# OpenFusion-Z evaluation", ""]
    lines.append(
        f"Encoder `{cfg['encoder']}` (noise `{cfg['noise']}`, text `{cfg['text_encoder']}`), "
        f"{cfg['frames']} frames at {cfg['width_px']}x{cfg['height_px']}, voxel {cfg['voxel_size_m'] * 100:.1f} cm, "
        f"semantic step every {cfg['semantic_every']} frame(s), "
        f"background {'excluded: ' + ', '.join(cfg['background_classes']) if cfg['exclude_background'] else 'included'}, "
        f"unlabelled points count as `{cfg['unlabelled']}`."
    )
    lines.append("")

    lines += ["## Quality (confusion summed over scenes)", ""]
    rows = []
    for s in scenes:
        m = s["quality"]["region_map"]["metrics"]
        rows.append(
            [
                s["scene"],
                _f(m["f_mIoU"]),
                _f(m["mAcc"]),
                _f(m["mIoU"]),
                _f(m["unlabelled_fraction"]),
                str(m["num_points"]),
            ]
        )
    sm = summary["quality"].get("region_map", {}).get("metrics")
    if sm:
        rows.append(
            [
                "**all (summed)**",
                _f(sm["f_mIoU"]),
                _f(sm["mAcc"]),
                _f(sm["mIoU"]),
                _f(sm["unlabelled_fraction"]),
                str(sm["num_points"]),
            ]
        )
    lines += _table(["scene", "f-mIoU", "mAcc", "mIoU", "unlabelled", "points"], rows)
    lines.append("")

    reg = summary.get("regions")
    if reg:
        lines += ["## Regions per object", ""]
        rows = [[s["scene"], str(s["regions"]["regions_100"]), str(s["regions"]["gt_objects"]),
                 _f(s["regions"]["regions_100_per_object"]), str(s["regions"]["regions_merged"])]
                for s in scenes if "regions" in s]
        rows.append(["**all**", str(reg["regions_100"]), str(reg["gt_objects"]),
                     _f(reg["regions_100_per_object"]), str(reg["regions_merged"])])
        lines += _table(["scene", "regions (>= 100 points)", "objects seen", "regions per object", "merged"], rows)
        lines.append("")

    if sm:
        lines += ["## Per class (region map, all scenes)", ""]
        cm = summary["quality"]["region_map"]["confusion"]
        unl = {n: (r[-1] / max(sum(r), 1)) for n, r in zip(cm["class_names"], cm["counts"], strict=True)}
        rows = [
            [
                c["name"],
                str(c["gt_count"]),
                _f(c["recall"]),
                _f(c["precision"]),
                _f(c["iou"]),
                _f(unl.get(c["name"])),
            ]
            for c in sorted(sm["per_class"], key=lambda c: -c["gt_count"])
        ]
        lines += _table(["class", "GT points", "recall", "precision", "IoU", "left unlabelled"], rows)
        lines.append("")

    wrong = [(s["scene"], r) for s in scenes for r in s.get("wrong_regions", [])[:3]]
    if wrong:
        lines += ["## Regions holding the most mislabelled surface (top 3 per scene)", ""]
        rows = [[scene, str(r["key"]), str(r["mapped_class"]), f"{r['wrong']} of {r['points']}",
                 ", ".join(f"{n} {c}" for n, c in r["gt_classes"].items()), str(r["views"]), _f(r["agreement"])]
                for scene, r in wrong]
        lines += _table(["scene", "region", "labelled", "wrong points", "ground truth under it", "views",
                         "agreement"], rows)
        lines.append("")

    lines += ["## Geometry", ""]
    rows = []
    for s in scenes:
        g = s["geometry"]
        rows.append(
            [
                s["scene"],
                _f(g["accuracy_m"] and g["accuracy_m"] * 100, "{:.2f}"),
                _f(g["accuracy_vox"], "{:.2f}"),
                _f(g["completeness"]),
                str(g["num_reconstructed"]),
                f"{g['num_gt_observed']}/{g['num_gt']}",
                s["ground_truth"]["accuracy_reference"],
            ]
        )
    lines += _table(
        ["scene", "accuracy (cm)", "accuracy (voxels)", f"completeness (<= {cfg['completeness_voxels']:g} voxels)",
         "reconstructed points", "observed / GT points", "accuracy against"],
        rows,
    )  # fmt: skip
    lines.append("")

    lines += ["## Speed", ""]
    rows = [
        [
            s["scene"],
            str(s["speed"]["frames"]),
            _f(s["speed"]["rec3d_fps"], "{:.1f}"),
            _f(s["speed"].get("raw_open3d_fps"), "{:.1f}"),
            _ratio(s["speed"]["rec3d_fps"], s["speed"].get("raw_open3d_fps")),
            _f(s["speed"]["sem_rec3d_fps"], "{:.1f}"),
            _f(s["speed"]["encode_ms"], "{:.1f}"),
            _f(s["speed"]["semantic_step_ms"], "{:.1f}"),
        ]
        for s in scenes
    ]
    sp = summary["speed"]
    rows.append(
        [
            "**all**",
            str(sp["frames"]),
            _f(sp["rec3d_fps"], "{:.1f}"),
            _f(sp.get("raw_open3d_fps"), "{:.1f}"),
            _ratio(sp["rec3d_fps"], sp.get("raw_open3d_fps")),
            _f(sp["sem_rec3d_fps"], "{:.1f}"),
            "",
            "",
        ]
    )
    lines += _table(
        ["scene", "frames", "3D-Rec fps (ours, geometry)", "raw Open3D fps (baseline)", "ratio",
         "Sem-3D-Rec fps", "encode ms/frame", "semantic step ms/frame"],
        rows,
    )  # fmt: skip
    lines.append("")
    lines.append(
        "3D-Rec = frames / time in `SemanticVolume.integrate`; raw Open3D = a plain `VoxelBlockGrid` "
        "(tsdf, weight, color) integrating the same frames in the same loop; Sem-3D-Rec = frames / "
        "(integrate + encode + semantic step). Frame loading/rendering is not counted."
    )
    lines.append("")

    sel = summary.get("selection")
    if sel is not None:
        lines += ["## Frame selection (encoder calls)", ""]
        rows = [[s["scene"], str(s["speed"]["frames"]), str(s["speed"].get("encoder_calls", "")),
                 str(s["speed"].get("encoder_regions", "")), str(s["speed"].get("regions_not_embedded", "")),
                 _f(s["regions"].get("calls_per_region"), "{:.1f}"),
                 _f(s["regions"].get("calls_per_object"), "{:.1f}"), str(s["speed"].get("skipped_no_gain", "")),
                 str(s["speed"].get("skipped_switch", "")), _f(s["speed"].get("select_ms"), "{:.1f}")]
                for s in scenes]
        rows.append(["**all**", str(sel["frames"]), str(sel["encoder_calls"]), str(sel["encoder_regions"]),
                     str(sel.get("regions_not_embedded", "")),
                     _f(reg.get("calls_per_region") if reg else None, "{:.1f}"),
                     _f(reg.get("calls_per_object") if reg else None, "{:.1f}"), str(sel["skipped_no_gain"]),
                     str(sel.get("skipped_switch", "")), _f(sel["select_ms"], "{:.1f}")])
        lines += _table(["scene", "frames", "encoder calls (frames)", "regions embedded", "regions not embedded",
                         "calls per region",
                         "calls per object", "skipped (no gain)", "skipped (--semantic-every)", "scoring ms/frame"],
                        rows)
        lines.append("")
        lines.append(
            f"`--select {sel['select']}` (openfusion.mapping.selection). Calls per region = regions the encoder "
            "embedded / regions of the final map; calls per object = regions the encoder embedded / ground-truth "
            "objects seen (OVI-MAP's VLM calls per instance); regions not embedded: regions of encoded frames that "
            "added nothing (`select_embed_share`), fused without an embedding; scoring = render at the scored size + scoring, per "
            f"frame scored (a semantic step: {_f(sel.get('semantic_step_ms'), '{:.1f}')} ms). Each frame ends in one "
            "of: encoded, skipped (no gain), skipped (--semantic-every); through the services run.json's "
            "`semantic_outcomes` names more (superseded, dropped, evicted, no render...).")
        lines.append("")

    lines += ["## Baselines (same encoder outputs, same run; ratios to the region map)", ""]
    base_q = summary["quality"].get("region_map", {}).get("metrics", {})
    base_mem = summary["memory_bytes"].get("region_map")
    base_query = summary["query_ms"].get("region_map", {})
    rows = []
    for name in MAP_NAMES:
        q = summary["quality"].get(name, {}).get("metrics")
        if q is None:
            continue
        mem = summary["memory_bytes"].get(name)
        qt = summary["query_ms"].get(name, {})
        rows.append(
            [
                MAP_TITLES[name],
                _f(q["f_mIoU"]),
                _ratio(q["f_mIoU"], base_q.get("f_mIoU")),
                _f(q["mAcc"]),
                _f(mem and mem / 2**20, "{:.2f}"),
                _ratio(mem, base_mem),
                _f(qt.get("segment_ms"), "{:.2f}"),
                _ratio(qt.get("segment_ms"), base_query.get("segment_ms")),
                _f(qt.get("rank_one_ms"), "{:.3f}"),
                _ratio(qt.get("rank_one_ms"), base_query.get("rank_one_ms")),
            ]
        )
    lines += _table(
        ["map", "f-mIoU", "f-mIoU ratio", "mAcc", "semantic memory (MiB)", "memory ratio",
         "segment all points (ms)", "segment ratio", "rank one query (ms)", "rank ratio"],
        rows,
    )  # fmt: skip
    lines.append("")
    lines.append(
        "Semantic memory: region map = key slot (uint16) + confidence (uint16) for every voxel of every allocated "
        "block + the region dictionary; per-point features = one float32 embedding + weight per reconstructed "
        "point; 16 samples per block = key + confidence + position per kept sample + the dictionary. "
        "Geometry (TSDF, weight, color) is the same for all and not counted."
    )
    lines.append("")

    lines += ["## Targets", ""]
    rows = [[t["name"], _f(t["value"]), "pass" if t["passed"] else "**FAIL**"] for t in summary["targets"]]
    lines += _table(["target", "measured", "result"], rows)
    lines.append("")
    return "\n".join(lines)
