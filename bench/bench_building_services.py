#!/usr/bin/env python3
"""The synthetic building through the services (``openfusion run``: bridge, geometry, semantic with
the gt encoder, query), with and without a memory budget, in one run: geometry's resident memory
sampled every second from outside the process for the whole run (mapping, merge passes, region
summaries, periodic checkpoints, the final merge pass and save), the run's exit code and outputs.

For each budget it prints geometry's RSS and RssAnon (RSS without the tile store's memory-mapped
file pages, which are the kernel's page cache) at 25 / 50 / 75 / 100 % of geometry's life and the
peak, the peak against the budget (the overhead), the final save as the run reports it, and the
map on disk per m^2 of floor.

    .venv/bin/python bench/bench_building_services.py --quick   # 3 rooms, 90 frames at 160x120, budgets none,60
    .venv/bin/python bench/bench_building_services.py --full    # 10 rooms, 300 frames at 320x240, budgets none,300
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path


def _anon_mib(pid: int) -> float:
    with open(f"/proc/{pid}/status") as fh:
        for line in fh:
            if line.startswith("RssAnon:"):
                return int(line.split()[1]) / 1024
    return 0.0


def _geometry_of(run: object) -> object | None:
    import psutil

    try:
        for child in run.children(recursive=True):  # type: ignore[attr-defined]
            cmd = " ".join(child.cmdline())
            if " service geometry" in cmd or "service\x00geometry" in cmd:
                return child
    except psutil.Error:
        return None
    return None


def _sample(proc: subprocess.Popen[str], samples: list[tuple[float, float, float]], stop: threading.Event) -> None:
    """Every second: geometry's (time, RSS MiB, RssAnon MiB), from the moment it exists."""
    import psutil

    run = psutil.Process(proc.pid)
    geometry = None
    while not stop.is_set():
        if geometry is None:
            geometry = _geometry_of(run)
        if geometry is not None:
            try:
                samples.append((time.monotonic(), geometry.memory_info().rss / 2**20, _anon_mib(geometry.pid)))  # type: ignore[attr-defined]
            except (psutil.Error, OSError):
                geometry = None
        stop.wait(1.0)


def _one(args: argparse.Namespace, budget: str, out: Path) -> dict[str, object]:
    spec = f"synthetic:building,rooms={args.rooms},width={args.width},height={args.height}"
    cmd = [sys.executable, "-m", "openfusion.app.cli", "run", "--source", spec, "--frames", str(args.frames),
           "--rate-hz", "0", "--out", str(out), "--quiet", "--map", f"bench-{budget}-{os.getpid()}"]
    if budget != "none":
        cmd += ["--memory-budget-mb", budget]
    samples: list[tuple[float, float, float]] = []
    stop = threading.Event()
    started = time.monotonic()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "HF_HUB_OFFLINE": "1"})
    sampler = threading.Thread(target=_sample, args=(proc, samples, stop), daemon=True)
    sampler.start()
    stdout, stderr = proc.communicate()
    stop.set()
    sampler.join()
    wall = time.monotonic() - started
    summary = json.loads((out / "run.json").read_text()) if (out / "run.json").is_file() else {}
    store = out / "map" / "map.ofz"
    map_bytes = sum(f.stat().st_size for f in store.iterdir()) if store.is_dir() else 0
    return {"budget": budget, "exit": proc.returncode, "wall_s": wall, "samples": samples, "summary": summary,
            "map_bytes": map_bytes, "mesh": (out / "mesh.ply").is_file(), "stderr": stderr[-2000:], "stdout": stdout}


def _at(samples: list[tuple[float, float, float]], q: float, col: int) -> float:
    t0, t1 = samples[0][0], samples[-1][0]
    when = t0 + q * (t1 - t0)
    return [s[col] for s in samples if s[0] <= when][-1]


def _quarter_medians(samples: list[tuple[float, float, float]], col: int) -> list[float]:
    """The median of the samples in each quarter of geometry's life (the level a quarter holds,
    where one sample may catch a read-out's chunk or not)."""
    import statistics

    t0, t1 = samples[0][0], samples[-1][0]
    out = []
    for q in range(4):
        lo, hi = t0 + q / 4 * (t1 - t0), t0 + (q + 1) / 4 * (t1 - t0)
        vals = [s[col] for s in samples if lo <= s[0] <= hi]
        out.append(statistics.median(vals) if vals else float("nan"))
    return out


