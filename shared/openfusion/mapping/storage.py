"""Voxel storage of the semantic volume: the Open3D ``VoxelBlockGrid`` and its bookkeeping.

Named *storage* because this module is the only one that knows how the map's values are laid out in
memory (attributes, key encoding, flat voxel indices, block buffer indices and when they move); the
ray-cast (:mod:`openfusion.mapping.raycast`) and read-out (:mod:`openfusion.mapping.readout`)
modules and :class:`~openfusion.mapping.volume.SemanticVolume` reach the values only through
:class:`VoxelStorage`.

Attributes (compact voxels: 16 bytes each)
    ``tsdf`` float32 (4 B), ``weight`` uint16 (2 B) and ``color`` uint16 x 3 (6 B, values 0-255):
    the narrowest types Open3D's ``integrate`` takes (it dispatches on (float, float) or
    (uint16, uint16) weight/colour and keeps the TSDF a float); ``key`` uint16 (2 B) and ``conf``
    uint16 (2 B). Together 16 bytes per voxel including semantics (was 28: float32 weight and
    colour, int32 key, float32 confidence); nvblox needs 16 without semantics.

    - ``key`` holds a *slot*, and :class:`~openfusion.mapping.keyslots.KeySlots` says which region
      key each slot stands for (slot 0 = none; the table's docstring says why and how key
      exhaustion is handled: compaction, never a limit on region keys).
    - ``conf`` holds ``round(conf * 65535)`` (a resolution of 1.5e-5, far below what the update
      rule's arithmetic distinguishes; ``tests/unit/test_mapping_storage.py`` checks the round trip).
    - ``weight``: Open3D adds 1 per observation and a uint16 wraps at 65,535 to 0 (measured:
      open3d 0.20 does not clamp), so :meth:`VoxelStorage.clamp_weights` caps every weight at
      :data:`MAX_WEIGHT` once every :data:`WEIGHT_CLAMP_EVERY` integrations (a voxel gains at most
      one per frame, so none can wrap in between). A voxel seen 64,000 times is as certain as the
      TSDF average can make it.

    Open3D zero-fills the grid's buffers when it creates them, but *not* a buffer it reuses after
    an erase (measured), so :meth:`VoxelStorage.erase_blocks` zeroes a block's values before it
    frees the block: a stored 0 always reads back as key ``-1`` (never labelled) without any
    per-block initialisation on the integration path. Every public method of the volume speaks
    real keys (-1 = none) and float confidences; :meth:`VoxelStorage.gather` /
    :meth:`VoxelStorage.scatter` speak *key + 1* (0 = none) and float32 confidences, translating
    slots and quantised confidences, so the update rule never sees the layout.

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

from openfusion.mapping.keyslots import KeySlots
from openfusion.mapping.params import VolumeParams
from openfusion.mapping.voxel_arrays import labelled_of, voxels_of_labelled

logger = logging.getLogger(__name__)

ATTR_NAMES = ("tsdf", "weight", "color", "key", "conf")
_ATTR_DTYPES = (o3c.float32, o3c.uint16, o3c.uint16, o3c.uint16, o3c.uint16)
#: numpy dtypes of the stored attributes (what tiles hold), in ATTR_NAMES order.
RAW_DTYPES = {"tsdf": np.float32, "weight": np.uint16, "color": np.uint16, "key": np.uint16, "conf": np.uint16}
_ATTR_CHANNELS = (1, 1, 3, 1, 1)
ATTR_CHANNELS = dict(zip(ATTR_NAMES, _ATTR_CHANNELS, strict=True))
SEMANTIC_BYTES_PER_VOXEL = 4  # key slot uint16 + conf uint16
BYTES_PER_VOXEL = 16  # tsdf 4 + weight 2 + color 6 + key 2 + conf 2
CONF_SCALE = 65535.0  # stored conf = round(conf * CONF_SCALE)
MAX_WEIGHT = 64000  # weights are capped here (uint16 wraps at 65535)
WEIGHT_CLAMP_EVERY = 1000  # integrations between two caps (MAX_WEIGHT + this < 65536)
_DENSE_LOOKUP_MAX_CELLS = 16_000_000


def conf_to_stored(conf: np.ndarray) -> np.ndarray:
    """uint16 stored confidences of float confidences in [0, 1]."""
    return np.round(np.clip(np.asarray(conf, np.float32), 0.0, 1.0) * np.float32(CONF_SCALE)).astype(np.uint16)


def conf_from_stored(stored: np.ndarray) -> np.ndarray:
    """float32 confidences of stored uint16 values."""
    return np.asarray(stored, np.float32) * np.float32(1.0 / CONF_SCALE)


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


def split_voxel_coords(voxel_xyz: np.ndarray, block_resolution: int) -> tuple[np.ndarray, np.ndarray]:
    """(block coordinates, voxel within the block) of int64 voxel coordinates ``(..., 3)``: floor
    division, by bit shifts when the block side is a power of two (8 by default; 0.88x a probe's time)."""
    res = int(block_resolution)
    if res & (res - 1) == 0:
        return voxel_xyz >> (res.bit_length() - 1), voxel_xyz & (res - 1)
    block = np.floor_divide(voxel_xyz, res)
    return block, voxel_xyz - block * res


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

    ``generation`` changes whenever buffer indices may have changed (growth, reset, load, blocks
    erased by paging); ``geometry_version`` after every change of the set of blocks or their
    geometry (the owner calls :meth:`mark_geometry_changed` after integrating). Caches keyed on
    both (active blocks, block lookup) are rebuilt on the first use after a change.

    ``on_compact_keys``: set by the owner of stored (paged-out) blocks; called with the slot
    remap of a key compaction, it must rewrite every stored block's key slots through it and
    return the slots still present in them (:mod:`openfusion.mapping.keyslots`).
    """

    def __init__(self, params: VolumeParams, device: o3c.Device, *, capacity: int | None = None) -> None:
        """``capacity``: blocks of the first grid (default: the configured initial count); a
        memory budget's grid is made at its size at once (never a default-sized one first)."""
        self.params = params
        self.device = device
        #: CPU grids are read and written through numpy views of the buffers, others through tensors.
        self.use_numpy_views = device.get_type() == o3c.Device.DeviceType.CPU
        self.generation = 0
        self.geometry_version = 0
        self.slots = KeySlots()
        self.on_compact_keys: object = None
        #: Called with (slots whose key changed, the mapping) after every :meth:`relabel_keys`.
        self.on_relabel: object = None
        self.integrations_since_clamp = 0
        self.compactions = 0  # key compactions so far (every voxel's slot rewritten)
        self.reset(capacity)

    # ------------------------------------------------------------------ grid lifetime and growth
    def reset(self, capacity: int | None = None, *, keep_slots: bool = False) -> None:
        """A new empty grid of ``capacity`` blocks (default: the configured initial count)."""
        p = self.params
        if capacity is None:
            capacity = (
                p.initial_block_count if p.max_blocks is None else min(p.initial_block_count, p.max_blocks)
            )
        self.vbg = self.new_grid(int(capacity))
        self._capacity = self.vbg.hashmap().capacity()
        self.generation += 1
        self.geometry_version += 1
        if not keep_slots:
            self.slots = KeySlots(self.slots.max_slots)
        self._blocks_cache: tuple[int, int, np.ndarray, np.ndarray] | None = None
        self._lookup_cache: tuple[int, int, _BlockLookup] | None = None
        #: Range-map fragments Open3D's ray-cast buffer (owned by this grid) is known to hold;
        #: :func:`openfusion.mapping.raycast.ensure_fragment_capacity` grows it.
        self.fragment_capacity = 0

    def new_grid(self, capacity: int) -> o3d.t.geometry.VoxelBlockGrid:
        """An empty Open3D grid of this storage's layout holding ``capacity`` blocks."""
        p = self.params
        return o3d.t.geometry.VoxelBlockGrid(
            attr_names=ATTR_NAMES,
            attr_dtypes=_ATTR_DTYPES,
            attr_channels=_ATTR_CHANNELS,
            voxel_size=p.voxel_size_m,
            block_resolution=p.block_resolution,
            block_count=int(capacity),
            device=self.device,
        )

    def replace_grid(self, vbg: o3d.t.geometry.VoxelBlockGrid) -> None:
        """Swap in another grid holding the same blocks (a grown copy, :mod:`openfusion.mapping.growth`)."""
        self.vbg = vbg
        self._capacity = vbg.hashmap().capacity()
        self.generation += 1
        self.geometry_version += 1
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

    def note_integrated(self) -> np.ndarray:
        """Call after every integration: caps weights once every :data:`WEIGHT_CLAMP_EVERY` calls;
        returns the buffer indices of the blocks a cap changed (their tiles changed)."""
        self.integrations_since_clamp += 1
        if self.integrations_since_clamp >= WEIGHT_CLAMP_EVERY:
            return self.clamp_weights()
        return np.zeros(0, np.int64)

    def clamp_weights(self) -> np.ndarray:
        """Cap every weight at :data:`MAX_WEIGHT` (module docstring); returns the buffer indices of
        the blocks that held a weight above it."""
        self.integrations_since_clamp = 0
        n = self.voxels_per_block
        if self.use_numpy_views:
            w = self.vbg.attribute("weight").numpy().reshape(-1, n)
            over = np.flatnonzero((w > MAX_WEIGHT).any(axis=1))
            if len(over):
                np.minimum(w, np.uint16(MAX_WEIGHT), out=w)
            return over.astype(np.int64)
        w = self.vbg.attribute("weight")
        over_t = w > MAX_WEIGHT
        over = np.flatnonzero(over_t.cpu().numpy().reshape(-1, n).any(axis=1)).astype(np.int64)
        if len(over):
            w[over_t] = MAX_WEIGHT
        return over

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

    @property
    def bytes_per_block(self) -> int:
        return BYTES_PER_VOXEL * self.voxels_per_block

    # ------------------------------------------------------------------ attribute access
    def _attr_flat_view(self, name: str) -> np.ndarray:
        """Writable numpy view of a 1-channel attribute over the whole buffer (CPU only)."""
        return self.vbg.attribute(name).numpy().reshape(-1)

    def _raw_gather(self, name: str, flat_index: np.ndarray, clip: bool) -> np.ndarray:
        if self.use_numpy_views:
            view = self._attr_flat_view(name)
            return np.take(view, flat_index, mode="clip") if clip else view[flat_index]
        flat = self.vbg.attribute(name).reshape((-1,))
        idx = np.ascontiguousarray(flat_index, np.int64)
        if clip:
            idx = np.clip(idx, 0, flat.shape[0] - 1)
        return flat[o3c.Tensor(idx, device=self.device)].cpu().numpy()

    def _raw_scatter(self, name: str, flat_index: np.ndarray, raw: np.ndarray) -> None:
        if self.use_numpy_views:
            self._attr_flat_view(name)[flat_index] = raw
            return
        flat = self.vbg.attribute(name).reshape((-1,))
        flat[o3c.Tensor(np.ascontiguousarray(flat_index, np.int64), device=self.device)] = o3c.Tensor(
            np.ascontiguousarray(raw), device=self.device
        )

    def _decode(self, name: str, raw: np.ndarray) -> np.ndarray:
        if name == "key":
            return self.slots.key1_of(raw)
        if name == "conf":
            return conf_from_stored(raw)
        return raw

    def _encode(self, name: str, values: np.ndarray) -> np.ndarray:
        if name == "key":
            return self.slots.slots_for(values, compact=self.compact_keys)
        if name == "conf":
            return conf_to_stored(values)
        return np.asarray(values).astype(RAW_DTYPES[name], copy=False)

    def gather(self, name: str, flat_index: np.ndarray, *, clip: bool = False) -> np.ndarray:
        """Values of a 1-channel attribute at flat voxel indices (``key``: key + 1, 0 = none;
        ``conf``: float32); ``clip`` clamps out-of-range indices (ray-cast neighbours that do not
        exist carry index 0 today, but their values are masked out anyway)."""
        return self._decode(name, self._raw_gather(name, flat_index, clip))

    def scatter(self, name: str, flat_index: np.ndarray, values: np.ndarray) -> None:
        """Write values of a 1-channel attribute at flat voxel indices (the forms of :meth:`gather`)."""
        self._raw_scatter(name, flat_index, self._encode(name, values))

    def gather_blocks(self, name: str, buf: np.ndarray) -> np.ndarray:
        """Values of a 1-channel attribute for whole blocks: ``(len(buf), res**3)``, row ``i``
        in the order of :meth:`voxel_flat_indices` ``(buf[i:i + 1])`` (the forms of :meth:`gather`)."""
        n = self.voxels_per_block
        if self.use_numpy_views:
            raw = self.vbg.attribute(name).numpy().reshape(-1, n)[buf]
        else:
            raw = self.vbg.attribute(name)[o3c.Tensor(np.ascontiguousarray(buf, np.int64), device=self.device)]
            raw = raw.cpu().numpy().reshape(-1, n)
        return self._decode(name, raw)

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

    def block_coords_of_buf(self, buf: np.ndarray) -> np.ndarray:
        """Block coordinates (int32 (N, 3)) of active blocks at buffer indices ``buf``."""
        keys = self.vbg.hashmap().key_tensor()
        if self.use_numpy_views:
            return keys.numpy()[np.asarray(buf, np.int64)].astype(np.int32)
        return keys[o3c.Tensor(np.ascontiguousarray(buf, np.int64), device=self.device)].cpu().numpy()

    def block_lookup(self) -> _BlockLookup:
        """Block coordinate -> buffer index of the active blocks, cached per version."""
        cache = self._lookup_cache
        if cache is not None and cache[0] == self.geometry_version and cache[1] == self.generation:
            return cache[2]
        coords, buf = self.active_blocks()
        lookup = _BlockLookup(coords, buf, self.vbg.hashmap(), self.device)
        self._lookup_cache = (self.geometry_version, self.generation, lookup)
        return lookup

    def find_blocks(self, coords: np.ndarray) -> np.ndarray:
        """Buffer index (int64) of each block coordinate (int (N, 3)); -1 where not resident."""
        if len(coords) == 0:
            return np.zeros(0, np.int64)
        buf_t, found_t = self.vbg.hashmap().find(o3c.Tensor(np.ascontiguousarray(coords, np.int32), device=self.device))
        buf = buf_t.cpu().numpy().astype(np.int64)
        buf[~found_t.cpu().numpy()] = -1
        return buf

    # ------------------------------------------------------------------ raw blocks (tiles, paging, growth)
    def read_raw_blocks(self, buf: np.ndarray, *, names: tuple[str, ...] = ATTR_NAMES) -> dict[str, np.ndarray]:
        """Stored values of whole blocks, as kept in the grid: ``{name: (n, res, res, res[, 3])}``
        in :data:`RAW_DTYPES` (key slots, quantised confidences), of the attributes ``names``. A copy."""
        res = self.params.block_resolution
        buf = np.asarray(buf, np.int64)
        out: dict[str, np.ndarray] = {}
        for name in names:
            shape = (len(buf), res, res, res) + ((3,) if name == "color" else ())
            if len(buf) == 0:
                out[name] = np.zeros(shape, RAW_DTYPES[name])
            elif self.use_numpy_views:
                out[name] = self.vbg.attribute(name).numpy()[buf].reshape(shape)
            else:
                t = self.vbg.attribute(name)[o3c.Tensor(buf, device=self.device)]
                out[name] = t.cpu().numpy().reshape(shape)
        return out

    def write_raw_blocks(self, coords: np.ndarray, raw: dict[str, np.ndarray]) -> np.ndarray:
        """Activate the blocks ``coords`` (int (n, 3), none resident yet) and fill them with ``raw``
        (:meth:`read_raw_blocks` form); returns their buffer indices. The caller makes room first:
        the grid must not grow here (``ValueError`` when the blocks do not fit)."""
        n = len(coords)
        if n == 0:
            return np.zeros(0, np.int64)
        if self.num_blocks + n > self.capacity_blocks:
            raise ValueError(f"{n} blocks do not fit: {self.num_blocks} of {self.capacity_blocks} in use")
        hm = self.vbg.hashmap()
        buf_t, ok_t = hm.activate(o3c.Tensor(np.ascontiguousarray(coords, np.int32), device=self.device))
        if not bool(ok_t.all()):
            raise ValueError("write_raw_blocks: some blocks were resident already")
        buf = buf_t.cpu().numpy().astype(np.int64)
        idx = o3c.Tensor(buf, device=self.device)
        for name in ATTR_NAMES:
            arr = np.ascontiguousarray(raw[name], RAW_DTYPES[name])
            if name != "color":
                arr = arr[..., None]
            if self.use_numpy_views:
                self.vbg.attribute(name).numpy()[buf] = arr
            else:
                self.vbg.attribute(name)[idx] = o3c.Tensor(arr, device=self.device)
        self.mark_geometry_changed()
        return buf

    def erase_blocks(self, coords: np.ndarray, buf: np.ndarray) -> None:
        """Free resident blocks (``coords`` with their buffer indices ``buf``): their values are
        zeroed first, because Open3D hands a freed buffer out again without clearing it."""
        if len(buf) == 0:
            return
        buf = np.asarray(buf, np.int64)
        for name in ATTR_NAMES:
            if self.use_numpy_views:
                self.vbg.attribute(name).numpy()[buf] = 0
            else:
                t = self.vbg.attribute(name)
                shape = (len(buf), *tuple(t.shape)[1:])
                t[o3c.Tensor(buf, device=self.device)] = o3c.Tensor.zeros(shape, t.dtype, self.device)
        self.vbg.hashmap().erase(o3c.Tensor(np.ascontiguousarray(coords, np.int32), device=self.device))
        self.mark_geometry_changed()
        self.generation += 1  # buffer indices of renders taken before may now name other blocks

    # ------------------------------------------------------------------ keys
    def relabel_keys(self, mapping: dict[int, int]) -> int:
        """Rewrite region keys ``{old: new}`` (``new`` -1 clears the key) in the slot table: every
        voxel (resident or paged out) of ``old`` reads ``new`` at once. Returns the number of
        resident voxels that changed."""
        if not mapping:
            return 0
        for old, new in mapping.items():
            if int(old) < 0 or int(new) < -1:
                raise ValueError(f"cannot relabel {old} -> {new}: keys are >= 0 (-1 only as target)")
        changed = self.slots.relabel(mapping)
        if callable(self.on_relabel) and len(changed):
            self.on_relabel(changed, dict(mapping))
        if len(changed) == 0 or self.num_blocks == 0:
            return 0
        lut = np.zeros(self.slots.max_slots + 1, bool)
        lut[changed] = True
        _, buf = self.active_blocks()
        if self.use_numpy_views:
            raw = self.vbg.attribute("key").numpy().reshape(-1, self.voxels_per_block)[buf]
        else:
            raw = self.read_raw_blocks(buf)["key"]
        return int(lut[raw].sum())

    def compact_keys(self) -> None:
        """Reclaim key slots (:mod:`openfusion.mapping.keyslots`): rewrite every resident voxel's
        slot through the compaction map, let the owner of stored blocks do the same
        (``on_compact_keys``) and free the slots no voxel uses any more."""
        remap = self.slots.compaction_map()
        self.compactions += 1
        used: list[np.ndarray] = []
        if self.num_blocks:
            if self.use_numpy_views:
                view = self.vbg.attribute("key").numpy()
                view[...] = remap[view]
                used.append(np.unique(view))
            else:
                t = self.vbg.attribute("key")
                arr = remap[t.cpu().numpy()]
                t[:] = o3c.Tensor(arr, device=self.device)
                used.append(np.unique(arr))
        if callable(self.on_compact_keys):
            used.append(np.asarray(self.on_compact_keys(remap), np.int64))
        before = self.slots.used_slots
        self.slots.compacted(remap, np.unique(np.concatenate(used)) if used else np.zeros(0, np.int64))
        logger.info("key slots compacted: %d -> %d in use", before, self.slots.used_slots)

    def labelled_blocks(self) -> tuple[np.ndarray, np.ndarray]:
        """(block coordinates (N, 3) int64, keys (N, R, R, R) int32 indexed [z, y, x], -1 = none) of
        every active block holding at least one labelled voxel (the buffers' own layout)."""
        coords, buf = self.active_blocks()
        return labelled_of(coords, self.gather_blocks("key", buf) if len(buf) else None, self.params.block_resolution)

    def labelled_voxels(self) -> tuple[np.ndarray, np.ndarray]:
        """(integer voxel coordinates (n, 3) int64, keys (n,) int64) of every voxel carrying a key,
        in the grid's voxel units (block coordinate * resolution + position in the block)."""
        coords, keys = self.labelled_blocks()
        return voxels_of_labelled(coords, keys, self.params.block_resolution)

    # ------------------------------------------------------------------ arrays (map files)
    def to_arrays(self) -> dict[str, np.ndarray]:
        """All active blocks as plain arrays: ``key`` holds real keys (-1 = none, confidence 0
        there), ``weight``, ``color`` and ``conf`` float32 (the form of map files version 1)."""
        coords, buf = self.active_blocks()
        return logical_arrays(coords, self.read_raw_blocks(buf), self.slots)

    def load_arrays(self, arrays: dict[str, np.ndarray]) -> bool:
        """Activate and fill the blocks of :meth:`to_arrays` output (checked with :func:`~openfusion.mapping.voxel_arrays.check_arrays`)
        in this (empty) grid; returns True when the grid grew to hold them."""
        coords = np.asarray(arrays["block_coords"])
        n = len(coords)
        if n == 0:
            return False
        grew = False
        if n > self.capacity_blocks:
            self.reset(capacity=n)
            grew = True
        self.write_raw_blocks(coords, raw_arrays(arrays, self.slots))
        return grew


def raw_arrays(arrays: dict[str, np.ndarray], slots: KeySlots) -> dict[str, np.ndarray]:
    """Stored (raw) block values of plain arrays (:meth:`VoxelStorage.to_arrays` form); key slots
    are allocated in ``slots``."""
    out: dict[str, np.ndarray] = {"tsdf": np.asarray(arrays["tsdf"], np.float32)}
    out["weight"] = np.clip(np.round(np.asarray(arrays["weight"], np.float64)), 0, MAX_WEIGHT).astype(np.uint16)
    out["color"] = np.clip(np.round(np.asarray(arrays["color"], np.float64)), 0, 255).astype(np.uint16)
    out["key"] = slots.slots_for(np.asarray(arrays["key"], np.int64) + 1)
    out["conf"] = conf_to_stored(arrays["conf"])
    return out


def logical_arrays(coords: np.ndarray, raw: dict[str, np.ndarray], slots: KeySlots) -> dict[str, np.ndarray]:
    """Plain arrays (:meth:`VoxelStorage.to_arrays` form) of raw block values."""
    key = slots.key1_of(raw["key"]).astype(np.int32) - 1
    conf = conf_from_stored(raw["conf"])
    conf[key < 0] = 0.0
    return {
        "block_coords": np.ascontiguousarray(coords, np.int32),
        "tsdf": np.ascontiguousarray(raw["tsdf"], np.float32),
        "weight": raw["weight"].astype(np.float32),
        "color": raw["color"].astype(np.float32),
        "key": key,
        "conf": conf,
    }
