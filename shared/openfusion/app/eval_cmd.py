"""``openfusion eval``: map scenes, score them with the ConceptFusion protocol, write results.

Usage::

    openfusion eval --scenes synthetic:seed=1,synthetic:seed=2 --encoder gt --noise standard --out out/eval
    openfusion eval --scenes scannet:/data/scannet/scans/scene0000_00 --frames 300 --exclude-background --full

Writes ``results.json`` and ``results.md`` into ``--out``. Exit codes: 0 ok, 2 bad usage or
input (one line on stderr), 1 a target missed with ``--check-targets``.

Wiring: :class:`EvalCommand` fits the ``openfusion`` CLI registry (``add_arguments`` +
``run``); ``python -m openfusion.eval`` runs the same command.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
from dataclasses import replace
from typing import get_args

from openfusion.encoders.gt import REGION_TEXTS
from openfusion.errors import OpenFusionError, UsageError
from openfusion.eval.classes import DEFAULT_BACKGROUND_CLASSES
from openfusion.eval.config import FULL, QUICK, EvalConfig
from openfusion.mapping.params import SelectMode

logger = logging.getLogger(__name__)

NOISE_CHOICES = ("off", "light", "standard", "heavy")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The ``openfusion eval`` options."""
    parser.add_argument(
        "--scenes",
        nargs="+",
        default=["synthetic:seed=1,synthetic:seed=2"],
        metavar="SPEC",
        help="scenes to evaluate: synthetic[:seed=N[,frames=N,width=W,height=H,noise=0|1]], "
        "synthetic:building[,rooms=N,route=A-B,revisit=N,seed=N,frames=N,...] (rooms along a corridor; its walk "
        "sets its frames, not --frames) or scannet:PATH; "
        "comma-separated and/or several arguments (default: synthetic:seed=1,synthetic:seed=2)",
    )
    parser.add_argument("--encoder", default="gt", help="region encoder (default gt: ground-truth regions)")
    parser.add_argument(
        "--text-encoder",
        default=None,
        help="with --encoder gt: text encoder for its embeddings and the class queries (minilm (default) or hash); "
        "another encoder brings its own",
    )
    parser.add_argument(
        "--noise", default="off", choices=NOISE_CHOICES, help="with --encoder gt: its noise profile (default off)"
    )
    parser.add_argument(
        "--region-text", default=None, choices=REGION_TEXTS,
        help="with --encoder gt: what a region's embedding holds: caption (default: its name and six captions "
        "where openfusion.encoders.captions knows the category) or name",
    )
    parser.add_argument("--frames", type=int, default=None, help="frames per scene (default 24, --full 150)")
    parser.add_argument("--width", type=int, default=None, help="synthetic image width (default 640)")
    parser.add_argument("--height", type=int, default=None, help="synthetic image height (default 480)")
    parser.add_argument("--voxel-size", type=float, default=None, help="voxel size in metres (default 0.02)")
    parser.add_argument("--memory-budget-mb", type=float, default=None,
                        help="map with a memory budget: tiles paged out to a scratch tile store (default none)")
    parser.add_argument(
        "--semantic-every", type=int, default=None, help="semantic step every k-th frame (default 1)"
    )
    parser.add_argument(
        "--select", choices=get_args(SelectMode), default=None,
        help="which frames are encoded: coverage (default: those that add something, "
        "openfusion.mapping.selection), every, or latest (the same as every in one process)")
    parser.add_argument(
        "--embed-share", default=None, metavar="SHARE|none",
        help="with --select coverage: a region of a chosen frame is embedded only when this share of its pixels "
        "adds something (default 0.3, semantic.select_embed_share); none: every region of a chosen frame")
    parser.add_argument(
        "--gt-spacing",
        type=float,
        default=None,
        help="synthetic ground-truth sampling spacing in metres (default 0.03, --full 0.02)",
    )
    parser.add_argument(
        "--exclude-background",
        action="store_true",
        help="drop background classes from queries and scores (ConceptGraphs protocol)",
    )
    parser.add_argument(
        "--background-classes",
        default=None,
        help=f"with --exclude-background: the comma-separated classes it drops "
        f"(default {','.join(DEFAULT_BACKGROUND_CLASSES)})",
    )
    parser.add_argument(
        "--unlabelled",
        choices=("miss", "ignore"),
        default="miss",
        help="points the map leaves unlabelled count as misses (default, as ConceptFusion) or are ignored",
    )
    parser.add_argument(
        "--no-baselines", action="store_true", help="skip the per-point and 16-per-block baselines"
    )
    parser.add_argument("--full", action="store_true", help="full size (150-frame laps, 2 cm GT sampling)")
    parser.add_argument(
        "--check-targets", action="store_true", help="exit 1 when a quality or geometry target is missed"
    )
    parser.add_argument("--out", default="eval-out", help="output folder for results.json and results.md (default eval-out)")


