#!/usr/bin/env python3
"""A building, not a room: geometry's memory, integration rate and checkpoint cost over a walk
through the synthetic building (``synthetic:building``, rooms along a corridor, rooms revisited at
the end), with and without a memory budget, in one run.

The walk is rendered once to disk; each configuration maps the same frames in its own process (so
resident memory is that process's alone, without the building's renderer), as the geometry
service does: ``SemanticVolume.integrate`` per frame (3D-Rec, geometry
only), an incremental checkpoint into the map's tile store every ``--checkpoint-every`` frames,
a final checkpoint with region summaries. The parent samples each child's resident set size
(RSS, psutil) every second and prints, per configuration:

- resident memory at 25 / 50 / 75 / 100 % of the run and its peak (MiB), and the share of the
  budget it stays within (the fixed overhead is the RSS beyond the budget: the process itself,
  Open3D, one frame's buffers);
- integration frames/s per quarter (median of the integrate calls in that quarter);
- periodic checkpoint time near 25 / 50 / 100 % of the run (seconds, and tiles written), and the
  final save's (a checkpoint with region summaries: a whole-map surface read-out);
- map on disk (MiB) and per m^2 of floor (the building's floor area, from the source);
- surface points of the whole map and of the revisited rooms, against the run without budget.

Rows per building size (``--rooms 4,10``) show how each grows. ``--devices CPU:0,CUDA:0`` adds
rows on Open3D's CUDA device (3D-Rec on the GPU; where CUDA exists). Ratios are against the
first configuration of the same size (no budget, CPU).

    .venv/bin/python bench/bench_building.py --quick     # 2 and 4 rooms at 160x120, budget 40 MiB (default)
    .venv/bin/python bench/bench_building.py --full      # 4 and 10 rooms at 320x240, budget 300 MiB
    .venv/bin/python bench/bench_building.py --rooms 10 --frames-per-room 60 --width 640 --height 480
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

import numpy as np

_CHILD_FLAG = "--child"


# ---------------------------------------------------------------------------- frames rendered once
def _render_frames(spec: str, folder: Path) -> int:
    """Render the walk once into ``folder`` (one ``.npz`` per frame): the children then hold only
    what geometry holds, not the building's renderer."""
    from openfusion.sources import open_source

    folder.mkdir(parents=True, exist_ok=True)
    n = 0
    for i, f in enumerate(open_source(spec)):
        np.savez(folder / f"{i:06d}.npz", depth=f.depth, color=f.color, K=f.intrinsics.K,
                 size=np.array([f.intrinsics.width_px, f.intrinsics.height_px]), T=f.T_world_cam,
                 scale=np.array(f.depth_scale), stamp=np.array(f.stamp_ns))
        n += 1
    return n


class _FramesOnDisk:
    def __init__(self, folder: Path) -> None:
        self.files = sorted(folder.glob("*.npz"))

    def __len__(self) -> int:
        return len(self.files)

    def __iter__(self):  # noqa: ANN204
        from openfusion.frame import CameraIntrinsics, Frame

        for i, path in enumerate(self.files):
            z = np.load(path)
            K = z["K"]
            w, h = (int(v) for v in z["size"])
            intr = CameraIntrinsics(fx=float(K[0, 0]), fy=float(K[1, 1]), cx=float(K[0, 2]), cy=float(K[1, 2]),
                                    width_px=w, height_px=h)
            yield Frame(frame_id=i, stamp_ns=int(z["stamp"]), color=z["color"], depth=z["depth"],
                        depth_scale=float(z["scale"]), intrinsics=intr, T_world_cam=z["T"])


