"""The semantic TSDF volume: Open3D ``VoxelBlockGrid`` plus a region key and confidence per voxel.

Storage
    Attributes ``tsdf``, ``weight``, ``color`` (Open3D's own) and ``key`` (int32), ``conf`` (float32).
    Open3D zero-fills the values of a block when it activates it, so ``key`` is stored as
    *key + 1*: a stored 0 reads back as key ``-1`` (never labelled) without any per-block
    initialisation on the integration path. Every public method speaks real keys (-1 = none).

Geometry
    :meth:`SemanticVolume.integrate` is plain Open3D integration (``compute_unique_block_coordinates``
    + ``integrate`` with the configured truncation), so it runs as fast as Open3D alone.

Render (depth-tested)
    :meth:`SemanticVolume.render` ray-casts the TSDF from a pose with Open3D's ``ray_cast``. Each
    pixel's ray stops at the first zero crossing, so occluded surfaces never appear. The ray cast
    returns the 8 voxels around the hit with their trilinear weights; the pixel takes the key and
    confidence of the labelled voxel among them with the largest weight (the nearest one).

Update rule (inverse render), per voxel near the surface seen from the pose
    The same ray cast picks, for every pixel of the update's key/confidence map, the 8 voxels around
    its surface hit; a voxel reached by several pixels takes the pixel whose hit is nearest to it
    (largest trilinear weight). The voxel's key and confidence then follow the rule of
    :mod:`openfusion.mapping.update_rule` (``fuse_semantics``): with
    ``w = VolumeParams.conf_history_weight`` and an observation (key ``k``, confidence ``c``)

    - never labelled:  key <- k,  conf <- c
    - same key:        conf <- (w * conf + c) / (w + 1)               (weighted average)
    - other key:       conf <- conf - c / (w + 1); if that is negative the new key wins:
                       key <- k, conf <- c / (w + 1) - conf_old      (the remaining evidence)

    Pixels with key -1 or confidence 0 change nothing. Voxels behind the first surface are never
    reached by the rays, so occluded voxels are not updated.

Read-out
    Surface points (queries, segmentation, exports) take the key of the nearest labelled voxel of
    their cell; points with none take the nearest same-facing labelled point's within
    ``VolumeParams.label_fill_radius_m`` (:func:`fill_nearest_labels`).

Open3D ray-cast notes (open3d 0.20, measured)
    ``ray_cast`` estimates a per-pixel depth range from the blocks it is given, in fragments kept
    in a buffer owned by the grid. When the buffer is too small it logs "Could not generate full
    range map" and renders an *incomplete* image for that call. We pass only the blocks in the view
    frustum and, before casting, grow the buffer (one quiet warm-up cast with synthetic blocks)
    to an upper bound of the fragments the cast can need. The range-map down factor must divide
    the image size (otherwise the last rows read outside the range map); we pick 8, 4, 2 or 1.
"""

from __future__ import annotations

import functools
import logging
import math
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, TypeVar

import numpy as np
import open3d as o3d
import open3d.core as o3c
from scipy.spatial import cKDTree

from openfusion.frame import CameraIntrinsics, Frame, resize_nearest
from openfusion.mapping.errors import CapacityError
from openfusion.mapping.params import VolumeParams
from openfusion.mapping.update_rule import fuse_semantics
from openfusion.poses import check_pose, invert_pose

logger = logging.getLogger(__name__)

ATTR_NAMES = ("tsdf", "weight", "color", "key", "conf")
_ATTR_DTYPES = (o3c.float32, o3c.float32, o3c.float32, o3c.int32, o3c.float32)
_ATTR_CHANNELS = (1, 1, 3, 1, 1)
SEMANTIC_BYTES_PER_VOXEL = 8  # key int32 + conf float32
_FRAGMENT_SIZE = 16  # Open3D's range-map fragment edge, in range-map cells
_DENSE_LOOKUP_MAX_CELLS = 16_000_000


@dataclass
class RayHits:
    """Raw ray-cast result of one view: per pixel the 8 voxels around the surface hit.

    ``index`` holds flat voxel indices into the grid's attribute buffers; they are valid only while
    the volume's ``generation`` is unchanged (a grid that grows re-hashes its blocks).
    """

    depth_m: np.ndarray  # (h, w) float32, 0 = no surface
    index: np.ndarray  # (h, w, 8) int64
    ratio: np.ndarray  # (h, w, 8) float32 trilinear weights
    mask: np.ndarray  # (h, w, 8) bool, voxel exists and was observed
    generation: int
    pose_key: bytes


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


@dataclass
class SurfacePoints:
    """Surface points (TSDF zero crossings) with the region key and confidence of each."""

    points: np.ndarray  # (N, 3) float32, world metres
    colors: np.ndarray  # (N, 3) uint8 RGB
    keys: np.ndarray  # (N,) int32, -1 = no region
    conf: np.ndarray  # (N,) float32

    def __len__(self) -> int:
        return int(self.points.shape[0])


