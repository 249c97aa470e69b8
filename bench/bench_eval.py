#!/usr/bin/env python3
"""Evaluation benchmark: quality, geometry, speed and memory of the region map against the
per-point-feature map (ConceptFusion-style) and the 16-samples-per-block storage policy, all
measured in the same run with the gt encoder on synthetic scenes, noise off and standard.

    python bench/bench_eval.py            # --quick (default): 2 scenes x 2 noise profiles, CI-sized
    python bench/bench_eval.py --full     # 3 scenes, 640x480, 150-frame laps
    python bench/bench_eval.py --out DIR  # also write results.json / results.md per noise profile
    python bench/bench_eval.py --compare-merging [--merge-embedding weighted,mean,first]
        # region merging and the matcher's join off (before) vs on (after), same run; no baselines
    python bench/bench_eval.py --full --compare-select
        # every frame encoded (before) vs coverage-driven frame selection (after), same run: quality,
        # encoder calls (frames, regions, per ground-truth object), scoring cost; no baselines
    python bench/bench_eval.py --full --compare-select --select-also select_lookahead=3
    python bench/bench_eval.py --full --compare-select --select-also select_embed_share=   # FIELD= is None
        # ... plus a row per --select-also (comma-separated FIELD=VALUE of select_*), same run
    python bench/bench_eval.py --full --compare-vote
        # the read-out's vote off (before) and at its default radius (after), every frame encoded and
        # the default selection, same run: quality and what a read-out of the map costs
    python bench/bench_eval.py --full --compare-update-width --size 320x240 --scenes synthetic:seed=4,synthetic:seed=5
        # the semantic update at the encoder maps' own size (before) and with at least
        # volume.update_min_width_px rays across (after), every frame and the default selection

Prints markdown tables (the ratios are to the region map). Exit 0 always unless it crashes;
targets are reported, not asserted (use ``openfusion eval --check-targets`` for that).
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from dataclasses import replace
from pathlib import Path

from openfusion.encoders.gt import REGION_TEXTS
from openfusion.eval.report import render_markdown, write_results
from openfusion.eval.runner import FULL, QUICK, run_eval
from openfusion.eval.scenes import parse_scene_specs
from openfusion.mapping.params import MatchParams, MergeParams, SelectParams, VolumeParams

QUICK_SCENES = "synthetic:seed=1,synthetic:seed=2"
FULL_SCENES = "synthetic:seed=1,synthetic:seed=2,synthetic:seed=3"


def _f(v: float | None, fmt: str = "{:.3f}") -> str:
    return "n/a" if v is None else fmt.format(v)


def _ratio(v: float | None, base: float | None) -> str:
    return "n/a" if v is None or not base else f"{v / base:.2f}x"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    size = parser.add_mutually_exclusive_group()
    size.add_argument("--quick", action="store_true", help="CI-sized run (default)")
    size.add_argument("--full", action="store_true", help="full-size run")
    parser.add_argument(
        "--noise", default="off,standard", help="comma-separated gt noise profiles (default off,standard)"
    )
    parser.add_argument(
        "--scenes", default=None, help=f"scene specs (default {QUICK_SCENES}; --full {FULL_SCENES})"
    )
    parser.add_argument("--text-encoder", default="minilm", help="minilm (default) or hash")
    parser.add_argument("--region-text", default="caption", choices=REGION_TEXTS,
                        help="the gt encoder's region embeddings: name and captions (default) or name")
    parser.add_argument("--out", default=None, help="folder for results.json/results.md per noise profile")
    parser.add_argument("--details", action="store_true", help="print the full results.md of every profile")
    parser.add_argument("--compare-merging", action="store_true",
                        help="each profile with region merging + join off (before) and on (after); no baselines")
    parser.add_argument("--compare-select", action="store_true",
                        help="each profile with every frame encoded (before) and coverage selection (after); "
                             "no baselines")
    parser.add_argument("--select-set", action="append", default=[], metavar="FIELD=VALUE",
                        help="with --compare-select: a select_* parameter of the 'after' run (repeatable)")
    parser.add_argument("--select-also", action="append", default=[], metavar="FIELD=VALUE[,FIELD=VALUE]",
                        help="with --compare-select: one more coverage row with these select_* parameters "
                             "(repeatable: a row each)")
    parser.add_argument("--compare-vote", action="store_true",
                        help="each profile and selection (every frame, coverage) with the read-out's vote off "
                             "(before) and at its default radius (after); no baselines")
    parser.add_argument("--compare-update-width", action="store_true",
                        help="each profile and selection with the semantic update at the encoder maps' own size "
                             "(before) and enlarged to volume.update_min_width_px (after); no baselines")
    parser.add_argument("--size", default=None, metavar="WxH", help="frame size (default: --quick's or --full's)")
    parser.add_argument("--frames", type=int, default=None, help="frames per scene (default: --quick's or --full's)")
    parser.add_argument("--merge-embedding", default="weighted",
                        help="with --compare-merging: comma-separated merged-embedding rules to compare "
                             "(weighted, mean, first)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")

    base = FULL if args.full else QUICK
    base = replace(base, text_encoder=args.text_encoder, region_text=args.region_text)
    if args.size:
        try:
            width_px, height_px = (int(v) for v in args.size.lower().split("x"))
        except ValueError:
            parser.error(f"--size must be WxH (e.g. 320x240), got {args.size!r}")
        base = replace(base, width_px=width_px, height_px=height_px)
    if args.frames is not None:
        base = replace(base, frames=args.frames)
    specs = parse_scene_specs([args.scenes or (FULL_SCENES if args.full else QUICK_SCENES)])
    profiles = [p.strip() for p in args.noise.split(",") if p.strip()]

    if args.compare_select:
        after = SelectParams.from_pairs(args.select_set)  # FIELD= (empty) is none, as with --set
        also = [SelectParams.from_pairs([kv for kv in row.split(",") if kv]) for row in args.select_also]
        return compare_select(base, specs, profiles, after, also)
    if args.compare_vote:
        return compare_vote(base, specs, profiles)
    if args.compare_update_width:
        return compare_update_width(base, specs, profiles)
    if args.compare_merging:
        return compare_merging(base, specs, profiles, [e.strip() for e in args.merge_embedding.split(",") if e.strip()])

    runs = {}
    for noise in profiles:
        t0 = time.perf_counter()
        results = run_eval(specs, replace(base, noise=noise))
        results["wall_s"] = time.perf_counter() - t0
        runs[noise] = results
        if args.out:
            write_results(results, Path(args.out) / f"noise-{noise}")

    size_name = "full" if args.full else "quick"
    print(f"### Evaluation ({size_name}: {len(specs)} synthetic scenes, {base.frames} frames at "
          f"{base.width_px}x{base.height_px}, voxel {base.voxel_size_m * 100:.0f} cm, gt encoder + {base.text_encoder})")  # fmt: skip
    print()
    print(
        "| noise | f-mIoU | mAcc | accuracy (voxels) | completeness | 3D-Rec fps | raw Open3D fps (baseline) "
        "| ratio | Sem-3D-Rec fps | wall (s) |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for noise, r in runs.items():
        s = r["summary"]
        m = s["quality"]["region_map"]["metrics"]
        print(
            f"| {noise} | {_f(m['f_mIoU'])} | {_f(m['mAcc'])} | {_f(s['geometry']['accuracy_vox'], '{:.2f}')} | "
            f"{_f(s['geometry']['completeness'])} | {_f(s['speed']['rec3d_fps'], '{:.1f}')} | "
            f"{_f(s['speed'].get('raw_open3d_fps'), '{:.1f}')} | "
            f"{_ratio(s['speed']['rec3d_fps'], s['speed'].get('raw_open3d_fps'))} | "
            f"{_f(s['speed']['sem_rec3d_fps'], '{:.1f}')} | {r['wall_s']:.0f} |"
        )
    print()
    for noise, r in runs.items():
        md = render_markdown(r)
        if args.details:
            print(md.replace("# OpenFusion-Z evaluation", f"### Details, noise {noise}"))
            continue
        # Only the baselines and targets sections.
        start = md.index("## Baselines")
        print(md[start:].replace("## ", f"#### noise {noise}: ", 2).rstrip())
        print()
    return 0


def compare_merging(base, specs, profiles: list[str], embeddings: list[str]) -> int:  # noqa: ANN001
    """Before (no merging, no join) and after (the defaults; one row per merged-embedding rule), per
    noise profile, in one run: quality and regions with >= 100 surface points per ground-truth object."""
    base = replace(base, baselines=False, raw_open3d_baseline=False)
    variants = [("before (no merge, no join)", MatchParams(join_min_coverage=None), MergeParams(merge_every=0))]
    variants += [(f"after (merge: {e})", MatchParams(), MergeParams(merge_embedding=e)) for e in embeddings]
    print(f"### Region merging, before / after ({len(specs)} synthetic scenes, {base.frames} frames at "
          f"{base.width_px}x{base.height_px}, gt encoder + {base.text_encoder})")
    print()
    print("| noise | map | f-mIoU | mAcc | regions >= 100 pts | GT objects | regions per object | merged | "
          "merge ms/pass | wall (s) |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for noise in profiles:
        for name, match, merge in variants:
            t0 = time.perf_counter()
            r = run_eval(specs, replace(base, noise=noise, match=match, merge=merge))
            wall = time.perf_counter() - t0
            s = r["summary"]
            m = s["quality"]["region_map"]["metrics"]
            reg = s["regions"]
            passes = sum(sc["regions"]["merge_passes"] for sc in r["scenes"])
            merge_ms = 1e3 * sum(sc["regions"]["merge_s"] for sc in r["scenes"]) / passes if passes else None
            print(f"| {noise} | {name} | {_f(m['f_mIoU'])} | {_f(m['mAcc'])} | {reg['regions_100']} | "
                  f"{reg['gt_objects']} | {_f(reg['regions_100_per_object'], '{:.2f}')} | {reg['regions_merged']} | "
                  f"{_f(merge_ms, '{:.0f}')} | {wall:.0f} |", flush=True)
    return 0


def compare_select(base, specs, profiles: list[str], after: SelectParams,  # noqa: ANN001
                   also: list[SelectParams] = ()) -> int:
    """Every frame encoded (before) and coverage-driven selection (after; and a row per ``also``),
    per noise profile, in one run: quality, encoder calls (frames; regions; per ground-truth object:
    OVI-MAP's measure) and what scoring costs per frame against a semantic step measured in the
    same run."""

    def changed_of(p: SelectParams) -> dict:
        return {k: v for k, v in p.model_dump().items() if v != SelectParams.model_fields[k].default}

    base = replace(base, baselines=False, raw_open3d_baseline=False)
    changed = changed_of(after)
    print(f"### Frame selection, every frame vs coverage ({len(specs)} synthetic scenes, {base.frames} frames at "
          f"{base.width_px}x{base.height_px}, gt encoder + {base.text_encoder}{', after: ' + str(changed) if changed else ''})")
    print()
    print("| noise | frames encoded | f-mIoU | Δ f-mIoU | mAcc | unlabelled | encoder calls | share of frames | "
          "regions encoded | calls per object | calls per region | scoring ms/frame | semantic step ms | "
          "scoring / step | wall (s) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for noise in profiles:
        before_f = None
        rows = [("every", SelectParams(select="every")), ("coverage", after)]
        rows += [("coverage " + ", ".join(f"{k}={v}" for k, v in changed_of(p).items()), p) for p in also]
        for name, select in rows:
            t0 = time.perf_counter()
            r = run_eval(specs, replace(base, noise=noise, select=select))
            wall = time.perf_counter() - t0
            s = r["summary"]
            m, sel, reg = s["quality"]["region_map"]["metrics"], s["selection"], s["regions"]
            before_f = m["f_mIoU"] if before_f is None else before_f
            share = sel["encoder_calls"] / sel["frames"] if sel["frames"] else None
            cost = (sel["select_ms"] / sel["semantic_step_ms"] if sel["select_ms"] and sel["semantic_step_ms"]
                    else None)
            print(f"| {noise} | {name} | {_f(m['f_mIoU'], '{:.4f}')} | {m['f_mIoU'] - before_f:+.4f} | "
                  f"{_f(m['mAcc'])} | {_f(m['unlabelled_fraction'])} | {sel['encoder_calls']} of {sel['frames']} | "
                  f"{_f(share, '{:.2f}')} | {sel['encoder_regions']} | {_f(reg['calls_per_object'], '{:.1f}')} | "
                  f"{_f(reg['calls_per_region'], '{:.1f}')} | {_f(sel['select_ms'], '{:.1f}')} | "
                  f"{_f(sel['semantic_step_ms'], '{:.1f}')} | {_f(cost, '{:.2f}')} | {wall:.0f} |", flush=True)
    return 0


def compare_vote(base, specs, profiles: list[str]) -> int:  # noqa: ANN001
    """The read-out's vote (``volume.label_vote_radius_m``) off and at its default, per noise profile
    and selection, in one run: quality and the time of the eval's read-out of the whole map."""
    radius = VolumeParams().label_vote_radius_m
    return compare_volume_field(base, specs, profiles, "label_vote_radius_m", [0.0, radius],
                                f"The read-out's vote, off / {radius * 100:g} cm", "vote",
                                lambda v: "off" if v == 0 else f"{v * 100:g} cm")


def compare_update_width(base, specs, profiles: list[str]) -> int:  # noqa: ANN001
    """The semantic update at the encoder maps' own size and enlarged to ``volume.update_min_width_px``
    (its default), per noise profile and selection, in one run: quality, encoder calls and the
    semantic step's time."""
    width = VolumeParams().update_min_width_px
    return compare_volume_field(base, specs, profiles, "update_min_width_px", [0, width],
                                f"The update's rays, the maps' own size / at least {width} px wide",
                                "update rays", lambda v: "maps' size" if v == 0 else f">= {v} px")


def compare_volume_field(base, specs, profiles: list[str], field: str, values: list,  # noqa: ANN001
                         title: str, column: str, label) -> int:  # noqa: ANN001
    """One ``VolumeParams`` field at each of ``values`` (the first is the 'before'), per noise
    profile and selection (every frame, coverage), in one run."""
    base = replace(base, baselines=False, raw_open3d_baseline=False)
    print(f"### {title} ({len(specs)} synthetic scenes, {base.frames} frames at {base.width_px}x{base.height_px}, "
          f"gt encoder + {base.text_encoder})")
    print()
    print(f"| noise | frames encoded | {column} | f-mIoU | Δ f-mIoU | mAcc | Δ mAcc | unlabelled | encoder calls | "
          "calls per object | semantic step ms | read-out ms (ratio) | wall (s) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for noise in profiles:
        for select in ("every", "coverage"):
            before: dict | None = None
            for value in values:
                t0 = time.perf_counter()
                volume = base.volume.model_copy(update={field: value})
                r = run_eval(specs, replace(base, noise=noise, select=SelectParams(select=select), volume=volume))
                wall = time.perf_counter() - t0
                s = r["summary"]
                m, sel, reg = s["quality"]["region_map"]["metrics"], s["selection"], s["regions"]
                readout_ms = 1e3 * sum(sc["speed"]["readout_s"] for sc in r["scenes"]) / len(r["scenes"])
                before = before or {"f": m["f_mIoU"], "a": m["mAcc"], "ms": readout_ms}
                print(f"| {noise} | {select} | {label(value)} | {m['f_mIoU']:.4f} | "
                      f"{m['f_mIoU'] - before['f']:+.4f} | {m['mAcc']:.4f} | {m['mAcc'] - before['a']:+.4f} | "
                      f"{_f(m['unlabelled_fraction'])} | {sel['encoder_calls']} of {sel['frames']} | "
                      f"{_f(reg['calls_per_object'], '{:.1f}')} | {_f(sel['semantic_step_ms'], '{:.1f}')} | "
                      f"{readout_ms:.0f} ({readout_ms / before['ms']:.2f}x) | {wall:.0f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
