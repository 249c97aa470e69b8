"""A map saved by geometry shards, read under a memory budget (mapping/shardstore.py): the parts
merged into one scratch tile store read as the same map saved as one store (points with keys), as
the resident merge (surface, mesh, summaries, blocks), nothing is read at load, the scratch folder goes with the volume, and a part of another
block layout is refused."""

from __future__ import annotations

import gc
from pathlib import Path

import numpy as np
import pytest

from openfusion.frame import resize_nearest
from openfusion.mapping import (
    MapFormatError,
    RegionDictionary,
    SemanticVolume,
    VolumeParams,
    load_map,
    save_map,
)
from openfusion.mapping.keyslots import KeySlots
from openfusion.mapping.mapfile import load_map_summary
from openfusion.mapping.tilestore import STORE_DIR_NAME, TileStore
from openfusion.sources import open_source

FRAMES = list(open_source("synthetic:seed=1,frames=10,width=160,height=120,lap=10"))
BASE = {"voxel_size_m": 0.05, "tile_blocks": 4, "depth_max_m": 5.0}
K = FRAMES[0].intrinsics.scaled(80, 60)


def _map(shard: str, **changes: object) -> SemanticVolume:
    volume = SemanticVolume(VolumeParams(**{**BASE, **changes}, shard=shard))
    order = FRAMES if shard != "1/2" else FRAMES[::-1]  # shard 1 meets the keys in another order: other slots
    for f in order:
        volume.integrate(f)
    for f in order[::2]:
        keys = resize_nearest(f.instance, (60, 80)).astype(np.int32) - 1
        volume.apply_update(f.T_world_cam, K, keys, np.full((60, 80), 0.8, np.float32), observed_depth_m=f.depth_m())
    return volume


@pytest.fixture(scope="module")
def saved(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("sharded")
    for i in range(2):
        volume = _map(f"{i}/2")
        save_map(folder / f"shard-{i}of2", volume, RegionDictionary("none", 1), meta={"last_frame_id": 9 - i})
        volume.close()
    return folder


def _slots(part: Path) -> np.ndarray:
    with TileStore(part / STORE_DIR_NAME, readonly=True) as store:
        return store.read_arrays(["key_slots"], store.read_header())["key_slots"]


def _sorted_points(volume: SemanticVolume) -> np.ndarray:
    p = volume.extract_points()
    rows = np.concatenate([p.points, p.keys[:, None].astype(np.float32)], axis=1)
    return rows[np.lexsort(rows.T[::-1])]


def test_a_budgeted_load_of_shard_parts_equals_the_resident_merge(saved: Path) -> None:
    a, b = KeySlots.from_array(_slots(saved / "shard-0of2")), KeySlots.from_array(_slots(saved / "shard-1of2"))
    assert not np.array_equal(a.key1, b.key1)  # the parts' slot tables differ: the merge rewrites slots
    resident = load_map(saved, memory_budget_mb=None)
    budget_mb = 0.4 * resident.volume.num_blocks * 8192 / 2**20
    paged = load_map(saved, memory_budget_mb=budget_mb)
    try:
        assert paged.volume.num_blocks == 0  # nothing read at load
        assert paged.volume.num_blocks_total == resident.volume.num_blocks  # every owned tile, no ghost
        assert paged.meta["geometry_shards"] == 2 and paged.meta["last_frame_id"] == 8
        # The same map saved as one store and read under the same budget: the same points and keys.
        save_map(saved.parent / "as-one", resident.volume, RegionDictionary("none", 1))
        as_one = load_map(saved.parent / "as-one", memory_budget_mb=budget_mb)
        np.testing.assert_array_equal(_sorted_points(paged.volume), _sorted_points(as_one.volume))
        as_one.volume.close()
        # Against the resident merge: the same surface; a key may differ where the read-out's label
        # fill meets a tie at a chunk seam (measured on a 3 cm map of these frames: 1 point in 198,867, with or
        # without shards: paging alone does it).
        pa, pb = _sorted_points(paged.volume), _sorted_points(resident.volume)
        np.testing.assert_array_equal(pa[:, :3], pb[:, :3])
        assert (pa[:, 3] != pb[:, 3]).mean() <= 1e-4
        ma, mb = paged.volume.extract_mesh(), resident.volume.extract_mesh()
        assert (len(ma.vertices), len(ma.triangles)) == (len(mb.vertices), len(mb.triangles))
        assert paged.volume.num_blocks <= paged.volume.budget_blocks < resident.volume.num_blocks
        ta, tb = paged.volume.region_table(), resident.volume.region_table()
        np.testing.assert_array_equal(ta.keys, tb.keys)
        np.testing.assert_array_equal(ta.num_points, tb.num_points)
    finally:
        scratch = paged.volume.pager.base.path.parent
        resident.volume.close()
        paged.volume.close()
    del paged
    gc.collect()
    assert not scratch.exists()  # the scratch store went with the volume


def test_the_parts_own_budget_is_used_and_summaries_still_merge(tmp_path: Path) -> None:
    for i in range(2):
        volume = _map(f"{i}/2", memory_budget_mb=12.0)
        save_map(tmp_path / f"shard-{i}of2", volume, RegionDictionary("none", 1))
        volume.close()
    loaded = load_map(tmp_path)  # "map": the parts' own budget
    try:
        assert loaded.volume.params.memory_budget_mb == 12.0 and loaded.volume.num_blocks == 0
        assert len(loaded.volume.extract_points()) > 0
    finally:
        loaded.volume.close()
    summary = load_map_summary(tmp_path)
    assert summary is not None and len(summary.regions) > 3


def test_a_part_of_another_block_layout_is_refused(tmp_path: Path) -> None:
    # Bad input: shard 1's part written with 6 cm voxels beside shard 0's 5 cm ones.
    for i, voxel in enumerate((0.05, 0.06)):
        volume = _map(f"{i}/2", voxel_size_m=voxel)
        save_map(tmp_path / f"shard-{i}of2", volume, RegionDictionary("none", 1))
        volume.close()
    with pytest.raises(MapFormatError, match="another block layout"):
        load_map(tmp_path, memory_budget_mb=1.0)
