#!/usr/bin/env python3
"""Map-core speed and memory, each against a baseline measured in the same run on the same data.

1. Geometry: frames/s of ``SemanticVolume.integrate`` (tsdf/weight/color + key/conf attributes,
   frame checks, depth_min) vs plain Open3D (``compute_unique_block_coordinates`` + ``integrate``
   on a tsdf/weight/color grid with the same parameters), 640x480 frames of a furnished room,
   2 cm voxels, truncation 4 voxels. Target ratio >= 0.9.
2. Semantic step: render + match + plan + update at 160x120 with 50 regions per frame and a
   dictionary of >= 1,000 regions, vs the bare Open3D ``ray_cast`` of the same view (the floor).
   Target >= 30 Hz.
3. Vector query: ``RegionDictionary.top_k`` over 10,000 regions of 512-d (ranking only), p50,
   vs a full argsort of the same scores. Target p50 <= 2 ms.
4. Memory: semantic bytes per voxel (key int32 + conf float32) vs a ConceptFusion-style map
   with one 512-d float32 feature per surface point; also totals for the bench map.

    .venv/bin/python bench/bench_mapping.py --quick   # CI-sized (well under a minute on 2 cores)
    .venv/bin/python bench/bench_mapping.py           # full size (90 frames)
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np
import open3d as o3d
import open3d.core as o3c

from openfusion.frame import CameraIntrinsics, Frame, resize_nearest
from openfusion.mapping import RegionDictionary, SemanticMapper, SemanticVolume, VolumeParams
from openfusion.mapping.volume import range_map_down_factor
from openfusion.testing.analytic_scene import SimpleObservation, furnished_room, orbit_poses

OBS_W, OBS_H = 160, 120
REGIONS_PER_FRAME = 50
MAP_REGIONS = 1000
EMB_DIM = 512
QUERY_REGIONS = 10_000


def load_frames(num_frames: int) -> tuple[list[Frame], str]:
    """Frames of the project's synthetic world when available, else of the analytic box room."""
    try:
        from openfusion.sources.synthetic import SyntheticSource, SyntheticWorld

        source = SyntheticSource(SyntheticWorld(0), num_frames=num_frames, width_px=640, height_px=480)
        return list(source), "openfusion.sources.synthetic (seed 0, depth noise on)"
    except ImportError:
        scene = furnished_room()
        K = CameraIntrinsics(640, 480, 525.0, 525.0, 319.5, 239.5)
        frames = [scene.make_frame(T, K, frame_id=i) for i, T in enumerate(orbit_poses(num_frames))]
        return frames, "analytic furnished room (openfusion.sources.synthetic not found)"


def geometry(frames: list[Frame], repeats: int) -> dict[str, float]:
    """Per-frame interleaved timing (ours, plain, ours, plain, ... with the order alternating per
    frame), so load from other processes hits both alike; the best of ``repeats`` passes."""
    params = VolumeParams(initial_block_count=16384)

    def new_plain() -> o3d.t.geometry.VoxelBlockGrid:
        return o3d.t.geometry.VoxelBlockGrid(
            attr_names=("tsdf", "weight", "color"),
            attr_dtypes=(o3c.float32, o3c.float32, o3c.float32),
            attr_channels=(1, 1, 3),
            voxel_size=params.voxel_size_m,
            block_resolution=params.block_resolution,
            block_count=params.initial_block_count,
            device=o3c.Device("CPU:0"),
        )

    def plain_integrate(vbg: o3d.t.geometry.VoxelBlockGrid, f: Frame) -> None:
        depth = o3d.t.geometry.Image(o3c.Tensor.from_numpy(f.depth))
        color = o3d.t.geometry.Image(o3c.Tensor.from_numpy(f.color))
        K = o3c.Tensor(f.intrinsics.K)
        extrinsic = o3c.Tensor(np.linalg.inv(f.T_world_cam))
        coords = vbg.compute_unique_block_coordinates(
            depth, K, extrinsic, f.depth_scale, params.depth_max_m, params.trunc_voxels
        )
        vbg.integrate(
            coords, depth, color, K, extrinsic, f.depth_scale, params.depth_max_m, params.trunc_voxels
        )

    best_ours = best_plain = float("inf")
    volume = SemanticVolume(params)
    for _ in range(repeats):
        volume = SemanticVolume(params)
        vbg = new_plain()
        t_ours = t_plain = 0.0
        for i, f in enumerate(frames):
            for which in (0, 1) if i % 2 == 0 else (1, 0):
                t0 = time.perf_counter()
                if which == 0:
                    volume.integrate(f)
                    t_ours += time.perf_counter() - t0
                else:
                    plain_integrate(vbg, f)
                    t_plain += time.perf_counter() - t0
        best_ours, best_plain = min(best_ours, t_ours), min(best_plain, t_plain)
    return {
        "ours_fps": len(frames) / best_ours,
        "plain_fps": len(frames) / best_plain,
        "blocks": volume.num_blocks,
    }