# ---------------------------------------------------------------------------- child: one configuration
def _child(argv: list[str]) -> int:
    from openfusion.mapping import RegionDictionary, SemanticVolume, VolumeParams
    from openfusion.mapping.mapstore import checkpoint
    from openfusion.mapping.tilestore import TileStore

    frames_dir, budget_text, device, every, out_dir = argv
    budget = None if budget_text == "none" else float(budget_text)
    out = Path(out_dir)
    volume = SemanticVolume(VolumeParams(memory_budget_mb=budget, device=device), store=TileStore(out / "map.ofz"))
    dictionary = RegionDictionary("none", 1)
    source = _FramesOnDisk(Path(frames_dir))
    n = len(source)

    def emit(**record: object) -> None:
        print(json.dumps(record), flush=True)

    emit(event="start", frames=n, t=time.monotonic())
    settled = 0  # the change clock at the checkpoint before the last: tiles unchanged since have settled
    for i, frame in enumerate(source):
        t0 = time.perf_counter()
        volume.integrate(frame)
        dt = time.perf_counter() - t0
        emit(event="frame", i=i, integrate_s=dt, t=time.monotonic(), resident_blocks=volume.num_blocks,
             blocks=volume.num_blocks_total)
        if (i + 1) % int(every) == 0:
            t0 = time.perf_counter()
            info = checkpoint(volume, dictionary, {"frames": i + 1})
            emit(event="checkpoint", i=i, seconds=time.perf_counter() - t0, tiles=info["tiles"], bytes=info["bytes"],
                 slices=info["slices"])
            # The geometry service's idle work: region-summary parts of the tiles that settled.
            t0 = time.perf_counter()
            tiles = volume.refresh_region_table(settled_clock=settled)
            emit(event="idle_readout", i=i, seconds=time.perf_counter() - t0, tiles=tiles)
            settled = volume.change_clock
    read_before = volume.readout_stats["summary_tiles_read"]
    t0 = time.perf_counter()  # the final save: a checkpoint with region summaries (the tiles not read out yet)
    info = checkpoint(volume, dictionary, {"frames": n}, summary=True)
    emit(event="final", seconds=time.perf_counter() - t0, tiles=info["tiles"],
         summary_tiles=volume.readout_stats["summary_tiles_read"] - read_before)
    store = volume.store
    assert store is not None
    store.copy_to(out / "copy" / "map.ofz")  # compacted copy: what a save elsewhere writes
    size = sum(f.stat().st_size for f in (out / "copy" / "map.ofz").iterdir())
    emit(event="done", map_bytes=size, paged_out=volume.pager.stats.tiles_paged_out,
         paged_in=volume.pager.stats.tiles_paged_in, blocks=volume.num_blocks_total, t=time.monotonic())
    volume.close()
    return 0


# ---------------------------------------------------------------------------- parent
def _anon_mib(pid: int) -> float:
    """RssAnon of a process (MiB): its own memory, without file pages mapped from the page cache
    (LMDB reads the store through a memory map; those pages are the OS's cache, dropped under
    pressure, and are counted in RSS but not here)."""
    with open(f"/proc/{pid}/status") as fh:
        for line in fh:
            if line.startswith("RssAnon:"):
                return int(line.split()[1]) / 1024
    return 0.0


def _sample_rss(proc: subprocess.Popen[str], samples: list[tuple[float, float, float]], stop: threading.Event) -> None:
    import psutil

    p = psutil.Process(proc.pid)
    while not stop.is_set():
        try:
            samples.append((time.monotonic(), p.memory_info().rss / 2**20, _anon_mib(proc.pid)))
        except (psutil.Error, OSError):
            return
        stop.wait(1.0)


def _run(frames_dir: Path, budget: str, device: str, every: int, work: Path) -> dict[str, object]:
    out = work / f"{budget}-{device.replace(':', '')}"
    out.mkdir(parents=True, exist_ok=True)
    proc = subprocess.Popen([sys.executable, __file__, _CHILD_FLAG, str(frames_dir), budget, device, str(every), str(out)],
                            stdout=subprocess.PIPE, text=True, env={**os.environ, "OPENFUSION_QUIET": "1"})
    samples: list[tuple[float, float]] = []
    stop = threading.Event()
    sampler = threading.Thread(target=_sample_rss, args=(proc, samples, stop), daemon=True)
    sampler.start()
    records = [json.loads(line) for line in proc.stdout or [] if line.startswith("{")]
    proc.wait()
    stop.set()
    sampler.join()
    if proc.returncode != 0:
        raise SystemExit(f"configuration {budget} {device} failed (exit {proc.returncode})")
    return {"budget": budget, "device": device, "records": records, "rss": samples, "out": out}


def _quarters(values: list[float]) -> list[float]:
    n = len(values)
    return [float(np.median(values[int(n * q / 4) : max(int(n * (q + 1) / 4), int(n * q / 4) + 1)])) for q in range(4)]


