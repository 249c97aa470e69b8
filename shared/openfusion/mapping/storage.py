"""Voxel storage of the semantic volume: the Open3D ``VoxelBlockGrid`` and its bookkeeping.

Named *storage* because this module is the only one that knows how the map's values are laid out in
memory (attributes, key encoding, flat voxel indices, block buffer indices and when they move); the
ray-cast (:mod:`openfusion.mapping.raycast`) and read-out (:mod:`openfusion.mapping.readout`)
modules and :class:`~openfusion.mapping.volume.SemanticVolume` reach the values only through
:class:`VoxelStorage`.

Attributes
    ``tsdf``, ``weight``, ``color`` (Open3D's own) and ``key`` (int32), ``conf`` (float32).
    Open3D zero-fills the values of a block when it activates it, so ``key`` is stored as
    *key + 1*: a stored 0 reads back as key ``-1`` (never labelled) without any per-block
    initialisation on the integration path. Every public method of the volume speaks real keys
    (-1 = none); :meth:`VoxelStorage.gather` / :meth:`VoxelStorage.scatter` speak stored values.

Flat voxel indices
    Every attribute buffer is ``(capacity, res, res, res, channels)``; a voxel's flat index is
    ``buf * res**3 + (z * res + y) * res + x`` (``buf`` the block's buffer index, ``x, y, z`` its
    place in the block), the layout of Open3D's ``voxel_coordinates_and_flattened_indices`` and of
    the ray cast's ``index`` output. Indices stay valid while :attr:`VoxelStorage.generation` is
    unchanged (a grid that grows re-hashes its blocks).

:class:`VoxelStorage` is not locked: the volume that owns it serialises every call.
"""

from __future__ import annotations

import logging

import numpy as np
import open3d as o3d
import open3d.core as o3c

from openfusion.mapping.params import VolumeParams

logger = logging.getLogger(__name__)

ATTR_NAMES = ("tsdf", "weight", "color", "key", "conf")
_ATTR_DTYPES = (o3c.float32, o3c.float32, o3c.float32, o3c.int32, o3c.float32)
_ATTR_CHANNELS = (1, 1, 3, 1, 1)
SEMANTIC_BYTES_PER_VOXEL = 8  # key int32 + conf float32
BYTES_PER_VOXEL = 28  # tsdf 4 + weight 4 + color 12 + key 4 + conf 4
_DENSE_LOOKUP_MAX_CELLS = 16_000_000


def flat_voxel_index(buf_index: np.ndarray, local_xyz: np.ndarray, block_resolution: int) -> np.ndarray:
    """Flat voxel index (int64 (N,)) of the voxel at ``local_xyz`` (int (N, 3), x y z within the
    block, each in ``[0, block_resolution)``) of the blocks at ``buf_index`` (int (N,)).

    Hand-written on purpose: Open3D's ``voxel_coordinates_and_flattened_indices`` enumerates *all*
    ``res**3`` voxels of the blocks it is given (with their coordinates), and Open3D has no call
    that maps an arbitrary point to its voxel's index, so a per-point lookup through it would do
    ``res**3`` (512) times the work. ``tests/unit/test_mapping_storage.py`` checks this formula against
    that Open3D call on a real grid.
    """
    res = int(block_resolution)
    local = np.asarray(local_xyz, np.int64)
    return np.asarray(buf_index, np.int64) * res**3 + (local[:, 2] * res + local[:, 1]) * res + local[:, 0]


class _BlockLookup:
    """Block coordinate -> buffer index, dense over the active bounding box when that is small."""

    def __init__(self, coords: np.ndarray, buf: np.ndarray, hashmap: o3c.HashMap, device: o3c.Device) -> None:
        self._hashmap = hashmap
        self._device = device
        self._dense: np.ndarray | None = None
        if len(coords) == 0:
            self._lo = np.zeros(3, np.int64)
            self._dense = np.full((1, 1, 1), -1, np.int64)
            return
        lo = coords.min(axis=0).astype(np.int64)
        hi = coords.max(axis=0).astype(np.int64)
        dims = hi - lo + 1
        if int(np.prod(dims)) <= _DENSE_LOOKUP_MAX_CELLS:
            dense = np.full(tuple(int(d) for d in dims), -1, np.int64)
            rel = coords.astype(np.int64) - lo
            dense[rel[:, 0], rel[:, 1], rel[:, 2]] = buf
            self._dense = dense
            self._lo = lo

    def find(self, block_coords: np.ndarray) -> np.ndarray:
        """Buffer index per row of ``block_coords`` (int64 (N, 3)); -1 where the block does not exist."""
        if self._dense is not None:
            rel = block_coords - self._lo
            shape = np.array(self._dense.shape)
            inside = ((rel >= 0) & (rel < shape)).all(axis=1)
            out = np.full(len(block_coords), -1, np.int64)
            r = rel[inside]
            out[inside] = self._dense[r[:, 0], r[:, 1], r[:, 2]]
            return out
        uniq, inverse = np.unique(block_coords, axis=0, return_inverse=True)
        buf_t, found_t = self._hashmap.find(o3c.Tensor(uniq.astype(np.int32), device=self._device))
        buf = buf_t.cpu().numpy().astype(np.int64)
        buf[~found_t.cpu().numpy()] = -1
        return buf[inverse.reshape(-1)]


