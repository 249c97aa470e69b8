#!/usr/bin/env python3
"""Cold ``openfusion query --map-dir DIR chair``: a fresh process per run, old path against new.

The map is the built-in synthetic room made by ``openfusion run --in-process`` (``--full``: its
default 120 frames, the ~150 MB map of the issue; ``--quick``: 40 frames), or ``--map-dir DIR``.
Each variant runs the real console script as a new process ``--runs`` times (after one untimed
run that warms the OS file cache and, for the new path, makes the ONNX export), wall time from
spawn to exit:

1. **legacy** (``OPENFUSION_QUERY_LEGACY=1``): the command as it was before region summaries:
   reads the whole map (volume + dictionary, Open3D), reads out every queried region's surface,
   embeds the text with sentence-transformers (torch, transformers).
2. **old-format map**: the same map rewritten without summaries (as saved before them): the
   command falls back to reading the whole map, text through onnxruntime.
3. **summaries**: the map's dictionary + region summaries only, MiniLM through onnxruntime
   (no torch, no Open3D). Goal: median <= 2 s on a 2-core machine.

The one-off first use (ONNX export with torch into an empty cache) is timed once and printed
separately. The answers of all variants must agree (keys, or labels where same-label regions
tie; scores to 1e-3), else exit 1.

    .venv/bin/python bench/bench_query_cold.py --quick
    .venv/bin/python bench/bench_query_cold.py --full --runs 5
    .venv/bin/python bench/bench_query_cold.py --map-dir out/map
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
_SCRIPT = Path(sys.executable).parent / "openfusion"
OPENFUSION = [str(_SCRIPT)] if _SCRIPT.exists() else [sys.executable, "-m", "openfusion.app.cli"]
GOAL_S = 2.0


def _env(cache: Path, **extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("OPENFUSION_")}
    env.update(HF_HUB_OFFLINE="1", OPENFUSION_CACHE=str(cache), **extra)
    return env


def build_room_map(out: Path, frames: int) -> Path:
    """``openfusion run --in-process`` on the built-in room; returns the map folder."""
    t0 = time.perf_counter()
    proc = subprocess.run(
        [*OPENFUSION, "run", "--in-process", "--quiet", "--frames", str(frames), "--out", str(out)],
        capture_output=True, text=True, cwd=ROOT, env=_env(out / "cache"), check=False,
    )
    if proc.returncode != 0:
        raise SystemExit(f"bench_query_cold: `openfusion run` failed:\n{proc.stderr[-2000:]}")
    print(f"[bench_query_cold] built the room map ({frames} frames) in {time.perf_counter() - t0:.0f} s",
          file=sys.stderr)
    return out / "map"


def run_query(map_dir: Path, env: dict[str, str], text: str) -> tuple[float, list[dict]]:
    t0 = time.perf_counter()
    proc = subprocess.run(
        [*OPENFUSION, "query", "--map-dir", str(map_dir), text, "--json"],
        capture_output=True, text=True, cwd=ROOT, env=env, check=False,
    )
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"bench_query_cold: query failed (exit {proc.returncode}):\n{proc.stderr[-2000:]}")
    return wall, json.loads(proc.stdout)["regions"]


def same_answer(a: list[dict], b: list[dict]) -> bool:
    """Same regions in the same order, scores to 1e-3; where two regions of one label tie (gt
    maps give every region of a category the same embedding), either may rank first: the text
    encoders differ by ~1e-7, which decides such ties."""
    return len(a) == len(b) and all(
        abs(x["score"] - y["score"]) <= 1e-3 and (x["key"] == y["key"] or x["label"] == y["label"])
        for x, y in zip(a, b, strict=True)
    )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    size = parser.add_mutually_exclusive_group()
    size.add_argument("--quick", action="store_true", help="40-frame map, 3 runs")
    size.add_argument("--full", action="store_true", help="120-frame map (the default run), 5 runs (default)")
    parser.add_argument("--map-dir", type=Path, help="use this saved map instead of building one")
    parser.add_argument("--runs", type=int, default=None, help="timed runs per variant (default 5; 3 with --quick)")
    parser.add_argument("--text", default="chair", help="query text (default chair)")
    args = parser.parse_args()
    runs = args.runs or (3 if args.quick else 5)
    frames = 40 if args.quick else 120

    from openfusion.mapping.mapfile import load_map_summary, resolve_map_path
    from openfusion.testing.maps import strip_region_summaries

    with tempfile.TemporaryDirectory(prefix="bench-query-cold-") as tmp_name:
        tmp = Path(tmp_name)
        map_dir = args.map_dir if args.map_dir is not None else build_room_map(tmp / "run", frames)
        if load_map_summary(map_dir) is None:
            raise SystemExit(f"bench_query_cold: {map_dir} has no region summaries: save it again first")
        old_dir = strip_region_summaries(map_dir, tmp / "old-format").parent
        cache = tmp / "cache"

        t0 = time.perf_counter()
        _, first_answer = run_query(map_dir, _env(cache), args.text)
        first_use_s = time.perf_counter() - t0

        variants = [
            ("legacy: whole map + sentence-transformers", map_dir, _env(cache, OPENFUSION_QUERY_LEGACY="1")),
            ("old-format map: whole map + onnxruntime", old_dir, _env(cache)),
            ("summaries + onnxruntime (new)", map_dir, _env(cache)),
        ]
        rows, answers = [], {}
        for name, folder, env in variants:
            run_query(folder, env, args.text)  # untimed: file cache warm, as for every variant
            times = []
            for _ in range(runs):
                wall, regions = run_query(folder, env, args.text)
                times.append(wall)
            answers[name] = regions
            rows.append((name, min(times), statistics.median(times), max(times)))
            print(f"[bench_query_cold] {name}: median {statistics.median(times):.2f} s", file=sys.stderr)

        size_mb = resolve_map_path(map_dir).stat().st_size / 1e6
        legacy_median = rows[0][2]
        print(f"### Cold `openfusion query --map-dir DIR {args.text}` (fresh process per run)")
        print()
        print(f"Map: {size_mb:.0f} MB ({'given' if args.map_dir else f'built-in room, {frames} frames'}); "
              f"{runs} timed runs per variant after one warm-up run; {os.cpu_count()} CPU(s).")
        print()
        print("| variant | min (s) | median (s) | max (s) | speed-up vs legacy (median) |")
        print("|---|---|---|---|---|")
        for name, lo, med, hi in rows:
            print(f"| {name} | {lo:.2f} | {med:.2f} | {hi:.2f} | {legacy_median / med:.1f}x |")
        print()
        print(f"First use into an empty cache (exports MiniLM to ONNX with torch, once): {first_use_s:.1f} s.")
        new_median = rows[-1][2]
        print(f"Goal: new path median <= {GOAL_S:.0f} s: **{'met' if new_median <= GOAL_S else 'NOT met'}** "
              f"({new_median:.2f} s).")
        agree = all(same_answer(first_answer, a) for a in answers.values())
        print(f"Answers of all variants agree: {'yes' if agree else '**NO**'} "
              f"(top keys {[r['key'] for r in first_answer]}).")
    return 0 if agree else 1


if __name__ == "__main__":
    sys.exit(main())
