"""Geometry shards: which shard owns which tile, and one map out of the shards' parts.

The map is split by tile (:mod:`openfusion.mapping.tiles`) across ``N`` geometry shards
(docs/SHARDS.md). Every frame reaches every shard; a shard integrates only the blocks of the
tiles it owns. The reasoning, the keys and the deployment are in docs/SHARDS.md; this module is
the plain-numpy part the volume, the services and the client-side merge helper share (no Open3D,
no bus).

Ownership (:func:`shard_of_tiles`)
    A fixed integer mix (the splitmix64 finaliser) of the packed tile coordinates, modulo ``N``:
    the same on every host and every Python (never the salted built-in ``hash``), no table of
    tiles to share, and spatially scattered, so a robot in one room touches tiles of every shard
    and each shard integrates about ``1/N`` of every frame's blocks (ranges would put a room on
    one shard: no per-frame speed-up). ``N = 1`` owns everything (today's single service).

One map to every reader
    - :func:`composite_renders`: per pixel the shard render with the nearest surface (depth > 0)
      gives depth, key and confidence (each shard ray-casts only its own blocks; a surface of
      another shard in front of it is simply nearer).
    - :func:`merge_region_tables` / :func:`merge_contacts` / :func:`concat_points` /
      :func:`concat_meshes`: region summaries, region contacts, points and meshes of the shards'
      disjoint tiles as one map's. Summaries: point counts add, centroids are count-weighted
      means, boxes are the union of the shards' boxes (each shard's box is its points' 1st-99th
      percentile box, so the union can be slightly larger than the whole map's robust box).
      Contacts: voxel counts and contact counts add per pair (across a tile face between two
      shards, the lower tile's shard sees the contact through its ghosts, the upper one's does not:
      such a pair's count on the upper side is short).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from openfusion.mapping.tiles import pack_coords, unpack_coords
from openfusion.wire.keys import ShardId

__all__ = [
    "OtherBlocks",
    "ShardId",
    "composite_renders",
    "concat_meshes",
    "concat_points",
    "ghost_blocks",
    "own_points",
    "merge_contacts",
    "merge_region_tables",
    "owned_blocks",
    "shard_of_tiles",
    "take_blocks",
]

_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)


def _mix64(x: np.ndarray) -> np.ndarray:
    """splitmix64's finaliser: a bijection of uint64 whose every output bit depends on every input bit."""
    x = x.astype(np.uint64, copy=True)
    with np.errstate(over="ignore"):
        x ^= x >> np.uint64(30)
        x *= _M1
        x ^= x >> np.uint64(27)
        x *= _M2
        x ^= x >> np.uint64(31)
    return x


def shard_of_tiles(tile_ijk: np.ndarray, n_shards: int) -> np.ndarray:
    """The shard index (int64 (T,)) owning each tile of ``tile_ijk`` (int (T, 3) tile coordinates,
    within +-2**20 per axis) of a map split ``n_shards`` ways (module docstring)."""
    if n_shards < 1:
        raise ValueError(f"n_shards must be >= 1, got {n_shards}")
    tiles = np.asarray(tile_ijk, np.int64).reshape(-1, 3)
    if n_shards == 1 or len(tiles) == 0:
        return np.zeros(len(tiles), np.int64)
    return (_mix64(pack_coords(tiles).astype(np.uint64)) % np.uint64(n_shards)).astype(np.int64)


def owned_blocks(block_coords: np.ndarray, tile_blocks: int, shard: ShardId) -> np.ndarray:
    """Bool mask over ``block_coords`` (int (N, 3) block coordinates): the blocks whose tile
    ``shard`` owns (all of them for an unsharded map)."""
    coords = np.asarray(block_coords, np.int64).reshape(-1, 3)
    if not shard.sharded:
        return np.ones(len(coords), bool)
    tiles = np.floor_divide(coords, int(tile_blocks))
    return shard_of_tiles(tiles, shard.count) == shard.index