def main(argv: list[str] | None = None) -> int:
    from openfusion.sources import open_source

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    size = parser.add_mutually_exclusive_group()
    size.add_argument("--quick", action="store_true", help="3 rooms, 90 frames at 160x120, budgets none,60 (default)")
    size.add_argument("--full", action="store_true", help="10 rooms, 300 frames at 320x240, budgets none,300")
    parser.add_argument("--rooms", type=int, default=None)
    parser.add_argument("--frames", type=int, default=None)
    parser.add_argument("--width", type=int, default=None)
    parser.add_argument("--height", type=int, default=None)
    parser.add_argument("--budgets", default=None, help="memory budgets in MiB ('none': no budget)")
    args = parser.parse_args(argv)
    preset = (10, 300, 320, 240, "none,300") if args.full else (3, 90, 160, 120, "none,60")
    for name, value in zip(("rooms", "frames", "width", "height", "budgets"), preset, strict=True):
        if getattr(args, name) is None:
            setattr(args, name, value)
    source = open_source(f"synthetic:building,rooms={args.rooms},frames={args.frames},width={args.width},height={args.height}")
    meta = source.metadata() if callable(source.metadata) else source.metadata  # type: ignore[attr-defined]
    floor_m2 = float(meta["floor_area_m2"])
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-building-services-") as tmp:
        for budget in args.budgets.split(","):
            print(f"# openfusion run: {args.rooms} rooms ({floor_m2:.0f} m^2), {args.frames} frames at "
                  f"{args.width}x{args.height}, budget {budget} ...", file=sys.stderr, flush=True)
            rows.append(_one(args, budget, Path(tmp) / f"out-{budget}"))
    print(f"\n## Geometry's memory through the services: {args.rooms} rooms, {floor_m2:.0f} m^2, {args.frames} frames "
          f"at {args.width}x{args.height} (MiB, sampled every second for geometry's whole life)\n")
    print("| budget MiB | exit | RSS 25% | 50% | 75% | 100% | peak | RssAnon 25% | 50% | 75% | 100% | peak | "
          "RssAnon peak - budget | frames integrated | run wall s | map MiB | MB per m^2 | mesh.ply |")
    print("|" + "---|" * 18)
    for r in rows:
        s = r["samples"]
        summary = r["summary"]
        if not s:
            print(f"| {r['budget']} | {r['exit']} | no samples |" + " |" * 15)
            continue
        rss = [_at(s, q, 1) for q in (0.25, 0.5, 0.75, 1.0)]  # type: ignore[arg-type]
        anon = [_at(s, q, 2) for q in (0.25, 0.5, 0.75, 1.0)]  # type: ignore[arg-type]
        peak_rss, peak_anon = max(x[1] for x in s), max(x[2] for x in s)  # type: ignore[union-attr]
        over = "-" if r["budget"] == "none" else f"{peak_anon - float(r['budget']):.0f}"  # type: ignore[arg-type]
        frames = summary.get("frames_integrated", "?") if isinstance(summary, dict) else "?"
        mib = float(r["map_bytes"]) / 2**20  # type: ignore[arg-type]
        print(f"| {r['budget']} | {r['exit']} | " + " | ".join(f"{v:.0f}" for v in rss) + f" | {peak_rss:.0f} | "
              + " | ".join(f"{v:.0f}" for v in anon) + f" | {peak_anon:.0f} | {over} | {frames} | {r['wall_s']:.0f} | "
              f"{mib:.1f} | {float(r['map_bytes']) / 1e6 / floor_m2:.3f} | {'yes' if r['mesh'] else 'no'} |")
    print("\nRssAnon median per quarter of geometry's life (MiB; the last quarter includes its exit):\n")
    print("| budget MiB | q1 | q2 | q3 | q4 | q2-q4 max / q1 |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        s = r["samples"]
        if s:
            med = _quarter_medians(s, 2)  # type: ignore[arg-type]
            print(f"| {r['budget']} | " + " | ".join(f"{v:.0f}" for v in med) + f" | {max(med[1:]) / med[0]:.2f} |")
    for r in rows:
        if r["exit"] != 0:
            print(f"\nbudget {r['budget']}: exit {r['exit']}; stderr tail:\n{r['stderr']}")
    return 0 if all(r["exit"] == 0 for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
