"""Voxel storage: flat voxel indices agree with Open3D's, whole-block access, relabelling.

The per-point lookup of the read-out computes flat voxel indices by hand
(:func:`openfusion.mapping.storage.flat_voxel_index`); these tests pin that formula to Open3D's
``voxel_coordinates_and_flattened_indices`` on real grids.
"""

from __future__ import annotations

import numpy as np
import open3d.core as o3c
import pytest

from openfusion.frame import CameraIntrinsics
from openfusion.mapping import SemanticVolume, VolumeParams
from openfusion.mapping.storage import VoxelStorage, flat_voxel_index, split_voxel_coords
from openfusion.poses import look_at
from openfusion.testing.analytic_scene import AnalyticScene, Box, Room

K = CameraIntrinsics(160, 120, 131.25, 131.25, 79.5, 59.5)
EXTRA_BLOCKS = np.array([[-3, -1, -2], [-1, 0, 5], [7, -4, 0], [0, 0, 0]], np.int32)  # negative corners too


def integrated_storage(use_numpy_views: bool = True) -> VoxelStorage:
    """A grid holding the blocks of two integrated frames plus a few hand-made blocks."""
    scene = AnalyticScene(
        room=Room(size_m=(2.0, 2.0, 2.0)), boxes=[Box((0.8, 1.2, 0.0), (1.2, 1.6, 0.5), 1, "box")]
    )
    volume = SemanticVolume(VolumeParams(initial_block_count=256))
    for i, eye in enumerate(((1.0, 0.2, 1.2), (0.3, 0.4, 1.2))):
        volume.integrate(scene.make_frame(look_at(eye, (1.0, 1.4, 0.3)), K, frame_id=i))
    storage = volume._storage
    storage.vbg.hashmap().activate(o3c.Tensor(EXTRA_BLOCKS, device=storage.device))
    storage.mark_geometry_changed()
    storage.use_numpy_views = use_numpy_views
    return storage


@pytest.fixture(scope="module")
def storage() -> VoxelStorage:
    return integrated_storage()


def test_flat_voxel_index_matches_open3d(storage: VoxelStorage) -> None:
    """Same flat index for the same voxel coordinate as ``voxel_coordinates_and_flattened_indices``."""
    coords, buf = storage.active_blocks()
    assert len(buf) > 50 and {tuple(c) for c in EXTRA_BLOCKS} <= {tuple(c) for c in coords}
    xyz_t, flat_t = storage.vbg.voxel_coordinates_and_flattened_indices(o3c.Tensor(buf.astype(np.int32)))
    voxel = np.round(xyz_t.cpu().numpy().astype(np.float64) / storage.params.voxel_size_m).astype(np.int64)
    res = storage.params.block_resolution
    block = np.floor_divide(voxel, res)
    local = voxel - block * res
    block_buf = storage.block_lookup().find(block)
    assert (block_buf >= 0).all()
    np.testing.assert_array_equal(flat_voxel_index(block_buf, local, res), flat_t.cpu().numpy().reshape(-1))


@pytest.mark.parametrize("use_numpy_views", [True, False])
def test_block_access_agrees_with_flat_access(use_numpy_views: bool) -> None:
    """``gather_blocks`` rows are the voxels of ``voxel_flat_indices``, in the same order."""
    storage = integrated_storage(use_numpy_views)
    _, buf = storage.active_blocks()
    some = buf[:: max(len(buf) // 7, 1)]
    flat = storage.voxel_flat_indices(some)
    assert flat.shape == (len(some) * storage.voxels_per_block,)
    for name in ("tsdf", "weight", "key"):
        np.testing.assert_array_equal(
            storage.gather_blocks(name, some).reshape(-1), storage.gather(name, flat)
        )
    assert storage.voxel_flat_indices(np.zeros(0, np.int64)).shape == (0,)


def test_relabel_touches_only_the_voxels_of_the_old_keys() -> None:
    """Relabelling matches a plain numpy rewrite of every voxel, chains included ({1: 2, 2: 3})."""
    local = integrated_storage()
    _, buf = local.active_blocks()
    flat = local.voxel_flat_indices(buf)
    rng = np.random.default_rng(0)
    stored = np.zeros(len(flat), np.int32)
    labelled = rng.random(len(flat)) < 0.01  # a sparse labelling leaves most blocks untouched
    stored[labelled] = rng.integers(1, 5, int(labelled.sum()))
    local.scatter("key", flat, stored)
    local.scatter("conf", flat, np.where(labelled, np.float32(0.5), np.float32(0.0)))
    expected = stored.copy()
    expected[stored == 2] = 3  # key 1 -> 2 (stored 2 -> 3)
    expected[stored == 3] = 4  # key 2 -> 3
    expected[stored == 4] = 0  # key 3 -> cleared
    changed = local.relabel_keys({1: 2, 2: 3, 3: -1})
    assert changed == int(np.isin(stored, [2, 3, 4]).sum())
    np.testing.assert_array_equal(local.gather("key", flat), expected)
    # A cleared voxel reads no key; its stored confidence is left as it was (the slot table changed,
    # not the voxel) and reads 0 wherever the volume reports it (to_arrays, renders, read-outs).
    conf, key1 = local.gather("conf", flat), local.gather("key", flat)
    np.testing.assert_array_equal((conf == 0) | (key1 == 0), ~labelled | (stored == 4))
    arrays = local.to_arrays()
    assert (arrays["conf"][arrays["key"] < 0] == 0).all()
    assert local.relabel_keys({42: 1}) == 0


@pytest.mark.parametrize("res", [8, 6])
def test_voxel_coordinates_split_into_block_and_voxel_as_floor_division(res: int) -> None:
    """Negative coordinates too (the shifts of a power-of-two block must floor, not truncate), and a
    block side that is not a power of two."""
    voxel = np.random.default_rng(res).integers(-40, 40, (500, 3)).astype(np.int64)
    block, local = split_voxel_coords(voxel, res)
    np.testing.assert_array_equal(block, np.floor_divide(voxel, res))
    np.testing.assert_array_equal(local, np.mod(voxel, res))
    assert ((local >= 0) & (local < res)).all()
