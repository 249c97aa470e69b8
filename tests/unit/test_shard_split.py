"""A shard's per-frame split of the touched blocks (mapping/shards.py): the fast ownership and ghost
masks equal the rule as written (the owner of every block and of its 7 lower neighbours hashed one
by one), and the batched record of other shards' blocks answers what a per-frame record did."""

from __future__ import annotations

import numpy as np
import pytest

from openfusion.mapping import SemanticVolume, VolumeParams, shards
from openfusion.sources import open_source
from openfusion.wire.keys import ShardId


def _rule(coords: np.ndarray, tile_blocks: int, shard: ShardId) -> tuple[np.ndarray, np.ndarray]:
    """The ghost rule block by block: owned, or not owned with a block of an owned tile in -u."""
    owned = shards.shard_of_tiles(np.floor_divide(coords, tile_blocks), shard.count) == shard.index
    ghost = np.zeros(len(coords), bool)
    for i, c in enumerate(coords):
        if owned[i]:
            continue
        below = np.floor_divide(c - shards._UPPER, tile_blocks)
        ghost[i] = bool((shards.shard_of_tiles(below, shard.count) == shard.index).any())
    return owned, owned | ghost


@pytest.mark.parametrize("seed", range(6))
def test_take_blocks_equals_the_rule_block_by_block(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = int(rng.integers(2, 5))
    tile_blocks = int(rng.integers(1, 9))
    # Negative coordinates too: the tile of -1 is -1 (floor division), its lower face at -tile_blocks.
    coords = rng.integers(-3 * tile_blocks - 2, 3 * tile_blocks + 2, size=(600, 3))
    for index in range(n):
        shard = ShardId(index, n)
        owned, taken = shards.take_blocks(coords, tile_blocks, shard)
        want_owned, want_taken = _rule(coords, tile_blocks, shard)
        np.testing.assert_array_equal(owned, want_owned)
        np.testing.assert_array_equal(taken, want_taken)
        np.testing.assert_array_equal(owned, shards.owned_blocks(coords, tile_blocks, shard))
        np.testing.assert_array_equal(shards.ghost_blocks(coords, owned, tile_blocks, shard), taken & ~owned)
        assert taken[~owned].any(), "a random cube of blocks has ghosts"


def test_take_blocks_of_an_unsharded_map_and_of_nothing() -> None:
    coords = np.array([[0, 0, 0], [-1, 5, 9]])
    owned, taken = shards.take_blocks(coords, 8, ShardId())
    assert owned.all() and taken.all()
    owned, taken = shards.take_blocks(np.zeros((0, 3), np.int32), 8, ShardId(1, 2))
    assert owned.shape == taken.shape == (0,)
    assert not shards.ghost_blocks(np.zeros((0, 3)), np.zeros(0, bool), 8, ShardId(0, 2)).any()


def test_other_blocks_batched_record_answers_as_each_frame_merged() -> None:
    rng = np.random.default_rng(3)
    record = shards.OtherBlocks(4)
    record.PENDING_MAX = 500  # a merge while frames are still added, and pending ones at the end
    seen: set[tuple[int, int, int]] = set()
    for _ in range(30):
        frame = rng.integers(-12, 12, size=(int(rng.integers(0, 80)), 3))
        record.add(frame)
        seen.update(tuple(int(v) for v in c) for c in frame)
        record.add(np.zeros((0, 3), np.int64))  # an empty frame adds nothing
    assert len(record) == len(seen)
    tiles = record.tiles()
    want_tiles = {tuple(int(v) for v in np.floor_divide(c, 4)) for c in seen}
    assert {tuple(int(v) for v in t) for t in tiles} == want_tiles
    some = tiles[::3]
    got = {tuple(int(v) for v in c) for c in record.blocks_of(some)}
    wanted = {c for c in seen if tuple(int(v) for v in np.floor_divide(c, 4)) in {tuple(t) for t in some.tolist()}}
    assert got == wanted and record.blocks_of(some).dtype == np.int32
    record.add(np.array([[100, 100, 100]]))
    record.clear()
    assert len(record) == 0 and len(record.tiles()) == 0


def test_a_cleared_shard_forgets_the_other_shards_blocks() -> None:
    frame = next(iter(open_source("synthetic:seed=1,frames=1,width=80,height=60")))
    volume = SemanticVolume(VolumeParams(voxel_size_m=0.03, tile_blocks=4, shard="1/2"))
    stats = volume.integrate(frame)
    assert stats.blocks_not_owned > 0 and len(volume._others) > 0
    volume.clear()  # a reset: no stand-ins remain for blocks of the map that was
    assert len(volume._others) == 0 and volume.num_blocks == 0
    volume.close()
