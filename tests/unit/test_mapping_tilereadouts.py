"""Region summaries and region contacts kept per tile (map core, no bus).

The reference is always the whole map at once: ``RegionTable.of_points`` of every surface point and
``block_contacts`` of every labelled block. The per-tile parts must add up to exactly that (boxes,
counts, contacts equal; centroids to float rounding), with tiles paged out, after merges, cleared
keys and new frames, while reading out again only the tiles whose neighbourhood changed."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from openfusion.mapping import SemanticVolume, VolumeParams, chunkreadouts, tilereadouts
from openfusion.mapping.merging import RegionContacts, block_contacts
from openfusion.mapping.summaries import RegionTable
from openfusion.sources import open_source

FRAMES = list(open_source("synthetic:seed=1,frames=12,width=160,height=120,lap=12"))
# 4 cm voxels and 2-block tiles: many small tiles, so regions span many of them.
BASE = {"voxel_size_m": 0.04, "tile_blocks": 2, "depth_max_m": 4.0}
K = FRAMES[0].intrinsics.scaled(80, 60)


def _labelled(volume: SemanticVolume, frames: list, first_key: int = 0) -> None:  # noqa: ANN001
    for i, f in enumerate(frames):
        volume.integrate(f)
        if i % 3 == 0:  # vertical bands of keys, a new set every update
            keys = (np.arange(80)[None].repeat(60, 0) // 10 + first_key + i).astype(np.int32)
            volume.apply_update(f.T_world_cam, K, keys, np.full((60, 80), 0.7, np.float32))


def _reference(volume: SemanticVolume) -> RegionTable:
    pts = volume.extract_points()
    return RegionTable.of_points(pts.keys, pts.points)


def _assert_same_table(got: RegionTable, ref: RegionTable) -> None:
    assert len(ref) > 5
    np.testing.assert_array_equal(got.keys, ref.keys)
    np.testing.assert_array_equal(got.num_points, ref.num_points)
    np.testing.assert_array_equal(got.bbox_min, ref.bbox_min)
    np.testing.assert_array_equal(got.bbox_max, ref.bbox_max)
    np.testing.assert_allclose(got.centroid, ref.centroid, rtol=0, atol=1e-6)  # sums added in another order


def _assert_same_contacts(got: RegionContacts, ref: RegionContacts) -> None:
    assert len(ref.pair_a) > 0
    for name in ("keys", "surface_voxels", "pair_a", "pair_b", "contact_a", "contact_b"):
        np.testing.assert_array_equal(getattr(got, name), getattr(ref, name), err_msg=name)


def _read(volume: SemanticVolume, what: str) -> int:
    return volume._readouts.stats[f"{what}_tiles_read"]


@pytest.fixture(scope="module")
def paged() -> SemanticVolume:
    """The room mapped with keys under a budget of 75 % of its blocks (tiles paged out)."""
    probe = SemanticVolume(VolumeParams(**BASE))
    _labelled(probe, FRAMES)
    budget = 0.75 * probe.num_blocks * 8192 / 2**20
    probe.close()
    volume = SemanticVolume(VolumeParams(**BASE, memory_budget_mb=budget))
    _labelled(volume, FRAMES)
    assert volume.pager.stored_blocks
    yield volume
    volume.close()


def test_summaries_per_tile_equal_the_whole_surface_and_only_changed_tiles_are_read_again(paged: SemanticVolume) -> None:
    """Exact against the whole surface's table; an unchanged map reads no tile, a merge only the
    tiles whose read-out vote read the merged-away key (none without the vote), a cleared key only
    the tiles holding it, a frame only the tiles around what it changed."""
    v = paged
    every = len(v.pager.all_tiles())
    _assert_same_table(v.region_table(), _reference(v))
    assert _read(v, "summary") == every
    v.region_table()
    assert _read(v, "summary") == every  # nothing changed: nothing read
    ref = _reference(v)
    a, b = int(ref.keys[0]), int(ref.keys[1])
    v.relabel_keys({a: b})  # a merge: the parts speak slots; only the votes around key a change
    _assert_same_table(v.region_table(), _reference(v))
    merged = _read(v, "summary") - every
    assert 0 < merged < every / 4
    v.relabel_keys({int(ref.keys[2]): -1})  # a cleared key: the fill labels its points anew
    _assert_same_table(v.region_table(), _reference(v))
    cleared = _read(v, "summary") - every - merged
    assert 0 < cleared < every
    v.integrate(FRAMES[-1])
    _assert_same_table(v.region_table(), _reference(v))
    assert 0 < _read(v, "summary") - every - merged - cleared < every


def test_without_the_vote_a_merge_reads_no_tile_and_the_table_stays_exact() -> None:
    """``label_vote_radius_m`` 0: no point's slot depends on another's key, so a merge reads
    nothing and the parts still add up to the whole surface's table."""
    volume = SemanticVolume(VolumeParams(**BASE, label_vote_radius_m=0.0))
    _labelled(volume, FRAMES[:6])
    ref = _reference(volume)
    _assert_same_table(volume.region_table(), ref)
    every = _read(volume, "summary")
    volume.relabel_keys({int(ref.keys[0]): int(ref.keys[1])})
    _assert_same_table(volume.region_table(), _reference(volume))
    assert _read(volume, "summary") == every
    volume.close()