class OtherBlocks:
    """The coordinates (no voxels) of the blocks frames touched in tiles other shards own, by tile:
    what a shard's ray cast stands in for as free space so its rays step as one whole volume's do
    (:mod:`openfusion.mapping.raycast`). 8 bytes per block; kept in memory only (after a restart a
    shard learns them again from the frames that follow).

    :meth:`add` (every frame) only keeps the frame's packed coordinates; they are sorted into their
    tiles when a reader asks (a ray cast, a few times a second) or when :data:`PENDING_MAX` of them
    wait: consecutive frames touch mostly the same blocks, so one merge per tile for many frames
    replaces one per tile per frame (0.25 ms a frame at 640x480, measured)."""

    #: Coordinates waiting to be sorted into tiles before :meth:`add` merges them anyway.
    PENDING_MAX = 1 << 18

    def __init__(self, tile_blocks: int) -> None:
        self.tile_blocks = int(tile_blocks)
        self._by_tile: dict[int, np.ndarray] = {}  # packed tile -> sorted packed block coordinates
        self._pending: list[np.ndarray] = []  # packed block coordinates not sorted into tiles yet
        self._pending_n = 0

    def __len__(self) -> int:
        self._merge()
        return sum(len(v) for v in self._by_tile.values())

    def add(self, block_coords: np.ndarray) -> None:
        """Remember ``block_coords`` (int (N, 3)), blocks of other shards' tiles a frame touched."""
        coords = np.asarray(block_coords, np.int64).reshape(-1, 3)
        if len(coords) == 0:
            return
        self._pending.append(pack_coords(coords))
        self._pending_n += len(coords)
        if self._pending_n >= self.PENDING_MAX:
            self._merge()

    def _merge(self) -> None:
        if not self._pending:
            return
        blocks = np.unique(np.concatenate(self._pending))
        self._pending.clear()
        self._pending_n = 0
        tiles = pack_coords(np.floor_divide(unpack_coords(blocks), self.tile_blocks))
        order = np.argsort(tiles, kind="stable")  # blocks stay sorted within each tile
        tiles, blocks = tiles[order], blocks[order]
        cuts = np.flatnonzero(np.diff(tiles)) + 1
        for t, group in zip(tiles[np.r_[0, cuts]], np.split(blocks, cuts), strict=True):
            known = self._by_tile.get(int(t))
            self._by_tile[int(t)] = group if known is None else np.union1d(known, group)

    def tiles(self) -> np.ndarray:
        """The tiles (int64 (T, 3)) with remembered blocks."""
        self._merge()
        return unpack_coords(np.fromiter(self._by_tile, np.int64, len(self._by_tile)))

    def blocks_of(self, tiles: np.ndarray) -> np.ndarray:
        """The remembered blocks (int32 (M, 3)) of ``tiles`` (int (T, 3))."""
        self._merge()
        parts = [self._by_tile[int(t)] for t in pack_coords(tiles) if int(t) in self._by_tile]
        if not parts:
            return np.zeros((0, 3), np.int32)
        return unpack_coords(np.concatenate(parts)).astype(np.int32)

    def clear(self) -> None:
        self._by_tile.clear()
        self._pending.clear()
        self._pending_n = 0


#: A block's neighbours in +x, +y, +z (and their combinations): the blocks whose voxels Open3D
#: reads with a block's when it extracts zero crossings (+x/+y/+z) and marching-cube triangles.
_UPPER = np.array([(x, y, z) for x in (0, 1) for y in (0, 1) for z in (0, 1) if (x, y, z) != (0, 0, 0)], np.int64)
_UPPER_BITS = (_UPPER[:, 0] | (_UPPER[:, 1] << 1) | (_UPPER[:, 2] << 2)).astype(np.int8)


