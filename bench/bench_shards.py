#!/usr/bin/env python3
"""Geometry shards: process CPU time per frame of each geometry process, one geometry against 2
(and 3) shards, in one run (docs/SHARDS.md).

For each shard count N the bench starts N geometry processes (``openfusion service geometry
--shard I/N``, no checkpoints) and a bridge process playing the synthetic room as fast as the
shards take it (``--rate-hz 0``, flow control over every shard's acknowledgements), all peers of
a router this process opens on loopback. It reads each geometry process's CPU time (user + system,
``psutil``) once the shards are ready and again when every shard has taken every frame: the
difference over the frames is the process CPU time per frame of that shard (decoding the frame,
the touched blocks, integration of its own blocks and ghosts, acknowledgements: all of it). Also
its ``integrate_busy_s`` (time inside integration) per frame and its blocks. The ratio column is
the slowest shard's CPU per frame against one geometry's, measured in the same run; the issue's
target is <= 0.6 at 2 shards. A row per image size and shard count.

    .venv/bin/python bench/bench_shards.py --quick    # 60 frames at 320x240 and 640x480, 1 and 2 shards
    .venv/bin/python bench/bench_shards.py            # 150 frames, 1, 2 and 3 shards
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _run_one(shards: int, width: int, height: int, frames: int, log_dir: Path) -> dict[str, object]:
    import psutil

    from openfusion.bus import collect_health, open_session
    from openfusion.config import ServiceConfig, ZenohSettings
    from openfusion.testing.bus import (
        free_port,
        loopback_args,
        subprocess_env,
        unique_map_id,
        wait_for_services,
    )
    from openfusion.wire.counters import BridgeCounter, GeometryCounter
    from openfusion.wire.keys import ShardId

    map_id = unique_map_id("shards")
    port = free_port()
    router = open_session(ServiceConfig(map_id=map_id, zenoh=ZenohSettings(
        mode="router", listen=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)))
    env = subprocess_env(HF_HUB_OFFLINE="1")
    names = [s.service for s in ShardId.all(shards)]
    procs: list[subprocess.Popen[bytes]] = []
    try:
        for shard in ShardId.all(shards):
            cmd = [sys.executable, "-m", "openfusion.app.cli", "service", "geometry", *loopback_args(map_id, connect=[port])]
            if shard.sharded:
                cmd += ["--shard", str(shard)]
            log = (log_dir / f"{shard.service}-{shards}-{width}.log").open("wb")
            procs.append(subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, cwd=ROOT, env=env))
        keys = ServiceConfig(map_id=map_id).keys
        wait_for_services(router, map_id, names, timeout_s=120)
        cpu0 = [sum(psutil.Process(p.pid).cpu_times()[:2]) for p in procs]
        bridge_log = (log_dir / f"bridge-{shards}-{width}.log").open("wb")
        bridge = subprocess.Popen(
            [sys.executable, "-m", "openfusion.app.cli", "service", "bridge", *loopback_args(map_id, connect=[port]),
             "--source", f"synthetic:seed=1,width={width},height={height}", "--max-frames", str(frames),
             "--rate-hz", "0", "--geometry-shards", str(shards)],
            stdout=bridge_log, stderr=subprocess.STDOUT, cwd=ROOT, env=env)
        procs.append(bridge)
        started = time.monotonic()
        while True:
            stats = collect_health(router, keys, timeout_s=1.0)
            taken = [stats[n].counter(GeometryCounter.FRAMES_INTEGRATED) if n in stats else 0.0 for n in names]
            done = stats.get("bridge") is not None and stats["bridge"].counter(BridgeCounter.PLAYBACK_DONE) >= 1
            if done and min(taken) >= frames:
                break
            if time.monotonic() - started > 600:
                raise RuntimeError(f"{shards} shards: took {taken} of {frames} frames in 600 s")
            time.sleep(0.2)  # polling remote counters: there is no event to wait on from outside
        wall = time.monotonic() - started
        cpu = [sum(psutil.Process(p.pid).cpu_times()[:2]) - c0 for p, c0 in zip(procs, cpu0, strict=False)]
        busy = [stats[n].counter(GeometryCounter.INTEGRATE_BUSY_S) for n in names]
        blocks = [stats[n].counter(GeometryCounter.NUM_BLOCKS) for n in names]
        return {"shards": shards, "size": f"{width}x{height}", "cpu_ms": [1000 * c / frames for c in cpu],
                "busy_ms": [1000 * b / frames for b in busy], "blocks": blocks, "fps": frames / wall}
    finally:
        for p in procs:
            p.terminate()
        for p in procs:
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
        router.close()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="60 frames, 1 and 2 shards")
    parser.add_argument("--frames", type=int, default=None)
    parser.add_argument("--shards", default=None, help="comma-separated shard counts (default 1,2,3; quick 1,2)")
    parser.add_argument("--sizes", default="320x240,640x480")
    args = parser.parse_args(argv)
    frames = args.frames or (60 if args.quick else 150)
    counts = [int(x) for x in (args.shards or ("1,2" if args.quick else "1,2,3")).split(",")]
    sizes = [tuple(int(v) for v in s.split("x")) for s in args.sizes.split(",")]
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-shards-") as tmp:
        for width, height in sizes:
            for n in counts:
                rows.append(_run_one(n, width, height, frames, Path(tmp)))
                print(f"  done: {n} shard(s) at {width}x{height}", file=sys.stderr)
    print(f"\ngeometry shards, {frames} frames of the synthetic room, playback as fast as the shards take it")
    print(f"{'size':>8} {'shards':>6} {'CPU ms/frame per shard':>28} {'max':>7} {'ratio':>6} "
          f"{'integrate ms/frame':>22} {'blocks per shard':>22} {'fps':>6}")
    base: dict[str, float] = {}
    for r in rows:
        cpu = r["cpu_ms"][: r["shards"]]  # type: ignore[index]
        worst = max(cpu)
        if r["shards"] == 1:
            base[r["size"]] = worst  # type: ignore[index]
        ratio = worst / base[r["size"]] if r["size"] in base else float("nan")
        print(f"{r['size']:>8} {r['shards']:>6} {' '.join(f'{c:6.1f}' for c in cpu):>28} {worst:7.1f} {ratio:6.2f} "
              f"{' '.join(f'{b:5.1f}' for b in r['busy_ms']):>22} "  # type: ignore[union-attr]
              f"{' '.join(f'{int(b):6d}' for b in r['blocks']):>22} {r['fps']:6.1f}")  # type: ignore[union-attr]
    print("\nratio: the slowest shard's CPU per frame / one geometry's (target <= 0.6 at 2 shards)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
