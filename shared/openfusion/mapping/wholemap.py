"""Read-outs of the whole map when part of it is paged out: surface points and meshes, chunk by chunk.

When tiles are paged out (:mod:`openfusion.mapping.paging`), queries, ``segment``, exports and
``eval`` still see the whole map: :func:`extract_points` and :func:`extract_mesh` walk every tile
(resident and stored) in chunks of at most :data:`CHUNK_BLOCKS` blocks. Each chunk's blocks, plus
every existing block next to them (a one-block halo: Open3D's zero crossings and normals read the
neighbouring voxels, and the read-out's label fill looks 6 cm around), are copied into a scratch
grid of the same layout, read out there with the ordinary rule (:mod:`openfusion.mapping.readout`),
and only the points (triangles) whose owning block is in the chunk are kept. Every point is owned
by exactly one block, so chunks neither drop nor duplicate points; the result equals the read-out
of the whole map in one grid (``tests/unit/test_mapping_paging.py`` checks it), in the same
sorted order. With a key filter only the tiles holding one of the keys, and their neighbours, are
read out (a query's points: a few tiles, not the building). Stored tiles are read from the store one at a time (a small cache keeps the
neighbours of the current chunk), so the read-out needs the scratch grid and the result, never the
whole map, in memory; each read-out is one job of the read-out worker
(:mod:`openfusion.mapping.readout_worker`), so two read-outs never hold their chunks at once. Triangles
are never duplicated; a vertex on a chunk seam appears once per chunk in :func:`iter_mesh_parts`
(parts sent one by one) and once in :func:`extract_mesh` (welded: :mod:`openfusion.mapping.mesh_weld`).
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Iterator

import numpy as np

from openfusion.mapping import readout
from openfusion.mapping.heap import release_freed_memory
from openfusion.mapping.mesh_weld import join_welded
from openfusion.mapping.paging import TilePager
from openfusion.mapping.readout import SurfaceMesh, SurfacePoints
from openfusion.mapping.storage import ATTR_NAMES, VoxelStorage
from openfusion.mapping.tiles import NEIGHBOUR_OFFSETS, pack_coords

Tile = tuple[int, int, int]
#: Blocks read out at once (4 MiB of compact voxels, plus the halo and Open3D's read-out buffers).
#: Measured (a 3-room map loaded lazily, key-filtered points, RssAnon above the loaded map): +127
#: MiB per read-out at 1,024 blocks with a 2,048-block cache, +73 MiB at 512 and 512 (the 1,024 one
#: also made a default-sized 128 MiB scratch grid first: +161 before that fix), 1.2x the time.
CHUNK_BLOCKS = 512
#: Decoded stored tiles kept for the halos of the next chunks, bounded by their blocks (a tile
#: holds up to 512 blocks, 4 MiB: 48 whole tiles, the bound before, could hold 190 MiB).
_CACHE_BLOCKS = CHUNK_BLOCKS


class _TileSource:
    """Raw blocks of any tile, resident (copied from the grid) or stored (decoded, cached)."""

    def __init__(self, storage: VoxelStorage, pager: TilePager) -> None:
        self.storage = storage
        self.pager = pager
        self.groups = pager._resident_groups()
        self.cache: OrderedDict[Tile, tuple[np.ndarray, dict[str, np.ndarray]]] = OrderedDict()
        self.cached_blocks = 0

    def tiles(self) -> list[Tile]:
        return sorted(set(self.groups) | set(self.pager.stored_blocks))

    def blocks(self, tile: Tile) -> int:
        if tile in self.groups:
            return len(self.groups[tile][1])
        return self.pager.stored_blocks.get(tile, 0)

    def get(self, tile: Tile) -> tuple[np.ndarray, dict[str, np.ndarray]] | None:
        if tile in self.groups:
            coords, buf = self.groups[tile]
            return coords, self.storage.read_raw_blocks(buf)
        if tile not in self.pager.stored_blocks:
            return None
        hit = self.cache.get(tile)
        if hit is None:
            hit = self.pager._read(tile)
            self.cache[tile] = hit
            self.cached_blocks += len(hit[0])
            while self.cached_blocks > _CACHE_BLOCKS and len(self.cache) > 1:
                _t, (old_coords, _raw) = self.cache.popitem(last=False)
                self.cached_blocks -= len(old_coords)
        else:
            self.cache.move_to_end(tile)
        return hit


def _tiles_holding(source: _TileSource, keys: np.ndarray | list[int] | None) -> list[Tile]:
    """The tiles to read out for a key filter: those with a voxel of one of ``keys``, and their
    neighbours (a point there can take such a key from the label fill, within 6 cm)."""
    tiles = source.tiles()
    if keys is None:
        return tiles
    wanted = np.asarray(list(keys) if not isinstance(keys, np.ndarray) else keys, np.int64) + 1
    slots = np.flatnonzero(np.isin(source.storage.slots.key1, wanted))
    slots = slots[slots > 0]
    if len(slots) == 0:
        return []
    hit: list[Tile] = []
    for t in tiles:
        if t in source.groups:  # resident: its key slots only
            present = source.storage.read_raw_blocks(source.groups[t][1], names=("key",))["key"]
        elif t in source.pager.stored_slots:  # stored: the slots recorded when it left, no decoding
            present = source.pager.stored_slots[t]
        else:  # stored and never indexed (loaded from a map): decoded once, and indexed
            got = source.get(t)
            if got is None:
                continue
            present = np.unique(got[1]["key"])
            source.pager.stored_slots[t] = present
        if np.isin(present, slots).any():
            hit.append(t)
    around = {(t[0] + dx, t[1] + dy, t[2] + dz) for t in hit for dx in (-1, 0, 1) for dy in (-1, 0, 1) for dz in (-1, 0, 1)}
    return [t for t in tiles if t in around]


def _chunks(source: _TileSource, keys: np.ndarray | list[int] | None = None) -> Iterator[list[Tile]]:
    chunk: list[Tile] = []
    size = 0
    for t in _tiles_holding(source, keys):
        n = source.blocks(t)
        if chunk and size + n > CHUNK_BLOCKS:
            yield chunk
            chunk, size = [], 0
        chunk.append(t)
        size += n
    if chunk:
        yield chunk


def _owner_blocks(points: np.ndarray, voxel_size_m: float, res: int) -> np.ndarray:
    voxel = np.floor(points.astype(np.float64) / voxel_size_m + 1e-4).astype(np.int64)
    return np.floor_divide(voxel, res)


def _iter_scratch(
    storage: VoxelStorage, pager: TilePager, keys: np.ndarray | list[int] | None = None
) -> Iterator[tuple[VoxelStorage, np.ndarray]]:
    """Per chunk: a scratch storage holding the chunk's blocks and their halo, and the owned blocks
    (:func:`~openfusion.mapping.tiles.pack_coords` keys, sorted)."""
    source = _TileSource(storage, pager)
    grid = pager.grid
    scratch: VoxelStorage | None = None
    offsets = NEIGHBOUR_OFFSETS
    for chunk in _chunks(source, keys):
        own_coords: list[np.ndarray] = []
        raws: list[dict[str, np.ndarray]] = []
        for t in chunk:
            got = source.get(t)
            if got is not None and len(got[0]):
                own_coords.append(np.asarray(got[0], np.int64))
                raws.append(got[1])
        if not own_coords:
            continue
        own = np.concatenate(own_coords)
        own_keys = np.unique(pack_coords(own))
        # Halo: existing blocks next to the chunk's, from the tiles they fall in.
        around = (own[:, None, :] + offsets[None]).reshape(-1, 3)
        around_keys, first = np.unique(pack_coords(around), return_index=True)
        around = around[first[~np.isin(around_keys, own_keys, assume_unique=True)]]
        halo_coords: list[np.ndarray] = []
        halo_raws: list[dict[str, np.ndarray]] = []
        if len(around):
            tiles_of, inverse = grid.group_blocks(around)
            chunk_set = set(chunk)
            for i, t in enumerate(tiles_of):
                tt: Tile = (int(t[0]), int(t[1]), int(t[2]))
                if tt in chunk_set:
                    continue
                got = source.get(tt)
                if got is None or not len(got[0]):
                    continue
                want = pack_coords(around[inverse == i])
                coords_t = np.asarray(got[0], np.int64)
                sel = np.isin(pack_coords(coords_t), want)
                if sel.any():
                    halo_coords.append(coords_t[sel])
                    halo_raws.append({k: v[sel] for k, v in got[1].items()})
        coords = np.concatenate(own_coords + halo_coords)
        raw = {k: np.concatenate([r[k] for r in raws + halo_raws]) for k in ATTR_NAMES}
        if scratch is None or scratch.capacity_blocks < len(coords):
            # Made at the chunk's size at once: a default-sized grid first (16,384 blocks, 128 MiB,
            # touched by Open3D at creation) was a transient +128 MiB per read-out (measured).
            scratch = None
            scratch = VoxelStorage(storage.params.with_changes(memory_budget_mb=None), storage.device,
                                   capacity=len(coords) + len(coords) // 8)
        else:
            c_old, b_old = scratch.active_blocks()
            scratch.erase_blocks(c_old, b_old)
        scratch.slots = storage.slots  # one key table: slots mean the same keys
        scratch.write_raw_blocks(coords.astype(np.int32), raw)
        yield scratch, own_keys


def extract_points(
    storage: VoxelStorage,
    pager: TilePager,
    keys: np.ndarray | list[int] | None = None,
    max_points: int | None = None,
    *,
    seed: int = 0,
) -> SurfacePoints:
    """:func:`openfusion.mapping.readout.extract_points` of the whole map (resident and stored)."""
    if max_points is not None and max_points < 0:
        raise ValueError(f"max_points must be >= 0, got {max_points}")
    p = storage.params
    parts: list[SurfacePoints] = []
    for scratch, own in _iter_scratch(storage, pager, keys):
        pts = readout.extract_points(scratch, keys)
        if len(pts) == 0:
            continue
        owner = _owner_blocks(pts.points, p.voxel_size_m, p.block_resolution)
        keep = np.isin(pack_coords(owner), own)
        parts.append(SurfacePoints(pts.points[keep], pts.colors[keep], pts.keys[keep], pts.conf[keep]))
    release_freed_memory()  # the chunks' scratch buffers, back to the OS
    if not parts:
        return readout._empty_points()
    points = np.concatenate([s.points for s in parts])
    colors = np.concatenate([s.colors for s in parts])
    pkeys = np.concatenate([s.keys for s in parts])
    pconf = np.concatenate([s.conf for s in parts])
    order = np.lexsort((points[:, 2], points[:, 1], points[:, 0]))
    points, colors, pkeys, pconf = points[order], colors[order], pkeys[order], pconf[order]
    if max_points is not None and len(points) > max_points:
        rng = np.random.default_rng(seed)
        sel = np.sort(rng.choice(len(points), size=max_points, replace=False))
        points, colors, pkeys, pconf = points[sel], colors[sel], pkeys[sel], pconf[sel]
    return SurfacePoints(points, colors, pkeys, pconf)


def iter_mesh_parts(
    storage: VoxelStorage, pager: TilePager, keys: np.ndarray | list[int] | None = None
) -> Iterator[SurfaceMesh]:
    """The whole map's mesh, one part per chunk (module docstring: seams)."""
    p = storage.params
    for scratch, own in _iter_scratch(storage, pager, keys):
        mesh = readout.extract_mesh(scratch, keys)
        if len(mesh.triangles) == 0:
            continue
        centroid = mesh.vertices[mesh.triangles].mean(axis=1)
        owner = _owner_blocks(centroid, p.voxel_size_m, p.block_resolution)
        tri_keep = np.isin(pack_coords(owner), own)
        tris = mesh.triangles[tri_keep]
        used = np.zeros(len(mesh.vertices), bool)
        used[tris.reshape(-1)] = True
        remap = np.full(len(mesh.vertices), -1, np.int64)
        remap[used] = np.arange(int(used.sum()))
        yield SurfaceMesh(
            mesh.vertices[used], remap[tris].astype(np.int32), mesh.colors[used], mesh.normals[used],
            mesh.keys[used], mesh.conf[used],
        )


def extract_mesh(storage: VoxelStorage, pager: TilePager, keys: np.ndarray | list[int] | None = None) -> SurfaceMesh:
    """The whole map's mesh in one: the parts of :func:`iter_mesh_parts` joined and their seams
    welded (:mod:`openfusion.mapping.mesh_weld`), so it equals the mesh read out in one grid."""
    parts = list(iter_mesh_parts(storage, pager, keys))
    if not parts:
        return readout._empty_mesh()
    return join_welded(parts)
