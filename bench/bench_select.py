#!/usr/bin/env python3
"""Coverage-driven frame selection: encoder calls and quality, before (every frame / the latest
frame) and after (``--select coverage``), each pair measured in the same run.

    python bench/bench_select.py --full --laps   # three 120-frame laps of the built-in room, in process
    python bench/bench_select.py --full --laps --select-also select_lookahead=3   # ... and a row with these
    python bench/bench_select.py --full --cost   # scoring cost per frame against a semantic step, per map size
    python bench/bench_select.py --full --render-growth   # a map render's cost as the map grows (building walk)
    python bench/bench_select.py --views-services 150   # the building's walk through the services: a
        # candidate rendered against probed on the large map (select_view render / auto), geometry's load
    python bench/bench_select.py --stops 0,30,90 --lap 120 [--stops-services]
        # a camera standing still 4 times a lap: its render reused or not (and through the services)
    python bench/bench_select.py --services [--repeat 2]
        # a 90-frame ScanNet-layout scene through `openfusion run` at its own rate (30 fps) with the gt
        # encoder and a fixed --encoder-delay-ms 150: latest (before) and coverage (after), with the
        # local encoder and with an encoder pool of 2 workers, against the in-process every-frame map
    python bench/bench_select.py --services --repeat 1 --run-set semantic.select_lookahead=3
        # ... every run with that --set (the look-ahead's in-process/services parity)
    python bench/bench_select.py --full       # all three
    python bench/bench_select.py [--quick]    # CI-sized: laps of 40 frames at 320x240 and their cost
    python bench/bench_eval.py --full --compare-select   # the three bench rooms, noise off and standard

Every map is scored the same way (:func:`openfusion.eval.saved_map.map_quality`: the ConceptFusion
protocol of ``openfusion eval``, unlabelled points count as misses). The services section prints
the machine's load average before and after each run: the services' timing depends on it.
Prints markdown tables; exit 0 unless it crashes.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from openfusion.encoders import make_region_encoder, make_text_encoder
from openfusion.eval.ground_truth import load_scannet_ground_truth, synthetic_ground_truth
from openfusion.eval.saved_map import map_quality
from openfusion.frame import resize_nearest
from openfusion.mapping import load_map
from openfusion.mapping.params import SelectParams, VolumeParams
from openfusion.mapping.pipeline import map_scene
from openfusion.sources import open_source

BUILTIN_LAP = 120  # openfusion run's lap of the built-in room (BUILTIN_LAP_FRAMES)


def _f(v: float | None, fmt: str = "{:.3f}") -> str:
    return "n/a" if v is None else fmt.format(v)


def _load() -> str:
    one, five, _ = os.getloadavg()
    return f"{one:.1f}/{five:.1f}"


# ----------------------------------------------------------------------------------- laps


def laps(laps_n: int, lap: int, width: int, height: int, also: list[SelectParams] = ()) -> None:
    """``laps_n`` laps of the built-in room in one process, every frame vs coverage (and a row per
    ``also``): encoder calls per lap and quality at the end, in one run."""
    spec = f"synthetic:lap={lap},frames={laps_n * lap},width={width},height={height}"
    text = make_text_encoder("minilm")
    encoder = make_region_encoder("gt", text_encoder=text)
    from openfusion.sources.synthetic import SyntheticWorld

    gt = synthetic_ground_truth(SyntheticWorld(0), spacing_m=0.03)
    print(f"### {laps_n} laps of the built-in room ({spec}, in process, gt encoder + minilm)")
    print()
    lap_cols = " | ".join(f"lap {i + 1} calls" for i in range(laps_n))
    print(f"| select | {lap_cols} | last lap / first | all calls | regions encoded | f-mIoU | mAcc | "
          "skipped (no gain) | scoring ms/frame | wall (s) |")
    print("|---|" + "---|" * (laps_n + 8))
    rows = [("every", SelectParams(select="every")), ("coverage", SelectParams())]
    for p in also:
        changed = {k: v for k, v in p.model_dump().items() if v != SelectParams.model_fields[k].default}
        rows.append(("coverage " + ", ".join(f"{k}={v}" for k, v in changed.items()), p))
    for name, params in rows:
        per_lap: list[int] = []

        def on_frame(frame, stats, per_lap=per_lap) -> None:  # noqa: ANN001
            if stats.frames_integrated % lap == 0:
                per_lap.append(stats.encoder_calls - sum(per_lap))

        t0 = time.perf_counter()
        r = map_scene(open_source(spec), region_encoder=encoder, volume_params=VolumeParams(),
                      select_params=params, on_frame=on_frame)
        wall = time.perf_counter() - t0
        q = map_quality(r.volume, r.dictionary, gt, text_encoder=text)
        s = r.stats
        if per_lap:  # a look-ahead run decided at the end of the source counts in the last lap
            per_lap[-1] += s.encoder_calls - sum(per_lap)
        ratio = per_lap[-1] / per_lap[0] if per_lap and per_lap[0] else None
        score_ms = 1e3 * s.select_s / s.frames_scored if s.frames_scored else None
        print(f"| {name} | {' | '.join(str(n) for n in per_lap)} | {_f(ratio, '{:.3f}')} | {s.encoder_calls} | "
              f"{s.encoder_regions} | {q['f_mIoU']:.4f} | {q['mAcc']:.4f} | {s.skipped_no_gain} | "
              f"{_f(score_ms, '{:.1f}')} | {wall:.0f} |", flush=True)
    print()


# ----------------------------------------------------------------------------------- still camera


def stops(lap: int, width: int, height: int, stop_lengths: list[int]) -> None:
    """One lap of the built-in room in one process where the camera stands still ``stop`` frames at
    the start and at each quarter of the lap (``synthetic:...,stop=N``, depth noise on): every
    candidate rendered (``select_still_s`` none: the baseline) against a still camera's candidates
    reusing its last render (the default), one row pair per stop length, measured in the same run."""
    text = make_text_encoder("minilm")
    encoder = make_region_encoder("gt", text_encoder=text)
    from openfusion.sources.synthetic import SyntheticWorld

    gt = synthetic_ground_truth(SyntheticWorld(0), spacing_m=0.03)
    print(f"### A camera that stands still (built-in room, {lap}-frame lap at {width}x{height} with stops of N "
          "frames at its start and quarters, in process, gt encoder + minilm)")
    print()
    print("| stop (frames) | frames | still camera's render | renders | reused | encoder calls | f-mIoU | "
          "scoring ms/frame | scoring s | scoring × every-render |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for stop in stop_lengths:
        frames = lap + 4 * stop
        spec = f"synthetic:lap={lap},frames={frames},width={width},height={height},stop={stop}"
        base_s = None
        for name, params in (("rendered every frame", SelectParams(select_still_s=None)), ("reused", SelectParams())):
            r = map_scene(open_source(spec), region_encoder=encoder, volume_params=VolumeParams(), select_params=params)
            q = map_quality(r.volume, r.dictionary, gt, text_encoder=text)
            st = r.stats
            base_s = st.select_s if base_s is None else base_s
            score_ms = 1e3 * st.select_s / st.frames_scored if st.frames_scored else None
            print(f"| {stop} | {frames} | {name} | {st.frames_scored - st.renders_reused} | {st.renders_reused} | "
                  f"{st.encoder_calls} | {q['f_mIoU']:.4f} | {_f(score_ms, '{:.1f}')} | {st.select_s:.2f} | "
                  f"{_f(st.select_s / base_s if base_s else None, '{:.2f}')} |", flush=True)
    print()


def stops_services(work: Path, lap: int, width: int, height: int, stop: int) -> None:
    """The same lap with stops through ``openfusion run`` (the services, at the source's 30 fps):
    every candidate rendered by geometry against a still camera's candidates reusing its last
    render, with each service's process CPU time, measured in the same run."""
    frames = lap + 4 * stop
    spec = f"synthetic:lap={lap},frames={frames},width={width},height={height},stop={stop}"
    print(f"### A camera that stands still, through the services (`openfusion run --source {spec}`, gt encoder)")
    print()
    print("| still camera's render | frames scored | reused | encoder calls | f-mIoU | geometry CPU s | semantic CPU s | "
          "geometry CPU × every-render | load before -> after |")
    print("|---|---|---|---|---|---|---|---|---|")
    from openfusion.sources.synthetic import SyntheticWorld

    text = make_text_encoder("minilm")
    gt = synthetic_ground_truth(SyntheticWorld(0), spacing_m=0.03)
    base = None
    for name, extra in (("rendered every frame", ["--set", "semantic.select_still_s="]), ("reused", [])):
        out = work / f"stops-{name.split()[0]}"
        summary, cpu, load = _run_sampling_cpu(out, ["--source", spec, "--frames", str(frames), *extra])
        base = cpu.get("geometry") if base is None else base
        geo = cpu.get("geometry")
        loaded = load_map(out / "map")
        q = map_quality(loaded.volume, loaded.dictionary, gt, text_encoder=text)
        print(f"| {name} | {summary['frames_scored']} | {summary['renders_reused']} | {summary['encoder_calls']} | "
              f"{q['f_mIoU']:.4f} | {_f(geo, '{:.1f}')} | {_f(cpu.get('semantic'), '{:.1f}')} | "
              f"{_f(geo / base if geo and base else None, '{:.2f}')} | {load} |", flush=True)
    print()


def views_services(work: Path, frames: int, width: int, height: int) -> None:
    """The synthetic building's walk through ``openfusion run`` (the services, at the source's 30
    fps, gt encoder): every candidate rendered by geometry (``select_view=render``) against the
    default (``auto``: probed once the map holds more than ``select_probe_blocks``), with geometry's
    view load from its health (ray casts and probes, their time) and each service's process CPU
    time, in the same run."""
    from openfusion.sources.synthetic.building import SyntheticBuilding

    spec = f"synthetic:building,frames={frames},width={width},height={height}"
    print(f"### A candidate's view on a growing map, through the services (`openfusion run --source {spec}`, "
          "gt encoder)")
    print()
    print("| select_view | frames scored | encoder calls | f-mIoU | blocks | geometry ray casts | their time s | "
          "probes | their time s | ms per view | geometry CPU s | semantic CPU s | geometry CPU × render | "
          "load before -> after |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    text = make_text_encoder("minilm")
    gt = synthetic_ground_truth(SyntheticBuilding(0), spacing_m=0.05)
    base = None
    for view in ("render", "auto"):
        out = work / f"views-{view}"
        summary, cpu, load = _run_sampling_cpu(out, ["--source", spec, "--frames", str(frames),
                                                     "--set", f"semantic.select_view={view}"])
        geo = cpu.get("geometry")
        base = geo if base is None else base
        health = summary["shards"]["geometry"]
        renders, probes = health.get("renders", 0), health.get("probes", 0)
        busy = health.get("render_busy_s", 0.0) + health.get("probe_busy_s", 0.0)
        loaded = load_map(out / "map")
        q = map_quality(loaded.volume, loaded.dictionary, gt, text_encoder=text)
        print(f"| {view} | {summary['frames_scored']} | {summary['encoder_calls']} | {q['f_mIoU']:.4f} | "
              f"{int(health['num_blocks'])} | {int(renders)} | {health.get('render_busy_s', 0.0):.1f} | {int(probes)} | "
              f"{health.get('probe_busy_s', 0.0):.1f} | {1e3 * busy / max(1, renders + probes):.1f} | "
              f"{_f(geo, '{:.1f}')} | {_f(cpu.get('semantic'), '{:.1f}')} | "
              f"{_f(geo / base if geo and base else None, '{:.2f}')} | {load} |", flush=True)
    print()
    print("Ray casts include the semantic steps' renders (one per encoded frame, at the encoder's size); the "
          "candidates' views are the rest. ms per view = their time over their count.")
    print()


def _run_sampling_cpu(out: Path, args: list[str]) -> tuple[dict, dict[str, float], str]:
    """``openfusion run`` with ``args``; (run.json, each service's CPU seconds, load before -> after).
    A service's CPU time is read from its process every 0.2 s while the run lasts (the last reading
    before it exits: the run ends its services itself)."""
    import psutil

    load_before = _load()
    with open(out.with_suffix(".stderr"), "w") as err:
        proc = subprocess.Popen([sys.executable, "-m", "openfusion.app.cli", "run", "--out", str(out), "--quiet",
                                 *args], stdout=subprocess.DEVNULL, stderr=err, env={**os.environ, "HF_HUB_OFFLINE": "1"})
        cpu: dict[str, float] = {}
        parent = psutil.Process(proc.pid)
        while proc.poll() is None:
            for child in parent.children(recursive=True):
                try:
                    cmd = child.cmdline()
                    if "service" in cmd[:-1]:
                        name = cmd[cmd.index("service") + 1]
                        cpu[name] = max(cpu.get(name, 0.0), sum(child.cpu_times()[:2]))
                except (psutil.Error, IndexError):  # exited between the listing and the reading
                    continue
            time.sleep(0.2)  # sampling, not waiting for an event: the figure is the last reading
    if proc.returncode != 0:
        raise RuntimeError(f"openfusion run {' '.join(args)} failed ({proc.returncode}): see {out.with_suffix('.stderr')}")
    return json.loads((out / "run.json").read_text()), cpu, f"{load_before} -> {_load()}"


# ----------------------------------------------------------------------------------- cost


def cost(laps_n: int, lap: int, width: int, height: int, widths: list[int]) -> None:
    """What scoring costs per frame against a semantic step (encode + render + match + update at the
    encoder's size), measured on the same frames, one row per map size (laps walked), scored width
    and way of reading the map's view (``select_view``: a probe at the frame's depth, the default, or
    a ray cast, the baseline)."""
    from openfusion.mapping import RegionDictionary, SemanticMapper, SemanticVolume
    from openfusion.mapping.selection import CoverageScorer

    text = make_text_encoder("minilm")
    encoder = make_region_encoder("gt", text_encoder=text)
    frames = list(open_source(f"synthetic:lap={lap},frames={laps_n * lap},width={width},height={height}"))
    volume = SemanticVolume(VolumeParams())
    dictionary = RegionDictionary(encoder.embedding_space, encoder.dim)
    mapper = SemanticMapper(volume, dictionary)
    scorers = {(view, w): CoverageScorer(SelectParams(select_width_px=w, select_view=view))
               for w in widths for view in ("render", "probe")}
    print(f"### Scoring cost per frame against a semantic step ({width}x{height} frames, every frame encoded, "
          "in process; the same frames for every row)")
    print()
    print("| map (frames) | blocks | scored width | view | view ms | score ms | scoring ms/frame | × render | "
          "semantic step ms | scoring / step | cubes recorded | regions recorded | record (MiB) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    rows: dict[tuple[int, str, int], list] = {}
    for i, frame in enumerate(frames):
        volume.integrate(frame)
        for (view, w), scorer in scorers.items():
            t0 = time.perf_counter()
            K_s = frame.intrinsics.scaled(w, round(frame.intrinsics.height_px * w / frame.intrinsics.width_px))
            if view == "probe":  # the frame's depth at the scored size, converted as the scorer does
                rendered = volume.probe(frame.T_world_cam, K_s, frame.depth_m((K_s.height_px, K_s.width_px)))
            else:
                rendered = volume.render(frame.T_world_cam, K_s)
            t1 = time.perf_counter()
            ev = scorer.prepare_frame(frame, lambda *_a, rendered=rendered: rendered)
            score = scorer.score(ev)
            if scorer.worth_encoding(score):
                scorer.mark_selected(ev)
            t2 = time.perf_counter()
            rows.setdefault((i // lap, view, w), []).append([t1 - t0, t2 - t1, 0.0])
        t0 = time.perf_counter()
        obs = encoder.encode(frame)
        mapper.step(obs, frame.T_world_cam, frame.intrinsics, depth_m=frame.depth_m())
        step = time.perf_counter() - t0
        for (view, w), scorer in scorers.items():
            rows[(i // lap, view, w)][-1][2] = step
            scorer.observe_plan(mapper.last_plan.key_map, frame.T_world_cam,
                                frame.intrinsics.scaled(*mapper.last_plan.key_map.shape[::-1]), frame.stamp_ns)
        if (i + 1) % lap == 0:
            for (view, w), scorer in scorers.items():
                t = np.median(np.asarray(rows[(i // lap, view, w)]), axis=0) * 1e3
                base = np.median(np.asarray(rows[(i // lap, "render", w)]), axis=0)[:2].sum() * 1e3
                print(f"| {i + 1} | {volume.num_blocks} | {w} | {view} | {t[0]:.1f} | {t[1]:.1f} | {t[0] + t[1]:.1f} | "
                      f"{(t[0] + t[1]) / base:.2f} | {t[2]:.1f} | {(t[0] + t[1]) / t[2]:.2f} | {scorer.cells_recorded} | "
                      f"{scorer.regions_recorded} | {scorer.record_bytes() / 2**20:.1f} |", flush=True)
    print()
    print("Medians per frame over each lap; view = the map's view at the candidate's pose at the scored size "
          "(probe: at the frame's own depth, openfusion.mapping.surface_probe; render: a ray cast; in the services "
          "a geometry/render request), score = preparing and scoring the view.")
    print()


# ----------------------------------------------------------------------------------- render growth


def render_growth(frames_n: int, width: int, height: int, sizes: list[int]) -> None:
    """What a render of the map costs as the map grows: the synthetic building's walk integrated
    into one volume, and after each of ``sizes`` frames the render at the scored size (64 px wide)
    and at the semantic step's 160x120, from the poses of the last frames, CPU time per render (and
    per probe at the frame's own depth, at both sizes: what the scorer and, past
    ``step_probe_blocks``, the semantic step read instead);
    Open3D's ``ray_cast`` given only 50 blocks (the floor of a call); and the same 50 blocks cast in
    a grid of the same capacity that holds only them (what a call would cost if it followed the
    blocks it is given). Ratios against the first row.

    Why the floor grows (Open3D 0.20's source, ``t/geometry/kernel/VoxelBlockGridImpl.h``): the
    CPU ray cast takes ``auto hashmap_impl = *cpu_hashmap->GetImpl();``, a copy by value of the
    grid's whole TBB block hash map, on every call. The CUDA path takes a lightweight view of it."""
    from openfusion.mapping import SemanticVolume, raycast
    from openfusion.mapping.coverage import scoring_size

    frames = list(open_source(f"synthetic:building,frames={frames_n},width={width},height={height}"))
    volume = SemanticVolume(VolumeParams())
    storage = volume._storage  # noqa: SLF001 (the floor column drives Open3D's ray cast directly)
    print(f"### Map render cost as the map grows (synthetic building walk, {width}x{height} frames, in process, "
          "CPU ms per render, median of the last 8 frames' poses)")
    print()
    print("| frames integrated | resident blocks | 64 px render ms | × first | 160x120 render ms | × first | "
          "ray cast of 50 blocks ms | × first | the 50 blocks alone in a grid ms | × first | 64 px probe ms | × first | "
          "probe / 64 px render | 160x120 probe ms | × first | 160x120 probe / render |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    first: list[float] = []
    done = 0
    for target in sorted(n for n in sizes if n <= len(frames)):
        for frame in frames[done:target]:
            volume.integrate(frame)
        done = target
        recent = frames[max(0, target - 8):target]
        row = []
        for w in (64, 160):
            ms = []
            for frame in recent:
                K = frame.intrinsics.scaled(*scoring_size(frame.intrinsics, w)[::-1])
                volume.render(frame.T_world_cam, K)  # its fragment buffer grown, outside the timing
                t0 = time.process_time()
                volume.render(frame.T_world_cam, K)
                ms.append((time.process_time() - t0) * 1e3)
            row.append(float(np.median(ms)))
        ms, alone_ms = [], []
        alone = _GridShim(storage)
        for frame in recent:
            K = frame.intrinsics.scaled(*scoring_size(frame.intrinsics, 64)[::-1])
            coords, _ = raycast.frustum_blocks(storage.active_blocks()[0], storage.params, frame.T_world_cam, K)
            for target_storage, out in ((storage, ms), (alone.holding(coords[:50]), alone_ms)):
                raycast._cast(target_storage, coords[:50], frame.T_world_cam, K, volume._intrinsic_tensor(K))  # noqa: SLF001
                t0 = time.process_time()
                raycast._cast(target_storage, coords[:50], frame.T_world_cam, K, volume._intrinsic_tensor(K))  # noqa: SLF001
                out.append((time.process_time() - t0) * 1e3)
        row += [float(np.median(ms)), float(np.median(alone_ms))]
        for w in (64, 160):  # the scorer's probe and the semantic step's (MatchParams.step_probe_blocks)
            probe_ms = []
            for frame in recent:  # timed as the renders are: a call before, outside the timing
                K = frame.intrinsics.scaled(*scoring_size(frame.intrinsics, w)[::-1])
                depth_small = resize_nearest(frame.depth_m(), (K.height_px, K.width_px))
                volume.probe(frame.T_world_cam, K, depth_small)
                t0 = time.process_time()
                volume.probe(frame.T_world_cam, K, depth_small)
                probe_ms.append((time.process_time() - t0) * 1e3)
            row.append(float(np.median(probe_ms)))
        first = first or row
        print(f"| {target} | {volume.num_blocks} | {row[0]:.1f} | {row[0] / first[0]:.2f} | {row[1]:.1f} | "
              f"{row[1] / first[1]:.2f} | {row[2]:.1f} | {row[2] / first[2]:.2f} | {row[3]:.1f} | "
              f"{row[3] / first[3]:.2f} | {row[4]:.1f} | {row[4] / first[4]:.2f} | {row[4] / row[0]:.2f} | "
              f"{row[5]:.1f} | {row[5] / first[5]:.2f} | {row[5] / row[1]:.2f} |", flush=True)
    print()
    print("Open3D's CPU ray cast costs in proportion to the blocks the grid holds, whatever blocks it is given "
          "(the 50-block column; the same 50 blocks alone in a grid of the same capacity grow only with that "
          "capacity, the hash map's buckets): every call "
          "copies the grid's whole block hash map (Open3D 0.20, VoxelBlockGridImpl.h, RayCastCPU). So every "
          "render grows with the map: a scoring render of a large map costs what a semantic step of a small one "
          "does. A geometry shard holds only its tiles' blocks; the memory budget bounds them.")
    print()


class _GridShim:
    """A second grid of ``storage``'s layout and capacity, holding only the blocks it is told to (no
    voxels written: the cast's cost, not its picture), standing in for ``storage`` in ``raycast._cast``."""

    def __init__(self, storage) -> None:
        self.params = storage.params
        self.device = storage.device
        self.vbg = storage.new_grid(storage.capacity_blocks)
        self._held: np.ndarray | None = None

    def holding(self, coords: np.ndarray) -> _GridShim:
        import open3d.core as o3c

        hm = self.vbg.hashmap()
        if self._held is not None:
            hm.erase(o3c.Tensor(self._held, device=self.device))
        self._held = np.ascontiguousarray(coords, np.int32)
        hm.activate(o3c.Tensor(self._held, device=self.device))
        return self


# ----------------------------------------------------------------------------------- services


def _scene(work: Path, frames: int) -> Path:
    """The ScanNet-layout scene (the built-in world, seed 1, 640x480, one lap of ``frames`` frames)."""
    from openfusion.sources.scannet_writer import write_scannet_layout
    from openfusion.sources.synthetic import SyntheticSource, SyntheticWorld

    path = work / "scans" / "scene0001_00"
    if not (path / "pose").is_dir():
        write_scannet_layout(SyntheticSource(SyntheticWorld(1), frames, 640, 480, frames_per_lap=frames), path,
                             ground_truth_spacing_m=0.02, overwrite=True)
    return path


def _run(out: Path, scene: Path, frames: int, *args: str) -> tuple[dict, float, str]:
    load_before = _load()
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "openfusion.app.cli", "run", "--source", f"scannet:{scene}",
                           "--frames", str(frames), "--out", str(out), "--quiet", "--query", "chair",
                           # the scene's mesh (about 600,000 vertices at 640x480) is over geometry's reply
                           # limit; openfusion run then builds mesh.ply from the saved map (app.end_of_run)
                           *args],
                          capture_output=True, text=True, env={**os.environ, "HF_HUB_OFFLINE": "1"}, timeout=1800)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"openfusion run {' '.join(args)} failed ({proc.returncode}): {proc.stderr[-2000:]}")
    return json.loads((out / "run.json").read_text()), wall, f"{load_before} -> {_load()}"


def _outcomes(summary: dict) -> str:
    """run.json's account of the semantic service's frames (services; in process: every frame)."""
    if summary.get("mode") != "services":
        return ""
    parts = ", ".join(f"{k} {v}" for k, v in summary.get("semantic_outcomes", {}).items())
    pending = summary.get("semantic_frames_pending", 0)
    return f"{summary.get('semantic_frames_received', 0)}: {parts}" + (f", pending {pending}" if pending else "")


def services(work: Path, frames: int, delay_ms: float, repeat: int, sets: list[str] = ()) -> None:
    """The services variants (and the in-process maps) of the scene; ``sets``: ``--set`` options of
    every run (``semantic.select_lookahead=3``), so each pair stays measured alike."""
    scene = _scene(work, frames)
    gt = load_scannet_ground_truth(scene)
    text = make_text_encoder("minilm")
    print(f"### Through the services at the scene's own rate ({frames}-frame ScanNet-layout scene of the built-in "
          f"world, 30 fps, gt encoder + {delay_ms:g} ms per frame; {os.cpu_count()} cores"
          f"{'; every run with ' + ', '.join(sets) if sets else ''})")
    print()
    print("| run | mode | select | encoder workers | f-mIoU | Δ vs in-process every frame | mAcc | unlabelled | "
          "encoder calls | regions embedded / not | skipped (no gain) | regions | calls per region | wall (s) | "
          "load 1/5 min before -> after | semantic frames received: outcomes |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    baseline = None
    variants = [("in-process", "every", 0), ("in-process", "coverage", 0), ("services", "latest", 0),
                ("services", "coverage", 0),
                ("services", "latest", 2), ("services", "coverage", 2)]
    for rep in range(repeat):
        for mode, select, workers in variants:
            if mode == "in-process" and rep:
                continue  # deterministic: once is enough
            out = work / f"run-{mode}-{select}-{workers}-{rep}"
            args = ["--select", select, "--encoder", "gt", "--encoder-delay-ms", str(delay_ms)]
            if mode == "in-process":
                args = ["--in-process", "--select", select, "--encoder", "gt"]
            elif workers:
                args += ["--encoder-workers", str(workers)]
            for kv in sets:
                args += ["--set", kv]
            summary, wall, load = _run(out, scene, frames, *args)
            loaded = load_map(out / "map")
            q = map_quality(loaded.volume, loaded.dictionary, gt, text_encoder=text)
            baseline = q["f_mIoU"] if baseline is None else baseline
            print(f"| {rep + 1} | {mode} | {select} | {workers} | {q['f_mIoU']:.4f} | {q['f_mIoU'] - baseline:+.4f} | "
                  f"{q['mAcc']:.4f} | {q['unlabelled_fraction']:.3f} | {summary['encoder_calls']} of "
                  f"{summary['frames_integrated']} | {summary['encoder_regions']} / {summary.get('regions_not_embedded', 0)} | "
                  f"{summary['skipped_no_gain']} | {summary['regions']} | "
                  f"{_f(summary.get('calls_per_region'), '{:.1f}')} | {wall:.0f} | {load} | {_outcomes(summary)} |",
                  flush=True)
    print()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    size = parser.add_mutually_exclusive_group()
    size.add_argument("--quick", action="store_true", help="CI-sized (default): 40-frame laps at 320x240, no services")
    size.add_argument("--full", action="store_true", help="120-frame laps at 640x480, and the services section")
    parser.add_argument("--laps", action="store_true", help="three laps of the built-in room, in process")
    parser.add_argument("--cost", action="store_true", help="scoring cost per frame against a semantic step")
    parser.add_argument("--stops", default=None, metavar="N[,N...]",
                        help="a lap with the camera standing still N frames at 4 points: renders reused or not "
                             "(e.g. 0,30,90)")
    parser.add_argument("--stops-services", action="store_true",
                        help="--stops: also the longest stop through openfusion run, with each service's CPU time")
    parser.add_argument("--services", action="store_true", help="a ScanNet-layout scene through openfusion run")
    parser.add_argument("--render-growth", action="store_true", help="map render cost as the map grows (building)")
    parser.add_argument("--views-services", type=int, metavar="FRAMES", default=None,
                        help="the building's walk of FRAMES frames through openfusion run: candidates rendered "
                        "against the default (probed on a large map)")
    parser.add_argument("--lap", type=int, default=None, help=f"frames per lap (default 40, --full {BUILTIN_LAP})")
    parser.add_argument("--laps-n", type=int, default=3, help="laps (default 3)")
    parser.add_argument("--widths", default="32,64,128", help="--cost: scored widths (default 32,64,128)")
    parser.add_argument("--frames", type=int, default=90, help="--services: frames of the scene (default 90)")
    parser.add_argument("--delay-ms", type=float, default=150.0, help="--services: encoder delay (default 150)")
    parser.add_argument("--repeat", type=int, default=2, help="--services: runs of each services variant (default 2)")
    parser.add_argument("--select-also", action="append", default=[], metavar="FIELD=VALUE[,FIELD=VALUE]",
                        help="--laps: one more coverage row with these select_* parameters (repeatable)")
    parser.add_argument("--run-set", action="append", default=[], metavar="SECTION.FIELD=VALUE",
                        help="--services: a --set option of every openfusion run (repeatable)")
    parser.add_argument("--work", type=Path, default=None, help="--services: working folder (default a temporary one)")
    args = parser.parse_args(argv)
    everything = not (args.laps or args.cost or args.services or args.render_growth or args.stops
                      or args.views_services)
    lap = args.lap or (BUILTIN_LAP if args.full else 40)
    width, height = (640, 480) if args.full else (320, 240)
    if args.laps or everything:
        also = [SelectParams.from_pairs([kv for kv in row.split(",") if kv]) for row in args.select_also]
        laps(args.laps_n, lap, width, height, also)
    if args.cost or everything:
        cost(args.laps_n, lap, width, height, [int(w) for w in args.widths.split(",")])
    if args.stops:
        stop_lengths = [int(n) for n in args.stops.split(",")]
        stops(lap, width, height, stop_lengths)
        if args.stops_services:
            with tempfile.TemporaryDirectory(prefix="bench-stops-") as tmp:
                stops_services(Path(tmp), lap, width, height, max(stop_lengths))
    if args.views_services:
        with tempfile.TemporaryDirectory(prefix="bench-views-") as tmp:
            views_services(Path(tmp), args.views_services, 320, 240)
    if args.render_growth:
        sizes = [1, 30, 120, 240] if args.full else [1, 30, 90]
        render_growth(max(sizes), 320, 240, sizes)
    if args.services or (everything and args.full):
        if args.work is not None:
            args.work.mkdir(parents=True, exist_ok=True)
            services(args.work, args.frames, args.delay_ms, args.repeat, args.run_set)
        else:
            with tempfile.TemporaryDirectory(prefix="bench-select-") as tmp:
                services(Path(tmp), args.frames, args.delay_ms, args.repeat, args.run_set)
    return 0


if __name__ == "__main__":
    sys.exit(main())
