"""Geometry integration inputs of the semantic volume: a frame's Open3D images and the block budget.

Named after Open3D's ``integrate``, which :meth:`~openfusion.mapping.volume.SemanticVolume.integrate`
calls with what this module prepares; the volume keeps the policy (counters, refusing or clipping).

Geometry
    Integration is plain Open3D integration (``compute_unique_block_coordinates`` + ``integrate``
    with the configured truncation), so it runs as fast as Open3D alone. Depth below
    ``depth_min_m`` is zeroed first (:func:`frame_images`). With ``max_blocks`` set, a frame that
    needs more new blocks than the budget allows is refused or clipped to the blocks that exist
    and the first free ones (:func:`block_budget`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import open3d as o3d
import open3d.core as o3c

from openfusion.frame import Frame
from openfusion.mapping.storage import VoxelStorage


def frame_images(
    storage: VoxelStorage, frame: Frame
) -> tuple[o3d.t.geometry.Image, o3d.t.geometry.Image, float]:
    """``(depth image, color image, depth scale)`` of ``frame`` for Open3D, on the grid's device,
    with depth below ``depth_min_m`` zeroed (uint16 depth stays raw, float depth is metres)."""
    p = storage.params
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
        color = frame.color.astype(np.float32) * np.float32(1.0 / 255.0)  # Open3D scales float color by 255
    depth_t = o3c.Tensor.from_numpy(np.ascontiguousarray(depth))
    color_t = o3c.Tensor.from_numpy(color)
    if not storage.use_numpy_views:
        depth_t = depth_t.to(storage.device)
        color_t = color_t.to(storage.device)
    return o3d.t.geometry.Image(depth_t), o3d.t.geometry.Image(color_t), depth_scale


@dataclass
class BlockBudget:
    """How a frame's touched blocks fit ``max_blocks``."""

    blocks_new: int  # touched blocks not allocated yet
    blocks_free: int  # new blocks the budget still allows (0 when full)
    admitted: o3c.Tensor | None  # the blocks to integrate when clipping (None: none), else all

    @property
    def blocks_refused(self) -> int:
        return max(self.blocks_new - self.blocks_free, 0)


def block_budget(storage: VoxelStorage, block_coords: o3c.Tensor, max_blocks: int) -> BlockBudget:
    """The budget check of ``block_coords`` (Open3D's touched blocks) against ``max_blocks``; when
    blocks are refused, ``admitted`` keeps the existing blocks and the first ``blocks_free`` new ones."""
    hm = storage.vbg.hashmap()
    _, found_t = hm.find(block_coords)
    found = found_t.cpu().numpy()
    n_new = int((~found).sum())
    free = max_blocks - int(hm.size())
    if n_new <= free:
        return BlockBudget(n_new, free, block_coords)
    keep = found.copy()
    if free > 0:
        keep[np.flatnonzero(~found)[:free]] = True
    admitted = (
        block_coords[o3c.Tensor(np.flatnonzero(keep).astype(np.int64), device=storage.device)]
        if keep.any()
        else None
    )
    return BlockBudget(n_new, max(free, 0), admitted)