def ghost_blocks(block_coords: np.ndarray, owned: np.ndarray, tile_blocks: int, shard: ShardId) -> np.ndarray:
    """Bool mask over ``block_coords`` (int (N, 3)): the blocks not owned (``owned`` mask) that sit
    in +x/+y/+z of a block of a tile ``shard`` owns (a rule of coordinates only, so every frame
    that reaches such a block integrates it: its voxels are exactly one whole volume's). A shard
    integrates these *ghosts* with its own blocks so the surface crossing from its last voxel into
    the next tile, and the triangles of the cubes there, are read out by it; its read-outs keep
    only what its own tiles own (:func:`own_points`), a merged load only its tiles' blocks.

    Only a block on a lower face of its tile (``coord % tile_blocks == 0`` on some axis) can be a
    ghost: the block below it in ``u`` (a step of 0 or 1 per axis) lies in the tile ``tile - (u &
    lower faces)``, its own tile unless ``u`` crosses one of those faces. So the owners of at most
    the 7 tiles below such a block are hashed, not the 7 neighbours of every block."""
    coords = np.asarray(block_coords, np.int64).reshape(-1, 3)
    owned = np.asarray(owned, bool).reshape(-1)
    out = np.zeros(len(coords), bool)
    if not shard.sharded or owned.all():
        return out
    tb = int(tile_blocks)
    tiles = np.floor_divide(coords, tb)
    face = (coords - tiles * tb == 0).astype(np.int8)  # on its tile's lower face in x, y, z
    faces = face[:, 0] | (face[:, 1] << 1) | (face[:, 2] << 2)  # as bits (a row reduction is slow in numpy)
    cand = np.flatnonzero(~owned & (faces != 0))
    if not len(cand):
        return out
    faces, base = faces[cand], tiles[cand]
    below = (base[:, None, :] - _UPPER[None]).reshape(-1, 3)  # the 7 tiles below each candidate, in one hash
    mine = (shard_of_tiles(below, shard.count) == shard.index).reshape(-1, len(_UPPER))
    fits = (faces[:, None] & _UPPER_BITS[None]) == _UPPER_BITS[None]  # every axis u steps in is a lower face
    found = (mine & fits).any(axis=1)
    out[cand] = found
    return out


def take_blocks(block_coords: np.ndarray, tile_blocks: int, shard: ShardId) -> tuple[np.ndarray, np.ndarray]:
    """``(owned, taken)`` bool masks over a frame's touched ``block_coords`` (int (N, 3)): the blocks
    of tiles ``shard`` owns, and those plus their ghosts (:func:`ghost_blocks`): what the shard
    integrates (one hash of the frame's blocks' tiles, and one of the tiles below its lower-face
    blocks that are not its own: 0.1-0.2 ms a frame at 640x480, measured)."""
    coords = np.asarray(block_coords, np.int64).reshape(-1, 3)
    if not shard.sharded or len(coords) == 0:
        every = np.ones(len(coords), bool)
        return every, every.copy()
    owned = shard_of_tiles(np.floor_divide(coords, int(tile_blocks)), shard.count) == shard.index
    return owned, owned | ghost_blocks(coords, owned, tile_blocks, shard)


def own_points(points: np.ndarray, voxel_size_m: float, block_resolution: int, tile_blocks: int,
               shard: ShardId) -> np.ndarray:
    """Bool mask over surface ``points`` (or triangle centroids) (N, 3): those whose owning block
    (the block of the voxel a crossing starts from, the read-out's rule of
    :mod:`openfusion.mapping.wholemap`) lies in a tile ``shard`` owns."""
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    if not shard.sharded or len(pts) == 0:
        return np.ones(len(pts), bool)
    voxel = np.floor(pts / voxel_size_m + 1e-4).astype(np.int64)
    return owned_blocks(np.floor_divide(voxel, block_resolution), tile_blocks, shard)


