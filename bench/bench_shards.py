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
target is <= 0.6 at 2 shards. A row per image size and shard count. ``--with-semantic`` starts the
default semantic service too (gt encoder, coverage selection): its render of every candidate frame
it scores, and of every frame it encodes, asks every shard, so the geometry processes' CPU then
includes the renders they answer (the last column: renders per frame, scoring / encoded).

A second table (in this process, no bus): the same frames into one volume and into the shards'
volumes (``VolumeParams.shard``), CPU time of ``integrate`` per frame, blocks (own + ghosts), and how
close the composited render of the shards is to the single volume's (share of pixels with depth
within one voxel and the same region key, frames' instances as keys), with the single volume's own
spread under a 1 mm camera shift as the floor of what a render can agree on.

A third table (``--phases``, in this process): where a frame's CPU goes in one geometry and in each
shard, phase by phase (process CPU time around each step of ``SemanticVolume.integrate``: the frame's
wire decode, its Open3D images, Open3D's touched-block pass over the whole frame, the shard's split
into own blocks + ghosts and its record of the others', Open3D's ``integrate``, the rest): the part
that does not shrink with the share of blocks is what keeps a shard above half of one geometry.

A fourth table (``--ownership``, no integration): Open3D's touched blocks of every frame split by
ownership schemes (the tile hash that runs, tile columns, stripes along x at several tile sizes;
slabs along x and districts, which keep space together) on the room or (``--ownership-scene
building``) the building's walk: the slowest shard's share of the blocks one geometry integrates
(own + ghosts), ghosts per own block, and the share of frames that touch each shard at all. It is
why the hash of 8-block tiles stays (docs/SHARDS.md).