def test_a_part_that_kept_too_few_values_is_read_again_until_the_box_is_exact(monkeypatch: pytest.MonkeyPatch) -> None:
    """With parts keeping 2 values per axis, most regions' percentiles need more of some tile: the
    check finds them, those tiles are read again keeping enough, and the box comes out exact."""
    monkeypatch.setattr(chunkreadouts, "KEEP_MIN", 2)
    monkeypatch.setattr(chunkreadouts, "KEEP_SHARE", 0.0)
    volume = SemanticVolume(VolumeParams(**BASE))
    _labelled(volume, FRAMES[:6])
    _assert_same_table(volume.region_table(), _reference(volume))
    assert volume._readouts.keep  # tiles were asked to keep more
    assert _read(volume, "summary") > len(volume.pager.all_tiles())  # and read again
    volume.close()


def test_contacts_per_tile_equal_block_contacts_and_a_merge_recounts_only_its_tiles() -> None:
    volume = SemanticVolume(VolumeParams(**BASE))
    _labelled(volume, FRAMES[:7])
    _assert_same_contacts(volume.region_contacts(), block_contacts(*volume.labelled_blocks()))
    every = _read(volume, "contact")
    volume.region_contacts()
    assert _read(volume, "contact") == every
    c = volume.region_contacts()
    volume.relabel_keys({int(c.pair_b[0]): int(c.pair_a[0])})
    _assert_same_contacts(volume.region_contacts(), block_contacts(*volume.labelled_blocks()))
    assert 0 < _read(volume, "contact") - every < every
    volume.close()


def test_a_chunk_whose_labelled_points_all_lie_in_its_halo_gives_empty_parts(monkeypatch: pytest.MonkeyPatch) -> None:
    """One tile per chunk: a tile whose own blocks hold no labelled surface point, while its halo
    (the neighbours' blocks) does, has an empty part; the table still equals the whole surface's
    (a building's final save failed here with an IndexError and no map was saved)."""
    monkeypatch.setattr(tilereadouts, "CHUNK_BLOCKS", 1)
    volume = SemanticVolume(VolumeParams(**BASE))
    try:
        _labelled(volume, FRAMES[:6])
        _assert_same_table(volume.region_table(), _reference(volume))
    finally:
        volume.close()


def test_paged_out_tiles_parts_come_from_the_part_store_without_decoding(monkeypatch: pytest.MonkeyPatch) -> None:
    """Parts of tiles that leave the grid go to the part store (memory keeps an index); the next
    summaries and contacts read those small parts, never decode the tiles again while nothing
    changed around them, and still equal the whole map's. A merge rewrites the stored contact parts
    that hold only its merged-away key instead of counting their tiles again. Bad input tried: a
    part store entry that went missing (the part is dropped and its tile read out again)."""
    probe = SemanticVolume(VolumeParams(**BASE))
    _labelled(probe, FRAMES)
    budget = 0.75 * probe.num_blocks * 8192 / 2**20
    probe.close()
    v = SemanticVolume(VolumeParams(**BASE, memory_budget_mb=budget))
    try:
        _labelled(v, FRAMES[:6])
        v.region_table()
        v.region_contacts()
        _labelled(v, FRAMES[6:])  # walk on: tiles read out above leave the grid
        parts = v._readouts
        stored = [t for t in v.pager.stored_blocks if isinstance(parts.summaries.get(t), tilereadouts.StoredPart)]
        assert stored and parts.stats["parts_to_store"] >= len(stored)
        assert all(isinstance(parts.contacts.get(t), tilereadouts.StoredPart) for t in stored)
        decoded: list[tuple] = []
        real = chunkreadouts.decode_tile

        def counted(codec, blob, where="tile"):  # noqa: ANN001, ANN202
            decoded.append(where)
            return real(codec, blob, where)

        monkeypatch.setattr(chunkreadouts, "decode_tile", counted)
        stale = {t for chunk in parts.stale(dict(parts.summaries)) for t in chunk}
        stale |= {t for chunk in parts.stale(dict(parts.contacts)) for t in chunk}
        before = parts.stats["parts_from_store"]
        _assert_same_table(v.region_table(), _reference(v))
        _assert_same_contacts(v.region_contacts(), block_contacts(*v.labelled_blocks()))
        assert parts.stats["parts_from_store"] - before >= 2 * len(stored)
        # Every decode was of a stale tile or a stale tile's neighbour (its halo), none of the stored
        # tiles whose neighbourhood is unchanged.
        halo = {(t[0] + dx, t[1] + dy, t[2] + dz) for t in stale for dx in (-1, 0, 1) for dy in (-1, 0, 1) for dz in (-1, 0, 1)}
        quiet = [t for t in stored if t not in halo]
        assert quiet
        assert not [w for w in decoded if any(w == f"tile {t}" for t in quiet)]
        decoded.clear()
        v.region_table()
        v.region_contacts()
        assert not decoded  # nothing changed: nothing decoded at all
        # A merge of a key into one a stored part does not hold: rewritten in place, not recounted.
        c = v.region_contacts()
        read = _read(v, "contact")
        b, a = int(c.keys[-1]), int(c.keys[0])
        v.relabel_keys({b: a})
        _assert_same_contacts(v.region_contacts(), block_contacts(*v.labelled_blocks()))
        assert parts.stats["contact_parts_relabelled"] > 0
        assert _read(v, "contact") - read < len(v.pager.all_tiles())
        # A cleared key: its rows and pairs leave the parts that hold it, exactly.
        relabelled = parts.stats["contact_parts_relabelled"]
        v.relabel_keys({int(v.region_contacts().keys[1]): -1})
        _assert_same_contacts(v.region_contacts(), block_contacts(*v.labelled_blocks()))
        assert parts.stats["contact_parts_relabelled"] > relabelled
        # A stored part gone missing: dropped, and its tile read out again (exact all the same).
        parts.part_store.delete("summaries", quiet[0])
        _assert_same_table(v.region_table(), _reference(v))
    finally:
        v.close()
    assert v._readouts.part_store is None


