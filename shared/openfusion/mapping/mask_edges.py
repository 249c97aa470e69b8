"""Pixel-level cleaning of one frame's masks before its update is planned: how much each pixel's
label is trusted near a mask edge, and which pixels of a mask's border band lie on another surface
than its body (:mod:`openfusion.mapping.matching` plans the update with them).

Mask-edge weight (``MatchParams.mask_edge_px``, :func:`mask_edge_weights`)
    A planned pixel's confidence (after the contested margin, :mod:`openfusion.mapping.matching`) is
    scaled by ``min(1, (d + 1) / (mask_edge_px + 1))``, where ``d`` is the Euclidean distance in
    pixels from the pixel to the nearest *edge pixel* (a pixel whose winning region, or "none",
    differs from one of its 4 neighbours inside the image; edge pixels have d = 0). With the
    default ``mask_edge_px = 2`` the two pixel rows on each side of a region border weigh 1/3 and
    2/3 and everything further inside weighs 1. Masks are least reliable at their edges (a
    segmenter's masks are commonly a pixel or two too large or too small there, and a dilated
    mask's border pixels lie on the neighbouring object), so a voxel near an object border gets
    most of its evidence from the views in which it lies well inside its own object's mask.

Depth-edge cut (``MatchParams.depth_cut_rel``, ``crease_rel``)
    A mask dilated over an object's outline puts its spill on another surface: behind an occlusion
    edge (a jump in the rendered depth) or around a corner (a crease: the rendered inverse depth,
    linear in the pixel coordinates on a plane, changes slope). A pixel of that border band which its
    region's interior cannot reach within ``mask_edge_px`` + 1 steps through 4-neighbours of the same
    region without crossing such an edge (:func:`depth_cut_spill`) fuses nothing, where the map
    already renders another region there; on a surface the map has not labelled yet, where it lies
    behind the mask's body across an occlusion edge (``depth_cut_new_rel``: farther than the body's
    surface, extrapolated, predicts by more than 10 %; :func:`behind_body`), the background a
    foreground mask was dilated over; on other new surface, or one the map gives this region's key,
    it fuses as before. The noise model's dilation does not know about surfaces, a real segmenter's
    masks mostly follow depth edges, so this keeps most of the spill of the former off its
    neighbour's voxels (measured in docs/EVAL.md "Standard noise: depth-edge cut"). It uses the
    rendered depth only, which the semantic service receives with every render.

Written with numpy shifts rather than ``scipy.ndimage``: they look only a few pixels away
(``mask_edge_px`` + 1 steps; the shifted edge mask is a quarter of the cost of a full
``distance_transform_edt`` with the same result), and the growth through a mask follows links
between pairs of pixels (same label, no depth jump between them), which a structuring element
cannot express.
"""

from __future__ import annotations

import functools
import math

import numpy as np


def mask_edge_weights(labels: np.ndarray, mask_edge_px: float) -> np.ndarray:
    """Per-pixel weight ``min(1, (d + 1) / (mask_edge_px + 1))`` of a label image (h, w).

    ``d`` is the Euclidean distance in pixels to the nearest edge pixel: a pixel whose label differs
    from one of its 4 neighbours (the image border is not an edge). ``mask_edge_px <= 0`` or an
    image without edges gives weight 1 everywhere. Returns float32 (h, w).

    Only distances below ``mask_edge_px`` matter, so instead of a full distance transform the
    edge mask is shifted by every pixel offset shorter than that (8 offsets for the default 2 px),
    nearest first: about 0.2 ms at 160x120, a quarter of ``scipy.ndimage.distance_transform_edt``,
    with the same result.
    """
    if not (math.isfinite(mask_edge_px) and mask_edge_px >= 0):
        raise ValueError(f"mask_edge_px must be finite and >= 0, got {mask_edge_px}")
    labels = np.asarray(labels)
    if labels.ndim != 2:
        raise ValueError(f"labels must be (h, w), got {labels.shape}")
    h, w = labels.shape
    weight = np.ones((h, w), np.float32)
    if mask_edge_px == 0:
        return weight
    edge = np.zeros((h, w), bool)
    across = labels[:, 1:] != labels[:, :-1]
    edge[:, 1:] |= across
    edge[:, :-1] |= across
    down = labels[1:, :] != labels[:-1, :]
    edge[1:, :] |= down
    edge[:-1, :] |= down
    if not edge.any():
        return weight
    scale = 1.0 / (mask_edge_px + 1.0)
    weight[edge] = scale
    done = edge.copy()
    near = np.empty_like(edge)
    for dist2, offsets in _offsets_by_distance(mask_edge_px):
        near[:] = False
        for dy, dx in offsets:  # near[y, x] |= edge[y - dy, x - dx]
            near[max(0, dy) : h + min(0, dy), max(0, dx) : w + min(0, dx)] |= edge[
                max(0, -dy) : h + min(0, -dy), max(0, -dx) : w + min(0, -dx)
            ]
        new = near & ~done
        weight[new] = (math.sqrt(dist2) + 1.0) * scale
        done |= new
    return weight