@dataclass
class SurfaceMesh:
    """Triangle mesh of the surface with a region key per vertex."""

    vertices: np.ndarray  # (V, 3) float32
    triangles: np.ndarray  # (T, 3) int32
    colors: np.ndarray  # (V, 3) uint8
    normals: np.ndarray  # (V, 3) float32
    keys: np.ndarray  # (V,) int32
    conf: np.ndarray  # (V,) float32

    def to_open3d(self) -> o3d.t.geometry.TriangleMesh:
        mesh = o3d.t.geometry.TriangleMesh()
        mesh.vertex.positions = o3c.Tensor(self.vertices)
        mesh.vertex.colors = o3c.Tensor(self.colors.astype(np.float32) / 255.0)
        mesh.vertex.normals = o3c.Tensor(self.normals)
        mesh.triangle.indices = o3c.Tensor(self.triangles)
        return mesh


def _empty_points() -> SurfacePoints:
    return SurfacePoints(
        np.zeros((0, 3), np.float32),
        np.zeros((0, 3), np.uint8),
        np.zeros(0, np.int32),
        np.zeros(0, np.float32),
    )


def range_map_down_factor(width_px: int, height_px: int) -> int:
    """Largest of 8, 4, 2, 1 dividing both image sides (Open3D reads past the range map otherwise)."""
    for factor in (8, 4, 2, 1):
        if width_px % factor == 0 and height_px % factor == 0:
            return factor
    return 1


_F = TypeVar("_F", bound=Callable[..., Any])


def _locked(method: _F) -> _F:
    """Serialise a public method on the volume's lock (Open3D's grid is not thread-safe)."""

    @functools.wraps(method)
    def wrapper(self: SemanticVolume, *args: Any, **kwargs: Any) -> Any:
        with self._lock:
            return method(self, *args, **kwargs)

    return wrapper  # type: ignore[return-value]


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