# ------------------------------------------------------------------------------------ renders
def composite_renders(
    renders: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]],
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(key_map, conf_map, depth_m)`` of one view from the shards' renders of it (each a
    ``(key_map int32, conf_map float32, depth_m float32)`` triple of one shape, depth 0 = no
    surface): per pixel, the render with the nearest surface wins all three; no surface in any: key
    -1, confidence 0, depth 0. ValueError for no renders or renders of different shapes."""
    if not renders:
        raise ValueError("composite_renders needs at least one render")
    shape = np.asarray(renders[0][2]).shape
    for keys, conf, depth in renders:
        if np.asarray(keys).shape != shape or np.asarray(conf).shape != shape or np.asarray(depth).shape != shape:
            raise ValueError(f"every render must be {shape}: got key {np.shape(keys)}, conf {np.shape(conf)}, "
                             f"depth {np.shape(depth)}")
    if len(renders) == 1:
        keys, conf, depth = renders[0]
        return np.asarray(keys, np.int32), np.asarray(conf, np.float32), np.asarray(depth, np.float32)
    depth_all = np.stack([np.asarray(r[2], np.float32) for r in renders])  # (S, h, w)
    hit = depth_all > 0
    nearest = np.where(hit, depth_all, np.inf).argmin(axis=0)[None]  # (1, h, w)
    any_hit = hit.any(axis=0)
    keys = np.take_along_axis(np.stack([np.asarray(r[0], np.int32) for r in renders]), nearest, 0)[0]
    conf = np.take_along_axis(np.stack([np.asarray(r[1], np.float32) for r in renders]), nearest, 0)[0]
    depth = np.take_along_axis(depth_all, nearest, 0)[0]
    keys = np.where(any_hit, keys, np.int32(-1)).astype(np.int32)
    conf = np.where(any_hit, conf, np.float32(0)).astype(np.float32)
    depth = np.where(any_hit, depth, np.float32(0)).astype(np.float32)
    return keys, conf, depth


# ---------------------------------------------------------------------------- region read-outs
def merge_region_tables(
    parts: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]],
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One map's region summaries from the shards': each part is ``(keys (n,), num_points (n,),
    bbox_min (n, 3), bbox_max (n, 3), centroid (n, 3) | None)`` (a part without centroids counts its
    box centres); returns ``(keys sorted int32, num_points int64, bbox_min, bbox_max, centroid)``
    (float32): counts add, boxes unite, centroids are count-weighted means."""
    if not parts:
        z3 = np.zeros((0, 3), np.float32)
        return np.zeros(0, np.int32), np.zeros(0, np.int64), z3, z3.copy(), z3.copy()
    keys = np.concatenate([np.asarray(p[0], np.int64).reshape(-1) for p in parts])
    counts = np.concatenate([np.asarray(p[1], np.int64).reshape(-1) for p in parts])
    lo = np.concatenate([np.asarray(p[2], np.float64).reshape(-1, 3) for p in parts])
    hi = np.concatenate([np.asarray(p[3], np.float64).reshape(-1, 3) for p in parts])
    cen = np.concatenate([
        np.asarray(p[4], np.float64).reshape(-1, 3) if p[4] is not None
        else (np.asarray(p[2], np.float64).reshape(-1, 3) + np.asarray(p[3], np.float64).reshape(-1, 3)) / 2
        for p in parts
    ])
    uniq, inv = np.unique(keys, return_inverse=True)
    n = len(uniq)
    num = np.zeros(n, np.int64)
    np.add.at(num, inv, counts)
    bmin = np.full((n, 3), np.inf)
    bmax = np.full((n, 3), -np.inf)
    np.minimum.at(bmin, inv, lo)
    np.maximum.at(bmax, inv, hi)
    weight = np.maximum(counts, 1).astype(np.float64)
    wsum = np.zeros(n)
    np.add.at(wsum, inv, weight)
    csum = np.zeros((n, 3))
    np.add.at(csum, inv, cen * weight[:, None])
    centroid = csum / np.maximum(wsum, 1e-12)[:, None]
    return (uniq.astype(np.int32), num, bmin.astype(np.float32), bmax.astype(np.float32),
            centroid.astype(np.float32))


