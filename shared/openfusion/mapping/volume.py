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
  ``VolumeParams.label_fill_radius_m`` (:meth:`SemanticVolume.extract_points`, ``extract_mesh``).

Names that moved to those modules (``RayHits``, ``SurfacePoints``, ``fill_nearest_labels``, ...)
are re-exported here, so ``from openfusion.mapping.volume import ...`` keeps working.
"""

from __future__ import annotations

import functools
import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, TypeVar

import numpy as np
import open3d as o3d
import open3d.core as o3c

from openfusion.frame import CameraIntrinsics, Frame
from openfusion.mapping import integration, raycast, readout, view_update
from openfusion.mapping.errors import CapacityError
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
    updates: int = 0
    voxels_updated: int = 0


_F = TypeVar("_F", bound=Callable[..., Any])


def _locked(method: _F) -> _F:
    """Serialise a public method on the volume's lock (Open3D's grid is not thread-safe)."""

    @functools.wraps(method)
    def wrapper(self: SemanticVolume, *args: Any, **kwargs: Any) -> Any:
        with self._lock:
            return method(self, *args, **kwargs)

    return wrapper  # type: ignore[return-value]


class SemanticVolume:
    """Semantic TSDF volume; the module docstring says which module holds each rule.

    Public methods are serialised on an internal lock, so a service may integrate on one thread
    and answer render requests on another.
    """

    def __init__(self, params: VolumeParams | None = None) -> None:
        self.params = params if params is not None else VolumeParams()
        if self.params.device.startswith("CUDA") and not o3c.cuda.is_available():
            raise ValueError(
                f"device {self.params.device} requested but this Open3D build has no CUDA; use device='CPU:0'"
            )
        self._lock = threading.RLock()
        self.stats = VolumeStats()
        self._intrinsic_cache: dict[CameraIntrinsics, o3c.Tensor] = {}
        self._storage = VoxelStorage(self.params, o3c.Device(self.params.device))

    # ------------------------------------------------------------------ grid bookkeeping
    def _note_capacity_change(self) -> None:
        if self._storage.note_capacity_change():
            self.stats.grow_events += 1

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
        self._storage.reset()

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
        vbg.integrate(
            block_coords, depth_img, color_img, K, extrinsic, depth_scale, p.depth_max_m, p.trunc_voxels
        )
        self._note_capacity_change()
        self._storage.mark_geometry_changed()
        self._storage.note_integrated()
        self.stats.frames_integrated += 1
        return result

    # ------------------------------------------------------------------ render / update
    @_locked
    def ray_cast(self, T_world_cam: np.ndarray, intrinsics: CameraIntrinsics) -> RayHits:
        """Depth and the 8 voxels around the first surface hit of every pixel (depth-tested)."""
        T = check_pose(T_world_cam)
        return raycast.ray_cast(self._storage, T, intrinsics, self._intrinsic_tensor(intrinsics))

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
        stats.voxels_updated, counts = view_update.write_view(
            self._storage, hits, use, key_map, conf_map, self.params.conf_history_weight
        )
        stats.voxels_labelled, stats.voxels_reinforced, stats.voxels_weakened, stats.voxels_switched = counts
        self.stats.voxels_updated += stats.voxels_updated
        return stats

    @_locked
    def relabel_keys(self, mapping: dict[int, int]) -> int:
        """Rewrite voxel keys (e.g. after a dictionary merge ``{b: a}``); ``{k: -1}`` clears a key.

        Returns the number of voxels changed. Confidences are kept (cleared voxels get 0).
        """
        return self._storage.relabel_keys(mapping)

    @_locked
    def labelled_voxels(self) -> tuple[np.ndarray, np.ndarray]:
        """(integer voxel coordinates (n, 3) int64, keys (n,) int64) of every voxel carrying a key."""
        return self._storage.labelled_voxels()

    @_locked
    def labelled_blocks(self) -> tuple[np.ndarray, np.ndarray]:
        """(block coordinates (N, 3), keys (N, R, R, R) [z, y, x], -1 = none) of the blocks holding a key."""
        return self._storage.labelled_blocks()

    def region_contacts(self, *, radius_vox: int = 1) -> Any:
        """Which regions' labelled voxels touch, how much, and each region's labelled voxel count
        (:func:`openfusion.mapping.merging.block_contacts`; what a merge pass decides on). Holds
        the volume's lock only while copying the labelled blocks out."""
        from openfusion.mapping.merging import block_contacts

        coords, keys = self.labelled_blocks()
        return block_contacts(coords, keys, radius_vox=radius_vox)

    # ------------------------------------------------------------------ read-out
    @_locked
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
        return readout.extract_points(self._storage, keys, max_points, seed=seed)

    @_locked
    def extract_mesh(self, keys: np.ndarray | list[int] | None = None) -> SurfaceMesh:
        """Surface mesh (marching cubes); with ``keys``, only triangles whose 3 vertices carry one of
        those keys (unreferenced vertices dropped)."""
        return readout.extract_mesh(self._storage, keys)

    # ------------------------------------------------------------------ arrays (save / load)
    @_locked
    def to_arrays(self) -> dict[str, np.ndarray]:
        """All active blocks as plain arrays (``key`` holds real keys, -1 = none)."""
        return self._storage.to_arrays()

    @classmethod
    def from_arrays(cls, params: VolumeParams, arrays: dict[str, np.ndarray]) -> SemanticVolume:
        """Build a volume from :meth:`to_arrays` output; raises ``ValueError`` on inconsistent arrays."""
        check_arrays(params, arrays)
        volume = cls(params)
        if volume._storage.load_arrays(arrays):
            volume.stats.grow_events += 1
        return volume