class SemanticVolume:
    """Semantic TSDF volume; see the module docstring for storage, render and update rules.

    Public methods are serialised on an internal lock, so a service may integrate on one thread
    and answer render requests on another.
    """

    def __init__(self, params: VolumeParams | None = None) -> None:
        self.params = params if params is not None else VolumeParams()
        if self.params.device.startswith("CUDA") and not o3c.cuda.is_available():
            raise ValueError(
                f"device {self.params.device} requested but this Open3D build has no CUDA; use device='CPU:0'"
            )
        self._device = o3c.Device(self.params.device)
        self._lock = threading.RLock()
        self._use_numpy_views = self._device.get_type() == o3c.Device.DeviceType.CPU
        self.stats = VolumeStats()
        self._intrinsic_cache: dict[CameraIntrinsics, o3c.Tensor] = {}
        self._reset_grid()

    # ------------------------------------------------------------------ grid bookkeeping
    def _reset_grid(self, capacity: int | None = None) -> None:
        p = self.params
        if capacity is None:
            capacity = (
                p.initial_block_count if p.max_blocks is None else min(p.initial_block_count, p.max_blocks)
            )
        self._vbg = o3d.t.geometry.VoxelBlockGrid(
            attr_names=ATTR_NAMES,
            attr_dtypes=_ATTR_DTYPES,
            attr_channels=_ATTR_CHANNELS,
            voxel_size=p.voxel_size_m,
            block_resolution=p.block_resolution,
            block_count=int(capacity),
            device=self._device,
        )
        self._capacity = self._vbg.hashmap().capacity()
        self._generation = getattr(self, "_generation", 0) + 1
        self._geometry_version = getattr(self, "_geometry_version", 0) + 1
        self._blocks_cache: tuple[int, int, np.ndarray, np.ndarray] | None = None
        self._lookup_cache: tuple[int, int, _BlockLookup] | None = None
        self._fragment_capacity = 0

    def _note_capacity_change(self) -> None:
        capacity = self._vbg.hashmap().capacity()
        if capacity != self._capacity:
            logger.info("voxel block grid grew from %d to %d blocks", self._capacity, capacity)
            self._capacity = capacity
            self._generation += 1
            self.stats.grow_events += 1

    @property
    def device(self) -> str:
        return self.params.device

    @property
    def num_blocks(self) -> int:
        """Allocated (active) blocks."""
        return int(self._vbg.hashmap().size())

    @property
    def capacity_blocks(self) -> int:
        """Blocks the grid's buffers hold before the next growth."""
        return int(self._vbg.hashmap().capacity())

    @property
    def generation(self) -> int:
        """Changes whenever voxel buffer indices may have changed (growth, reset, load)."""
        return self._generation

    @property
    def geometry_version(self) -> int:
        """Changes after every integration (and reset/load)."""
        return self._geometry_version

    @property
    def voxels_per_block(self) -> int:
        return self.params.block_resolution**3

    @property
    def bytes_per_voxel(self) -> int:
        """All attributes: tsdf 4 + weight 4 + color 12 + key 4 + conf 4."""
        return 28

    @property
    def open3d_grid(self) -> o3d.t.geometry.VoxelBlockGrid:
        """The underlying grid (read-only use: writing to it bypasses the key encoding)."""
        return self._vbg

    @_locked
    def clear(self) -> None:
        """Drop all geometry and semantics (counters are kept)."""
        self._reset_grid()

    # ------------------------------------------------------------------ attribute access
    def _attr_flat_view(self, name: str) -> np.ndarray:
        """Writable numpy view of a 1-channel attribute over the whole buffer (CPU only)."""
        return self._vbg.attribute(name).numpy().reshape(-1)

    def _gather(self, name: str, flat_index: np.ndarray, *, clip: bool = False) -> np.ndarray:
        """Values at flat voxel indices; ``clip`` clamps out-of-range indices (ray-cast neighbours
        that do not exist carry index 0 today, but their values are masked out anyway)."""
        if self._use_numpy_views:
            view = self._attr_flat_view(name)
            return np.take(view, flat_index, mode="clip") if clip else view[flat_index]
        flat = self._vbg.attribute(name).reshape((-1,))
        return flat[o3c.Tensor(np.ascontiguousarray(flat_index, np.int64), device=self._device)].cpu().numpy()

    def _scatter(self, name: str, flat_index: np.ndarray, values: np.ndarray) -> None:
        if self._use_numpy_views:
            self._attr_flat_view(name)[flat_index] = values
            return
        flat = self._vbg.attribute(name).reshape((-1,))
        flat[o3c.Tensor(np.ascontiguousarray(flat_index, np.int64), device=self._device)] = o3c.Tensor(
            np.ascontiguousarray(values), device=self._device
        )

    def _active_blocks(self) -> tuple[np.ndarray, np.ndarray]:
        """(coords (N, 3) int32, buffer indices (N,) int64) of all active blocks, cached per version."""
        cache = self._blocks_cache
        if cache is not None and cache[0] == self._geometry_version and cache[1] == self._generation:
            return cache[2], cache[3]
        hm = self._vbg.hashmap()
        buf_t = hm.active_buf_indices().to(o3c.int64)
        if buf_t.shape[0] == 0:
            coords = np.zeros((0, 3), np.int32)
            buf = np.zeros(0, np.int64)
        else:
            coords = hm.key_tensor()[buf_t].cpu().numpy().astype(np.int32)
            buf = buf_t.cpu().numpy()
        self._blocks_cache = (self._geometry_version, self._generation, coords, buf)
        return coords, buf

    def _block_lookup(self) -> _BlockLookup:
        cache = self._lookup_cache
        if cache is not None and cache[0] == self._geometry_version and cache[1] == self._generation:
            return cache[2]
        coords, buf = self._active_blocks()
        lookup = _BlockLookup(coords, buf, self._vbg.hashmap(), self._device)
        self._lookup_cache = (self._geometry_version, self._generation, lookup)
        return lookup

    def _intrinsic_tensor(self, intrinsics: CameraIntrinsics) -> o3c.Tensor:
        K = self._intrinsic_cache.get(intrinsics)
        if K is None:
            if len(self._intrinsic_cache) > 32:
                self._intrinsic_cache.clear()
            K = o3c.Tensor(intrinsics.K, o3c.float64)
            self._intrinsic_cache[intrinsics] = K
        return K

    # ------------------------------------------------------------------ integration
    def _frame_images(self, frame: Frame) -> tuple[o3d.t.geometry.Image, o3d.t.geometry.Image, float]:
        p = self.params
        depth = frame.depth
        if depth.dtype == np.uint16:
            depth_scale = float(frame.depth_scale)
            min_raw = p.depth_min_m * depth_scale
            if min_raw >= 1.0:
                depth = np.where(depth < np.uint16(min(math.ceil(min_raw), 65535)), np.uint16(0), depth)
            color = np.ascontiguousarray(frame.color)
        else:
            depth = frame.depth_m()
            depth_scale = 1.0
            if p.depth_min_m > 0:
                depth = np.where(depth < p.depth_min_m, np.float32(0.0), depth)
            color = frame.color.astype(np.float32) * np.float32(
                1.0 / 255.0
            )  # Open3D scales float color by 255
        depth_t = o3c.Tensor.from_numpy(np.ascontiguousarray(depth))
        color_t = o3c.Tensor.from_numpy(color)
        if not self._use_numpy_views:
            depth_t = depth_t.to(self._device)
            color_t = color_t.to(self._device)
        return o3d.t.geometry.Image(depth_t), o3d.t.geometry.Image(color_t), depth_scale

    @_locked
    def integrate(self, frame: Frame) -> IntegrateStats:
        """Fuse one frame's depth and color (geometry only; semantics are untouched).

        Raises :class:`CapacityError` (volume unchanged) when ``max_blocks`` is set, the frame needs
        more new blocks than the budget allows and ``when_full == "raise"``. A frame with no valid
        depth is counted in ``stats.frames_empty`` and changes nothing.
        """
        frame.validate()
        p = self.params
        depth_img, color_img, depth_scale = self._frame_images(frame)
        K = self._intrinsic_tensor(frame.intrinsics)
        extrinsic = o3c.Tensor(invert_pose(np.asarray(frame.T_world_cam, np.float64)))
        try:
            block_coords = self._vbg.compute_unique_block_coordinates(
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
            block_coords = self._apply_block_budget(block_coords, result, frame.frame_id)
            if block_coords is None:
                return result
        self._vbg.integrate(
            block_coords, depth_img, color_img, K, extrinsic, depth_scale, p.depth_max_m, p.trunc_voxels
        )
        self._note_capacity_change()
        self._geometry_version += 1
        self.stats.frames_integrated += 1
        return result

    def _apply_block_budget(
        self, block_coords: o3c.Tensor, result: IntegrateStats, frame_id: int
    ) -> o3c.Tensor | None:
        assert self.params.max_blocks is not None
        hm = self._vbg.hashmap()
        _, found_t = hm.find(block_coords)
        found = found_t.cpu().numpy()
        n_new = int((~found).sum())
        free = self.params.max_blocks - int(hm.size())
        result.blocks_new = n_new
        if n_new <= free:
            return block_coords
        self.stats.capacity_refusals += 1
        self.stats.blocks_refused += n_new - max(free, 0)
        result.blocks_refused = n_new - max(free, 0)
        message = (
            f"frame {frame_id} needs {n_new} new blocks but only {max(free, 0)} of max_blocks="
            f"{self.params.max_blocks} are free"
        )
        if self.params.when_full == "raise":
            raise CapacityError(
                message + "; nothing was integrated", blocks_needed=n_new, blocks_free=max(free, 0)
            )
        logger.warning("%s; integrating into existing blocks only", message)
        keep = found.copy()
        if free > 0:
            keep[np.flatnonzero(~found)[:free]] = True
        if not keep.any():
            return None
        return block_coords[o3c.Tensor(np.flatnonzero(keep).astype(np.int64), device=self._device)]

    # ------------------------------------------------------------------ ray casting
    def _frustum_blocks(
        self, T_world_cam: np.ndarray, intrinsics: CameraIntrinsics
    ) -> tuple[np.ndarray, int]:
        """Active blocks that can project into the image, and an upper bound of the range-map
        fragments Open3D needs for them at the chosen down factor."""
        coords, _ = self._active_blocks()
        if len(coords) == 0:
            return coords, 0
        p = self.params
        bs = p.block_size_m
        radius = bs * math.sqrt(3.0) / 2.0
        centers = (coords.astype(np.float64) + 0.5) * bs
        R = T_world_cam[:3, :3]
        pc = (centers - T_world_cam[:3, 3]) @ R
        z = pc[:, 2]
        keep = (z > -radius) & (z < p.depth_max_m + radius)
        z_near = np.maximum(z - radius, 1e-3)
        zc = np.maximum(z, 1e-3)
        w, h = intrinsics.width_px, intrinsics.height_px
        u = intrinsics.fx * pc[:, 0] / zc + intrinsics.cx
        v = intrinsics.fy * pc[:, 1] / zc + intrinsics.cy
        span_u = 2.0 * radius * intrinsics.fx / z_near
        span_v = 2.0 * radius * intrinsics.fy / z_near
        in_view = (u > -span_u) & (u < w + span_u) & (v > -span_v) & (v < h + span_v)
        keep &= in_view | (z <= radius)
        factor = range_map_down_factor(w, h)
        cells_u = np.minimum(span_u[keep], w) / factor + 2.0
        cells_v = np.minimum(span_v[keep], h) / factor + 2.0
        fragments = int(np.sum(np.ceil(cells_u / _FRAGMENT_SIZE) * np.ceil(cells_v / _FRAGMENT_SIZE)))
        return np.ascontiguousarray(coords[keep]), fragments

    def _ensure_fragment_capacity(self, fragments_needed: int) -> None:
        """Grow Open3D's range-map fragment buffer (owned by the grid) above ``fragments_needed``.

        One quiet ray cast over synthetic blocks that fill a small 90-degree view: Open3D reallocates
        its buffer to the number of fragments that cast needs (at least one per synthetic block)."""
        if fragments_needed < self._fragment_capacity:
            return
        target = max(2 * fragments_needed, 2 * self._fragment_capacity, 2048)
        layers = []
        total = 0
        zb = 2
        while total < target:
            xs = np.arange(-zb, zb)
            gx, gy = np.meshgrid(xs, xs, indexing="ij")
            layer = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, zb)], axis=1)
            layers.append(layer)
            total += len(layer)
            zb += 1
        fake = np.concatenate(layers).astype(np.int32)
        bs = self.params.block_size_m
        size_px = 32
        K = o3c.Tensor(
            np.array([[size_px / 2, 0, size_px / 2], [0, size_px / 2, size_px / 2], [0, 0, 1]], np.float64)
        )
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
            self._vbg.ray_cast(
                o3c.Tensor(fake, device=self._device),
                K,
                o3c.Tensor(np.eye(4)),
                size_px,
                size_px,
                ["depth"],
                1.0,
                0.01,
                float((zb + 2) * bs),
                float(self.params.min_weight),
                float(self.params.trunc_voxels),
                1,
            )
        # Blocks clipped at the view's edge may produce no fragment: count half of them.
        self._fragment_capacity = total // 2
        logger.debug("ray-cast fragment buffer grown to >= %d fragments", self._fragment_capacity)

    @_locked
    def ray_cast(self, T_world_cam: np.ndarray, intrinsics: CameraIntrinsics) -> RayHits:
        """Depth and the 8 voxels around the first surface hit of every pixel (depth-tested)."""
        T = check_pose(T_world_cam)
        h, w = intrinsics.height_px, intrinsics.width_px
        pose_key = T.tobytes() + repr(intrinsics).encode()
        coords, fragments = self._frustum_blocks(T, intrinsics)
        if len(coords) == 0:
            return RayHits(
                np.zeros((h, w), np.float32),
                np.zeros((h, w, 8), np.int64),
                np.zeros((h, w, 8), np.float32),
                np.zeros((h, w, 8), bool),
                self._generation,
                pose_key,
            )
        self._ensure_fragment_capacity(fragments)
        p = self.params
        result = self._vbg.ray_cast(
            o3c.Tensor(coords, device=self._device),
            self._intrinsic_tensor(intrinsics),
            o3c.Tensor(invert_pose(T)),
            w,
            h,
            ["depth", "index", "interp_ratio", "mask"],
            1.0,
            p.depth_min_m,
            p.depth_max_m,
            float(p.min_weight),
            float(p.trunc_voxels),
            range_map_down_factor(w, h),
        )
        return RayHits(
            result["depth"].cpu().numpy().reshape(h, w),
            result["index"].cpu().numpy(),
            result["interp_ratio"].cpu().numpy(),
            result["mask"].cpu().numpy(),
            self._generation,
            pose_key,
        )

    # ------------------------------------------------------------------ render / update
    @_locked
    def render(self, T_world_cam: np.ndarray, intrinsics: CameraIntrinsics) -> RenderedView:
        """Key, confidence and depth images of the map from ``T_world_cam`` at ``intrinsics``' size.

        ``intrinsics`` must already be scaled to the wanted (encoder) size, e.g. ``K.scaled(w, h)``.
        """
        hits = self.ray_cast(T_world_cam, intrinsics)
        h, w = hits.depth_m.shape
        # Stored keys (key + 1) of the 8 voxels around every pixel's hit; 0 where none / unobserved.
        index = hits.index.reshape(h * w, 8)
        stored = self._gather("key", index.reshape(-1), clip=True).reshape(h * w, 8)
        stored *= hits.mask.reshape(h * w, 8)
        labelled = stored > 0
        # The labelled voxel with the largest trilinear weight (the nearest one) names the pixel.
        best = np.where(labelled, hits.ratio.reshape(h * w, 8), -1.0).argmax(axis=1)[:, None]
        best_key1 = np.take_along_axis(stored, best, axis=1)[:, 0]
        px = np.flatnonzero(best_key1)
        key_map = (best_key1 - 1).astype(np.int32, copy=False).reshape(h, w)
        conf_map = np.zeros((h, w), np.float32)
        if len(px):
            best_index = np.take_along_axis(index, best, axis=1)[:, 0][px]
            conf_map.reshape(-1)[px] = self._gather("conf", best_index)
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

        The rule is in the module docstring. ``rendered`` (a render of the same pose and size) lets
        the update reuse that ray cast when the grid's buffers have not moved since.

        ``observed_depth_m`` (the frame's depth, any size; resampled to the map size) enables a
        depth gate: a pixel whose map surface is farther than ``depth_tolerance_m`` (default: the
        truncation distance + 2 % of the depth) from the observed depth is skipped. This stops
        labels of an object's silhouette pixels from landing on the background behind it.
        """
        T = check_pose(T_world_cam)
        h, w = intrinsics.height_px, intrinsics.width_px
        key_map = np.asarray(key_map)
        conf_map = np.asarray(conf_map)
        if key_map.shape != (h, w) or conf_map.shape != (h, w):
            raise ValueError(
                f"key_map {key_map.shape} and conf_map {conf_map.shape} must both be {(h, w)} (the intrinsics' size)"
            )
        if not np.issubdtype(key_map.dtype, np.integer):
            raise ValueError(f"key_map must be an integer array, got {key_map.dtype}")
        if key_map.size and (key_map.min() < -1 or key_map.max() >= np.iinfo(np.int32).max):
            raise ValueError("key_map values must be -1 (none) or non-negative int32 region keys")
        conf_map = conf_map.astype(np.float32, copy=False)
        if not ((conf_map >= 0) & (conf_map <= 1)).all():  # NaN fails both comparisons
            raise ValueError("conf_map must be finite and within [0, 1]")
        stats = UpdateStats()
        pose_key = T.tobytes() + repr(intrinsics).encode()
        hits = rendered.hits if rendered is not None else None
        if hits is not None and hits.generation == self._generation and hits.pose_key == pose_key:
            stats.reused_render = True
        else:
            hits = self.ray_cast(T, intrinsics)
        use = (key_map >= 0) & (conf_map > 0) & (hits.depth_m > 0)
        if observed_depth_m is not None:
            observed = resize_nearest(np.asarray(observed_depth_m, np.float32), (h, w))
            tol = (
                (self.params.trunc_m + 0.02 * hits.depth_m)
                if depth_tolerance_m is None
                else depth_tolerance_m
            )
            consistent = (observed > 0) & (np.abs(hits.depth_m - observed) <= tol)
            stats.pixels_depth_rejected = int((use & ~consistent).sum())
            use &= consistent
        stats.pixels_used = int(use.sum())
        self.stats.updates += 1
        if stats.pixels_used == 0:
            return stats
        entry = np.flatnonzero((hits.mask.reshape(h * w, 8) & use.reshape(h * w, 1)).reshape(-1))
        if len(entry) == 0:
            return stats
        voxel = hits.index.reshape(-1)[entry]
        ratio = hits.ratio.reshape(-1)[entry]
        pixel = entry >> 3
        # One observation per voxel: the pixel whose hit is nearest (largest trilinear weight).
        chosen = _nearest_per_voxel(voxel, ratio)
        voxel = voxel[chosen]
        pixel = pixel[chosen]
        new_key1 = key_map.reshape(-1)[pixel].astype(np.int32) + 1
        new_conf = conf_map.reshape(-1)[pixel]
        old_key1 = self._gather("key", voxel)
        old_conf = self._gather("conf", voxel)
        out_key1, out_conf, counts = fuse_semantics(
            old_key1, old_conf, new_key1, new_conf, history_weight=self.params.conf_history_weight
        )
        self._scatter("key", voxel, out_key1)
        self._scatter("conf", voxel, out_conf)
        stats.voxels_updated = int(len(voxel))
        stats.voxels_labelled, stats.voxels_reinforced, stats.voxels_weakened, stats.voxels_switched = counts
        self.stats.voxels_updated += stats.voxels_updated
        return stats

    @_locked
    def relabel_keys(self, mapping: dict[int, int]) -> int:
        """Rewrite voxel keys (e.g. after a dictionary merge ``{b: a}``); ``{k: -1}`` clears a key.

        Returns the number of voxels changed. Confidences are kept (cleared voxels get 0).
        """
        if not mapping:
            return 0
        for old, new in mapping.items():
            if int(old) < 0 or int(new) < -1:
                raise ValueError(f"cannot relabel {old} -> {new}: keys are >= 0 (-1 only as target)")
        _, buf = self._active_blocks()
        if len(buf) == 0:
            return 0
        n = self.voxels_per_block
        flat = (buf[:, None] * n + np.arange(n)[None, :]).reshape(-1)
        stored = self._gather("key", flat)
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
        self._scatter("key", flat[diff], new_stored[diff])
        if clear.any():
            idx = flat[clear]
            self._scatter("conf", idx, np.zeros(len(idx), np.float32))
        return changed_total

    # ------------------------------------------------------------------ extraction
    def _semantics_at_points(
        self, points: np.ndarray, normals: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Key and confidence for surface points: the nearest labelled voxel among the 8 corners of
        the voxel cell containing each point (surface points lie on cell edges); points left
        without one take the nearest labelled point's within ``params.label_fill_radius_m`` (facing
        the same way when ``normals`` are given; see :func:`fill_nearest_labels`)."""
        n_pts = len(points)
        keys = np.full(n_pts, -1, np.int32)
        conf = np.zeros(n_pts, np.float32)
        if n_pts == 0:
            return keys, conf
        vs = self.params.voxel_size_m
        res = self.params.block_resolution
        g = points.astype(np.float64) / vs
        base = np.floor(g).astype(np.int64)
        lookup = self._block_lookup()
        best_d2 = np.full(n_pts, np.inf)
        for dx in (0, 1):
            for dy in (0, 1):
                for dz in (0, 1):
                    gv = base + np.array([dx, dy, dz], np.int64)
                    block = np.floor_divide(gv, res)
                    local = gv - block * res
                    buf = lookup.find(block)
                    ok = np.flatnonzero(buf >= 0)
                    if len(ok) == 0:
                        continue
                    flat = buf[ok] * res**3 + (local[ok, 2] * res + local[ok, 1]) * res + local[ok, 0]
                    stored = self._gather("key", flat)
                    lab = stored > 0
                    ok, flat, stored = ok[lab], flat[lab], stored[lab]
                    d2 = ((g[ok] - gv[ok]) ** 2).sum(axis=1)
                    better = d2 < best_d2[ok]
                    sel = ok[better]
                    best_d2[sel] = d2[better]
                    keys[sel] = stored[better] - 1
                    conf[sel] = self._gather("conf", flat[better])
        fill_nearest_labels(points, keys, conf, self.params.label_fill_radius_m, normals)
        return keys, conf

    def _key_filter(self, keys: np.ndarray, wanted: np.ndarray | list[int] | None) -> np.ndarray | None:
        if wanted is None:
            return None
        wanted_arr = np.asarray(list(wanted) if not isinstance(wanted, np.ndarray) else wanted, np.int64)
        return np.isin(keys, wanted_arr)

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
        if max_points is not None and max_points < 0:
            raise ValueError(f"max_points must be >= 0, got {max_points}")
        if self.num_blocks == 0:
            return _empty_points()
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
            pcd = self._vbg.extract_point_cloud(float(self.params.min_weight) - 0.5)
        if "positions" not in pcd.point or pcd.point.positions.shape[0] == 0:
            return _empty_points()
        points = pcd.point.positions.cpu().numpy().astype(np.float32, copy=False)
        colors = np.clip(np.round(pcd.point.colors.cpu().numpy() * 255.0), 0, 255).astype(np.uint8)
        # Open3D emits points in a thread-dependent order: sort so results are reproducible.
        order = np.lexsort((points[:, 2], points[:, 1], points[:, 0]))
        points, colors = points[order], colors[order]
        normals = pcd.point.normals.cpu().numpy()[order] if "normals" in pcd.point else None
        pkeys, pconf = self._semantics_at_points(points, _unit_rows(normals) if normals is not None else None)
        keep = self._key_filter(pkeys, keys)
        if keep is not None:
            points, colors, pkeys, pconf = points[keep], colors[keep], pkeys[keep], pconf[keep]
        if max_points is not None and len(points) > max_points:
            rng = np.random.default_rng(seed)
            sel = np.sort(rng.choice(len(points), size=max_points, replace=False))
            points, colors, pkeys, pconf = points[sel], colors[sel], pkeys[sel], pconf[sel]
        return SurfacePoints(points, colors, pkeys, pconf)

    @_locked
    def extract_mesh(self, keys: np.ndarray | list[int] | None = None) -> SurfaceMesh:
        """Surface mesh (marching cubes); with ``keys``, only triangles whose 3 vertices carry one of
        those keys (unreferenced vertices dropped)."""
        empty = SurfaceMesh(
            np.zeros((0, 3), np.float32),
            np.zeros((0, 3), np.int32),
            np.zeros((0, 3), np.uint8),
            np.zeros((0, 3), np.float32),
            np.zeros(0, np.int32),
            np.zeros(0, np.float32),
        )
        if self.num_blocks == 0:
            return empty
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
            mesh = self._vbg.extract_triangle_mesh(float(self.params.min_weight) - 0.5)
        if "positions" not in mesh.vertex or mesh.vertex.positions.shape[0] == 0:
            return empty
        vertices = mesh.vertex.positions.cpu().numpy().astype(np.float32, copy=False)
        triangles = mesh.triangle.indices.cpu().numpy().astype(np.int32, copy=False)
        colors = np.clip(np.round(mesh.vertex.colors.cpu().numpy() * 255.0), 0, 255).astype(np.uint8)
        normals = (
            mesh.vertex.normals.cpu().numpy().astype(np.float32, copy=False)
            if "normals" in mesh.vertex
            else np.zeros_like(vertices)
        )
        vkeys, vconf = self._semantics_at_points(
            vertices, _unit_rows(normals) if "normals" in mesh.vertex else None
        )
        keep_vertex = self._key_filter(vkeys, keys)
        if keep_vertex is not None:
            tri_keep = keep_vertex[triangles].all(axis=1)
            triangles = triangles[tri_keep]
            used = np.zeros(len(vertices), bool)
            used[triangles.reshape(-1)] = True
            remap = np.full(len(vertices), -1, np.int64)
            remap[used] = np.arange(int(used.sum()))
            triangles = remap[triangles].astype(np.int32)
            vertices, colors, normals, vkeys, vconf = (
                vertices[used],
                colors[used],
                normals[used],
                vkeys[used],
                vconf[used],
            )
        return SurfaceMesh(vertices, triangles, colors, normals, vkeys, vconf)

    # ------------------------------------------------------------------ arrays (save / load)
    @_locked
    def to_arrays(self) -> dict[str, np.ndarray]:
        """All active blocks as plain arrays (``key`` holds real keys, -1 = none)."""
        coords, buf = self._active_blocks()
        res = self.params.block_resolution
        out: dict[str, np.ndarray] = {"block_coords": coords.astype(np.int32)}
        buf_t = o3c.Tensor(buf, device=self._device)
        for name in ATTR_NAMES:
            if len(buf) == 0:
                channels = _ATTR_CHANNELS[ATTR_NAMES.index(name)]
                dtype = np.int32 if name == "key" else np.float32
                arr = np.zeros((0, res, res, res, channels), dtype)
            else:
                arr = self._vbg.attribute(name)[buf_t].cpu().numpy()
            if name != "color":
                arr = arr.reshape(arr.shape[:4])
            if name == "key":
                arr = arr.astype(np.int32) - 1
            out[name] = np.ascontiguousarray(arr)
        return out

    @classmethod
    def from_arrays(cls, params: VolumeParams, arrays: dict[str, np.ndarray]) -> SemanticVolume:
        """Build a volume from :meth:`to_arrays` output; raises ``ValueError`` on inconsistent arrays."""
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
                raise ValueError(
                    f"{name} must be {np.dtype(dtype).name} {shape}, got {arr.dtype} {arr.shape}"
                )
        if n and len(np.unique(coords, axis=0)) != n:
            raise ValueError("block_coords contain duplicates")
        if n and int(np.asarray(arrays["key"]).min()) < -1:
            raise ValueError("key values must be >= -1")
        if params.max_blocks is not None and n > params.max_blocks:
            raise ValueError(f"{n} blocks exceed max_blocks={params.max_blocks}")
        volume = cls(params)
        if n == 0:
            return volume
        if n > volume.capacity_blocks:
            volume._reset_grid(capacity=n)
        hm = volume._vbg.hashmap()
        buf_t, _ = hm.activate(o3c.Tensor(coords.astype(np.int32), device=volume._device))
        volume._note_capacity_change()
        buf_t = buf_t.to(o3c.int64)
        for name in ATTR_NAMES:
            arr = np.asarray(arrays[name])
            if name == "key":
                arr = arr.astype(np.int32) + 1
            if name != "color":
                arr = arr[..., None]
            volume._vbg.attribute(name)[buf_t] = o3c.Tensor(np.ascontiguousarray(arr), device=volume._device)
        volume._geometry_version += 1
        return volume


def _unit_rows(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, np.float32)
    return v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)


