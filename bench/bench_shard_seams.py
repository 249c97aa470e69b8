"""The seam table of the geometry shards' bench (``bench_shards.py --seam-ghosts``, or this script):
Open3D's ``integrate`` CPU per frame of each shard of 2 with whole ghost blocks (what runs), with its
own blocks only, with the ghosts cut to the seam in a second Open3D grid of 1- or 2-voxel blocks, and
with the seam's first 1 or 2 voxel layers integrated by Open3D's kernel written out in numpy
(:func:`_seam_kernel`), and whether the seam's voxels equal the whole ghost blocks' (docs/SHARDS.md,
"What would close it"). Frames: the synthetic room, as ``bench_shards.py`` prepares them.

    .venv/bin/python bench/bench_shard_seams.py --quick    # 60 frames at 640x480 (--full: 150)
"""

from __future__ import annotations

import argparse
import functools
import time

from shard_frames import frame_inputs  # this folder is on the path when a bench runs as a script


@functools.lru_cache(maxsize=4)
def _block_voxels(res: int):  # noqa: ANN202
    """Every voxel's place (x, y, z) in a block of ``res`` cells, int (res**3, 3), x varying slowest (not the
    storage's flat order: :func:`~openfusion.mapping.storage.flat_voxel_index` gives that)."""
    import numpy as np

    return np.stack(np.meshgrid(*[np.arange(res)] * 3, indexing="ij"), -1).reshape(-1, 3)

def _seam_kernel(g, ghosts, bits, layers, depth, color, K, extrinsic, scale, p, cache):  # noqa: ANN001, ANN202
    """Open3D's TSDF integrate (``VoxelBlockGridImpl.h``, ``IntegrateCPU``: the same float32 steps in the
    same order) in numpy, on the first ``layers`` voxel layers of each ghost block that face a block of
    the shard's own below it (``bits``: which steps of ``_UPPER`` lead down to one); returns the voxels
    visited. A probe of the seam table, not the product's integrate."""
    import numpy as np
    import open3d.core as o3c

    from openfusion.mapping.shards import _UPPER
    from openfusion.mapping.storage import flat_voxel_index

    res, f32 = p.block_resolution, np.float32
    multiplier = f32(255) if color.dtype == np.float32 else f32(1)  # Open3D: float colour in [0, 1]
    loc = _block_voxels(res)
    keys = o3c.Tensor(np.ascontiguousarray(ghosts, np.int32))
    g.hashmap().activate(keys)
    buf = g.hashmap().find(keys)[0].numpy().astype(np.int64)
    rows, local = [], []
    for b in np.unique(bits).tolist():
        if (b, layers) not in cache:
            steps = _UPPER[[j for j in range(len(_UPPER)) if b >> j & 1]]
            cache[b, layers] = np.flatnonzero(((loc[None] < layers) | (steps[:, None] == 0)).all(-1).any(0))
        r = np.flatnonzero(bits == b)
        rows.append(np.repeat(r, len(cache[b, layers])))
        local.append(np.tile(cache[b, layers], len(r)))
    rows, local = np.concatenate(rows), np.concatenate(local)
    vox = (ghosts[rows] * res + loc[local]).astype(f32) * f32(p.voxel_size_m)
    e = extrinsic.astype(f32)
    xc, yc, zc = (vox[:, 0] * e[i, 0] + vox[:, 1] * e[i, 1] + vox[:, 2] * e[i, 2] + e[i, 3] for i in range(3))
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_z = f32(1) / zc
        u, v = f32(K[0, 0]) * xc * inv_z + f32(K[0, 2]), f32(K[1, 1]) * yc * inv_z + f32(K[1, 2])
    i = np.flatnonzero((v >= 0) & (u >= 0) & (v <= f32(depth.shape[0] - 1)) & (u <= f32(depth.shape[1] - 1)))
    ui, vi = u[i].astype(np.int64), v[i].astype(np.int64)
    d = depth[vi, ui].astype(f32) / f32(scale)
    sdf, trunc = d - zc[i], f32(p.trunc_voxels * p.voxel_size_m)
    ok = (d > 0) & (d <= f32(p.depth_max_m)) & (zc[i] > 0) & (sdf >= -trunc)
    i, ui, vi, sdf = i[ok], ui[ok], vi[ok], np.minimum(sdf[ok], trunc) / trunc
    flat = flat_voxel_index(buf[rows[i]], loc[local[i]], res)
    tsdf, weight = g.attribute("tsdf").numpy().reshape(-1), g.attribute("weight").numpy().reshape(-1)
    col = g.attribute("color").numpy().reshape(-1, 3)
    w = weight[flat].astype(f32)
    inv = f32(1) / (w + f32(1))
    tsdf[flat] = (w * tsdf[flat] + sdf) * inv
    col[flat] = ((w[:, None] * col[flat].astype(f32) + color[vi, ui].astype(f32) * multiplier) * inv[:, None]).astype(col.dtype)
    weight[flat] = (w + f32(1)).astype(weight.dtype)
    return len(rows)


