"""Geometry shards in the map core (no bus): tile ownership, integration of a shard's own blocks,
the composited render and the merged read-outs, always against one volume of the same frames."""

from __future__ import annotations

import numpy as np
import pytest

from openfusion.frame import resize_nearest
from openfusion.mapping import SemanticVolume, VolumeParams, shards
from openfusion.mapping.summaries import RegionTable
from openfusion.sources import open_source
from openfusion.wire.keys import InvalidKeyError, ShardId

FRAMES = list(open_source("synthetic:seed=1,frames=16,width=160,height=120,lap=16"))
BASE = {"voxel_size_m": 0.03, "tile_blocks": 4, "depth_max_m": 5.0}
K = FRAMES[0].intrinsics.scaled(80, 60)


def _map(shard: str) -> SemanticVolume:
    volume = SemanticVolume(VolumeParams(**BASE, shard=shard))
    for i, f in enumerate(FRAMES):
        volume.integrate(f)
        if i % 2 == 0:  # the frame's instances as region keys (the same update reaches every shard)
            keys = resize_nearest(f.instance, (60, 80)).astype(np.int32) - 1
            volume.apply_update(f.T_world_cam, K, keys, np.full((60, 80), 0.8, np.float32),
                                observed_depth_m=f.depth_m())
    return volume


@pytest.fixture(scope="module")
def maps() -> tuple[SemanticVolume, list[SemanticVolume]]:
    return _map("0/1"), [_map("0/2"), _map("1/2")]


def _blocks(volume: SemanticVolume) -> dict[tuple[int, int, int], int]:
    coords, buf = volume._storage.active_blocks()
    return {tuple(int(v) for v in c): int(b) for c, b in zip(coords, buf, strict=True)}


# ------------------------------------------------------------------------------- ownership
def test_shard_ids_parse_name_and_refuse_bad_input() -> None:
    assert ShardId.parse("1/3") == ShardId(1, 3) and str(ShardId(1, 3)) == "1/3"
    assert ShardId().service == "geometry" and ShardId(0, 2).service == "geometry-0of2"
    assert ShardId.of_service("geometry-1of2") == ShardId(1, 2) and ShardId.of_service("geometry") == ShardId()
    assert ShardId.of_service("query") is None and ShardId.of_service("geometry-2of2") is None
    # Replicas: their own names, their shard's keys and parts.
    r1 = ShardId.of_service("geometry-0of2-r1")
    assert r1 == ShardId(0, 2, 1) and r1.part == ShardId(0, 2) and r1.service == "geometry-0of2-r1"
    assert ShardId.of_service("geometry-r2") == ShardId(0, 1, 2) and ShardId.of_service("geometry-0of1") is None
    assert ShardId.of_service("geometry-0of2-r10") is None  # bad input: more replicas than allowed
    # Bad input: not I/N, an index past the count, no shards, a count nobody means.
    for bad in ("1", "a/b", "2/2", "0/0", "-1/2", "0/1000"):
        with pytest.raises(InvalidKeyError):
            ShardId.parse(bad)
    with pytest.raises(ValueError, match="I/N"):
        VolumeParams(shard="first")


def test_ownership_is_fixed_and_balanced() -> None:
    tiles = np.stack(np.meshgrid(np.arange(-10, 10), np.arange(-8, 8), np.arange(-2, 3), indexing="ij"), -1).reshape(-1, 3)
    # A fixed mix, not Python's salted hash: these values are the same in every process and host.
    np.testing.assert_array_equal(
        shards.shard_of_tiles([[0, 0, 0], [1, 0, 0], [0, 1, 0], [-3, 7, 2], [5, -2, 1], [0, 0, 1]], 4),
        [1, 1, 1, 3, 0, 2])
    np.testing.assert_array_equal(shards.shard_of_tiles(tiles, 1), 0)
    for n in (2, 3, 4, 8):
        owner = shards.shard_of_tiles(tiles, n)
        share = np.bincount(owner, minlength=n) / len(tiles)
        assert owner.min() >= 0 and owner.max() < n
        assert np.abs(share - 1 / n).max() < 0.2 / n, (n, share)
    # Per frame: each shard gets a share of every frame's tiles (a room is not one shard's).
    grid_blocks = 4
    for f in FRAMES[::4]:
        vol = SemanticVolume(VolumeParams(**BASE))
        vol.integrate(f)
        coords, _ = vol._storage.active_blocks()
        owned = shards.owned_blocks(coords, grid_blocks, ShardId(0, 2))
        assert 0.2 < owned.mean() < 0.8, owned.mean()