FILL_MIN_NORMAL_COS = 0.5  # a fill source must face within 60 degrees of the point it labels
_FILL_CANDIDATES = 8


def fill_nearest_labels(
    points: np.ndarray,
    keys: np.ndarray,
    conf: np.ndarray,
    radius_m: float,
    normals: np.ndarray | None = None,
) -> int:
    """Give every unlabelled point (key -1) the key and confidence of the nearest labelled point
    within ``radius_m``, in place; returns the number filled.

    One pass from the originally labelled points only, so labels never creep further than
    ``radius_m`` from a voxel the update actually labelled. With ``normals`` (unit, per point) a
    source must face the same way (cosine >= ``FILL_MIN_NORMAL_COS``, among the 8 nearest): the
    floor behind a table, hidden at encoder resolution, does not take the table's key from the
    table's back face, while a thin pole still takes the key of the pole beside it.
    """
    if radius_m <= 0:
        return 0
    missing = np.flatnonzero(keys < 0)
    labelled = np.flatnonzero(keys >= 0)
    if len(missing) == 0 or len(labelled) == 0:
        return 0
    tree = cKDTree(points[labelled])
    k = 1 if normals is None else min(_FILL_CANDIDATES, len(labelled))
    dist, nearest = tree.query(points[missing], k=k, distance_upper_bound=radius_m)
    dist = dist.reshape(len(missing), k)
    nearest = nearest.reshape(len(missing), k)
    ok = np.isfinite(dist)
    if normals is not None:
        src = labelled[np.where(ok, nearest, 0)]
        facing = np.einsum("ij,ikj->ik", normals[missing], normals[src]) >= FILL_MIN_NORMAL_COS
        ok &= facing
    first = ok.argmax(axis=1)  # candidates come nearest first
    found = ok[np.arange(len(missing)), first]
    source = labelled[nearest[found, first[found]]]
    keys[missing[found]] = keys[source]
    conf[missing[found]] = conf[source]
    return int(found.sum())