A fifth table (``--seam-ghosts``, in this process): Open3D's ``integrate`` CPU per frame of each shard
of 2 with whole ghost blocks (what runs), with its own blocks only, and with the ghosts cut to the
seam (the cells of a ghost block that touch the shard's own blocks, in a second Open3D grid of 1- or
2-voxel blocks, or in numpy: Open3D's integrate kernel written out for the first 1 or 2 voxel layers of
each ghost block that face the shard's own blocks, ``bench_shard_seams.py``), and whether the seam's
voxels equal the whole ghost blocks' (docs/SHARDS.md, "What would close it").

    .venv/bin/python bench/bench_shards.py --quick    # 60 frames at 320x240 and 640x480, 1 and 2 shards
    .venv/bin/python bench/bench_shards.py --full     # 150 frames, 1, 2 and 3 shards (also the default)
    .venv/bin/python bench/bench_shards.py --quick --phases --ownership --no-services --no-in-process
    .venv/bin/python bench/bench_shards.py --sizes 320x240 --ownership --ownership-scene building --no-services --no-in-process
    .venv/bin/python bench/bench_shards.py --quick --sizes 640x480 --seam-ghosts --no-services --no-in-process
    .venv/bin/python bench/bench_shards.py --quick --sizes 640x480 --with-semantic --no-in-process
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from shard_frames import frame_inputs  # this folder is on the path when a bench runs as a script

ROOT = Path(__file__).resolve().parents[1]


def _run_one(shards: int, width: int, height: int, frames: int, log_dir: Path, *,
             semantic: bool = False) -> dict[str, object]:
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
    from openfusion.wire.counters import BridgeCounter, GeometryCounter, SemanticCounter
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
        if semantic:  # the default semantic service (gt encoder, coverage): its scoring renders ask every shard
            log = (log_dir / f"semantic-{shards}-{width}.log").open("wb")
            procs.append(subprocess.Popen(
                [sys.executable, "-m", "openfusion.app.cli", "service", "semantic", *loopback_args(map_id, connect=[port])],
                stdout=log, stderr=subprocess.STDOUT, cwd=ROOT, env=env))
        keys = ServiceConfig(map_id=map_id).keys
        wait_for_services(router, map_id, [*names, *(["semantic"] if semantic else [])], timeout_s=120)
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
        sem = stats.get("semantic")
        scored = sem.counter(SemanticCounter.FRAMES_SCORED) if sem is not None else 0.0
        encoded = sem.counter(SemanticCounter.SEMANTIC_FRAMES) if sem is not None else 0.0
        return {"shards": shards, "size": f"{width}x{height}", "cpu_ms": [1000 * c / frames for c in cpu],
                "busy_ms": [1000 * b / frames for b in busy], "blocks": blocks, "fps": frames / wall,
                "scored": scored / frames, "encoded": encoded / frames}
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


def _services_table(sizes: list[tuple[int, int]], counts: list[int], frames: int, repeat: int, *,
                    semantic: bool = False) -> None:
    """The services table (module docstring): every row ``repeat`` times, each run's ratio against
    one geometry's CPU in the same run; ``semantic``: with a semantic service mapping too."""
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-shards-") as tmp:
        for run in range(repeat):
            for width, height in sizes:
                for n in counts:
                    rows.append({**_run_one(n, width, height, frames, Path(tmp), semantic=semantic), "run": run})
                    print(f"  done: {n} shard(s) at {width}x{height} (run {run + 1})", file=sys.stderr)
    print(f"\ngeometry shards, {frames} frames of the synthetic room, playback as fast as the shards take it"
          + (", a semantic service mapping too (its renders per frame: scoring / encoded)" if semantic else ""))
    print(f"{'size':>8} {'run':>3} {'shards':>6} {'CPU ms/frame per shard':>28} {'max':>7} {'ratio':>6} "
          f"{'integrate ms/frame':>22} {'blocks per shard':>22} {'fps':>6}")
    base: dict[tuple[str, int], float] = {}
    for r in rows:
        cpu = r["cpu_ms"][: r["shards"]]  # type: ignore[index]
        worst = max(cpu)
        key = (r["size"], r["run"])
        if r["shards"] == 1:
            base[key] = worst  # type: ignore[index]
        ratio = worst / base[key] if key in base else float("nan")  # type: ignore[index]
        print(f"{r['size']:>8} {r['run'] + 1:>3} {r['shards']:>6} {' '.join(f'{c:6.1f}' for c in cpu):>28} "
              f"{worst:7.1f} {ratio:6.2f} {' '.join(f'{b:5.1f}' for b in r['busy_ms']):>22} "  # type: ignore[union-attr]
              f"{' '.join(f'{int(b):6d}' for b in r['blocks']):>22} {r['fps']:6.1f}"  # type: ignore[union-attr]
              + (f" {r['scored']:5.2f} / {r['encoded']:4.2f}" if semantic else ""))
    print("\nratio: the slowest shard's CPU per frame / one geometry's in the same run (target <= 0.6 at 2 shards)")


def _phases(shard_specs: list[str], width: int, height: int, frames: int) -> list[dict[str, float]]:
    """CPU ms per frame of each phase of a frame's integration (module docstring) in one volume per
    entry of ``shard_specs``, frames after the first 5 (the grid grown, Open3D's buffers made). The
    volumes take each frame in turn, so load from other work on the box falls on all of them alike."""
    from openfusion.mapping import SemanticVolume, VolumeParams, integration, shards
    from openfusion.sources import open_source
    from openfusion.wire import codec
    from openfusion.wire.schemas import RgbdFrame

    spent: dict[str, float] = {}

    def timed(label: str, fn):  # noqa: ANN001, ANN202
        def run(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
            t = time.process_time()
            try:
                return fn(*args, **kwargs)
            finally:
                spent[label] = spent.get(label, 0.0) + time.process_time() - t
        return run

    class Grid:  # Open3D's grid with its two kernels timed
        def __init__(self, vbg: object) -> None:
            self.vbg = vbg
            self.compute_unique_block_coordinates = timed("touched blocks (Open3D)", vbg.compute_unique_block_coordinates)
            self.integrate = timed("integrate (Open3D)", vbg.integrate)

        def __getattr__(self, name: str) -> object:
            return getattr(self.vbg, name)

    wire = [codec.encode(RgbdFrame.from_frame(f, with_instance=False))
            for f in open_source(f"synthetic:seed=1,width={width},height={height},frames={frames}")]
    saved = (integration.frame_images, shards.take_blocks, shards.OtherBlocks.add)
    integration.frame_images = timed("frame images", integration.frame_images)
    shards.take_blocks = timed("own blocks + ghosts", shards.take_blocks)
    shards.OtherBlocks.add = timed("others' blocks record", shards.OtherBlocks.add)
    vols = [SemanticVolume(VolumeParams(shard=spec)) for spec in shard_specs]
    sums: list[dict[str, float]] = [{} for _ in vols]
    try:
        for n, data in enumerate(wire):
            for vol, acc in zip(vols, sums, strict=True):
                spent.clear()
                t = time.process_time()
                frame = timed("wire decode", codec.decode)(data, expected=RgbdFrame).to_frame()
                vbg = vol._storage.vbg
                vol._storage.vbg = Grid(vbg)  # type: ignore[assignment]
                try:
                    vol.integrate(frame)
                finally:
                    if isinstance(vol._storage.vbg, Grid):
                        vol._storage.vbg = vbg
                total = time.process_time() - t
                if n >= 5:
                    for k, v in spent.items():
                        acc[k] = acc.get(k, 0.0) + v
                    acc["total"] = acc.get("total", 0.0) + total
    finally:
        integration.frame_images, shards.take_blocks, shards.OtherBlocks.add = saved
        for vol in vols:
            vol.close()
    out = []
    for acc in sums:
        ms = {k: 1000 * v / max(len(wire) - 5, 1) for k, v in acc.items()}
        ms["rest (Python: pager, counters, ...)"] = ms["total"] - sum(v for k, v in ms.items() if k != "total")
        out.append(ms)
    return out


def _print_phases(sizes: list[tuple[int, int]], counts: list[int], frames: int) -> None:
    for width, height in sizes:
        cols = [("one", "0/1")] + [(f"{i}/{n}", f"{i}/{n}") for n in counts if n > 1 for i in range(n)]
        runs = dict(zip([c[0] for c in cols], _phases([c[1] for c in cols], width, height, frames), strict=True))
        print(f"\nCPU ms per frame by phase, {width}x{height}, {frames} frames, in this process "
              "(shard columns: share of one geometry's)")
        labels = ["wire decode", "frame images", "touched blocks (Open3D)", "own blocks + ghosts",
                  "others' blocks record", "integrate (Open3D)", "rest (Python: pager, counters, ...)", "total"]
        print(f"{'phase':>36} " + " ".join(f"{name:>14}" for name, _ in cols))
        for label in labels:
            base = runs["one"].get(label, 0.0)
            cells = [f"{base:14.2f}"]
            for name, _ in cols[1:]:
                v = runs[name].get(label, 0.0)
                cells.append(f"{v:6.2f} ({v / base:4.2f})" if base > 0.05 else f"{v:14.2f}")
            print(f"{label:>36} " + " ".join(cells))


def _ownership(width: int, height: int, frames: int, scene: str = "room") -> None:
    """The ownership table (module docstring): Open3D's touched blocks of each frame, split. Besides
    the scattered schemes, two that keep space together (x slabs of 4 tiles, districts: the hash of
    columns of 4x4 tiles), so that a frame may leave a shard out altogether (``frames touching``:
    the share of frames with any block of the shard's, own or ghost; a shard could skip the rest)."""
    import numpy as np

    from openfusion.mapping import VolumeParams
    from openfusion.mapping.shards import _UPPER, _mix64
    from openfusion.mapping.tiles import pack_coords

    p = VolumeParams()
    touched = [coords for *_inputs, coords in frame_inputs(width, height, frames, scene)]
    total = sum(len(t) for t in touched)

    def owner(kind: str, tb: int, n: int):  # noqa: ANN202
        def of(blocks: np.ndarray) -> np.ndarray:
            units = np.floor_divide(blocks, tb)
            if kind == "x stripes":
                return np.mod(units[:, 0], n)
            if kind == "x slabs of 4":
                return np.mod(np.floor_divide(units[:, 0], 4), n)
            if kind in ("tile columns", "districts 4x4"):
                units = np.floor_divide(units, 4) if kind == "districts 4x4" else units.copy()
                units[:, 2] = 0
            return (_mix64(pack_coords(units).astype(np.uint64)) % np.uint64(n)).astype(np.int64)
        return of

    print(f"\nownership schemes: Open3D's touched blocks of {len(touched)} frames of the synthetic {scene} at "
          f"{width}x{height} ({total / len(touched):.0f} a frame), split; share = (own + ghosts) / one geometry's "
          "blocks; frames touching = share of frames with any block of the shard's")
    print(f"{'scheme':>14} {'tile blocks':>11} {'shards':>6} {'share per shard':>24} {'slowest':>8} {'ghosts/own':>18} "
          f"{'frames touching':>20}")
    for n in (2, 3):
        for kind in ("tile hash", "tile columns", "x stripes", "x slabs of 4", "districts 4x4"):
            for tb in (4, 8, 16) if kind in ("tile hash", "tile columns", "x stripes") else (p.tile_blocks,):
                of = owner(kind, tb, n)
                taken, own, frames_touching = np.zeros(n), np.zeros(n), np.zeros(n)
                for b in touched:
                    s = of(b)
                    below = [of(b - u) for u in _UPPER]
                    for i in range(n):
                        mine = s == i
                        ghost = ~mine & np.logical_or.reduce([x == i for x in below])
                        own[i] += mine.sum()
                        taken[i] += mine.sum() + ghost.sum()
                        frames_touching[i] += bool(mine.any() or ghost.any())
                share = taken / total
                marker = "  <- runs" if kind == "tile hash" and tb == p.tile_blocks else ""
                print(f"{kind:>14} {tb:>11} {n:>6} {' '.join(f'{x:.3f}' for x in share):>24} {share.max():8.3f} "
                      f"{' '.join(f'{x:.2f}' for x in (taken - own) / np.maximum(own, 1)):>18} "
                      f"{' '.join(f'{x:.2f}' for x in frames_touching / len(touched)):>20}{marker}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    size = parser.add_mutually_exclusive_group()
    size.add_argument("--quick", action="store_true", help="60 frames, 1 and 2 shards")
    size.add_argument("--full", action="store_true", help="150 frames, 1, 2 and 3 shards (the default)")
    parser.add_argument("--frames", type=int, default=None)
    parser.add_argument("--shards", default=None, help="comma-separated shard counts (default 1,2,3; quick 1,2)")
    parser.add_argument("--sizes", default="320x240,640x480")
    parser.add_argument("--no-in-process", action="store_true", help="no in-process volumes table")
    parser.add_argument("--no-services", action="store_true", help="no services table")
    parser.add_argument("--phases", action="store_true", help="CPU per frame by phase (in this process)")
    parser.add_argument("--ownership", action="store_true", help="ownership schemes' shares of the blocks")
    parser.add_argument("--ownership-scene", choices=("room", "building"), default="room",
                        help="--ownership: the synthetic room or the building's walk")
    parser.add_argument("--seam-ghosts", action="store_true", help="whole ghost blocks against ghosts cut to the seam")
    parser.add_argument("--repeat", type=int, default=1, help="services table: runs of every row (the spread)")
    parser.add_argument("--with-semantic", action="store_true",
                        help="services table: a semantic service maps too (its renders ask every shard)")
    args = parser.parse_args(argv)
    frames = args.frames or (60 if args.quick else 150)
    counts = [int(x) for x in (args.shards or ("1,2" if args.quick else "1,2,3")).split(",")]
    sizes = [tuple(int(v) for v in s.split("x")) for s in args.sizes.split(",")]
    if not args.no_services:
        _services_table(sizes, counts, frames, args.repeat, semantic=args.with_semantic)
    if args.phases:
        _print_phases(sizes, counts, frames)
    if args.ownership:
        _ownership(*sizes[-1], frames, args.ownership_scene)
    if args.seam_ghosts:
        from bench_shard_seams import seam_ghosts  # this folder is on the path when a bench runs as a script

        seam_ghosts(*sizes[-1], frames)
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
