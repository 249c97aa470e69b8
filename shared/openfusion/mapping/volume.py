"""The semantic TSDF volume: Open3D ``VoxelBlockGrid`` plus a region key and confidence per voxel.

:class:`SemanticVolume` is the map core's one volume class: it owns the lock, the counters and a
:class:`~openfusion.mapping.storage.VoxelStorage`, and composes the modules that each hold one
part of the story (read their docstrings for the rules):

- :mod:`openfusion.mapping.storage` -- the grid, attributes and key encoding (stored *key + 1*, so
  Open3D's zero-filled new blocks read as key -1), flat voxel indices, growth and versions,
  map-file arrays, key relabelling;
- :mod:`openfusion.mapping.integration` -- geometry: plain Open3D integration of a frame, the
  minimum-depth cut and the block budget (:meth:`SemanticVolume.integrate`);
- :mod:`openfusion.mapping.raycast` -- the depth-tested ray cast that render and update share,
  the render's pick (the nearest labelled voxel of the 8 around each pixel's hit) and the notes on
  driving Open3D's ``ray_cast`` (:meth:`SemanticVolume.render`);
- :mod:`openfusion.mapping.view_update` -- the update rule (inverse render): a key/confidence
  image written into the voxels at the surface seen from the pose, the nearest pixel per voxel,
  by :mod:`openfusion.mapping.update_rule` (:meth:`SemanticVolume.apply_update`);
- :mod:`openfusion.mapping.readout` -- surface points and meshes with a key each: the nearest
  labelled voxel of their cell, else the nearest same-facing labelled point's within
  ``VolumeParams.label_fill_radius_m`` (:meth:`SemanticVolume.extract_points`, ``extract_mesh``);
- :mod:`openfusion.mapping.tiles` / :mod:`openfusion.mapping.paging` /
  :mod:`openfusion.mapping.tilestore` -- tiles, the memory budget (``memory_budget_mb``: tiles
  paged out to the tile store and back in before a frame or a render reaches them), incremental
  checkpoints; :mod:`openfusion.mapping.wholemap` -- read-outs of the whole map while part of it
  is paged out; :mod:`openfusion.mapping.readout_worker` -- every whole-map read-out (points,
  meshes, summaries, contacts, checkpoint slices) as jobs of one worker thread, one chunk at a time
  in the process; :mod:`openfusion.mapping.partstore` -- paged-out tiles' read-out parts on disk.

Names that moved to those modules (``RayHits``, ``SurfacePoints``, ``fill_nearest_labels``, ...)
are re-exported here, so ``from openfusion.mapping.volume import ...`` keeps working.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import shutil
import tempfile
import threading
import weakref
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import open3d as o3d
import open3d.core as o3c

from openfusion.frame import CameraIntrinsics, Frame
from openfusion.mapping import (
    integration,
    raycast,
    readout,
    readout_worker,
    shards,
    tilereadouts,
    view_update,
)
from openfusion.mapping.errors import CapacityError
from openfusion.mapping.growth import GridGrower
from openfusion.mapping.merging import RegionContacts
from openfusion.mapping.paging import Snapshot, TilePager, budget_blocks, camera_center
from openfusion.mapping.params import VolumeParams
from openfusion.mapping.raycast import RayHits, range_map_down_factor
from openfusion.mapping.readout import FILL_MIN_NORMAL_COS, SurfaceMesh, SurfacePoints, fill_nearest_labels
from openfusion.mapping.storage import (
    ATTR_NAMES,
    BYTES_PER_VOXEL,
    SEMANTIC_BYTES_PER_VOXEL,
    VoxelStorage,
    check_arrays,
)
from openfusion.mapping.summaries import RegionTable
from openfusion.mapping.tilereadouts import TileReadouts
from openfusion.mapping.tiles import TileGrid
from openfusion.mapping.tilestore import TileStore
from openfusion.poses import check_pose, invert_pose

__all__ = [
    "ATTR_NAMES",
    "FILL_MIN_NORMAL_COS",
    "SEMANTIC_BYTES_PER_VOXEL",
    "IntegrateStats",
    "RayHits",
    "RenderedView",
    "SemanticVolume",
    "SurfaceMesh",
    "SurfacePoints",
    "UpdateStats",
    "VolumeStats",
    "fill_nearest_labels",
    "range_map_down_factor",
]

logger = logging.getLogger(__name__)


@dataclass
class RenderedView:
    """Region keys and confidences of the map seen from a pose, at the requested image size."""

    key_map: np.ndarray  # (h, w) int32, -1 = no labelled surface
    conf_map: np.ndarray  # (h, w) float32
    depth_m: np.ndarray  # (h, w) float32, 0 = no surface
    hits: RayHits | None = field(default=None, repr=False)

    @property
    def shape(self) -> tuple[int, int]:
        return self.key_map.shape  # type: ignore[return-value]


@dataclass
class UpdateStats:
    """What one :meth:`SemanticVolume.apply_update` changed."""

    pixels_used: int = 0
    pixels_depth_rejected: int = 0
    voxels_updated: int = 0
    render_budget_short: int = 0  # renders whose view did not fit the memory budget (rendered what was resident)
    voxels_labelled: int = 0  # previously unlabelled
    voxels_reinforced: int = 0  # same key
    voxels_weakened: int = 0  # other key, kept its key
    voxels_switched: int = 0  # other key, took the new key
    reused_render: bool = False


@dataclass
class IntegrateStats:
    """What one :meth:`SemanticVolume.integrate` did."""

    blocks_touched: int = 0
    blocks_new: int = 0
    blocks_refused: int = 0
    blocks_not_owned: int = 0  # touched blocks of tiles another geometry shard owns (left to it)
    empty: bool = False


@dataclass
class VolumeStats:
    """Running counters of a volume (published as service metrics)."""

    frames_integrated: int = 0
    frames_empty: int = 0
    capacity_refusals: int = 0
    blocks_refused: int = 0
    grow_events: int = 0
    renders: int = 0
    render_budget_short: int = 0  # renders whose view did not fit the memory budget (rendered what was resident)
    updates: int = 0
    voxels_updated: int = 0


_F = TypeVar("_F", bound=Callable[..., Any])


def _remove_scratch(store: TileStore, folder: str) -> None:
    store.close()
    shutil.rmtree(folder, ignore_errors=True)


def _locked(method: _F) -> _F:
    """Serialise a public method on the volume's lock (Open3D's grid is not thread-safe)."""

    @functools.wraps(method)
    def wrapper(self: SemanticVolume, *args: Any, **kwargs: Any) -> Any:
        with self._lock:
            return method(self, *args, **kwargs)

    return wrapper  # type: ignore[return-value]


def _read_out(method: _F) -> _F:
    """A whole-map read-out: one job on the read-out worker (:mod:`.readout_worker`: one at a time
    in the process, so its chunks never overlap another read-out's), holding the volume's lock there."""

    @functools.wraps(method)
    def wrapper(self: SemanticVolume, *args: Any, **kwargs: Any) -> Any:
        def job() -> Any:
            with self._lock:
                return method(self, *args, **kwargs)

        return readout_worker.run(method.__name__, job)

    return wrapper  # type: ignore[return-value]


class SemanticVolume:
    """Semantic TSDF volume; the module docstring says which module holds each rule.

    Public methods are serialised on an internal lock, so a service may integrate on one thread
    and answer render requests on another.
    """

    def __init__(self, params: VolumeParams | None = None, *, store: TileStore | None = None) -> None:
        """``store``: the tile store checkpoints go to and tiles are paged out to (a map folder's,
        :mod:`openfusion.mapping.tilestore`). With ``memory_budget_mb`` and no store, tiles are
        paged out to a scratch store in a temporary folder, removed by :meth:`close`."""
        self.params = params if params is not None else VolumeParams()
        if self.params.device.startswith("CUDA") and not o3c.cuda.is_available():
            raise ValueError(
                f"device {self.params.device} requested but this Open3D build has no CUDA; use device='CPU:0'"
            )
        self._lock = threading.RLock()
        readout_worker.register_lock(self._lock, owner=self)  # read-out jobs take it (rule 1 there)
        self.stats = VolumeStats()
        self._intrinsic_cache: dict[CameraIntrinsics, o3c.Tensor] = {}
        budget = None
        if self.params.memory_budget_mb is not None:
            budget = budget_blocks(self.params.memory_budget_mb, BYTES_PER_VOXEL * self.params.block_resolution**3)
        # With a budget the grid is made at its size once (a default-sized grid first would be
        # resident beside it for a moment: +128 MiB at start, measured).
        self._storage = VoxelStorage(self.params, o3c.Device(self.params.device), capacity=budget)
        self._scratch: weakref.finalize | None = None
        if budget is not None and store is None:
            folder = tempfile.mkdtemp(prefix="openfusion-tiles-")
            store = TileStore(Path(folder) / "map.ofz")
            # Removed by close(), or when the volume is collected (no warning: it is ours).
            self._scratch = weakref.finalize(self, _remove_scratch, store, folder)
        grid = TileGrid(self.params.tile_blocks, self.params.block_size_m)
        self._pager = TilePager(self._storage, grid, store, budget)
        #: Without a budget the grid grows ahead of need in the background (:mod:`.growth`).
        self._grower = GridGrower(self._storage, self._pager.versions, grid) if budget is None else None
        #: Region summaries and contacts kept per tile (:mod:`.tilereadouts`).
        self._readouts = TileReadouts(self._storage, self._pager)
        self._storage.on_relabel = self._readouts.relabelled
        #: The geometry shard this volume is (docs/SHARDS.md); 0/1: the whole map.
        self._shard = self.params.shard_id
        #: A shard's record of the blocks other shards hold (coordinates only; raycast.py).
        self._others = shards.OtherBlocks(self.params.tile_blocks)
        if self._shard.sharded:  # only its own tiles' summaries and contacts (the rest are ghosts)
            self._readouts.owns = lambda tile: bool(shards.owned_blocks(
                np.asarray(tile, np.int64).reshape(1, 3) * self.params.tile_blocks, self.params.tile_blocks,
                self._shard)[0])

    def close(self) -> None:
        """Release the tile store (and remove a scratch store's folder)."""
        with self._lock:
            if self._grower is not None:
                self._grower.close()
            self._readouts.close()
            store = self._pager.store
            if store is not None:
                store.close()
            if self._pager.base is not None:
                self._pager.base.close()
            if self._scratch is not None:
                self._scratch()
                self._scratch = None

    @property
    def store(self) -> TileStore | None:
        """The tile store of this volume (None: nothing is paged and no checkpoint store is set)."""
        return self._pager.store if self._scratch is None else None

    @property
    def pager(self) -> TilePager:
        return self._pager

    @property
    def budget_blocks(self) -> int | None:
        return self._pager.budget_blocks

    @property
    def resident_bytes(self) -> int:
        """Bytes of the grid's voxel buffers (its capacity: Open3D allocates and touches them all)."""
        return self._storage.capacity_blocks * self._storage.bytes_per_block

    # ------------------------------------------------------------------ grid bookkeeping
    def _note_capacity_change(self) -> None:
        if self._storage.note_capacity_change():
            self.stats.grow_events += 1
            if self._pager.budget_blocks is not None:
                logger.warning("the grid grew past the memory budget (%d blocks): a bug, please report it",
                               self._pager.budget_blocks)

    @property
    def device(self) -> str:
        return self.params.device

    @property
    def num_blocks(self) -> int:
        """Allocated (active) blocks."""
        return self._storage.num_blocks

    @property
    def capacity_blocks(self) -> int:
        """Blocks the grid's buffers hold before the next growth."""
        return self._storage.capacity_blocks

    @property
    def generation(self) -> int:
        """Changes whenever voxel buffer indices may have changed (growth, reset, load)."""
        return self._storage.generation

    @property
    def geometry_version(self) -> int:
        """Changes after every integration (and reset/load)."""
        return self._storage.geometry_version

    @property
    def voxels_per_block(self) -> int:
        return self._storage.voxels_per_block

    @property
    def bytes_per_voxel(self) -> int:
        """All attributes: tsdf 4 + weight 2 + color 6 + key 2 + conf 2 (``storage``'s docstring)."""
        return BYTES_PER_VOXEL

    @property
    def open3d_grid(self) -> o3d.t.geometry.VoxelBlockGrid:
        """The underlying grid (read-only use: writing to it bypasses the key encoding)."""
        return self._storage.vbg

    @property
    def _vbg(self) -> o3d.t.geometry.VoxelBlockGrid:
        """Older private name of :attr:`open3d_grid` (no caller in the repository; prefer that)."""
        return self._storage.vbg

    @_locked
    def clear(self) -> None:
        """Drop all geometry and semantics (counters are kept)."""
        if self._grower is not None:
            self._grower.close()
        self._storage.reset()
        self._readouts.forget()

    def _intrinsic_tensor(self, intrinsics: CameraIntrinsics) -> o3c.Tensor:
        K = self._intrinsic_cache.get(intrinsics)
        if K is None:
            if len(self._intrinsic_cache) > 32:
                self._intrinsic_cache.clear()
            K = o3c.Tensor(intrinsics.K, o3c.float64)
            self._intrinsic_cache[intrinsics] = K
        return K

    # ------------------------------------------------------------------ integration
    @_locked
    def integrate(self, frame: Frame) -> IntegrateStats:
        """Fuse one frame's depth and color (geometry only; semantics are untouched).

        Raises :class:`CapacityError` (volume unchanged) when ``max_blocks`` is set, the frame needs
        more new blocks than the budget allows and ``when_full == "raise"``. A frame with no valid
        depth is counted in ``stats.frames_empty`` and changes nothing.
        """
        frame.validate()
        p = self.params
        vbg = self._storage.vbg
        depth_img, color_img, depth_scale = integration.frame_images(self._storage, frame)
        K = self._intrinsic_tensor(frame.intrinsics)
        extrinsic = o3c.Tensor(invert_pose(np.asarray(frame.T_world_cam, np.float64)))
        try:
            block_coords = vbg.compute_unique_block_coordinates(
                depth_img, K, extrinsic, depth_scale, p.depth_max_m, p.trunc_voxels
            )
        except RuntimeError as exc:
            if "No block is touched" not in str(exc):
                raise
            self.stats.frames_empty += 1
            logger.debug("frame %s has no depth in range; nothing integrated", frame.frame_id)
            return IntegrateStats(empty=True)
        result = IntegrateStats(blocks_touched=int(block_coords.shape[0]))
        pager = self._pager
        pager.tick(camera_center(frame.T_world_cam))
        coords_np = block_coords.cpu().numpy()
        if self._shard.sharded:  # a geometry shard: only the blocks of its own tiles (mapping/shards.py)
            owned, taken = shards.take_blocks(coords_np, p.tile_blocks, self._shard)  # + ghosts: read-outs across seams
            result.blocks_not_owned = int((~owned).sum())
            self._others.add(coords_np[~taken])  # coordinates only: its ray casts stand in for them
            if not owned.any():
                self.stats.frames_integrated += 1  # taken: nothing of it is this shard's
                return result
            if not taken.all():
                coords_np = np.ascontiguousarray(coords_np[taken])
                block_coords = o3c.Tensor.from_numpy(coords_np).to(block_coords.device)  # shares coords_np on the CPU
        if pager.budget_blocks is not None or pager.stored_blocks:
            self._page_in_for(coords_np, frame.frame_id)
        if self._grower is not None:
            self._grower.before_integrate(len(coords_np))
        if p.max_blocks is not None:
            budget = integration.block_budget(self._storage, block_coords, p.max_blocks)
            result.blocks_new = budget.blocks_new
            if budget.blocks_refused:
                self.stats.capacity_refusals += 1
                self.stats.blocks_refused += budget.blocks_refused
                result.blocks_refused = budget.blocks_refused
                message = (
                    f"frame {frame.frame_id} needs {budget.blocks_new} new blocks but only "
                    f"{budget.blocks_free} of max_blocks={p.max_blocks} are free"
                )
                if p.when_full == "raise":
                    raise CapacityError(
                        message + "; nothing was integrated",
                        blocks_needed=budget.blocks_new,
                        blocks_free=budget.blocks_free,
                    )
                logger.warning("%s; integrating into existing blocks only", message)
            if budget.admitted is None:
                return result
            block_coords = budget.admitted
        vbg = self._storage.vbg  # the grid may have been swapped for a grown copy above
        vbg.integrate(
            block_coords, depth_img, color_img, K, extrinsic, depth_scale, p.depth_max_m, p.trunc_voxels
        )
        self._note_capacity_change()
        self._storage.mark_geometry_changed()
        capped = self._storage.note_integrated()
        if len(capped):  # weights capped: those blocks' tiles changed too
            pager.touched(self._storage.block_coords_of_buf(capped), changed=True)
        pager.touched(block_coords.cpu().numpy() if p.max_blocks is not None else coords_np, changed=True)
        self.stats.frames_integrated += 1
        return result

    def _page_in_for(self, coords: np.ndarray, frame_id: int) -> None:
        """Make the tiles of a frame's blocks resident (paging stored ones in) and room for its new
        blocks under the memory budget; :class:`CapacityError` (nothing written) when the frame
        alone needs more blocks than the budget holds."""
        pager = self._pager
        tiles = pager.touched(coords, changed=False)
        stored = {t for t in tiles if t in pager.stored_blocks}
        # Open3D's integrate grows the grid (a whole-grid copy) when the blocks in use plus *all* the
        # blocks it is given, not only the new ones, exceed its capacity (measured, open3d 0.20):
        # so room is made for the frame's whole block list after the stored tiles came back.
        try:
            pager.ensure_resident(tiles, extra_blocks=len(coords))
            if pager.budget_blocks is not None and stored:
                pager.ensure_resident(tiles, extra_blocks=len(coords))
        except CapacityError as exc:
            raise CapacityError(
                f"frame {frame_id}: {exc}; nothing was integrated", blocks_needed=exc.blocks_needed,
                blocks_free=exc.blocks_free,
            ) from exc

    # ------------------------------------------------------------------ render / update
    @_locked
    def ray_cast(self, T_world_cam: np.ndarray, intrinsics: CameraIntrinsics) -> RayHits:
        """Depth and the 8 voxels around the first surface hit of every pixel (depth-tested)."""
        T = check_pose(T_world_cam)
        self._settle_growth()
        self._page_in_view(T, intrinsics)
        return raycast.ray_cast(self._storage, T, intrinsics, self._intrinsic_tensor(intrinsics),
                                others=self._others_in_view(T, intrinsics) if self._shard.sharded else None)

    def _others_in_view(self, T_world_cam: np.ndarray, intrinsics: CameraIntrinsics) -> np.ndarray:
        """The blocks other shards hold in tiles a view can reach (a shard's ray cast stands in for them)."""
        tiles = self._others.tiles()
        seen = self._pager.grid.tiles_in_view(
            tiles, T_world_cam, fx=intrinsics.fx, fy=intrinsics.fy, cx=intrinsics.cx, cy=intrinsics.cy,
            width_px=intrinsics.width_px, height_px=intrinsics.height_px, depth_max_m=self.params.depth_max_m,
        )
        return self._others.blocks_of(tiles[seen])

    def _settle_growth(self) -> None:
        if self._grower is not None:
            self._grower.settle()

    def _page_in_view(self, T_world_cam: np.ndarray, intrinsics: CameraIntrinsics) -> None:
        """Page in the stored tiles a view can reach (renders see the whole map)."""
        pager = self._pager
        if not pager.stored_blocks:
            return
        stored = np.array(list(pager.stored_blocks), np.int64)
        seen = pager.grid.tiles_in_view(
            stored, T_world_cam, fx=intrinsics.fx, fy=intrinsics.fy, cx=intrinsics.cx, cy=intrinsics.cy,
            width_px=intrinsics.width_px, height_px=intrinsics.height_px, depth_max_m=self.params.depth_max_m,
        )
        if not seen.any():
            return
        pager.tick(camera_center(T_world_cam))
        resident = np.array(pager.resident_tiles(), np.int64).reshape(-1, 3)
        in_view = resident[pager.grid.tiles_in_view(
            resident, T_world_cam, fx=intrinsics.fx, fy=intrinsics.fy, cx=intrinsics.cx, cy=intrinsics.cy,
            width_px=intrinsics.width_px, height_px=intrinsics.height_px, depth_max_m=self.params.depth_max_m,
        )]
        tiles = [tuple(int(v) for v in t) for t in np.concatenate([stored[seen], in_view])]
        try:
            pager.ensure_resident(tiles)  # type: ignore[arg-type]
        except CapacityError as exc:  # a view wider than the budget: render what is resident
            self.stats.render_budget_short += 1
            logger.warning("render: the tiles in view do not fit the memory budget (%s); rendering the resident ones", exc)
        for t in tiles:
            if t in pager.last_used:
                pager.last_used[t] = pager.clock  # type: ignore[index]

    @_locked
    def render(self, T_world_cam: np.ndarray, intrinsics: CameraIntrinsics) -> RenderedView:
        """Key, confidence and depth images of the map from ``T_world_cam`` at ``intrinsics``' size.

        ``intrinsics`` must already be scaled to the wanted (encoder) size, e.g. ``K.scaled(w, h)``.
        """
        hits = self.ray_cast(T_world_cam, intrinsics)
        key_map, conf_map = raycast.semantics_at_hits(self._storage, hits)
        self.stats.renders += 1
        return RenderedView(key_map, conf_map, hits.depth_m, hits)

    @_locked
    def apply_update(
        self,
        T_world_cam: np.ndarray,
        intrinsics: CameraIntrinsics,
        key_map: np.ndarray,
        conf_map: np.ndarray,
        *,
        rendered: RenderedView | None = None,
        observed_depth_m: np.ndarray | None = None,
        depth_tolerance_m: float | None = None,
    ) -> UpdateStats:
        """Write per-pixel keys and confidences into the voxels at the surface seen from the pose.

        The rule is in :mod:`openfusion.mapping.view_update`. ``rendered`` (a render of the same pose and size) lets
        the update reuse that ray cast when the grid's buffers have not moved since.

        ``observed_depth_m`` (the frame's depth, any size; resampled to the map size) enables a
        depth gate: a pixel whose map surface is farther than ``depth_tolerance_m`` (default: the
        truncation distance + 2 % of the depth) from the observed depth is skipped. This stops
        labels of an object's silhouette pixels from landing on the background behind it.
        """
        T = check_pose(T_world_cam)
        key_map, conf_map = view_update.check_update_maps(
            key_map, conf_map, (intrinsics.height_px, intrinsics.width_px)
        )
        stats = UpdateStats()
        hits = rendered.hits if rendered is not None else None
        if (
            hits is not None
            and hits.generation == self._storage.generation
            and hits.pose_key == raycast.view_key(T, intrinsics)
        ):
            stats.reused_render = True
        else:
            hits = self.ray_cast(T, intrinsics)
        use = (key_map >= 0) & (conf_map > 0) & (hits.depth_m > 0)
        if observed_depth_m is not None:
            consistent = view_update.depth_consistent(
                hits.depth_m, observed_depth_m, self.params.trunc_m, depth_tolerance_m
            )
            stats.pixels_depth_rejected = int((use & ~consistent).sum())
            use &= consistent
        stats.pixels_used = int(use.sum())
        self.stats.updates += 1
        if stats.pixels_used == 0:
            return stats
        stats.voxels_updated, counts, voxels = view_update.write_view(
            self._storage, hits, use, key_map, conf_map, self.params.conf_history_weight
        )
        self._pager.touched_voxels(voxels)
        stats.voxels_labelled, stats.voxels_reinforced, stats.voxels_weakened, stats.voxels_switched = counts
        self.stats.voxels_updated += stats.voxels_updated
        return stats

    @_locked
    def relabel_keys(self, mapping: dict[int, int]) -> int:
        """Rewrite voxel keys (e.g. after a dictionary merge ``{b: a}``); ``{k: -1}`` clears a key.

        Returns the number of voxels changed. Confidences are kept (cleared voxels get 0).
        """
        return self._storage.relabel_keys(mapping)

    @_read_out
    def labelled_voxels(self) -> tuple[np.ndarray, np.ndarray]:
        """(integer voxel coordinates (n, 3) int64, keys (n,) int64) of every voxel carrying a key."""
        coords, keys = self.labelled_blocks()
        from openfusion.mapping.storage import voxels_of_labelled

        return voxels_of_labelled(coords, keys, self.params.block_resolution)

    @_read_out
    def labelled_blocks(self) -> tuple[np.ndarray, np.ndarray]:
        """(block coordinates (N, 3), keys (N, R, R, R) [z, y, x], -1 = none) of the blocks holding a key."""
        coords, keys = self._storage.labelled_blocks()
        if not self._pager.stored_blocks:
            return coords, keys
        from openfusion.mapping.storage import labelled_of

        parts_c, parts_k = [coords], [keys]
        res = self.params.block_resolution
        for _, tc, raw in self._pager.iter_stored():
            c, k = labelled_of(tc, self._storage.slots.key1_of(raw["key"].reshape(len(tc), -1)), res)
            parts_c.append(c)
            parts_k.append(k)
        return np.concatenate(parts_c), np.concatenate(parts_k)

    def region_contacts(self, *, radius_vox: int = 1, lock: Any = None) -> RegionContacts:
        """Which regions' labelled voxels touch, how much, and each region's labelled voxel count
        (what a merge pass decides on; equal to :func:`openfusion.mapping.merging.block_contacts`
        of every labelled block). Kept per tile (:mod:`.tilereadouts`): only tiles whose
        neighbourhood changed since the last call are counted again, a chunk at a time, copied
        holding ``lock`` (a caller's reentrant lock, e.g. a service's) and the volume's lock."""
        for _ in range(3):
            tilereadouts.refresh(self._lock, self._readouts, what="contacts", lock=lock, radius_vox=radius_vox)
            with self._lock:
                missing = self._readouts.missing
                parts = self._readouts.contact_parts()
                if self._readouts.missing == missing:
                    break  # else a stored part had gone missing: its tile is read out again
        return tilereadouts.combine_contacts(parts)

    def region_table(self, *, lock: Any = None) -> RegionTable:
        """Per-region surface summaries of the whole map (equal to ``RegionTable.of_points`` of
        :meth:`extract_points`), kept per tile (:mod:`.tilereadouts`): only the tiles whose
        neighbourhood changed since the last call are read out again, a chunk at a time, copied
        holding ``lock`` and the volume's lock and read out holding neither. A map that changes
        meanwhile gives a table of the tiles as each was read; when the parts kept too few values
        for an exact box, those tiles are read again (the last try holds the locks throughout)."""
        for attempt in range(6):
            hold = attempt >= 3
            tilereadouts.refresh(self._lock, self._readouts, what="summaries", lock=lock, hold=hold)
            with tilereadouts.both(lock, self._lock) if hold else self._lock:
                missing = self._readouts.missing
                # Streamed: stored parts are read from the part store one at a time, never all at once.
                table, failing = tilereadouts.combine_summaries(
                    self._readouts.iter_summary_parts, self._storage.slots.key1, index=self._readouts.summary_index())
                if self._readouts.missing != missing:
                    continue  # a stored part had gone missing: its tile is read out again
                if not failing:
                    return table
                for (tile, slot), want in failing.items():
                    self._readouts.keep[(tile, slot)] = max(self._readouts.keep.get((tile, slot), 0), want)
                    self._readouts.summaries.pop(tile, None)
        raise RuntimeError("region summaries did not settle: the parts kept too few values six times")

    def refresh_region_table(self, *, settled_clock: int | None = None, lock: Any = None,
                             max_s: float | None = None) -> int:
        """Read out the stale summary parts of tiles whose neighbourhood last changed at or before
        ``settled_clock`` (a service's idle work, so a save has little left), for at most about
        ``max_s`` seconds; returns the tiles read."""
        return tilereadouts.refresh(self._lock, self._readouts, what="summaries", lock=lock,
                                    settled_clock=settled_clock, max_s=max_s)

    @property
    def readout_stats(self) -> dict[str, int]:
        """Tiles read out for region summaries and contacts so far (:mod:`.tilereadouts`)."""
        return dict(self._readouts.stats)

    @property
    def change_clock(self) -> int:
        """The tile versions' clock (grows with every change of the map's voxels)."""
        return self._pager.versions.clock

    # ------------------------------------------------------------------ read-out
    @_read_out
    def extract_points(
        self,
        keys: np.ndarray | list[int] | None = None,
        max_points: int | None = None,
        *,
        seed: int = 0,
    ) -> SurfacePoints:
        """Surface points (zero crossings of voxels observed ``min_weight`` times) with keys.

        Points are sorted by (x, y, z), so the same map always gives the same array. ``keys`` keeps
        only points of those regions; ``max_points`` subsamples uniformly at random
        (deterministic for a given ``seed``).
        """
        self._settle_growth()
        if self._shard.sharded:  # only the points its own tiles own, then the cap
            pts = self._extract_points(keys, None, seed)
            p = self.params
            keep = shards.own_points(pts.points, p.voxel_size_m, p.block_resolution, p.tile_blocks, self._shard)
            pts = SurfacePoints(pts.points[keep], pts.colors[keep], pts.keys[keep], pts.conf[keep])
            if max_points is not None and len(pts) > max_points:
                sel = np.sort(np.random.default_rng(seed).choice(len(pts), size=max_points, replace=False))
                pts = SurfacePoints(pts.points[sel], pts.colors[sel], pts.keys[sel], pts.conf[sel])
            return pts
        return self._extract_points(keys, max_points, seed)

    def _extract_points(self, keys: np.ndarray | list[int] | None, max_points: int | None, seed: int) -> SurfacePoints:
        if self._pager.stored_blocks:
            from openfusion.mapping import wholemap

            return wholemap.extract_points(self._storage, self._pager, keys, max_points, seed=seed)
        return readout.extract_points(self._storage, keys, max_points, seed=seed)

    @_read_out
    def extract_mesh(self, keys: np.ndarray | list[int] | None = None) -> SurfaceMesh:
        """Surface mesh (marching cubes); with ``keys``, only triangles whose 3 vertices carry one of
        those keys (unreferenced vertices dropped)."""
        if self._pager.stored_blocks:
            from openfusion.mapping import wholemap

            return self._own_mesh(wholemap.extract_mesh(self._storage, self._pager, keys))
        return self._own_mesh(readout.extract_mesh(self._storage, keys))

    def _own_mesh(self, mesh: SurfaceMesh) -> SurfaceMesh:
        """A shard's mesh: the triangles whose cube its own tiles own (unreferenced vertices dropped)."""
        if not self._shard.sharded or len(mesh.triangles) == 0:
            return mesh
        p = self.params
        keep = shards.own_points(mesh.vertices[mesh.triangles].mean(axis=1), p.voxel_size_m, p.block_resolution,
                                 p.tile_blocks, self._shard)
        tris = mesh.triangles[keep]
        used = np.zeros(len(mesh.vertices), bool)
        used[tris.reshape(-1)] = True
        remap = np.full(len(mesh.vertices), -1, np.int64)
        remap[used] = np.arange(int(used.sum()))
        return SurfaceMesh(mesh.vertices[used], remap[tris].astype(np.int32), mesh.colors[used], mesh.normals[used],
                           mesh.keys[used], mesh.conf[used])

    @_read_out
    def mesh_parts(self, keys: np.ndarray | list[int] | None = None) -> list[SurfaceMesh]:
        """The mesh in parts of at most ``wholemap.CHUNK_BLOCKS`` blocks each (a large map's mesh
        written or sent part by part; one part for a map with nothing paged out)."""
        from openfusion.mapping import wholemap

        if not self._pager.stored_blocks and self._storage.num_blocks <= wholemap.CHUNK_BLOCKS:
            return [self._own_mesh(readout.extract_mesh(self._storage, keys))]
        return [self._own_mesh(m) for m in wholemap.iter_mesh_parts(self._storage, self._pager, keys)]

    # ------------------------------------------------------------------ arrays (save / load)
    @_read_out
    def to_arrays(self) -> dict[str, np.ndarray]:
        """Every block (resident and paged out) as plain arrays (``key`` holds real keys, -1 = none)."""
        arrays = self._storage.to_arrays()
        if not self._pager.stored_blocks:
            return arrays
        parts = [arrays, *self._pager.stored_arrays()]
        return {name: np.concatenate([p[name] for p in parts]) for name in arrays}

    def unshared_arrays(self) -> dict[str, np.ndarray]:
        """:meth:`to_arrays` on the calling thread, not as a read-out job: only for a volume no other
        thread can reach yet (a loaded map being moved into another volume by a caller that
        holds a service's lock, which a job may not be asked for under)."""
        with self._lock:
            return SemanticVolume.to_arrays.__wrapped__(self)  # type: ignore[attr-defined]

    @property
    def num_blocks_total(self) -> int:
        """Blocks of the whole map: resident and paged out."""
        return self._storage.num_blocks + sum(self._pager.stored_blocks.values())

    # ------------------------------------------------------------------ checkpoints (tile store)
    # The steps of :func:`openfusion.mapping.mapstore.checkpoint` (the rules: :mod:`.paging`).
    @_locked
    def checkpoint_plan(self, *, every_tile: bool = False) -> list[list[tuple[int, int, int]]]:
        """Slices of the resident tiles a checkpoint must write (``every_tile``: all)."""
        self._settle_growth()
        return self._pager.precopy_plan(every_tile=every_tile)

    @_locked
    def checkpoint_copy(self, tiles: list[tuple[int, int, int]]) -> tuple[dict, dict]:
        """Raw copies of one slice's tiles (still to be written) and their versions."""
        return self._pager.copy_tiles(tiles)

    @_locked
    def checkpoint_slice_written(self, versions: dict[tuple[int, int, int], int]) -> None:
        self._pager.slice_written(versions)

    @_locked
    def checkpoint_end(self) -> Snapshot:
        """A checkpoint's last step (:meth:`~openfusion.mapping.paging.TilePager.end_snapshot`)."""
        self._settle_growth()
        snap = self._pager.end_snapshot()
        snap.tile_index = self._tile_index()
        return snap

    @_locked
    def tile_index(self) -> np.ndarray:
        """int32 (T, 4): every tile of the map (x, y, z, block count)."""
        return self._tile_index()

    def _tile_index(self) -> np.ndarray:
        groups = self._pager._resident_groups()
        rows = [(*t, len(g[1])) for t, g in groups.items()] + [
            (*t, n) for t, n in self._pager.stored_blocks.items()
        ]
        return np.array(sorted(rows), np.int32).reshape(-1, 4)

    @_locked
    def checkpoint_committed(self, snap: Snapshot) -> None:
        """``snap``'s generation is durable in the store (bookkeeping of what is dirty)."""
        self._pager.committed(snap)

    @contextlib.contextmanager
    def locked(self) -> Iterator[None]:
        """Hold the volume's lock (nothing changes the map meanwhile): a save into a new store."""
        with self._lock:
            yield

    @classmethod
    def from_arrays(cls, params: VolumeParams, arrays: dict[str, np.ndarray]) -> SemanticVolume:
        """Build a volume from :meth:`to_arrays` output; raises ``ValueError`` on inconsistent arrays."""
        check_arrays(params, arrays)
        volume = cls(params)
        if volume._storage.load_arrays(arrays):
            volume.stats.grow_events += 1
        volume._pager.sync_resident()
        return volume
