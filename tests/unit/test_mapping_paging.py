"""Tiles, the tile store, the memory budget and incremental checkpoints (map core, no bus).

The reference everywhere is the same frames mapped without a budget: a map whose tiles were paged
out and back in must equal it voxel for voxel, and read-outs of a map with tiles paged out must
equal the read-outs of the whole map in one grid."""

from __future__ import annotations

import numpy as np
import pytest

from openfusion.errors import OpenFusionError
from openfusion.mapping import (
    CapacityError,
    MapFormatError,
    RegionDictionary,
    SemanticVolume,
    VolumeParams,
    load_map,
    save_map,
)
from openfusion.mapping.keyslots import KeySlots
from openfusion.mapping.mapstore import checkpoint
from openfusion.mapping.storage import MAX_WEIGHT, WEIGHT_CLAMP_EVERY
from openfusion.mapping.tiles import TileGrid, TileVersions, pack_coords, tile_key, tile_of_key, unpack_coords
from openfusion.mapping.tilestore import TileStore, decode_tile, encode_tile, make_codec
from openfusion.sources import open_source

FRAMES = list(open_source("synthetic:seed=1,frames=24,width=160,height=120,lap=24"))
# 4 cm voxels, 2-block tiles and a 4 m range: one frame touches a quarter of the room's blocks.
BASE = {"voxel_size_m": 0.04, "tile_blocks": 2, "depth_max_m": 4.0}



def _map(budget: float | None, frames: list = FRAMES, store: TileStore | None = None) -> SemanticVolume:  # noqa: ANN001
    volume = SemanticVolume(VolumeParams(**BASE, memory_budget_mb=budget), store=store)
    for f in frames:
        volume.integrate(f)
    return volume


