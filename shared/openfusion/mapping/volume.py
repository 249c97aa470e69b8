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

The volume's own methods are in three modules: this one (construction, integration, render and
update), :mod:`openfusion.mapping.volume_readouts` (points, meshes, labelled voxels, region
summaries and contacts) and :mod:`openfusion.mapping.volume_checkpoints` (arrays and checkpoint
steps), mixed into :class:`SemanticVolume`; :mod:`openfusion.mapping.volume_locks` holds how a
method takes the volume's lock.

Names that moved to those modules (``RayHits``, ``SurfacePoints``, ``fill_nearest_labels``, ...)
are re-exported here, so ``from openfusion.mapping.volume import ...`` keeps working.
"""

from __future__ import annotations

import logging
import shutil
import tempfile
import threading
import weakref
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import open3d as o3d
import open3d.core as o3c

from openfusion.frame import CameraIntrinsics, Frame, resize_nearest
from openfusion.mapping import (
    integration,
    raycast,
    readout_worker,
    shards,
    surface_probe,
    view_update,
)
from openfusion.mapping.errors import CapacityError
from openfusion.mapping.growth import GridGrower
from openfusion.mapping.paging import TilePager, budget_blocks, camera_center
from openfusion.mapping.params import VolumeParams
from openfusion.mapping.raycast import RayHits, range_map_down_factor
from openfusion.mapping.readout import FILL_MIN_NORMAL_COS, SurfaceMesh, SurfacePoints, fill_nearest_labels
from openfusion.mapping.storage import (
    ATTR_NAMES,
    BYTES_PER_VOXEL,
    SEMANTIC_BYTES_PER_VOXEL,
    VoxelStorage,
)
from openfusion.mapping.tilereadouts import TileReadouts
from openfusion.mapping.tiles import TileGrid
from openfusion.mapping.tilestore import TileStore
from openfusion.mapping.volume_checkpoints import VolumeCheckpoints
from openfusion.mapping.volume_locks import locked as _locked
from openfusion.mapping.volume_readouts import VolumeReadOuts
from openfusion.mapping.voxel_arrays import check_arrays
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
    probed: bool = False  # read by a probe at the frame's own depth (surface_probe), not a ray cast

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
    probes: int = 0  # frame selection's views read without a ray cast (surface_probe)
    render_budget_short: int = 0  # renders whose view did not fit the memory budget (rendered what was resident)
    updates: int = 0
    voxels_updated: int = 0


def _remove_scratch(store: TileStore, folder: str) -> None:
    store.close()
    shutil.rmtree(folder, ignore_errors=True)


class SemanticVolume(VolumeReadOuts, VolumeCheckpoints):
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
        self._others.clear()  # the other shards' blocks of the map dropped: no stand-ins for them

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
    def probe(self, T_world_cam: np.ndarray, intrinsics: CameraIntrinsics, depth_m: np.ndarray) -> RenderedView:
        """Key, confidence and depth images of the map's surface near a frame's own depth
        (``depth_m`` at ``intrinsics``' size) from ``T_world_cam``: frame selection's view of a
        candidate without a ray cast, at a cost that does not grow with the map
        (:mod:`openfusion.mapping.surface_probe`). Its ``hits`` name the voxels it read, so an
        update of the same view writes through them as through a render's (:meth:`apply_update`)."""
        T = check_pose(T_world_cam)
        self._settle_growth()
        self._page_in_view(T, intrinsics)
        key_map, conf_map, hits = surface_probe.probe_view(self._storage, T, intrinsics, depth_m)
        self.stats.probes += 1
        return RenderedView(key_map, conf_map, hits.depth_m, hits, probed=True)

    def candidate_view(self, T_world_cam: np.ndarray, intrinsics: CameraIntrinsics, depth_m: np.ndarray,
                       probe_above_blocks: int | None = 0) -> RenderedView:
        """Frame selection's view of a candidate: :meth:`probe` at its depth when the map holds more
        than ``probe_above_blocks`` blocks, else :meth:`render` (None: always rendered;
        ``SelectParams.probe_above_blocks``)."""
        if probe_above_blocks is not None and self.num_blocks > probe_above_blocks:
            return self.probe(T_world_cam, intrinsics, depth_m)
        return self.render(T_world_cam, intrinsics)

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

        Maps narrower than ``params.update_min_width_px`` are enlarged first
        (:func:`~openfusion.mapping.view_update.enlarge_update_maps`). With a reusable ``rendered``
        (the step's render or probe of the maps' view) each enlarged pixel's ray looks for the
        surface at the depth its map pixel's ray found it
        (:func:`~openfusion.mapping.surface_probe.probe_hits`; no ray cast, 37 ms at 160x120 on
        this 2-core box, whatever the map's size), else the update casts its own rays at that size;
        with ``observed_depth_m`` each enlarged pixel is gated by its map pixel's observed depth.
        Both keep a label on the surface its encoder pixel saw (docs/EVAL.md, "Rays for every
        voxel": a ray cast lets the rays near a silhouette label the background instead).

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
        reusable = (
            hits is not None
            and hits.generation == self._storage.generation
            and hits.pose_key == raycast.view_key(T, intrinsics)
        )
        small = intrinsics
        intrinsics, key_map, conf_map = view_update.enlarge_update_maps(
            intrinsics, key_map, conf_map, self.params.update_min_width_px)
        if reusable and hits is not None:
            stats.reused_render = True
            if intrinsics is not small:
                # The enlarged maps' rays find the surface at the depth their map pixel's ray found
                # it (a probe, no ray cast): a label stays on the surface its encoder pixel saw.
                hits = surface_probe.probe_hits(
                    self._storage, T, intrinsics, resize_nearest(hits.depth_m, (intrinsics.height_px, intrinsics.width_px)))
        else:
            hits = self.ray_cast(T, intrinsics)
        if observed_depth_m is not None and intrinsics is not small:
            # Each enlarged pixel is gated by its map pixel's depth: its label keeps to the surface
            # the encoder's pixel saw (at a silhouette, the rays between a map pixel's centre and
            # the object's edge reach the background, which the object's label must not take).
            observed_depth_m = resize_nearest(
                resize_nearest(np.asarray(observed_depth_m, np.float32), (small.height_px, small.width_px)),
                (intrinsics.height_px, intrinsics.width_px))
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

    @classmethod
    def from_arrays(cls, params: VolumeParams, arrays: dict[str, np.ndarray]) -> SemanticVolume:
        """Build a volume from :meth:`to_arrays` output; raises ``ValueError`` on inconsistent arrays."""
        check_arrays(params, arrays)
        volume = cls(params)
        if volume._storage.load_arrays(arrays):
            volume.stats.grow_events += 1
        volume._pager.sync_resident()
        return volume
