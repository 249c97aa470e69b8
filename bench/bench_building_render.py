"""What a frame of the synthetic building costs to render, against the built-in room in the same run.

One row per world: the room (the baseline) and buildings of 2, 4, 10 (the default), 20 and 40
rooms (``--quick``: 2 and 10). For each: floor area, triangles, frames of its default walk, the
time to plan it (floor plan + walk) and to render its first frame (building its Embree scenes),
the resident memory the world adds to a fresh process (plan, walk, scenes, shading tables), and per 640x480
frame: the render (``world.render``: ray cast through the doorways in view + shading +
instances), the same render cast into the whole building at once (``render_whole``, the cost
without portals), and the whole frame a source hands out (plus depth noise and the instance
categories), each with its ratio to the room's. Frames are spread over each world's own walk (the
room: its lap); the worlds are timed interleaved frame by frame in CPU time, best of
``--repeats``, so load from other processes hits all alike.

    .venv/bin/python bench/bench_building_render.py --quick   # CI-sized (~1 min on 2 cores)
    .venv/bin/python bench/bench_building_render.py           # full size
"""

from __future__ import annotations

import argparse
import gc
import os
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path


def _rss_mb() -> float:
    """Resident memory of this process (Linux /proc), MiB."""
    pages = int(Path("/proc/self/statm").read_text().split()[1])
    return pages * os.sysconf("SC_PAGE_SIZE") / 2**20


def _world_rss_mb(rooms: int, seed: int) -> float:
    """Resident memory (MiB) a world adds to a fresh process: its plan, walk, scenes and shading
    tables after one 640x480 frame (rooms 0: the room). Run in a subprocess of its own."""
    out = subprocess.run([sys.executable, __file__, "--rss-of", str(rooms), "--seed", str(seed)],
                         capture_output=True, text=True, check=True)
    return float(out.stdout.strip())


def _print_rss_of(rooms: int, seed: int) -> None:
    from openfusion.sources.synthetic import (
        BuildingSource,
        SyntheticBuilding,
        SyntheticSource,
        SyntheticWorld,
    )

    gc.collect()
    before = _rss_mb()
    if rooms == 0:
        world = SyntheticWorld(seed)
        src = SyntheticSource(world, 1, 640, 480)
    else:
        world = SyntheticBuilding(seed, rooms=rooms)
        src = BuildingSource(world, None, 640, 480)
    src.frame_at(0)
    print(f"{_rss_mb() - before:.1f}")


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    size = parser.add_mutually_exclusive_group()
    size.add_argument("--quick", action="store_true", help="CI-sized run (buildings of 2 and 10 rooms)")
    size.add_argument("--full", action="store_true", help="full size (the default): 2, 4, 10, 20 and 40 rooms")
    parser.add_argument("--frames", type=int, default=None, help="frames per world (default 16, --quick 8)")
    parser.add_argument("--repeats", type=int, default=None, help="timed passes, best kept (default 3, --quick 2)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--rss-of", type=int, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.rss_of is not None:
        _print_rss_of(args.rss_of, args.seed)
        return
    frames = args.frames or (8 if args.quick else 16)
    repeats = args.repeats or (2 if args.quick else 3)
    sizes = (2, 10) if args.quick else (2, 4, 10, 20, 40)

    from openfusion.sources.synthetic import (
        BuildingSource,
        SyntheticBuilding,
        SyntheticSource,
        SyntheticWorld,
    )

    rows = []
    t0 = time.perf_counter()
    room = SyntheticWorld(args.seed)
    plan_s = time.perf_counter() - t0
    src = SyntheticSource(room, frames, 640, 480, frames_per_lap=frames)
    t0 = time.perf_counter()
    room.render(src.poses[0], src.intrinsics)  # builds the Embree scene
    first_s = time.perf_counter() - t0
    W, D, _ = room.room_size_m
    rows.append(["room", W * D, room, src, plan_s, first_s, _world_rss_mb(0, args.seed), len(room.camera_path(120))])
    for n in sizes:
        t0 = time.perf_counter()
        building = SyntheticBuilding(args.seed, rooms=n)
        natural = len(building.camera_path())
        plan_s = time.perf_counter() - t0
        src = BuildingSource(building, frames, 640, 480)
        t0 = time.perf_counter()
        building.render(src.poses[0], src.intrinsics)  # builds the cells' Embree scenes
        first_s = time.perf_counter() - t0
        rows.append([f"building, {n} rooms", building.floor_area_m2, building, src, plan_s, first_s,
                     _world_rss_mb(n, args.seed), natural])

    # Interleaved frame by frame (every world's frame i, then frame i + 1, ...), each the fastest of
    # the repeats, in CPU time of this process (all its threads): load from other processes on a
    # shared machine hits all worlds alike and is not counted as theirs.
    kinds = ("render", "whole", "frame")
    best = {(k, kind, i): float("inf") for k in range(len(rows)) for kind in kinds for i in range(frames)}
    for _ in range(repeats):
        for i in range(frames):
            for k, (_name, _area, world, src, *_rest) in enumerate(rows):
                timed = {"render": lambda w=world, s=src, i=i: w.render(s.poses[i], s.intrinsics),
                         "frame": lambda s=src, i=i: s.frame_at(i)}
                if k > 0:
                    timed["whole"] = lambda w=world, s=src, i=i: w.render_whole(s.poses[i], s.intrinsics)
                for kind, fn in timed.items():
                    t0 = time.process_time()
                    fn()
                    best[k, kind, i] = min(best[k, kind, i], time.process_time() - t0)

    def ms(k: int, kind: str) -> float:
        return sum(best[k, kind, i] for i in range(frames)) * 1e3 / frames

    print(f"## Synthetic building vs the room: cost per 640x480 frame (seed {args.seed}, {frames} frames "
          f"spread over each walk, interleaved, CPU time, fastest of {repeats})\n")
    print("| world | floor m² | triangles | walk frames | plan + walk s | first frame s | RSS + MiB "
          "| render ms | × room | render, whole building ms | × room | frame ms (noise, instances) | × room |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for k, (name, area, world, _src, plan_s, first_s, rss, natural) in enumerate(rows):
        tris = sum(len(p.triangles) for o in world.objects for p in o.parts)
        walk = f"{natural} (lap 120)" if k == 0 else f"{natural}"
        whole = " | " if k == 0 else f"{ms(k, 'whole'):.1f} | {ms(k, 'whole') / ms(0, 'render'):.2f}"
        print(f"| {name} | {area:.0f} | {tris:,} | {walk} | {plan_s:.2f} | {first_s:.2f} | {rss:.0f} | "
              f"{ms(k, 'render'):.1f} | {ms(k, 'render') / ms(0, 'render'):.2f} | {whole} | "
              f"{ms(k, 'frame'):.1f} | {ms(k, 'frame') / ms(0, 'frame'):.2f} |")
    print("\nrender: ray cast + shading + instances (the building: cast into the camera's room or corridor and on "
          "through doorways); render, whole building: the same render cast into all of the building's triangles "
          "at once (what it would cost without portals; the same pixels); frame: what the source hands out (render, depth noise, "
          "categories). walk frames: the default walk (every room once, then the first two again; a frame every "
          "0.3 m or 20°); the room's is the lap of `openfusion run`. first frame: building the Embree scene(s). RSS: "
          "what the world adds to a fresh process (plan, walk, scenes, shading tables) after its first frame.")


if __name__ == "__main__":
    main()
