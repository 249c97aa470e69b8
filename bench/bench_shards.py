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

A second table (in this process, no bus): the same frames into one volume and into the shards'
volumes (``VolumeParams.shard``), CPU time of ``integrate`` per frame, blocks (own + ghosts), and how
close the composited render of the shards is to the single volume's (share of pixels with depth
within one voxel and the same region key, frames' instances as keys), with the single volume's own
spread under a 1 mm camera shift as the floor of what a render can agree on.

    .venv/bin/python bench/bench_shards.py --quick    # 60 frames at 320x240 and 640x480, 1 and 2 shards
    .venv/bin/python bench/bench_shards.py --full     # 150 frames, 1, 2 and 3 shards (also the default)
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


def _in_process(shards: int, width: int, height: int, frames: int) -> dict[str, object]:
    """Volumes of ``shards`` shards in this process (module docstring, second table)."""
    import numpy as np

    from openfusion.frame import resize_nearest
    from openfusion.mapping import SemanticVolume, VolumeParams
    from openfusion.sources import open_source

    source = list(open_source(f"synthetic:seed=1,width={width},height={height},frames={frames}"))
    K = source[0].intrinsics.scaled(160, 120)
    cpu, vols = [], []
    for i in range(shards):
        vol = SemanticVolume(VolumeParams(shard=f"{i}/{shards}"))
        spent = 0.0
        for n, f in enumerate(source):
            t = time.process_time()
            vol.integrate(f)
            if n >= 5:  # warm: the grid grown, Open3D's buffers made
                spent += time.process_time() - t
            if n % 3 == 0:
                keys = resize_nearest(f.instance, (120, 160)).astype(np.int32) - 1
                vol.apply_update(f.T_world_cam, K, keys, np.full((120, 160), 0.8, np.float32), observed_depth_m=f.depth_m())
        cpu.append(1000 * spent / max(len(source) - 5, 1))
        vols.append(vol)
    out: dict[str, object] = {"shards": shards, "size": f"{width}x{height}", "cpu_ms": cpu,
                              "blocks": [v.num_blocks for v in vols]}
    if shards > 1:
        out["vols"] = vols
    else:
        out["vol"] = vols[0]
    return out


def _agreement(single: object, parts: list, frames: list, voxel_m: float) -> tuple[float, float, float]:
    import numpy as np

    from openfusion.mapping.shards import composite_renders

    K = frames[0].intrinsics.scaled(160, 120)
    depth_ok = keys_ok = floor_ok = pixels = floor_px = 0
    for f in frames[1::7]:
        ref = single.render(f.T_world_cam, K)  # type: ignore[attr-defined]
        views = [p.render(f.T_world_cam, K) for p in parts]
        keys, _, depth = composite_renders([(v.key_map, v.conf_map, v.depth_m) for v in views])
        seen = (ref.depth_m > 0) | (depth > 0)
        pixels += int(seen.sum())
        depth_ok += int((np.abs(depth - ref.depth_m)[seen] <= voxel_m).sum())
        keys_ok += int((keys == ref.key_map)[seen].sum())
        moved = f.T_world_cam.copy()
        moved[:3, 3] += 0.001
        again = single.render(moved, K).depth_m  # type: ignore[attr-defined]
        both = (ref.depth_m > 0) | (again > 0)
        floor_px += int(both.sum())
        floor_ok += int((np.abs(again - ref.depth_m)[both] <= voxel_m).sum())
    return depth_ok / pixels, keys_ok / pixels, floor_ok / floor_px


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    size = parser.add_mutually_exclusive_group()
    size.add_argument("--quick", action="store_true", help="60 frames, 1 and 2 shards")
    size.add_argument("--full", action="store_true", help="150 frames, 1, 2 and 3 shards (the default)")
    parser.add_argument("--frames", type=int, default=None)
    parser.add_argument("--shards", default=None, help="comma-separated shard counts (default 1,2,3; quick 1,2)")
    parser.add_argument("--sizes", default="320x240,640x480")
    parser.add_argument("--no-in-process", action="store_true", help="only the services table")
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
    if args.no_in_process:
        return 0
    from openfusion.sources import open_source

    print(f"\nin this process: the same {frames} frames into one volume and into the shards' volumes")
    print(f"{'size':>8} {'shards':>6} {'integrate CPU ms/frame':>26} {'max':>6} {'ratio':>6} {'blocks (own+ghosts)':>22} "
          f"{'render depth ok':>15} {'keys ok':>8} {'1 mm floor':>10}")
    for width, height in sizes:
        single = _in_process(1, width, height, frames)
        base = single["cpu_ms"][0]  # type: ignore[index]
        print(f"{single['size']:>8} {1:>6} {base:26.1f} {base:6.1f} {1.0:6.2f} {single['blocks'][0]:>22d}")  # type: ignore[index]
        source = list(open_source(f"synthetic:seed=1,width={width},height={height},frames={frames}"))
        for n in [c for c in counts if c > 1]:
            r = _in_process(n, width, height, frames)
            cpu = r["cpu_ms"]
            d, k, fl = _agreement(single["vol"], r["vols"], source, 0.02)  # type: ignore[arg-type]
            print(f"{r['size']:>8} {n:>6} {' '.join(f'{c:5.1f}' for c in cpu):>26} {max(cpu):6.1f} "  # type: ignore[union-attr]
                  f"{max(cpu) / base:6.2f} {' '.join(str(b) for b in r['blocks']):>22} "  # type: ignore[union-attr, type-var]
                  f"{d:15.4f} {k:8.4f} {fl:10.4f}")
    print("\nrender: share of pixels (either render has a surface) whose composited depth is within one voxel "
          "of one volume's / whose key is the same; 1 mm floor: one volume against itself moved 1 mm")
    return 0


if __name__ == "__main__":
    sys.exit(main())