def _sorted(arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    order = np.lexsort(arrays["block_coords"].T)
    return {k: v[order] for k, v in arrays.items()}


def _assert_same_map(a: SemanticVolume, b: SemanticVolume) -> None:
    x, y = _sorted(a.to_arrays()), _sorted(b.to_arrays())
    assert len(x["block_coords"]) == len(y["block_coords"])
    for name in x:
        np.testing.assert_array_equal(x[name], y[name], err_msg=name)


_REFERENCE = _map(None)
#: 60 % of the room's blocks: tiles leave and come back during one lap.
BUDGET_MB = 0.6 * _REFERENCE.num_blocks * 8192 / 2**20


@pytest.fixture(scope="module")
def reference() -> SemanticVolume:
    return _REFERENCE


@pytest.fixture(scope="module")
def paged() -> SemanticVolume:
    volume = _map(BUDGET_MB)
    yield volume
    volume.close()


def test_a_budget_pages_tiles_out_and_back_and_changes_nothing(reference: SemanticVolume, paged: SemanticVolume) -> None:
    """Under the budget the resident blocks never exceed it, tiles went out and came back (the
    lap revisits walls), and the map equals the map made without a budget, voxel for voxel."""
    stats = paged.pager.stats
    assert stats.tiles_paged_out > 0 and stats.tiles_paged_in > 0
    assert paged.num_blocks <= paged.budget_blocks < reference.num_blocks
    assert paged.resident_bytes == paged.budget_blocks * 8192
    assert paged.num_blocks_total == reference.num_blocks
    _assert_same_map(paged, reference)


def test_read_outs_see_the_whole_map_while_tiles_are_paged_out(reference: SemanticVolume, paged: SemanticVolume) -> None:
    """Points (sorted, keys included), meshes (vertices, triangles) and labelled blocks of a map with
    tiles in the store equal those of the whole map in one grid; the read-out pages nothing in."""
    assert paged.pager.stored_blocks
    resident_before = paged.num_blocks
    a, b = paged.extract_points(), reference.extract_points()
    np.testing.assert_array_equal(a.points, b.points)
    np.testing.assert_array_equal(a.colors, b.colors)
    np.testing.assert_array_equal(a.keys, b.keys)
    # The mesh read out chunk by chunk, its seams welded: the same vertices and triangles as in one grid.
    ma, mb = paged.extract_mesh(), reference.extract_mesh()
    assert (len(ma.vertices), len(ma.triangles)) == (len(mb.vertices), len(mb.triangles))
    np.testing.assert_array_equal(np.unique(ma.vertices[ma.triangles].reshape(-1, 9), axis=0),
                                  np.unique(mb.vertices[mb.triangles].reshape(-1, 9), axis=0))
    assert paged.num_blocks == resident_before


def test_a_key_filtered_read_out_reads_only_the_tiles_of_those_keys() -> None:
    """Points of one region from a map with tiles paged out equal the whole map's points of it."""
    volume, ref = _map(BUDGET_MB, FRAMES[:4]), _map(None, FRAMES[:4])
    try:
        K = FRAMES[0].intrinsics.scaled(80, 60)
        keys = np.full((60, 80), 4, np.int32)
        keys[:, 40:] = 9
        for v in (volume, ref):
            v.apply_update(FRAMES[0].T_world_cam, K, keys, np.full((60, 80), 0.7, np.float32))
            for f in FRAMES[4:]:
                v.integrate(f)
        assert volume.pager.stored_blocks
        # Stored tiles are told apart by the key slots recorded when they left: a tile without
        # key 4 is not decoded to find that out (a query's points on a floor read only its tiles).
        pager = volume.pager
        assert set(pager.stored_slots) == set(pager.stored_blocks)
        decoded: list = []
        read = pager._read
        pager._read = lambda t: decoded.append(t) or read(t)  # type: ignore[method-assign]
        a, b = volume.extract_points(keys=[4]), ref.extract_points(keys=[4])
        assert len(a) > 0
        np.testing.assert_array_equal(a.points, b.points)
        slot4 = int(np.flatnonzero(volume._storage.slots.key1 == 5)[0])
        without_4 = {t for t, slots in pager.stored_slots.items() if slot4 not in slots}
        assert without_4, "the scene should leave some stored tiles without key 4"
        decoded.clear()
        assert len(volume.extract_points(keys=[12345])) == 0 and not decoded  # no tile read for an unknown key
        volume.extract_points(keys=[4])
        assert decoded and len(set(decoded) & without_4) < len(without_4)  # only tiles near key 4's
    finally:
        volume.close()


def test_render_pages_in_what_the_view_reaches(reference: SemanticVolume) -> None:
    """A render from the first pose after the camera moved on: the tiles it sees are read back,
    so its depth image equals the whole map's."""
    volume = _map(BUDGET_MB)
    try:
        assert volume.pager.stored_blocks
        K = FRAMES[0].intrinsics
        a = volume.render(FRAMES[0].T_world_cam, K)
        b = reference.render(FRAMES[0].T_world_cam, K)
        np.testing.assert_array_equal(a.depth_m, b.depth_m)
    finally:
        volume.close()


def test_semantics_survive_paging_and_a_merge_reaches_stored_tiles() -> None:
    """Keys written into voxels, the tiles paged out, a merge {7: 3} applied while they are out:
    read back, every voxel of 7 reads 3 (the slot table is global), confidences kept."""
    volume = _map(BUDGET_MB, FRAMES[:2])
    try:
        K = FRAMES[0].intrinsics.scaled(80, 60)
        keys = np.full((60, 80), 7, np.int32)
        keys[:, :40] = 5
        volume.apply_update(FRAMES[0].T_world_cam, K, keys, np.full((60, 80), 0.6, np.float32))
        labelled = {k: int((volume.to_arrays()["key"] == k).sum()) for k in (5, 7)}
        assert labelled[5] > 0 and labelled[7] > 0
        for f in FRAMES[2:]:  # walk on: the first view's tiles leave
            volume.integrate(f)
        assert volume.pager.stats.tiles_paged_out > 0
        _, before = volume.labelled_blocks()  # reads (and caches) the stored tiles' key slots
        assert int((before == 7).sum()) == labelled[7]
        volume.relabel_keys({7: 3})
        _, after = volume.labelled_blocks()  # the cache holds slots: the merge shows through
        assert int((after == 7).sum()) == 0 and int((after == 3).sum()) == labelled[7]
        arrays = volume.to_arrays()
        assert int((arrays["key"] == 7).sum()) == 0
        assert int((arrays["key"] == 3).sum()) == labelled[7]
        np.testing.assert_allclose(arrays["conf"][arrays["key"] == 3], 0.6, atol=1e-4)
        r = volume.render(FRAMES[0].T_world_cam, K)  # pages the first view back in
        assert set(np.unique(r.key_map)) <= {-1, 3, 5} and (r.key_map == 3).any()
    finally:
        volume.close()


def test_a_frame_larger_than_the_budget_is_refused_whole() -> None:
    """Bad input: a budget smaller than one frame needs. CapacityError naming the budget, and
    nothing of the frame is written; the volume keeps working for a frame that fits."""
    volume = SemanticVolume(VolumeParams(**BASE, memory_budget_mb=0.5))
    try:
        with pytest.raises(CapacityError, match="memory budget"):
            volume.integrate(FRAMES[0])
        assert volume.num_blocks_total == 0
    finally:
        volume.close()


def test_incremental_checkpoints_write_what_changed(tmp_path) -> None:  # noqa: ANN001
    """The first checkpoint writes every tile, one with nothing changed writes none, one after a
    frame writes only tiles that frame touched; the store then loads as the same map."""
    store = TileStore(tmp_path / "map.ofz")
    volume = _map(None, FRAMES[:8], store=store)
    d = RegionDictionary("none", 1)
    first = checkpoint(volume, d, {"n": 8})
    assert first["tiles"] == len(volume.pager.resident_tiles())
    assert checkpoint(volume, d, {"n": 8})["tiles"] == 0
    volume.integrate(FRAMES[8])
    touched = {tuple(t) for t in volume.pager.grid.group_blocks(volume._storage.active_blocks()[0])[0]}
    third = checkpoint(volume, d, {"n": 9})
    assert 0 < third["tiles"] < first["tiles"] and third["tiles"] <= len(touched)
    expected = volume.to_arrays()
    volume.close()
    loaded = load_map(tmp_path)
    assert loaded.meta["n"] == 9
    got = loaded.volume.to_arrays()
    a, b = _sorted(expected), _sorted(got)
    for name in a:
        np.testing.assert_array_equal(a[name], b[name])


def test_saved_map_loads_lazily_under_a_budget(tmp_path, reference: SemanticVolume) -> None:  # noqa: ANN001
    """A map folder loaded with a memory budget reads no tile at load; read-outs still see it all."""
    save_map(tmp_path, reference, RegionDictionary("none", 1))
    loaded = load_map(tmp_path, memory_budget_mb=BUDGET_MB)
    try:
        assert loaded.volume.num_blocks == 0 and loaded.volume.num_blocks_total == reference.num_blocks
        np.testing.assert_array_equal(loaded.volume.extract_points().points, reference.extract_points().points)
    finally:
        loaded.volume.close()


def test_key_slots_compact_when_full_and_refuse_only_live_keys() -> None:
    """With 4 slots: keys cleared or merged leave garbage slots that a compaction reclaims (the
    voxels of paged-out tiles included); 5 keys really present at once are refused with a
    CapacityError and nothing written."""
    volume = _map(BUDGET_MB, FRAMES[:2])
    try:
        storage = volume._storage
        storage.slots = KeySlots(max_slots=4)
        K = FRAMES[0].intrinsics.scaled(80, 60)
        keys = np.repeat(np.arange(4, dtype=np.int32), 20)[None].repeat(60, axis=0)
        volume.apply_update(FRAMES[0].T_world_cam, K, keys, np.full((60, 80), 0.9, np.float32))
        assert storage.slots.free_slots == 0
        for f in FRAMES[2:]:  # page the labelled tiles out
            volume.integrate(f)
        volume.relabel_keys({0: -1, 1: 2})  # two slots become garbage
        before = volume.to_arrays()["key"]
        keys2 = np.where(keys == 1, 2, keys)  # 1 was merged into 2
        keys2[keys == 0] = 11  # key 11 is new: needs a slot -> compaction frees the two
        volume.apply_update(FRAMES[0].T_world_cam, K, keys2, np.full((60, 80), 0.9, np.float32))
        after = volume.to_arrays()["key"]
        assert set(np.unique(after)) - {-1} == {2, 3, 11}
        assert storage.slots.used_slots == 3
        assert int((after == 2).sum()) >= int((before == 2).sum()) - int((before == 2).sum()) // 2
        with pytest.raises(CapacityError, match="distinct region keys"):
            storage.slots.slots_for(np.array([21, 22, 23, 24, 25]), compact=storage.compact_keys)
        assert isinstance(CapacityError("x", blocks_needed=1, blocks_free=0), OpenFusionError)
    finally:
        volume.close()


def test_weights_are_capped_before_uint16_wraps() -> None:
    """Open3D adds 1 per observation to a uint16 weight and wraps at 65,535 (measured); the cap
    keeps every weight at or below MAX_WEIGHT however long the camera stares."""
    volume = _map(None, FRAMES[:1])
    storage = volume._storage
    w = storage.vbg.attribute("weight").numpy()
    w[w > 0] = 65535 - WEIGHT_CLAMP_EVERY + 1
    storage.integrations_since_clamp = WEIGHT_CLAMP_EVERY - 1
    volume.integrate(FRAMES[0])  # the cap runs now
    for _ in range(3):
        volume.integrate(FRAMES[0])
    w = storage.vbg.attribute("weight").numpy()
    assert int(w.max()) <= MAX_WEIGHT + 3 and int(w[w > 0].min()) > 0


def test_tile_vocabulary() -> None:
    grid = TileGrid(tile_blocks=8, block_size_m=0.16)
    blocks = np.array([[0, 0, 0], [7, 7, 7], [8, 0, 0], [-1, 0, 0], [-9, 3, 4]])
    np.testing.assert_array_equal(grid.tiles_of_blocks(blocks), [[0, 0, 0], [0, 0, 0], [1, 0, 0], [-1, 0, 0], [-2, 0, 0]])
    tiles, inverse = grid.group_blocks(blocks)
    np.testing.assert_array_equal(tiles[inverse], grid.tiles_of_blocks(blocks))
    keys = [tile_key(t) for t in [(-2, 0, 0), (-1, 5, 0), (0, -3, 1), (3, 0, 0)]]
    assert keys == sorted(keys) and tile_of_key(keys[1]) == (-1, 5, 0)
    with pytest.raises(ValueError):
        tile_of_key(b"short")
    c = np.array([[-5, 7, 1_000_000], [0, 0, 0]])
    np.testing.assert_array_equal(unpack_coords(pack_coords(c)), c)
    versions = TileVersions()
    versions.touch([(0, 0, 0), (1, 0, 0)])
    snap = versions.dirty()
    versions.touch([(1, 0, 0)])  # changed while the checkpoint was writing
    versions.mark_written(snap)
    assert set(versions.dirty()) == {(1, 0, 0)}


def test_tiles_in_view_never_drop_a_seen_tile() -> None:
    """Conservative frustum test: every tile holding a point the camera sees is kept."""
    grid = TileGrid(tile_blocks=2, block_size_m=0.32)
    f = FRAMES[3]
    K = f.intrinsics
    v, u = np.mgrid[0 : K.height_px : 4, 0 : K.width_px : 4]
    z = f.depth_m()[v, u]
    ok = z > 0
    pts_c = np.stack([(u[ok] - K.cx) * z[ok] / K.fx, (v[ok] - K.cy) * z[ok] / K.fy, z[ok]], axis=1)
    pts_w = pts_c @ f.T_world_cam[:3, :3].T + f.T_world_cam[:3, 3]
    seen = np.unique(np.floor(pts_w / grid.tile_size_m).astype(np.int64), axis=0)
    lo, hi = seen.min(axis=0) - 6, seen.max(axis=0) + 6
    everything = np.stack(np.meshgrid(*[np.arange(a, b) for a, b in zip(lo, hi, strict=True)], indexing="ij"), -1).reshape(-1, 3)
    keep = grid.tiles_in_view(everything, f.T_world_cam, fx=K.fx, fy=K.fy, cx=K.cx, cy=K.cy,
                              width_px=K.width_px, height_px=K.height_px, depth_max_m=6.0)
    kept = {tuple(t) for t in everything[keep]}
    assert all(tuple(t) in kept for t in seen)
    assert keep.mean() < 0.6  # and it does cut: most of the cube is outside the view


def test_tile_blobs_round_trip_and_corruption_is_refused() -> None:
    """Bad input: a flipped byte, a truncated blob and a foreign magic each raise MapFormatError."""
    volume = _map(None, FRAMES[:1])
    coords, buf = volume._storage.active_blocks()
    raw = volume._storage.read_raw_blocks(buf[:5])
    for name in ("zstd", "lz4"):
        codec = make_codec(name)
        blob = encode_tile(codec, coords[:5], raw, 8)
        c2, r2 = decode_tile(codec, blob)
        np.testing.assert_array_equal(c2, coords[:5])
        for k in raw:
            np.testing.assert_array_equal(r2[k], raw[k])
        bad = bytearray(blob)
        bad[-10] ^= 0xFF
        for broken in (bytes(bad), blob[:12], b"XXXX" + blob[4:]):
            with pytest.raises(MapFormatError):
                decode_tile(codec, broken)
    with pytest.raises(MapFormatError, match="unknown tile codec"):
        make_codec("snappy")


def test_paging_through_tensors_as_on_cuda(reference: SemanticVolume) -> None:
    """The tensor code path (what a CUDA grid uses: no numpy views of the buffers), on the CPU:
    paging out and in, erasing and a key compaction give the same map."""
    volume = SemanticVolume(VolumeParams(**BASE, memory_budget_mb=BUDGET_MB))
    volume._storage.use_numpy_views = False
    try:
        for f in FRAMES:
            volume.integrate(f)
        assert volume.pager.stats.tiles_paged_in > 0
        volume._storage.compact_keys()
        _assert_same_map(volume, reference)
    finally:
        volume.close()


def test_each_thread_gets_its_own_zstd_objects() -> None:
    """A checkpoint encodes on one thread while integration pages tiles out on another; zstandard's
    objects are not thread-safe (sharing one crashed geometry with SIGSEGV), so each thread has its own."""
    import threading

    codec = make_codec("zstd")
    seen: list[object] = []
    threads = [threading.Thread(target=lambda: seen.append(codec._pair()[0])) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len({id(c) for c in seen}) == 2 and seen[0] is not codec._pair()[0]
    assert codec.decompress(codec.compress(b"tile" * 100)) == b"tile" * 100


def test_the_grid_grows_in_the_background_and_loses_nothing(reference: SemanticVolume) -> None:
    """A grid that starts with room for 64 blocks grows several times while frames and semantic
    updates go on: copies run beside integration, only what changed meanwhile is copied again
    under the lock, and the result equals the map of a grid that never had to grow."""
    volume = SemanticVolume(VolumeParams(**BASE, initial_block_count=64))
    K = FRAMES[0].intrinsics.scaled(80, 60)
    for i, f in enumerate(FRAMES):
        volume.integrate(f)
        if i == 5:  # a semantic update while a copy may be running: its tiles are copied again
            volume.apply_update(f.T_world_cam, K, np.full((60, 80), 2, np.int32), np.full((60, 80), 0.5, np.float32))
    assert volume._grower is not None and volume._grower.stats.grows >= 2
    ref = SemanticVolume(VolumeParams(**BASE))
    for i, f in enumerate(FRAMES):
        ref.integrate(f)
        if i == 5:
            ref.apply_update(f.T_world_cam, K, np.full((60, 80), 2, np.int32), np.full((60, 80), 0.5, np.float32))
    _assert_same_map(volume, ref)
    volume.close()


def test_a_grid_grown_large_without_a_budget_says_once_what_renders_will_cost(monkeypatch, caplog) -> None:  # noqa: ANN001
    """An operator reading geometry's log learns, once, why renders slow down as the map grows
    with no memory budget (Open3D's CPU ray cast copies the block hash map on every call), and
    which setting bounds it; a grid that stays under the threshold says nothing of it."""
    import logging

    from openfusion.mapping import growth

    def grown_log(threshold: int) -> list[str]:
        monkeypatch.setattr(growth, "RENDER_COST_HINT_BLOCKS", threshold)
        caplog.clear()
        volume = SemanticVolume(VolumeParams(**BASE, initial_block_count=64))
        with caplog.at_level(logging.INFO, logger=growth.__name__):
            for f in FRAMES:
                volume.integrate(f)
        assert volume._grower is not None and volume._grower.stats.grows >= 2
        volume.close()
        return [r.getMessage() for r in caplog.records if "memory_budget_mb" in r.getMessage()]

    hints = grown_log(128)
    assert len(hints) == 1 and "ray cast" in hints[0] and "no memory budget" in hints[0]
    assert grown_log(1 << 30) == []


def test_a_checkpoint_copies_one_slice_at_a_time(tmp_path, monkeypatch) -> None:  # noqa: ANN001
    """A checkpoint of many changed tiles never holds more than a slice of them (plus the last
    step's few) as raw copies, and the store then loads as the same map."""
    from openfusion.mapping import paging

    monkeypatch.setattr(paging, "SLICE_BLOCKS", 40)
    volume = _map(BUDGET_MB, FRAMES[:12], store=TileStore(tmp_path / "map.ofz"))
    copied: list[int] = []
    real = volume.pager.copy_tiles

    def counting(tiles, **kwargs):  # noqa: ANN001, ANN003, ANN202
        out = real(tiles, **kwargs)
        copied.append(sum(len(c) for c, _ in out[0].values()))
        return out

    volume.pager.copy_tiles = counting  # type: ignore[method-assign]
    info = checkpoint(volume, RegionDictionary("none", 1), {"n": 12})
    largest_tile = 2**3  # tile_blocks 2
    assert info["slices"] > 3 and max(copied) <= 40 + largest_tile
    assert sum(copied) >= volume.num_blocks  # every resident tile was written
    expected = _sorted(volume.to_arrays())
    volume.close()
    got = _sorted(load_map(tmp_path).volume.to_arrays())
    for name in expected:
        np.testing.assert_array_equal(expected[name], got[name], err_msg=name)


def test_a_page_out_newer_than_a_slice_wins_and_an_unfinished_checkpoint_is_not_read(tmp_path) -> None:  # noqa: ANN001
    """A slice copies a tile; the camera then changes it and it is paged out (written, newer); the
    slice's older copy must not overwrite it. Slices written but never committed (a writer that
    died) are not part of the map: a reader sees the last committed checkpoint, and the next
    writer deletes them."""
    volume = _map(None, FRAMES[:6], store=TileStore(tmp_path / "map.ofz"))
    d = RegionDictionary("none", 1)
    checkpoint(volume, d, {"n": 6})
    committed = _sorted(volume.to_arrays())
    for f in FRAMES[6:9]:
        volume.integrate(f)
    pager = volume.pager
    plan = volume.checkpoint_plan()
    copies, versions = volume.checkpoint_copy(plan[0])
    tile = next(iter(copies))
    coords, buf = pager._resident_groups()[tile]
    weight = volume._storage.vbg.attribute("weight").numpy()
    weight[buf[0]].reshape(-1)[0] += 1  # the camera changed the tile after the copy...
    pager.versions.touch([tile])
    pager._page_out(tile, coords, buf)  # ...and it left: written into the store, newer than the copy
    assert pager.write_slice(pager.encode(copies), versions) == len(copies) - 1  # the older copy is skipped
    volume.checkpoint_slice_written(versions)
    for tiles in plan[1:]:  # the rest of the passes, then no last step: the writer "dies"
        c, v = volume.checkpoint_copy(tiles)
        pager.write_slice(pager.encode(c), v)
    reader = load_map(tmp_path)
    got = _sorted(reader.volume.to_arrays())
    for name in committed:
        np.testing.assert_array_equal(got[name], committed[name], err_msg=name)
    assert reader.meta["n"] == 6
    # A last step and commit now: the page-out's copy is in the map, not the slice's.
    checkpoint(volume, d, {"n": 9})
    expected = _sorted(volume.to_arrays())
    volume.close()
    got = _sorted(load_map(tmp_path).volume.to_arrays())
    for name in expected:
        np.testing.assert_array_equal(got[name], expected[name], err_msg=name)
    # Uncommitted writes of a writer that died are deleted by the next writer.
    volume = load_map(tmp_path, writable=True).volume
    volume.integrate(FRAMES[9])
    c, v = volume.checkpoint_copy(volume.checkpoint_plan()[0])
    volume.pager.write_slice(volume.pager.encode(c), v)
    volume.close()
    store = TileStore(tmp_path / "map.ofz")
    assert store.discarded_on_open == len(c)
    store.close()


def test_tile_blobs_leave_out_unobserved_voxels_and_fall_back_when_one_holds_a_value() -> None:
    """Format 2 (observed voxels' TSDF and colour only) reads back exactly; a tile whose unobserved
    voxel holds a TSDF is written in format 1, also exactly; format 2 is smaller."""
    volume = _map(None, FRAMES[:2])
    coords, buf = volume._storage.active_blocks()
    raw = volume._storage.read_raw_blocks(buf[:20])
    codec = make_codec("zstd")
    assert (raw["weight"] == 0).any() and (raw["tsdf"] == 1.0).any()
    blob = encode_tile(codec, coords[:20], raw, 8)
    assert blob[4] == 2
    c2, r2 = decode_tile(codec, blob)
    for k in raw:
        np.testing.assert_array_equal(r2[k], raw[k], err_msg=k)
    odd = {k: v.copy() for k, v in raw.items()}
    odd["tsdf"][odd["weight"] == 0] = 0.25
    dense = encode_tile(codec, coords[:20], odd, 8)
    assert dense[4] == 1 and len(dense) > len(blob)
    for k, v in decode_tile(codec, dense)[1].items():
        np.testing.assert_array_equal(v, odd[k], err_msg=k)
    with pytest.raises(MapFormatError):
        decode_tile(codec, blob[:6] + b"\x09" + blob[7:])  # a block count the payload does not hold