def test_shards_integrate_disjoint_blocks_equal_to_one_volume(maps) -> None:  # noqa: ANN001
    whole, parts = maps
    ref = _blocks(whole)
    got = [_blocks(p) for p in parts]
    tb = BASE["tile_blocks"]
    owned = [{c for c in g if shards.owned_blocks(np.array([c]), tb, ShardId(i, 2))[0]} for i, g in enumerate(got)]
    # Each block of the map is owned by exactly one shard; a shard also holds ghosts: blocks of the
    # other's tiles just above its own (+x/+y/+z), no more than a fraction of its own.
    assert owned[0].isdisjoint(owned[1]) and owned[0] | owned[1] == set(ref)
    for i, g in enumerate(got):
        ghosts = set(g) - owned[i]
        assert ghosts <= owned[1 - i]
        assert len(ghosts) < 0.6 * len(owned[i]), (len(ghosts), len(owned[i]))
    assert parts[0].stats.frames_integrated == parts[1].stats.frames_integrated == len(FRAMES)
    # The voxels of every block (ghosts too) are the single volume's (Open3D integrates blocks independently).
    res3 = whole.params.block_resolution ** 3
    for part, blocks in zip(parts, got, strict=True):
        coords = list(blocks)
        mine = part._storage.read_raw_blocks(np.array([blocks[c] for c in coords]))
        theirs = whole._storage.read_raw_blocks(np.array([ref[c] for c in coords]))
        for name in ("tsdf", "weight", "color"):
            np.testing.assert_array_equal(mine[name], theirs[name], err_msg=name)
        assert mine["tsdf"].size == len(coords) * res3


def test_composited_render_equals_the_single_volume_render(maps) -> None:  # noqa: ANN001
    whole, parts = maps
    depth_ok = keys_ok = pixels = 0
    for f in FRAMES[1::3]:
        ref = whole.render(f.T_world_cam, K)
        views = [p.render(f.T_world_cam, K) for p in parts]
        keys, conf, depth = shards.composite_renders([(v.key_map, v.conf_map, v.depth_m) for v in views])
        seen = (ref.depth_m > 0) | (depth > 0)
        pixels += int(seen.sum())
        depth_ok += int((np.abs(depth - ref.depth_m)[seen] <= whole.params.voxel_size_m).sum())
        keys_ok += int((keys == ref.key_map)[seen].sum())
        assert (conf[keys < 0] == 0).all()
    assert pixels > 10_000
    # The target: 99 % for both (measured 99.2 % / 99.1 % here; 99.5 % / 99.5 % with 2 cm
    # voxels and 8-block tiles). Without the ghosts and the stand-ins for the other shards' blocks
    # (raycast.py) this was 82 % / 82 %; one volume against itself moved 1 mm: 96.6 %.
    print(f"composite vs single: depth {depth_ok / pixels:.4f}, keys {keys_ok / pixels:.4f}")
    assert depth_ok / pixels >= 0.99, depth_ok / pixels
    assert keys_ok / pixels >= 0.99, keys_ok / pixels


def test_composited_probes_equal_the_single_volume_probe(maps) -> None:  # noqa: ANN001
    """Frame selection's probe (:mod:`openfusion.mapping.surface_probe`) composites across shards
    as renders do: each shard finds the surface near the frame's depth in its own blocks."""
    whole, parts = maps
    keys_ok = pixels = 0
    for f in FRAMES[1::3]:
        depth = resize_nearest(f.depth_m(), (60, 80)).astype(np.float32)
        ref = whole.probe(f.T_world_cam, K, depth)
        views = [p.probe(f.T_world_cam, K, depth) for p in parts]
        keys, _conf, depth_c = shards.composite_renders([(v.key_map, v.conf_map, v.depth_m) for v in views])
        seen = (ref.depth_m > 0) | (depth_c > 0)
        pixels += int(seen.sum())
        keys_ok += int((keys == ref.key_map)[seen].sum())
    assert pixels > 10_000
    assert keys_ok / pixels >= 0.99, keys_ok / pixels


def test_composite_rules_and_bad_input() -> None:
    d1 = np.array([[1.0, 0.0, 2.0]], np.float32)
    d2 = np.array([[1.5, 0.0, 1.0]], np.float32)
    k1, k2 = np.array([[1, 2, 3]], np.int32), np.array([[4, 5, 6]], np.int32)
    c1, c2 = np.full((1, 3), 0.5, np.float32), np.full((1, 3), 0.9, np.float32)
    keys, conf, depth = shards.composite_renders([(k1, c1, d1), (k2, c2, d2)])
    np.testing.assert_array_equal(keys, [[1, -1, 6]])
    np.testing.assert_array_equal(depth, [[1.0, 0.0, 1.0]])
    np.testing.assert_array_equal(conf, np.array([[0.5, 0.0, 0.9]], np.float32))
    with pytest.raises(ValueError, match="at least one"):
        shards.composite_renders([])
    with pytest.raises(ValueError, match="must be"):  # bad input: renders of two sizes
        shards.composite_renders([(k1, c1, d1), (k2[:, :2], c2[:, :2], d2[:, :2])])


