#!/usr/bin/env python3
"""What a geometry checkpoint costs during ``openfusion run``: the built-in synthetic room mapped
in this process (geometry only, the run's default volume parameters), then ``save_map`` of it
into a new tile store (every tile), the whole-map version-1 file every checkpoint used to be (the
baseline), and incremental checkpoints into the map's own store with one frame integrated between
two (what geometry's periodic checkpoints are now), timed against the integration of one frame
measured in the same run.

A checkpoint holds geometry's lock while it copies the changed tiles; its cost per second is at
most ``checkpoint_s / checkpoint_period_s``; the table gives that share for a few periods, and the frames a
crash loses at most (the bridge replays them) at the run's frame rate.

    .venv/bin/python bench/bench_checkpoint.py --quick     # 40 frames, 320x240
    .venv/bin/python bench/bench_checkpoint.py --full      # the default run: 120 frames, 640x480
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

from openfusion.mapping import RegionDictionary, SemanticVolume, VolumeParams, save_map
from openfusion.mapping.mapstore import checkpoint
from openfusion.mapping.tilestore import TileStore
from openfusion.sources import open_source

PERIODS_S = (1.0, 2.0, 5.0, 10.0, 30.0)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    size = parser.add_mutually_exclusive_group()
    size.add_argument("--quick", action="store_true", help="40 frames at 320x240 (default)")
    size.add_argument("--full", action="store_true", help="120 frames at 640x480 (the default openfusion run)")
    parser.add_argument("--runs", type=int, default=3)
    args = parser.parse_args(argv)
    frames, width, height = (120, 640, 480) if args.full else (40, 320, 240)
    source = list(open_source(f"synthetic:seed=1,frames={frames},width={width},height={height}"))
    volume = SemanticVolume(VolumeParams())
    integrate_s = []
    for frame in source:
        t0 = time.perf_counter()
        volume.integrate(frame)
        integrate_s.append(time.perf_counter() - t0)
    per_frame_s = statistics.median(integrate_s[len(integrate_s) // 2:])  # warm frames
    dictionary = RegionDictionary("none", 1)
    saves: dict[bool, list[float]] = {True: [], False: []}
    v1_s: list[float] = []
    incr_s: list[float] = []
    incr_tiles: list[int] = []
    size_mb = v1_mb = 0.0
    frames_list = list(source)
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(args.runs):
            for summary in (True, False):  # interleaved: the same machine state for both
                t0 = time.perf_counter()
                path = save_map(Path(tmp) / "map", volume, dictionary, meta={"run": i, "last_frame_id": frames - 1},
                                summary=summary)
                saves[summary].append(time.perf_counter() - t0)
                if summary:
                    size_mb = sum(f.stat().st_size for f in path.iterdir()) / 1e6
            # The baseline: a whole-map version-1 file, as every checkpoint was written before.
            t0 = time.perf_counter()
            old = save_map(Path(tmp) / "v1" / "map.ofz.npz", volume, dictionary, meta={"run": i}, summary=False)
            v1_s.append(time.perf_counter() - t0)
            v1_mb = old.stat().st_size / 1e6
        # Incremental checkpoints into the map's own store: one frame integrated between two.
        own = SemanticVolume(VolumeParams(), store=TileStore(Path(tmp) / "own" / "map.ofz"))
        for frame in frames_list[: len(frames_list) // 2]:
            own.integrate(frame)
        checkpoint(own, dictionary, {"frames": len(frames_list) // 2})
        for frame in frames_list[len(frames_list) // 2 :][: args.runs * 3]:
            own.integrate(frame)
            t0 = time.perf_counter()
            incr_tiles.append(int(checkpoint(own, dictionary, {})["tiles"]))
            incr_s.append(time.perf_counter() - t0)
        own.close()
    full_s, save_s = statistics.median(saves[True]), statistics.median(saves[False])
    rate_fps = 1.0 / per_frame_s
    print(f"## Geometry checkpoint of the synthetic room ({frames} frames, {width}x{height}, "
          f"{volume.num_blocks} blocks, {size_mb:.1f} MB file)\n")
    print("| what | time | ratio to one frame's integration |")
    print("|---|---|---|")
    print(f"| integrate one frame (median of the warm half) | {per_frame_s * 1e3:.1f} ms | 1.0x |")
    print(f"| save_map with region summaries (control/save; median of {args.runs}) | {full_s * 1e3:.0f} ms | "
          f"{full_s / per_frame_s:.1f}x |")
    print(f"| save_map without, every tile into a new store (median of {args.runs}) | {save_s * 1e3:.0f} ms | "
          f"{save_s / per_frame_s:.1f}x |")
    print(f"| baseline: whole-map version-1 file ({v1_mb:.1f} MB; median of {args.runs}) | {statistics.median(v1_s) * 1e3:.0f}"
          f" ms | {statistics.median(v1_s) / per_frame_s:.1f}x |")
    inc = statistics.median(incr_s)
    print(f"| incremental checkpoint after one frame (a periodic one; median of {len(incr_s)}, "
          f"{statistics.median(incr_tiles):.0f} tiles) | {inc * 1e3:.0f} ms | {inc / per_frame_s:.1f}x |")
    print()
    save_s = inc  # what the periodic checkpoints cost now
    print("| checkpoint_period_s | share of geometry's time spent on periodic checkpoints | frames a crash loses "
          f"at most (replayed), at {rate_fps:.0f} fps |")
    print("|---|---|---|")
    for period in PERIODS_S:
        print(f"| {period:g} | {100 * save_s / (period + save_s):.1f} % | {int(period * rate_fps + 0.5)} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