def merge_contacts(
    parts: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]],
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One map's region contacts from the shards': each part is ``(keys, surface_voxels, pair_a,
    pair_b, contact_a, contact_b)`` (:class:`~openfusion.mapping.merging.RegionContacts`' fields);
    voxel counts add per key, contact counts per pair; the result is sorted by key and by pair."""
    def cat(i: int) -> np.ndarray:
        return np.concatenate([np.asarray(p[i], np.int64).reshape(-1) for p in parts]) if parts else np.zeros(0, np.int64)

    keys, surf = cat(0), cat(1)
    uk, inv = np.unique(keys, return_inverse=True)
    surface = np.zeros(len(uk), np.int64)
    np.add.at(surface, inv, surf)
    a, b, ca, cb = cat(2), cat(3), cat(4), cat(5)
    if len(a) == 0:
        z = np.zeros(0, np.int64)
        return uk, surface, z, z.copy(), z.copy(), z.copy()
    packed = np.stack([a, b], axis=1)
    up, pinv = np.unique(packed, axis=0, return_inverse=True)
    pinv = pinv.reshape(-1)
    sum_a = np.zeros(len(up), np.int64)
    sum_b = np.zeros(len(up), np.int64)
    np.add.at(sum_a, pinv, ca)
    np.add.at(sum_b, pinv, cb)
    return uk, surface, up[:, 0].copy(), up[:, 1].copy(), sum_a, sum_b


def concat_points(
    parts: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]], max_points: int | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool]:
    """``(points, colors, keys, subsampled)``: the shards' surface points (each ``(points (n, 3),
    colors (n, 3), keys (n,))``) as one cloud, subsampled uniformly (a fixed seed, in the order
    given) to ``max_points`` when there are more."""
    pts = np.concatenate([np.asarray(p[0], np.float32).reshape(-1, 3) for p in parts]) if parts else np.zeros((0, 3), np.float32)
    col = np.concatenate([np.asarray(p[1], np.uint8).reshape(-1, 3) for p in parts]) if parts else np.zeros((0, 3), np.uint8)
    key = np.concatenate([np.asarray(p[2], np.int32).reshape(-1) for p in parts]) if parts else np.zeros(0, np.int32)
    if max_points is not None and len(pts) > max_points:
        idx = np.sort(np.random.default_rng(0).choice(len(pts), size=max_points, replace=False))
        return pts[idx], col[idx], key[idx], True
    return pts, col, key, False


def concat_meshes(
    parts: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]],
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(vertices, triangles, colors, keys)``: the shards' meshes (each ``(vertices (V, 3),
    triangles (T, 3), colors (V, 3), keys (V,))``) as one mesh, triangle indices offset, the
    vertices a seam gives each side welded into one (:mod:`openfusion.mapping.mesh_weld`: each
    shard's triangles of a seam cube read the same voxels through its ghosts, so the copies are
    bit-identical)."""
    from openfusion.mapping.mesh_weld import weld_plan

    if not parts:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32), np.zeros((0, 3), np.uint8), np.zeros(0, np.int32)
    verts, tris, cols, keys = [], [], [], []
    offset = 0
    for v, t, c, k in parts:
        v = np.asarray(v, np.float32).reshape(-1, 3)
        verts.append(v)
        tris.append(np.asarray(t, np.int64).reshape(-1, 3) + offset)
        cols.append(np.asarray(c, np.uint8).reshape(-1, 3))
        keys.append(np.asarray(k, np.int32).reshape(-1))
        offset += len(v)
    v_all, t_all, c_all, k_all = np.concatenate(verts), np.concatenate(tris), np.concatenate(cols), np.concatenate(keys)
    plan = weld_plan(v_all, [len(v) for v in verts])
    if plan is None:
        return v_all, t_all.astype(np.int32), c_all, k_all
    kept, remap = plan
    return v_all[kept], remap[t_all].astype(np.int32), c_all[kept], k_all[kept]