# ---------------------------------------------------------------------------- read-outs merged
def _triangle_set(vertices: np.ndarray, triangles: np.ndarray) -> set[bytes]:
    """Each triangle as the bytes of its three corner positions in a fixed order (any vertex order)."""
    corners = np.ascontiguousarray(vertices[triangles], np.float32).view(np.dtype((np.void, 12))).reshape(len(triangles), 3)
    return {row.tobytes() for row in np.sort(corners, axis=1)}


def test_merged_read_outs_equal_the_single_volume(maps) -> None:  # noqa: ANN001
    whole, parts = maps
    ref_pts = whole.extract_points()
    part_pts = [p.extract_points() for p in parts]
    pts, _, keys, cut = shards.concat_points([(p.points, p.colors, p.keys) for p in part_pts])
    assert not cut
    # The shards' points are exactly the single volume's (same voxels; the ghosts give a shard the
    # crossings from its last voxel into the next tile, and each point is kept by one shard only).
    def rows(a: np.ndarray) -> set[bytes]:
        return {r.tobytes() for r in np.round(np.asarray(a, np.float64) / 1e-4).astype(np.int64)}

    assert rows(pts) == rows(ref_pts.points)
    assert abs(len(pts) - len(ref_pts.points)) <= 2  # Open3D emits a crossing twice now and then
    # Region summaries: every region's count, centroid and box as the single map's (the keys of
    # points differ where the shards' updates saw other voxels, docs/SHARDS.md: 5 % of labelled points at most).
    ref = RegionTable.of_points(ref_pts.keys, ref_pts.points)
    tables = [RegionTable.of_points(p.keys, p.points) for p in part_pts]
    k, n, lo, hi, cen = shards.merge_region_tables([(t.keys, t.num_points, t.bbox_min, t.bbox_max, t.centroid)
                                                    for t in tables])
    moved = 0
    for key in ref.keys:
        i, j = int(np.searchsorted(k, key)), ref.row(int(key))
        got_n = int(n[i]) if i < len(k) and k[i] == key else 0
        moved += abs(got_n - int(ref.num_points[j]))
        if ref.num_points[j] >= 5000:
            np.testing.assert_allclose(cen[i], ref.centroid[j], atol=0.05)
    assert moved <= 0.05 * int(ref.num_points.sum()), moved / int(ref.num_points.sum())
    # Capped points: uniformly subsampled to the cap, said so.
    capped = shards.concat_points([(p.points, p.colors, p.keys) for p in part_pts], max_points=1000)
    assert len(capped[0]) == 1000 and capped[3]
    # Meshes: one mesh, its seams welded: the single volume's vertices and triangles.
    meshes = [p.extract_mesh() for p in parts]
    v, t, c, mk = shards.concat_meshes([(m.vertices, m.triangles, m.colors, m.keys) for m in meshes])
    one = whole.extract_mesh()
    assert len(v) < sum(len(m.vertices) for m in meshes)  # the seams' copies merged
    assert len(v) == len(one.vertices)
    # Every triangle is one of the single volume's; a shard keeps a triangle by its centroid's cube,
    # so one lying flat on a seam face may be left by both sides (measured: 2 of 366,991).
    got, ref = _triangle_set(v, t), _triangle_set(one.vertices, one.triangles)
    assert got <= ref and len(ref) - len(got) <= 1e-4 * len(ref), (len(got), len(ref))
    np.testing.assert_array_equal(v[t[-1]], meshes[1].vertices[meshes[1].triangles[-1]])


def test_merged_contacts_add_up() -> None:
    a = (np.array([1, 2]), np.array([10, 5]), np.array([1]), np.array([2]), np.array([3]), np.array([2]))
    b = (np.array([2, 3]), np.array([4, 7]), np.array([1, 2]), np.array([2, 3]), np.array([1, 4]), np.array([1, 2]))
    keys, surf, pa, pb, ca, cb = shards.merge_contacts([a, b])
    np.testing.assert_array_equal(keys, [1, 2, 3])
    np.testing.assert_array_equal(surf, [10, 9, 7])
    np.testing.assert_array_equal(np.stack([pa, pb, ca, cb]), [[1, 2], [2, 3], [4, 4], [3, 2]])