def depth_jumps(depth_m: np.ndarray, rel: float, crease_rel: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Neighbour pairs on different surfaces: ``(across (h, w-1), down (h-1, w))`` bool, True where two
    4-neighbours' depths differ by more than ``rel`` times the nearer one, or one has no depth.
    With ``crease_rel`` also where the inverse depth's slope on one side of the pair differs from the
    slope on the other side by more than that share of the inverse depth (a crease: on a plane the
    inverse depth is linear in the pixel coordinates)."""
    z = np.asarray(depth_m, np.float32)

    def jump(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        near = np.minimum(a, b)
        return (near <= 0) | (np.abs(a - b) > rel * near)

    across, down = jump(z[:, 1:], z[:, :-1]), jump(z[1:, :], z[:-1, :])
    if crease_rel > 0:
        iz = np.where(z > 0, 1.0 / np.maximum(z, 1e-6), 0.0).astype(np.float32)
        for cut, v in ((across, iz), (down.T, iz.T)):  # down.T is a view: written in place
            if v.shape[1] < 4:
                continue
            slope = v[:, 1:] - v[:, :-1]  # slope[x] between x and x+1
            bend = np.abs(slope[:, 2:] - slope[:, :-2])  # around pair (x+1, x+2): slopes x and x+2
            ref = 0.5 * (v[:, 1:-2] + v[:, 2:-1])
            cut[:, 1:-1] |= bend > crease_rel * ref
    return across, down


def depth_cut_spill(
    labels: np.ndarray,
    band: np.ndarray,
    depth_m: np.ndarray,
    rel: float,
    crease_rel: float,
    reach_px: float,
) -> np.ndarray:
    """Pixels (bool (h, w)) of a label image's border ``band`` that are cut off from their label's
    interior by a depth edge: each label spreads from its pixels outside the band to 4-neighbours of
    the same label for ``ceil(reach_px) + 1`` steps, never across a pair of pixels
    :func:`depth_jumps` separates; band pixels it does not reach lie on another surface than the
    mask's body (a mask dilated over an occlusion edge or around a corner), or on a thin part of
    the mask far from its body. A label without interior (all band) is left alone.
    """
    labels = np.asarray(labels)
    across, down = depth_jumps(depth_m, rel, crease_rel)
    lab = labels >= 0
    link_x = (labels[:, 1:] == labels[:, :-1]) & ~across & lab[:, 1:]
    link_y = (labels[1:, :] == labels[:-1, :]) & ~down & lab[1:, :]
    interior = lab & ~band
    reached = interior.copy()
    if lab.any():  # labels with no interior pixel: nothing to cut them off from
        has_inside = np.bincount(labels[interior], minlength=int(labels.max()) + 1) > 0
        reached |= lab & ~has_inside[np.where(lab, labels, 0)]
    reached = _grow(reached, link_x, link_y, math.ceil(reach_px) + 1)
    return lab & band & ~reached


def _grow(mask: np.ndarray, link_x: np.ndarray, link_y: np.ndarray, steps: int) -> np.ndarray:
    """``mask`` (bool (h, w)) grown ``steps`` times to 4-neighbours across the linked pairs:
    ``link_x`` (h, w - 1) joins a pixel to its right neighbour, ``link_y`` (h - 1, w) to the one below."""
    for _ in range(steps):
        grow = mask.copy()
        grow[:, 1:] |= mask[:, :-1] & link_x
        grow[:, :-1] |= mask[:, 1:] & link_x
        grow[1:, :] |= mask[:-1, :] & link_y
        grow[:-1, :] |= mask[1:, :] & link_y
        mask = grow
    return mask


def behind_body(
    labels: np.ndarray, spill: np.ndarray, depth_m: np.ndarray, rel: float, jump_rel: float, steps: int
) -> np.ndarray:
    """Pixels of ``spill`` (bool (h, w), e.g. :func:`depth_cut_spill`'s) that lie behind the rest of
    their mask across an occlusion edge: a spill pixel whose depth exceeds, by more than ``rel`` of it,
    what a 4-neighbour of the same label predicts there (that neighbour's inverse depth extrapolated
    linearly from it and the next pixel of the label in line, where no depth jump (``jump_rel``,
    :func:`depth_jumps`) separates those two; on a plane, however grazing, the inverse
    depth is linear, so a slanted surface is no edge), and the spill pixels of the same label joined to
    such a pixel within ``steps`` 4-neighbour steps without a depth jump. A mask dilated over an occlusion edge puts such pixels on the background
    behind the object; spill nearer than the rest of its mask, or level with it, is not returned."""
    z = np.asarray(depth_m, np.float32)
    h, w = z.shape
    iz = np.where(z > 0, 1.0 / np.maximum(z, 1e-6), 0.0).astype(np.float32)
    pad = 2
    lab_p = np.pad(labels, pad, constant_values=-1)
    seen_p = np.pad((labels >= 0) & (z > 0), pad)
    iz_p = np.pad(iz, pad)
    z_p = np.pad(z, pad)
    behind = np.zeros((h, w), bool)
    cand = spill & (z > 0)
    for dy, dx in ((0, 1), (0, -1), (1, 0), (-1, 0)):  # the neighbour n = p - d and the next one nn = p - 2d
        n = (slice(pad - dy, pad - dy + h), slice(pad - dx, pad - dx + w))
        nn = (slice(pad - 2 * dy, pad - 2 * dy + h), slice(pad - 2 * dx, pad - 2 * dx + w))
        next_to = cand & seen_p[n] & (lab_p[n] == labels)
        near = np.minimum(z_p[n], z_p[nn])
        in_line = seen_p[nn] & (lab_p[nn] == labels) & (np.abs(z_p[n] - z_p[nn]) <= jump_rel * near)
        predicted = np.where(in_line, 2.0 * iz_p[n] - iz_p[nn], iz_p[n])
        behind |= next_to & (iz * (1.0 + rel) < predicted)
    if not behind.any():
        return behind
    across, down = depth_jumps(z, jump_rel)

    def spread(grow_from: np.ndarray, within: np.ndarray) -> np.ndarray:
        link_x = (labels[:, 1:] == labels[:, :-1]) & ~across & within[:, 1:] & within[:, :-1]
        link_y = (labels[1:, :] == labels[:-1, :]) & ~down & within[1:, :] & within[:-1, :]
        return _grow(grow_from, link_x, link_y, steps)

    behind = spread(behind, spill)
    # Only spill that continues, without a depth jump, into the surface of another label or of no
    # label (the background the mask was dilated over); a strip of the mask's own object seen behind
    # its front (a shelf's back panel) meets the next surface across another jump.
    other_x = (labels[:, 1:] != labels[:, :-1]) & ~across & (z[:, 1:] > 0) & (z[:, :-1] > 0)
    other_y = (labels[1:, :] != labels[:-1, :]) & ~down & (z[1:, :] > 0) & (z[:-1, :] > 0)
    meets = np.zeros((h, w), bool)
    meets[:, 1:] |= other_x
    meets[:, :-1] |= other_x
    meets[1:, :] |= other_y
    meets[:-1, :] |= other_y
    return spread(behind & meets, behind)


@functools.lru_cache(maxsize=8)
def _offsets_by_distance(radius_px: float) -> tuple[tuple[int, tuple[tuple[int, int], ...]], ...]:
    """Pixel offsets (dy, dx) with 0 < distance < radius_px, grouped by squared distance, nearest first."""
    r = math.ceil(radius_px)
    groups: dict[int, list[tuple[int, int]]] = {}
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            dist2 = dy * dy + dx * dx
            if 0 < dist2 < radius_px * radius_px:
                groups.setdefault(dist2, []).append((dy, dx))
    return tuple((d2, tuple(groups[d2])) for d2 in sorted(groups))