def _summarise(run: dict[str, object], floor_m2: float) -> dict[str, object]:
    records = run["records"]  # type: ignore[assignment]
    frames = [r for r in records if r["event"] == "frame"]  # type: ignore[index]
    ckpts = [r for r in records if r["event"] == "checkpoint"]  # type: ignore[index]
    done = next(r for r in records if r["event"] == "done")  # type: ignore[index]
    t0 = frames[0]["t"] - frames[0]["integrate_s"]
    t_end = frames[-1]["t"]
    rss = [(t, m, a) for t, m, a in run["rss"] if t >= t0]  # type: ignore[union-attr]

    def rss_at(q: float, col: int = 1) -> float:
        when = t0 + q * (t_end - t0)
        before = [s[col] for s in rss if s[0] <= when] or [rss[0][col]]
        return before[-1]

    during = [s for s in rss if s[0] <= t_end]  # the mapping itself, before the final save's read-out

    n = len(frames)

    def ckpt_at(q: float) -> tuple[float, int]:
        target = q * n
        best = min(ckpts, key=lambda c: abs(c["i"] + 1 - target))
        return float(best["seconds"]), int(best["tiles"])

    fps = [1.0 / f for f in _quarters([f["integrate_s"] for f in frames])]
    final = next((r for r in records if r["event"] == "final"), None)  # type: ignore[index]
    return {
        "budget": run["budget"], "device": run["device"], "frames": n,
        "rss_q": [rss_at(q) for q in (0.25, 0.5, 0.75, 1.0)], "rss_peak": max(s[1] for s in during),
        "anon_q": [rss_at(q, 2) for q in (0.25, 0.5, 0.75, 1.0)], "anon_peak": max(s[2] for s in during),
        "save_peak": max(s[1] for s in rss), "save_anon_peak": max(s[2] for s in rss),
        "idle_s": sum(float(r["seconds"]) for r in records if r["event"] == "idle_readout"),  # type: ignore[index]
        "fps_q": fps, "ckpt": [ckpt_at(q) for q in (0.25, 0.5, 1.0)],
        "final_s": float(final["seconds"]) if final else float("nan"),
        "final_summary_tiles": int(final.get("summary_tiles", 0)) if final else 0,
        "map_mb": done["map_bytes"] / 2**20, "mb_per_m2": done["map_bytes"] / 2**20 / floor_m2,
        "blocks": done["blocks"], "paged_out": done["paged_out"], "paged_in": done["paged_in"],
        "out": run["out"],
    }


def _surface(out: Path, rooms: list[dict[str, object]], budget: str) -> tuple[int, list[int]]:
    from openfusion.mapping import load_map

    loaded = load_map(out / "copy", memory_budget_mb=None if budget == "none" else float(budget))
    try:
        pts = loaded.volume.extract_points().points
    finally:
        loaded.volume.close()
    per_room = []
    for room in rooms:
        lo, hi = np.asarray(room["min"]), np.asarray(room["max"])
        per_room.append(int(((pts[:, :2] >= lo) & (pts[:, :2] <= hi)).all(axis=1).sum()))
    return len(pts), per_room


def _revisited_rooms(spec: str) -> tuple[float, list[dict[str, object]]]:
    from openfusion.sources import open_source

    source = open_source(spec)
    world = source.world  # type: ignore[attr-defined]
    meta = source.metadata() if callable(source.metadata) else source.metadata  # type: ignore[attr-defined]
    revisited = list(meta["visits"][len(meta["route"]):])
    rooms = []
    for k in revisited:
        x0, y0, x1, y1 = world.plan.rooms[k].rect_m
        rooms.append({"room": k, "min": [x0, y0], "max": [x1, y1]})
    return float(meta["floor_area_m2"]), rooms


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == _CHILD_FLAG:
        return _child(argv[1:])
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    size = parser.add_mutually_exclusive_group()
    size.add_argument("--quick", action="store_true",
                      help="2 and 4 rooms, 15 frames per room at 160x120, budgets none,40 (default; a few minutes)")
    size.add_argument("--full", action="store_true",
                      help="4 and 10 rooms, 30 frames per room at 320x240, budgets none,300 (README figures)")
    parser.add_argument("--rooms", default=None, help="building sizes, comma-separated (a row each)")
    parser.add_argument("--frames-per-room", type=int, default=None)
    parser.add_argument("--width", type=int, default=None)
    parser.add_argument("--height", type=int, default=None)
    parser.add_argument("--budgets", default=None, help="memory budgets in MiB ('none': no budget)")
    parser.add_argument("--devices", default="CPU:0", help="Open3D devices, e.g. CPU:0,CUDA:0")
    parser.add_argument("--checkpoint-every", type=int, default=25, help="frames between checkpoints")
    args = parser.parse_args(argv)
    preset = (("4,10", 30, 320, 240, "none,300") if args.full else ("2,4", 15, 160, 120, "none,40"))
    for name, value in zip(("rooms", "frames_per_room", "width", "height", "budgets"), preset, strict=True):
        if getattr(args, name) is None:
            setattr(args, name, value)
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-building-") as tmp:
        for rooms in [int(r) for r in args.rooms.split(",")]:
            frames = rooms * args.frames_per_room
            spec = f"synthetic:building,rooms={rooms},frames={frames},width={args.width},height={args.height}"
            floor_m2, revisited = _revisited_rooms(spec)
            frames_dir = Path(tmp) / f"frames-{rooms}"
            _render_frames(spec, frames_dir)
            base_points: tuple[int, list[int]] | None = None
            for device in args.devices.split(","):
                for budget in args.budgets.split(","):
                    print(f"# {rooms} rooms ({floor_m2:.0f} m^2, {frames} frames), budget {budget}, {device} ...",
                          file=sys.stderr, flush=True)
                    run = _run(frames_dir, budget, device, args.checkpoint_every, Path(tmp) / f"r{rooms}")
                    row = _summarise(run, floor_m2)
                    row.update(rooms=rooms, floor_m2=floor_m2)
                    row["points"], row["room_points"] = _surface(row["out"], revisited, budget)  # type: ignore[arg-type]
                    if base_points is None:
                        base_points = (row["points"], row["room_points"])  # type: ignore[assignment]
                    row["points_ratio"] = row["points"] / max(base_points[0], 1)  # type: ignore[operator]
                    row["room_ratio"] = [a / max(b, 1) for a, b in zip(row["room_points"], base_points[1], strict=True)]  # type: ignore[arg-type]
                    rows.append(row)
    _print(rows)
    return 0


