#!/usr/bin/env python3
"""A replica's copy of its peer's checkpoint (docs/SHARDS.md, "Replicas"), against what it would
cost without one: a walk through the synthetic building mapped into a geometry service's checkpoint
(the run's default volume parameters), then a replica's copy of it over Zenoh on loopback (a router
and two client sessions in this process: the peer's snapshot, the chunks with their digests, the
copy checked as a map), and the copied checkpoint loaded as the replica loads it. Baselines
measured in the same run:

- **replay**: integrating the same frames again (what a replica with no copy must redo, from a
  recording; impossible for a live source), process CPU time of ``integrate``;
- **local copy**: ``TileStore.copy_to`` of the same store on the same disk (the peer's snapshot
  alone, the floor of any copy of the files).

A row per building size: how the map on disk, the copy and the replay grow.

    .venv/bin/python bench/bench_peer_copy.py --quick    # 1, 2 and 4 rooms, 15 frames per room at 160x120
    .venv/bin/python bench/bench_peer_copy.py --full     # 2, 4 and 8 rooms, 30 frames per room at 320x240
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

from openfusion.bus import open_session
from openfusion.config import ServiceConfig, ZenohSettings
from openfusion.mapping import RegionDictionary, SemanticVolume, VolumeParams, load_map
from openfusion.mapping.mapstore import checkpoint
from openfusion.mapping.tilestore import STORE_DIR_NAME, TileStore
from openfusion.services.geometry.peer_copy import copy_checkpoint
from openfusion.services.geometry.service import GeometryConfig, GeometrySection, GeometryService
from openfusion.sources import open_source
from openfusion.testing.bus import ServiceThread, free_port, unique_map_id
from openfusion.wire.keys import ShardId


def _build(spec: str, folder: Path) -> tuple[int, float, int]:
    """Map ``spec`` into a checkpoint at ``folder``; (frames, CPU s of integrate, tiles)."""
    volume = SemanticVolume(VolumeParams(), store=TileStore(folder / STORE_DIR_NAME))
    busy = 0.0
    frames = 0
    last = -1
    for frame in open_source(spec):
        t0 = time.process_time()
        volume.integrate(frame)
        busy += time.process_time() - t0
        frames += 1
        last = frame.frame_id
    info = checkpoint(volume, RegionDictionary("none", 1), {"last_frame_id": last, "frames_integrated": frames})
    volume.close()
    return frames, busy, int(info["tiles"])


def _row(rooms: int, frames_per_room: int, width: int, height: int, runs: int, tmp: Path) -> dict[str, float]:
    spec = f"synthetic:building,rooms={rooms},frames={rooms * frames_per_room},width={width},height={height}"
    print(f"# {rooms} rooms: {spec}", file=sys.stderr, flush=True)
    map_id = unique_map_id("bench-peer-copy")
    peer_dir = tmp / f"peer-{rooms}"
    frames, replay_s, tiles = _build(spec, peer_dir / map_id)
    store_mb = (peer_dir / map_id / STORE_DIR_NAME / "data.mdb").stat().st_size / 1e6
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    client = {"map_id": map_id, "zenoh": ZenohSettings(mode="client", multicast_scouting=False, connect=[endpoint])}
    router = open_session(ServiceConfig(map_id=map_id, zenoh=ZenohSettings(mode="router", multicast_scouting=False,
                                                                           listen=[endpoint])))
    peer = GeometryService(GeometryConfig(**client, geometry=GeometrySection(map_dir=peer_dir, checkpoint_period_s=0)))
    session = open_session(ServiceConfig(**client))
    local_s: list[float] = []
    copy_s: list[float] = []
    load_s: list[float] = []
    copied_mb = 0.0
    try:
        with ServiceThread(peer, GeometryConfig(**client), "geometry"):
            for i in range(runs):
                t0 = time.perf_counter()
                with TileStore(peer_dir / map_id / STORE_DIR_NAME, readonly=True) as store:
                    store.copy_to(tmp / f"local-{rooms}-{i}" / STORE_DIR_NAME)
                local_s.append(time.perf_counter() - t0)
                shutil.rmtree(tmp / f"local-{rooms}-{i}")
                into = tmp / f"replica-{rooms}-{i}"
                t0 = time.perf_counter()
                result = copy_checkpoint(session, ServiceConfig(**client).keys, ShardId(), into,
                                         requester="bench", checkpoint_first=False)
                copy_s.append(time.perf_counter() - t0)
                copied_mb = result.bytes / 1e6
                t0 = time.perf_counter()
                loaded = load_map(into, writable=True)
                load_s.append(time.perf_counter() - t0)
                loaded.volume.close()
                shutil.rmtree(into)
    finally:
        peer.close()
        session.close()
        router.close()
    best = min
    return {"rooms": rooms, "frames": frames, "tiles": tiles, "store_mb": store_mb, "copied_mb": copied_mb,
            "replay_s": replay_s, "local_s": best(local_s), "copy_s": best(copy_s), "load_s": best(load_s)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    size = parser.add_mutually_exclusive_group()
    size.add_argument("--quick", action="store_true", help="1, 2 and 4 rooms, 15 frames per room at 160x120 (default)")
    size.add_argument("--full", action="store_true", help="2, 4 and 8 rooms, 30 frames per room at 320x240")
    parser.add_argument("--runs", type=int, default=3, help="copies per size (the fastest is reported)")
    args = parser.parse_args(argv)
    rooms, per_room, width, height = ((2, 4, 8), 30, 320, 240) if args.full else ((1, 2, 4), 15, 160, 120)
    with tempfile.TemporaryDirectory(prefix="bench-peer-copy-") as tmp:
        rows = [_row(r, per_room, width, height, args.runs, Path(tmp)) for r in rooms]
    print("\n## A replica's copy of its peer's checkpoint over Zenoh (loopback) against replaying the frames\n")
    print(f"synthetic building, {per_room} frames per room at {width}x{height}, default volume parameters; "
          f"best of {args.runs} copies; replay = CPU time of integrating the frames again\n")
    print("| rooms | frames | tiles | map on disk MB | local copy s | copy over Zenoh s | MB/s | load s | "
          "copy + load s | replay s | (copy + load) / replay | copy / local copy |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        total = r["copy_s"] + r["load_s"]
        print(f"| {r['rooms']} | {r['frames']} | {r['tiles']} | {r['copied_mb']:.1f} | {r['local_s']:.3f} | "
              f"{r['copy_s']:.3f} | {r['copied_mb'] / max(r['copy_s'], 1e-9):.0f} | {r['load_s']:.3f} | {total:.3f} | "
              f"{r['replay_s']:.2f} | {total / max(r['replay_s'], 1e-9):.3f} | "
              f"{r['copy_s'] / max(r['local_s'], 1e-9):.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