def config_from_args(args: argparse.Namespace) -> EvalConfig:
    """The run's :class:`EvalConfig` from parsed options (ValueError on bad values)."""
    base = FULL if args.full else QUICK
    region_text = getattr(args, "region_text", None)
    if args.encoder != "gt" and (args.noise != "off" or args.text_encoder is not None or region_text is not None):
        given = [f for f, v in (("--noise", args.noise != "off"), ("--text-encoder", args.text_encoder),
                                ("--region-text", region_text)) if v]
        raise UsageError(f"{' and '.join(given)} {'apply' if len(given) > 1 else 'applies'} to --encoder gt only, "
                         f"not {args.encoder!r} (it brings its own text encoder)")
    if args.background_classes is not None and not args.exclude_background:
        raise UsageError("--background-classes names the classes --exclude-background drops; give both or neither")
    background = DEFAULT_BACKGROUND_CLASSES if args.background_classes is None else args.background_classes.split(",")
    for opt in ("width", "height"):
        if getattr(args, opt) is not None and getattr(args, opt) < 1:
            raise UsageError(f"--{opt} must be >= 1, got {getattr(args, opt)}")
    overrides = {
        "encoder": args.encoder,
        "noise": args.noise,
        "exclude_background": bool(args.exclude_background),
        "background_classes": tuple(c.strip() for c in background if c.strip()),
        "unlabelled": args.unlabelled,
        "baselines": not args.no_baselines,
    }
    if args.text_encoder is not None:
        overrides["text_encoder"] = args.text_encoder
    if region_text is not None:
        overrides["region_text"] = region_text
    for opt, key in (
        ("frames", "frames"),
        ("width", "width_px"),
        ("height", "height_px"),
        ("semantic_every", "semantic_every"),
        ("gt_spacing", "gt_spacing_m"),
    ):
        v = getattr(args, opt)
        if v is not None:
            overrides[key] = v
    volume_changes: dict[str, float] = {}
    if args.voxel_size is not None:
        volume_changes["voxel_size_m"] = args.voxel_size
    if getattr(args, "memory_budget_mb", None) is not None:
        if args.memory_budget_mb <= 0:
            raise UsageError(f"--memory-budget-mb must be positive, got {args.memory_budget_mb:g}")
        volume_changes["memory_budget_mb"] = args.memory_budget_mb
    if volume_changes:
        overrides["volume"] = base.volume.with_changes(**volume_changes)
    select_changes: dict[str, object] = {}
    if getattr(args, "select", None) is not None:
        select_changes["select"] = args.select
    if getattr(args, "embed_share", None) is not None:
        select_changes["select_embed_share"] = _embed_share(args.embed_share)
    if select_changes:
        overrides["select"] = base.select.model_copy(update=select_changes)
    if overrides["exclude_background"] and not overrides["background_classes"]:
        raise UsageError("--exclude-background needs at least one class in --background-classes")
    return replace(base, **overrides)


def _embed_share(text: str) -> float | None:
    """``--embed-share``: a share in [0, 1] or ``none``; UsageError otherwise."""
    if text.strip().lower() == "none":
        return None
    try:
        share = float(text)
    except ValueError:
        share = math.nan
    if not 0.0 <= share <= 1.0:
        raise UsageError(f"--embed-share must be a share between 0 and 1 or none, got {text!r}")
    return share


def run(args: argparse.Namespace) -> int:
    """Run the evaluation described by ``args``; returns the exit code."""
    from openfusion.eval.report import write_results
    from openfusion.eval.runner import run_eval
    from openfusion.eval.scenes import parse_scene_specs

    try:
        specs = parse_scene_specs(args.scenes)
        config = config_from_args(args)
    except OpenFusionError:
        raise
    except (ValueError, OSError) as exc:  # a bad option value or scene path: the user's to fix
        raise UsageError(str(exc)) from exc
    results = run_eval(specs, config)
    json_path, md_path = write_results(results, args.out)
    summary = results["summary"]
    q = summary["quality"]["region_map"]["metrics"]
    print(
        f"f-mIoU {q['f_mIoU']:.3f}  mAcc {q['mAcc']:.3f}  "
        f"accuracy {summary['geometry']['accuracy_vox']:.2f} voxels  completeness {summary['geometry']['completeness']:.3f}"
    )
    sel = summary["selection"]
    print(f"encoder calls {sel['encoder_calls']} of {sel['frames']} frames (--select {sel['select']}), "
          f"{summary['regions']['calls_per_object'] or 0:.1f} per object")
    print(f"wrote {json_path} and {md_path}")
    missed = [t["name"] for t in summary["targets"] if not t["passed"]]
    if missed:
        print("targets missed: " + "; ".join(missed), file=sys.stderr)
        if args.check_targets:
            return 1
    return 0


class EvalCommand:
    """Registry entry for the ``openfusion`` console script (``openfusion.app.eval_cmd:EvalCommand``)."""

    add_arguments = staticmethod(add_arguments)
    run = staticmethod(run)