def test_a_summary_part_keeps_the_slots_its_vote_read_through_the_part_store() -> None:
    """A paged-out tile's part keeps ``seen`` on disk and in its index, so a merge of a slot its
    vote read drops it even while the tile is paged out; a part stored before ``seen`` existed
    reads as having seen none."""
    from openfusion.mapping.tileparts import SummaryPart, part_arrays, part_of, stored_index

    part = SummaryPart(7, np.array([2, 5], np.int64), np.array([10, 3], np.int64), np.ones((2, 3)),
                       low=[[np.zeros(1)] * 3] * 2, high=[[np.zeros(1)] * 3] * 2, seen=np.array([5, 9], np.int64))
    back = part_of("summaries", part_arrays(part))
    np.testing.assert_array_equal(back.seen, [5, 9])
    assert back.holds(np.array([9])) and not back.holds(np.array([4]))
    assert stored_index("summaries", part).holds(np.array([9]))
    old = part_arrays(part)
    del old["seen"]
    assert len(part_of("summaries", old).seen) == 0


def test_radii_that_reach_past_the_halo_are_refused_and_those_that_fit_read_out_exactly(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Bad input tried: 4-voxel blocks (8 cm at 2 cm voxels) with the default fill and vote radii
    (6 + 4.5 cm + a voxel > 8 cm), refused at construction with the three numbers named (built
    anyway, the per-tile summaries leave points in other regions than the whole map's read-out:
    the check is not needless). Radii that fit the same blocks give summaries equal to the whole
    surface's table."""
    small = {"block_resolution": 4, "tile_blocks": 4}
    with pytest.raises(ValidationError, match=r"= 0\.125 m exceeds one block \(4 voxels x 0\.02 m = 0\.08 m\)"):
        VolumeParams(**small)
    monkeypatch.setattr(VolumeParams, "with_changes", lambda self, **changes: self.model_copy(update=changes))
    forced = SemanticVolume(VolumeParams.model_construct(**{**VolumeParams().model_dump(), **small}))
    _labelled(forced, FRAMES[:12])
    got, ref = forced.region_table(), _reference(forced)
    forced.close()
    assert not np.array_equal(got.num_points, ref.num_points)
    monkeypatch.undo()
    volume = SemanticVolume(VolumeParams(**small, label_fill_radius_m=0.03, label_vote_radius_m=0.03))
    _labelled(volume, FRAMES[:12])
    _assert_same_table(volume.region_table(), _reference(volume))
    volume.close()


def test_a_merge_reads_again_only_the_tiles_where_the_merged_region_took_part_in_a_vote() -> None:
    """Six merges in a row, each key into the next: the table stays exact after every one, and
    together they read fewer tiles again than held the merged keys' points (a tile whose points of
    the key have only that key around them keeps its part: no vote there can change)."""
    volume = SemanticVolume(VolumeParams(**BASE))
    _labelled(volume, FRAMES)
    _assert_same_table(volume.region_table(), _reference(volume))
    read = holding = 0
    for _ in range(6):
        ref = _reference(volume)
        a, b = int(ref.keys[0]), int(ref.keys[1])
        slots_a = np.flatnonzero(volume._storage.slots.key1 == a + 1)
        holding += sum(bool(np.isin(slots_a, p.slots).any()) for p in volume._readouts.summaries.values())
        before = _read(volume, "summary")
        volume.relabel_keys({a: b})
        _assert_same_table(volume.region_table(), _reference(volume))
        read += _read(volume, "summary") - before
    volume.close()
    assert 0 < read < holding