def fifty_regions(
    frame: Frame, rng: np.random.Generator, emb_of: dict[tuple[int, int], np.ndarray]
) -> SimpleObservation:
    """50 regions at 160x120: instances split by a coarse image grid, largest first, soft confidences."""
    inst = resize_nearest(frame.instance, (OBS_H, OBS_W))
    for cells in (4, 6, 8, 12):
        cell = (np.arange(OBS_H)[:, None] * cells // OBS_H) * cells + (
            np.arange(OBS_W)[None, :] * cells // OBS_W
        )
        region_id = inst.astype(np.int64) * 1000 + cell
        region_id[inst == 0] = -1
        ids, counts = np.unique(region_id[region_id >= 0], return_counts=True)
        if len(ids) >= REGIONS_PER_FRAME:
            break
    ids = ids[np.argsort(-counts)][:REGIONS_PER_FRAME]
    conf = rng.uniform(0.5, 1.0, size=len(ids)).astype(np.float32)
    maps = np.stack([(region_id == i) * c for i, c in zip(ids, conf, strict=True)]).astype(np.float32)
    embs = []
    for i in ids:
        k = (int(i) // 1000, int(i) % 1000)
        if k not in emb_of:
            v = rng.standard_normal(EMB_DIM).astype(np.float32)
            emb_of[k] = v / np.linalg.norm(v)
        e = emb_of[k] + 0.05 * rng.standard_normal(EMB_DIM).astype(np.float32)
        embs.append(e / np.linalg.norm(e))
    return SimpleObservation(maps, np.stack(embs), "bench-random-512", None)


def semantic(frames: list[Frame], timed_frames: int) -> dict[str, float]:
    rng = np.random.default_rng(0)
    volume = SemanticVolume(VolumeParams(initial_block_count=16384))
    dictionary = RegionDictionary("bench-random-512", EMB_DIM)
    mapper = SemanticMapper(volume, dictionary)
    emb_of: dict[tuple[int, int], np.ndarray] = {}
    obs = [fifty_regions(f, rng, emb_of) for f in frames]
    for f in frames:
        volume.integrate(f)
    # Build the map's semantics: steps over every frame until >= 1,000 regions exist.
    passes = 0
    while len(dictionary) < MAP_REGIONS and passes < 4:
        for f, o in zip(frames, obs, strict=True):
            mapper.step(o, f.T_world_cam, f.intrinsics, depth_m=f.depth_m())
        passes += 1
    labelled_regions = len(dictionary)
    while len(dictionary) < MAP_REGIONS:  # pad the dictionary (ranking cost only)
        v = rng.standard_normal(EMB_DIM).astype(np.float32)
        dictionary.add(v)
    step_ms, render_ms, plan_ms, update_ms, in_view = [], [], [], [], []
    order = np.linspace(0, len(frames) - 1, timed_frames).astype(int)
    for i in order:
        f = frames[i]
        depth = f.depth_m()
        t0 = time.perf_counter()
        stats = mapper.step(obs[i], f.T_world_cam, f.intrinsics, depth_m=depth)
        step_ms.append((time.perf_counter() - t0) * 1e3)
        render_ms.append(stats.render_ms)
        plan_ms.append(stats.plan_ms)
        update_ms.append(stats.update_ms)
        in_view.append(stats.regions_in_view)
    # Floor: the bare Open3D ray cast of the same views with the same outputs.
    K_small = frames[0].intrinsics.scaled(OBS_W, OBS_H)
    hm = volume.open3d_grid.hashmap()
    all_blocks = hm.key_tensor()[hm.active_buf_indices().to(o3c.int64)]
    cast_ms = []
    for i in order:
        extrinsic = o3c.Tensor(np.linalg.inv(frames[i].T_world_cam))
        t0 = time.perf_counter()
        volume.open3d_grid.ray_cast(
            all_blocks,
            o3c.Tensor(K_small.K),
            extrinsic,
            OBS_W,
            OBS_H,
            ["depth", "index", "interp_ratio", "mask"],
            1.0,
            0.1,
            6.0,
            1.0,
            4.0,
            range_map_down_factor(OBS_W, OBS_H),
        )
        cast_ms.append((time.perf_counter() - t0) * 1e3)
    return {
        "step_p50_ms": float(np.median(step_ms)),
        "step_mean_ms": float(np.mean(step_ms)),
        "render_ms": float(np.median(render_ms)),
        "plan_ms": float(np.median(plan_ms)),
        "update_ms": float(np.median(update_ms)),
        "raycast_ms": float(np.median(cast_ms)),
        "regions_in_view": float(np.median(in_view)),
        "dictionary": len(dictionary),
        "labelled_regions": labelled_regions,
        "volume": volume,
    }


def query(repeats: int) -> dict[str, float]:
    rng = np.random.default_rng(1)
    d = RegionDictionary("bench-random-512", EMB_DIM, initial_capacity=QUERY_REGIONS)
    vecs = rng.standard_normal((QUERY_REGIONS, EMB_DIM)).astype(np.float32)
    for v in vecs:
        d.add(v)
    queries = rng.standard_normal((repeats, EMB_DIM)).astype(np.float32)
    units = d.unit_embeddings()
    ours, base = [], []
    for q in queries:  # interleaved
        t0 = time.perf_counter()
        d.top_k(q, 10)
        ours.append((time.perf_counter() - t0) * 1e3)
        t0 = time.perf_counter()
        np.argsort(-(units @ (q / np.linalg.norm(q))))[:10]
        base.append((time.perf_counter() - t0) * 1e3)
    return {
        "p50_ms": float(np.median(ours)),
        "p95_ms": float(np.percentile(ours, 95)),
        "base_p50_ms": float(np.median(base)),
    }


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--quick", action="store_true", help="CI-sized run")
    parser.add_argument("--full", action="store_true", help="the default size (bench/run_all.py --full passes it)")
    parser.add_argument("--frames", type=int, default=None, help="frames of the room scan")
    args = parser.parse_args()
    n_frames = args.frames or (24 if args.quick else 90)
    repeats = 2 if args.quick else 3
    frames, source = load_frames(n_frames)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"## bench_mapping ({'quick' if args.quick else 'full'})\n")
    print(
        f"{len(frames)} frames 640x480 from {source}; 2 cm voxels, trunc 4 voxels, depth <= 6 m; "
        f"open3d {o3d.__version__}, {os.cpu_count()} CPUs, load average {load:.1f} at start.\n"
    )

    g = geometry(frames, repeats)
    s = semantic(frames, timed_frames=min(len(frames), 30 if args.quick else 60))
    q = query(200 if args.quick else 1000)
    volume: SemanticVolume = s["volume"]
    surface = volume.extract_points()
    voxels = volume.num_blocks * volume.voxels_per_block
    cf_bytes = len(surface) * EMB_DIM * 4
    sem_bytes = voxels * 8

    ratio = g["ours_fps"] / g["plain_fps"]
    hz = 1e3 / s["step_p50_ms"]
    print("| measure | OpenFusion-Z | baseline (same run) | ratio | target |")
    print("|---|---|---|---|---|")
    print(
        f"| 1. geometry integrate, fps (best of {repeats} passes, per-frame interleaved) | {g['ours_fps']:.1f} | plain Open3D {g['plain_fps']:.1f} "
        f"| {ratio:.2f} | >= 0.9 {'met' if ratio >= 0.9 else 'MISSED'} |"
    )
    print(
        f"| 2. semantic step 160x120, {REGIONS_PER_FRAME} regions/frame, {s['dictionary']} in dictionary "
        f"({s['labelled_regions']} from the scan), p50 ms | {s['step_p50_ms']:.1f} ({hz:.0f} Hz; mean "
        f"{s['step_mean_ms']:.1f} ms) | bare ray_cast {s['raycast_ms']:.1f} ms | "
        f"{s['step_p50_ms'] / s['raycast_ms']:.2f} | >= 30 Hz {'met' if hz >= 30 else 'MISSED'} |"
    )
    print(
        f"|   render / plan (match + dictionary) / update, p50 ms | {s['render_ms']:.1f} / {s['plan_ms']:.1f} / "
        f"{s['update_ms']:.1f} (regions in view p50 {s['regions_in_view']:.0f}) | | | |"
    )
    print(
        f"| 3. vector query top-10 of {QUERY_REGIONS} x {EMB_DIM}, p50 ms | {q['p50_ms']:.3f} (p95 {q['p95_ms']:.3f}) "
        f"| full argsort {q['base_p50_ms']:.3f} | {q['p50_ms'] / q['base_p50_ms']:.2f} | <= 2 ms "
        f"{'met' if q['p50_ms'] <= 2 else 'MISSED'} |"
    )
    print(
        f"| 4. semantic bytes per voxel | 8 (key int32 + conf float32) | ConceptFusion {EMB_DIM * 4} per point "
        f"({EMB_DIM}-d float32) | {8 / (EMB_DIM * 4):.4f} | 8 met |"
    )
    print(
        f"|   this map: semantics / per-point features, MB | {sem_bytes / 1e6:.1f} ({voxels:,} voxels in "
        f"{volume.num_blocks} blocks) + dictionary {s['dictionary'] * EMB_DIM * 8 / 1e6:.1f} | "
        f"{cf_bytes / 1e6:.1f} ({len(surface):,} surface points) | "
        f"{(sem_bytes + s['dictionary'] * EMB_DIM * 8) / cf_bytes:.2f} | |"
    )
    print(f"|   whole volume incl. geometry (28 B/voxel) | {voxels * 28 / 1e6:.1f} MB | | | |")
    print()
    print(f"Geometry map: {g['blocks']} blocks after {len(frames)} frames.")


if __name__ == "__main__":
    main()