def _nearest_per_voxel(voxel: np.ndarray, ratio: np.ndarray) -> np.ndarray:
    """Index of the entry with the largest ratio for every distinct voxel (ties: lowest index).

    Packs (voxel, quantised 1 - ratio, entry index) into one int64 and sorts the values, which is
    about three times faster than an argsort of the same size.
    """
    n = len(voxel)
    entry_bits = max(int(n).bit_length(), 1)
    ratio_bits = 12
    shift = entry_bits + ratio_bits
    if int(voxel.max()) >= (1 << (62 - shift)):
        order = np.lexsort((np.arange(n), -ratio, voxel))
        voxel_sorted = voxel[order]
        first = np.ones(n, bool)
        first[1:] = voxel_sorted[1:] != voxel_sorted[:-1]
        return order[first]
    quant = np.round((1.0 - np.clip(ratio, 0.0, 1.0)) * ((1 << ratio_bits) - 1)).astype(np.int64)
    packed = (voxel.astype(np.int64) << shift) | (quant << entry_bits) | np.arange(n, dtype=np.int64)
    packed.sort()
    voxel_sorted = packed >> shift
    first = np.ones(n, bool)
    first[1:] = voxel_sorted[1:] != voxel_sorted[:-1]
    return packed[first] & ((1 << entry_bits) - 1)