class VoxelStorage:
    """The Open3D grid, its growth and version counters, and value access by flat voxel index.

    ``generation`` changes whenever buffer indices may have changed (growth, reset, load);
    ``geometry_version`` after every change of the set of blocks or their geometry (the owner calls
    :meth:`mark_geometry_changed` after integrating). Caches keyed on both (active blocks, block
    lookup) are rebuilt on the first use after a change.
    """

    def __init__(self, params: VolumeParams, device: o3c.Device) -> None:
        self.params = params
        self.device = device
        #: CPU grids are read and written through numpy views of the buffers, others through tensors.
        self.use_numpy_views = device.get_type() == o3c.Device.DeviceType.CPU
        self.generation = 0
        self.geometry_version = 0
        self.reset()

    # ------------------------------------------------------------------ grid lifetime and growth
    def reset(self, capacity: int | None = None) -> None:
        """A new empty grid of ``capacity`` blocks (default: the configured initial count)."""
        p = self.params
        if capacity is None:
            capacity = (
                p.initial_block_count if p.max_blocks is None else min(p.initial_block_count, p.max_blocks)
            )
        self.vbg = o3d.t.geometry.VoxelBlockGrid(
            attr_names=ATTR_NAMES,
            attr_dtypes=_ATTR_DTYPES,
            attr_channels=_ATTR_CHANNELS,
            voxel_size=p.voxel_size_m,
            block_resolution=p.block_resolution,
            block_count=int(capacity),
            device=self.device,
        )
        self._capacity = self.vbg.hashmap().capacity()
        self.generation += 1
        self.geometry_version += 1
        self._blocks_cache: tuple[int, int, np.ndarray, np.ndarray] | None = None
        self._lookup_cache: tuple[int, int, _BlockLookup] | None = None
        #: Range-map fragments Open3D's ray-cast buffer (owned by this grid) is known to hold;
        #: :func:`openfusion.mapping.raycast.ensure_fragment_capacity` grows it.
        self.fragment_capacity = 0

    def note_capacity_change(self) -> bool:
        """Call after Open3D may have grown the grid; returns True (and bumps ``generation``) if it did."""
        capacity = self.vbg.hashmap().capacity()
        if capacity == self._capacity:
            return False
        logger.info("voxel block grid grew from %d to %d blocks", self._capacity, capacity)
        self._capacity = capacity
        self.generation += 1
        return True

    def mark_geometry_changed(self) -> None:
        """Call after integrating: invalidates the caches of active blocks."""
        self.geometry_version += 1

    @property
    def num_blocks(self) -> int:
        """Allocated (active) blocks."""
        return int(self.vbg.hashmap().size())

    @property
    def capacity_blocks(self) -> int:
        """Blocks the grid's buffers hold before the next growth."""
        return int(self.vbg.hashmap().capacity())

    @property
    def voxels_per_block(self) -> int:
        return self.params.block_resolution**3

    # ------------------------------------------------------------------ attribute access
    def _attr_flat_view(self, name: str) -> np.ndarray:
        """Writable numpy view of a 1-channel attribute over the whole buffer (CPU only)."""
        return self.vbg.attribute(name).numpy().reshape(-1)

    def gather(self, name: str, flat_index: np.ndarray, *, clip: bool = False) -> np.ndarray:
        """Stored values of a 1-channel attribute at flat voxel indices; ``clip`` clamps out-of-range
        indices (ray-cast neighbours that do not exist carry index 0 today, but their values are
        masked out anyway)."""
        if self.use_numpy_views:
            view = self._attr_flat_view(name)
            return np.take(view, flat_index, mode="clip") if clip else view[flat_index]
        flat = self.vbg.attribute(name).reshape((-1,))
        return flat[o3c.Tensor(np.ascontiguousarray(flat_index, np.int64), device=self.device)].cpu().numpy()

    def scatter(self, name: str, flat_index: np.ndarray, values: np.ndarray) -> None:
        """Write stored values of a 1-channel attribute at flat voxel indices."""
        if self.use_numpy_views:
            self._attr_flat_view(name)[flat_index] = values
            return
        flat = self.vbg.attribute(name).reshape((-1,))
        flat[o3c.Tensor(np.ascontiguousarray(flat_index, np.int64), device=self.device)] = o3c.Tensor(
            np.ascontiguousarray(values), device=self.device
        )

    def gather_blocks(self, name: str, buf: np.ndarray) -> np.ndarray:
        """Stored values of a 1-channel attribute for whole blocks: ``(len(buf), res**3)``, row ``i``
        in the order of :meth:`voxel_flat_indices` ``(buf[i:i + 1])``."""
        n = self.voxels_per_block
        if self.use_numpy_views:
            return self.vbg.attribute(name).numpy().reshape(-1, n)[buf]
        values = self.vbg.attribute(name)[o3c.Tensor(np.ascontiguousarray(buf, np.int64), device=self.device)]
        return values.cpu().numpy().reshape(-1, n)

    def voxel_flat_indices(self, buf: np.ndarray) -> np.ndarray:
        """Flat indices (int64 (len(buf) * res**3,)) of every voxel of the blocks at ``buf``, block
        by block, from Open3D's ``voxel_coordinates_and_flattened_indices``."""
        if len(buf) == 0:
            return np.zeros(0, np.int64)
        buf_t = o3c.Tensor(np.ascontiguousarray(buf, np.int32), device=self.device)  # Open3D wants int32
        _, flat_t = self.vbg.voxel_coordinates_and_flattened_indices(buf_t)
        return flat_t.cpu().numpy().reshape(-1)

    # ------------------------------------------------------------------ blocks
    def active_blocks(self) -> tuple[np.ndarray, np.ndarray]:
        """(coords (N, 3) int32, buffer indices (N,) int64) of all active blocks, cached per version."""
        cache = self._blocks_cache
        if cache is not None and cache[0] == self.geometry_version and cache[1] == self.generation:
            return cache[2], cache[3]
        hm = self.vbg.hashmap()
        buf_t = hm.active_buf_indices().to(o3c.int64)
        if buf_t.shape[0] == 0:
            coords = np.zeros((0, 3), np.int32)
            buf = np.zeros(0, np.int64)
        else:
            coords = hm.key_tensor()[buf_t].cpu().numpy().astype(np.int32)
            buf = buf_t.cpu().numpy()
        self._blocks_cache = (self.geometry_version, self.generation, coords, buf)
        return coords, buf

    def block_lookup(self) -> _BlockLookup:
        """Block coordinate -> buffer index of the active blocks, cached per version."""
        cache = self._lookup_cache
        if cache is not None and cache[0] == self.geometry_version and cache[1] == self.generation:
            return cache[2]
        coords, buf = self.active_blocks()
        lookup = _BlockLookup(coords, buf, self.vbg.hashmap(), self.device)
        self._lookup_cache = (self.geometry_version, self.generation, lookup)
        return lookup

    # ------------------------------------------------------------------ keys
    def relabel_keys(self, mapping: dict[int, int]) -> int:
        """Rewrite voxel keys ``{old: new}`` (``new`` -1 clears the key and zeroes the confidence);
        returns the number of voxels changed. Only blocks holding one of the old keys are rewritten."""
        if not mapping:
            return 0
        for old, new in mapping.items():
            if int(old) < 0 or int(new) < -1:
                raise ValueError(f"cannot relabel {old} -> {new}: keys are >= 0 (-1 only as target)")
        _, buf = self.active_blocks()
        if len(buf) == 0:
            return 0
        stored_blocks = self.gather_blocks("key", buf)
        old_stored = np.array([int(old) + 1 for old in mapping], np.int32)
        touched = np.isin(stored_blocks, old_stored).any(axis=1)
        if not touched.any():
            return 0
        flat = self.voxel_flat_indices(buf[touched])
        stored = stored_blocks[touched].reshape(-1)
        changed_total = 0
        new_stored = stored.copy()
        clear = np.zeros(len(stored), bool)
        for old, new in mapping.items():
            hit = stored == int(old) + 1
            new_stored[hit] = int(new) + 1
            if int(new) < 0:
                clear |= hit
            changed_total += int(hit.sum())
        diff = np.flatnonzero(new_stored != stored)
        self.scatter("key", flat[diff], new_stored[diff])
        if clear.any():
            idx = flat[clear]
            self.scatter("conf", idx, np.zeros(len(idx), np.float32))
        return changed_total

    def labelled_blocks(self) -> tuple[np.ndarray, np.ndarray]:
        """(block coordinates (N, 3) int64, keys (N, R, R, R) int32 indexed [z, y, x], -1 = none) of
        every active block holding at least one labelled voxel (the buffers' own layout)."""
        coords, buf = self.active_blocks()
        res = self.params.block_resolution
        if len(buf) == 0:
            return np.zeros((0, 3), np.int64), np.zeros((0, res, res, res), np.int32)
        stored = self.gather_blocks("key", buf)
        keep = (stored > 0).any(axis=1)
        keys = stored[keep].astype(np.int32) - 1
        return coords[keep].astype(np.int64), keys.reshape(-1, res, res, res)

    def labelled_voxels(self) -> tuple[np.ndarray, np.ndarray]:
        """(integer voxel coordinates (n, 3) int64, keys (n,) int64) of every voxel carrying a key,
        in the grid's voxel units (block coordinate * resolution + position in the block)."""
        coords, buf = self.active_blocks()
        if len(buf) == 0:
            return np.zeros((0, 3), np.int64), np.zeros(0, np.int64)
        res = self.params.block_resolution
        stored = self.gather_blocks("key", buf)
        block, within = np.nonzero(stored > 0)
        # Position in the block: flat = (z * res + y) * res + x (see flat_voxel_index).
        local = np.stack([within % res, (within // res) % res, within // (res * res)], axis=1)
        voxels = coords[block].astype(np.int64) * res + local
        return voxels, stored[block, within].astype(np.int64) - 1

    # ------------------------------------------------------------------ arrays (map files)
    def to_arrays(self) -> dict[str, np.ndarray]:
        """All active blocks as plain arrays (``key`` holds real keys, -1 = none)."""
        coords, buf = self.active_blocks()
        res = self.params.block_resolution
        out: dict[str, np.ndarray] = {"block_coords": coords.astype(np.int32)}
        buf_t = o3c.Tensor(buf, device=self.device)
        for name in ATTR_NAMES:
            if len(buf) == 0:
                channels = _ATTR_CHANNELS[ATTR_NAMES.index(name)]
                dtype = np.int32 if name == "key" else np.float32
                arr = np.zeros((0, res, res, res, channels), dtype)
            else:
                arr = self.vbg.attribute(name)[buf_t].cpu().numpy()
            if name != "color":
                arr = arr.reshape(arr.shape[:4])
            if name == "key":
                arr = arr.astype(np.int32) - 1
            out[name] = np.ascontiguousarray(arr)
        return out

    def load_arrays(self, arrays: dict[str, np.ndarray]) -> bool:
        """Activate and fill the blocks of :meth:`to_arrays` output (checked with :func:`check_arrays`)
        in this (empty) grid; returns True when the grid grew to hold them."""
        coords = np.asarray(arrays["block_coords"])
        n = len(coords)
        if n == 0:
            return False
        if n > self.capacity_blocks:
            self.reset(capacity=n)
        buf_t, _ = self.vbg.hashmap().activate(o3c.Tensor(coords.astype(np.int32), device=self.device))
        grew = self.note_capacity_change()
        buf_t = buf_t.to(o3c.int64)
        for name in ATTR_NAMES:
            arr = np.asarray(arrays[name])
            if name == "key":
                arr = arr.astype(np.int32) + 1
            if name != "color":
                arr = arr[..., None]
            self.vbg.attribute(name)[buf_t] = o3c.Tensor(np.ascontiguousarray(arr), device=self.device)
        self.mark_geometry_changed()
        return grew


def check_arrays(params: VolumeParams, arrays: dict[str, np.ndarray]) -> None:
    """Raise ``ValueError`` unless ``arrays`` are consistent :meth:`VoxelStorage.to_arrays` output
    for ``params`` (shapes, dtypes, unique blocks, keys >= -1, within ``max_blocks``)."""
    res = params.block_resolution
    coords = np.asarray(arrays["block_coords"])
    if coords.ndim != 2 or coords.shape[1] != 3 or not np.issubdtype(coords.dtype, np.integer):
        raise ValueError(f"block_coords must be (N, 3) integers, got {coords.dtype} {coords.shape}")
    n = len(coords)
    expected = {
        "tsdf": ((n, res, res, res), np.float32),
        "weight": ((n, res, res, res), np.float32),
        "color": ((n, res, res, res, 3), np.float32),
        "key": ((n, res, res, res), np.int32),
        "conf": ((n, res, res, res), np.float32),
    }
    for name, (shape, dtype) in expected.items():
        arr = np.asarray(arrays[name])
        if arr.shape != shape or arr.dtype != dtype:
            raise ValueError(f"{name} must be {np.dtype(dtype).name} {shape}, got {arr.dtype} {arr.shape}")
    if n and len(np.unique(coords, axis=0)) != n:
        raise ValueError("block_coords contain duplicates")
    if n and int(np.asarray(arrays["key"]).min()) < -1:
        raise ValueError("key values must be >= -1")
    if params.max_blocks is not None and n > params.max_blocks:
        raise ValueError(f"{n} blocks exceed max_blocks={params.max_blocks}")