def _print(rows: list[dict[str, object]]) -> None:
    print("\n## Memory while mapping (MiB at 25/50/75/100 % of the frames and peak: RSS, and RssAnon = RSS without "
          "the store's memory-mapped file pages) and integration (frames/s per quarter)\n")
    print("| rooms | floor m^2 | frames | budget MiB | device | RSS 25% | 50% | 75% | 100% | peak | anon 25% | 50% | 75% "
          "| 100% | peak | fps q1 | q2 | q3 | q4 | blocks | paged out / in |")
    print("|" + "---|" * 21)
    for r in rows:
        rq, aq, fq = r["rss_q"], r["anon_q"], r["fps_q"]
        print(f"| {r['rooms']} | {r['floor_m2']:.0f} | {r['frames']} | {r['budget']} | {r['device']} | "
              + " | ".join(f"{v:.0f}" for v in rq) + f" | {r['rss_peak']:.0f} | "  # type: ignore[union-attr]
              + " | ".join(f"{v:.0f}" for v in aq) + f" | {r['anon_peak']:.0f} | "  # type: ignore[union-attr]
              + " | ".join(f"{v:.1f}" for v in fq) + f" | {r['blocks']} | {r['paged_out']} / {r['paged_in']} |")  # type: ignore[union-attr]
    print("\n## The whole run (mapping and the final save): peak memory against the budget\n")
    print("| rooms | budget MiB | device | RSS peak | RssAnon peak | RssAnon peak - budget (the overhead) |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        over = "-" if r["budget"] == "none" else f"{r['save_anon_peak'] - float(r['budget']):.0f}"  # type: ignore[operator, arg-type]
        print(f"| {r['rooms']} | {r['budget']} | {r['device']} | {r['save_peak']:.0f} | {r['save_anon_peak']:.0f} | {over} |")
    print("\n## Checkpoints (seconds, tiles written) near 25 / 50 / 100 % of the run, map on disk, surface\n")
    print("| rooms | budget MiB | device | ckpt 25% | ckpt 50% | ckpt 100% | idle read-outs (sum) | final save (+summaries; tiles "
          "read then) | map MiB | MB per m^2 | surface points (ratio) | revisited rooms' points (ratio) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        c = r["ckpt"]
        rooms_txt = ", ".join(f"{p} ({q:.3f})" for p, q in zip(r["room_points"], r["room_ratio"], strict=True))  # type: ignore[arg-type]
        mb = float(r["map_mb"]) * 2**20 / 1e6 / float(r["floor_m2"])  # type: ignore[arg-type]
        print(f"| {r['rooms']} | {r['budget']} | {r['device']} | "
              + " | ".join(f"{s:.2f} s ({t})" for s, t in c)  # type: ignore[union-attr]
              + f" | {r['idle_s']:.1f} s | {r['final_s']:.1f} s ({r['final_summary_tiles']}) | {r['map_mb']:.1f} | {mb:.3f} | "
              f"{r['points']} ({r['points_ratio']:.4f}) | {rooms_txt} |")


if __name__ == "__main__":
    sys.exit(main())