def seam_ghosts(width: int, height: int, frames: int) -> None:
    """The seam table (module docstring): whole ghost blocks against ghosts cut to the seam."""
    import numpy as np
    import open3d as o3d
    import open3d.core as o3c

    from openfusion.mapping import VolumeParams
    from openfusion.mapping.shards import _UPPER, owned_blocks, take_blocks
    from openfusion.mapping.storage import flat_voxel_index

    p = VolumeParams()
    res = p.block_resolution
    inputs = list(frame_inputs(width, height, frames))
    warm = min(5, len(inputs) - 1)  # the first frames grow the grids: not counted

    def grid(resolution: int, blocks: int) -> o3d.t.geometry.VoxelBlockGrid:
        return o3d.t.geometry.VoxelBlockGrid(("tsdf", "weight", "color"), (o3c.float32, o3c.float32, o3c.float32),
                                             ((1), (1), (3)), p.voxel_size_m, resolution, blocks, o3c.Device("CPU:0"))

    def integrate(g: o3d.t.geometry.VoxelBlockGrid, coords: np.ndarray, args: tuple) -> float:
        depth, color, scale, K, extrinsic = args
        t = time.process_time()
        if len(coords):
            g.integrate(o3c.Tensor(np.ascontiguousarray(coords, np.int32)), depth, color, K, extrinsic, scale,
                        p.depth_max_m, p.trunc_voxels)
        return time.process_time() - t

    def cell_patterns(cells: int) -> tuple[np.ndarray, np.ndarray]:
        """A block's cells (cells^3, 3) and, per step u of _UPPER, those on the lower faces u steps in."""
        local = _block_voxels(cells)
        return local, np.stack([((local == 0) | (u == 0)).all(axis=1) for u in _UPPER])

    def values(g: o3d.t.geometry.VoxelBlockGrid, resolution: int, voxels: np.ndarray) -> tuple[np.ndarray, ...]:
        blocks = np.floor_divide(voxels, resolution)
        buf, found = g.hashmap().find(o3c.Tensor(blocks.astype(np.int32)))
        flat = flat_voxel_index(buf.cpu().numpy(), voxels - blocks * resolution, resolution)
        flat = np.where(found.cpu().numpy(), flat, 0)
        return (found.cpu().numpy(), g.attribute("tsdf").numpy().reshape(-1)[flat],
                g.attribute("weight").numpy().reshape(-1)[flat])

    one = grid(res, 40_000)
    base = 0.0
    for n, (*args, coords) in enumerate(inputs):
        spent = integrate(one, coords, tuple(args))
        base += spent if n >= warm else 0.0
    counted = len(inputs) - warm
    print(f"\nseam ghosts: Open3D's integrate of {counted} frames at {width}x{height}, CPU ms per frame "
          f"(ratio against one geometry's {1000 * base / counted:.2f} ms); shard i of 2")
    print(f"{'shard':>5} {'what':>32} {'blocks or cells':>15} {'ms/frame':>9} {'ratio':>6} {'seam values equal':>18}")
    for index in range(2):
        shard = VolumeParams(shard=f"{index}/2").shard_id
        whole, own = grid(res, 40_000), grid(res, 40_000)
        seams = {cells: grid(res // cells, 400_000) for cells in (res, res // 2)}  # 1- and 2-voxel cells
        patterns = {cells: cell_patterns(cells) for cells in seams}
        kernels = {f"numpy {layers}": grid(res, 40_000) for layers in (1, 2)}  # _seam_kernel's layers
        kernel_bits: dict[str, dict[tuple, int]] = {name: {} for name in kernels}
        cache: dict = {}
        spent = {"whole": 0.0, "own": 0.0, **{c: 0.0 for c in seams}, **{k: 0.0 for k in kernels}}
        counts = {"whole": 0, "own": 0, **{c: 0 for c in seams}, **{k: 0 for k in kernels}}
        for n, (*args, coords) in enumerate(inputs):
            owned, taken = take_blocks(coords, p.tile_blocks, shard)
            ghosts = coords[taken & ~owned]
            below = owned_blocks((ghosts[:, None, :] - _UPPER[None]).reshape(-1, 3), p.tile_blocks, shard)
            below = below.reshape(len(ghosts), len(_UPPER))
            parts = {"whole": (whole, coords[taken]), "own": (own, coords[owned])}
            for cells, g in seams.items():
                local, on_faces = patterns[cells]
                on_seam = (below[:, :, None] & on_faces[None]).any(axis=1)
                b, c = np.nonzero(on_seam)
                parts[cells] = (g, ghosts[b] * cells + local[c])
            for name, (g, part) in parts.items():
                t = integrate(g, part, tuple(args))
                if n >= warm:
                    spent[name] += t
                    counts[name] += len(part)
            depth_np, color_np = (np.asarray(im.as_tensor().numpy()) for im in args[:2])
            bits = (below * (1 << np.arange(len(_UPPER)))).sum(axis=1)
            for name, g in kernels.items():
                layers = int(name.split()[1])
                t = time.process_time()
                visited = _seam_kernel(g, ghosts, bits, layers, depth_np.reshape(depth_np.shape[:2]), color_np,
                                       args[3].numpy(), args[4].numpy(), args[2], p, cache)
                if n >= warm:
                    spent[name] += time.process_time() - t
                    counts[name] += visited
                for key, b in zip(map(tuple, ghosts.tolist()), bits.tolist(), strict=True):
                    kernel_bits[name][key] = kernel_bits[name].get(key, 0) | b
        for name in spent:
            labels = {"whole": "own + whole ghost blocks (runs)", "own": "own blocks only"}
            what = labels.get(name) or (f"ghost seam, {name} layer(s)" if name in kernels
                                        else f"ghost seam, {res // name}-voxel cells")
            equal = ""
            if name in kernels:  # every seam voxel the whole ghost blocks observed, the kernel's alike
                layers = int(name.split()[1])
                ghost_keys = np.array(list(kernel_bits[name]), np.int64).reshape(-1, 3)
                local = [cache[b, layers] for b in kernel_bits[name].values()]
                loc = _block_voxels(res)
                voxels = np.concatenate([k * res + loc[lv] for k, lv in zip(ghost_keys, local, strict=True)])
                fw, tw, ww = values(whole, res, voxels)
                fs, ts, ws = values(kernels[name], res, voxels)
                seen = fw & (ww > 0)
                same = fs[seen] & (tw[seen] == ts[seen]) & (ww[seen] == ws[seen])
                equal = f"{np.mean(same):.6f} of {int(seen.sum())}"
            if name in seams:
                g = seams[name]
                cell_res = res // name
                hm = g.hashmap()
                keys = hm.key_tensor().cpu().numpy().astype(np.int64)[hm.active_buf_indices().cpu().numpy()]
                local, _ = cell_patterns(cell_res)
                voxels = (keys[:, None, :] * cell_res + local[None]).reshape(-1, 3)
                fw, tw, ww = values(whole, res, voxels)
                fs, ts, ws = values(g, cell_res, voxels)
                seen = fw & fs & (ws > 0)
                equal = f"{np.mean((tw[seen] == ts[seen]) & (ww[seen] == ws[seen])):.6f} of {int(seen.sum())}"
            ms = 1000 * spent[name] / counted
            print(f"{index:>5} {what:>32} {counts[name] / counted:15.0f} {ms:9.2f} {spent[name] / base:6.3f} {equal:>18}")
        ratio = (spent["own"] + min(spent[c] for c in [*seams, *kernels])) / base
        print(f"{index:>5} {'own + cheaper seam':>32} {'':>15} {'':>9} {ratio:6.3f}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    size = parser.add_mutually_exclusive_group()
    size.add_argument("--quick", action="store_true", help="60 frames (the default)")
    size.add_argument("--full", action="store_true", help="150 frames")
    parser.add_argument("--frames", type=int, default=None, help="frames (overrides --quick / --full)")
    parser.add_argument("--size", default="640x480", help="WIDTHxHEIGHT")
    args = parser.parse_args(argv)
    width, height = (int(v) for v in args.size.lower().split("x"))
    seam_ghosts(width, height, args.frames or (150 if args.full else 60))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
