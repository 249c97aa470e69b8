"""Region matching (soft IoU + Jonker-Volgenant) and the planned semantic update of one frame.

Soft IoU
    For confidence maps ``a`` and ``b`` (values in [0, 1]) we use the weighted Jaccard (Ruzicka)
    similarity ``sum(min(a, b)) / sum(max(a, b))``: 1 for identical maps, 0 for disjoint ones,
    and equal to the ordinary IoU for binary masks. Rendered maps of different keys never overlap
    (one key per pixel), which :func:`match_regions` uses to compute all n x m values in one pass
    over the labelled pixels; :func:`soft_iou_matrix` is the general (dense) form.

    The frame side is the encoder's soft maps, the map side the rendered confidence of each key
    (the paper's form). ``rendered_conf_weighted=False`` compares against each key's rendered
    *mask* instead (1 where the key is rendered with confidence > 0); on the synthetic evaluation
    both score the same (docs/EVAL.md), so the default stays with the paper.

Assignment
    ``scipy.optimize.linear_sum_assignment`` (a Jonker-Volgenant solver) maximises the total soft
    IoU; assigned pairs below ``min_iou`` (default 0.10) are dropped, so those regions count as new.

Per-pixel confidence of the planned update (contested pixels and mask edges count less)
    Each pixel takes the frame region with the highest confidence there. With
    ``MatchParams.contested_margin`` (default) its confidence is that region's *margin* over the
    runner-up there (best minus second-best confidence): where two frame regions both claim a
    pixel (a mask dilated over its neighbour, both at full confidence) the frame says nothing
    about which object the pixel belongs to, so the update fuses nothing there instead of
    weakening the neighbour's voxels; a pixel only one region claims keeps that region's
    confidence (measured in docs/EVAL.md "Standard noise after merging"). Pixels near a mask edge
    then count less (``mask_edge_px``) and a mask's spill over an occlusion edge or a crease not at
    all (``depth_cut_rel``, ``crease_rel``, ``depth_cut_new_rel``): :mod:`openfusion.mapping.mask_edges`.

Split along the map (``MatchParams.split_min_share``)
    A frame region that merged two objects (under-segmentation) is assigned to one of the two map
    regions; the other map region is then unmatched although it lies inside the frame region.
    Where it covers most of such a map region, over a substantial share of itself, and the two map
    regions' embeddings disagree, those pixels fuse the unmatched region's own key (:func:`_splits`).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy.optimize import linear_sum_assignment

from openfusion.mapping.dictionary import RegionDictionary
from openfusion.mapping.mask_edges import behind_body, depth_cut_spill, mask_edge_weights
from openfusion.mapping.params import MatchParams
from openfusion.mapping.volume import RenderedView

logger = logging.getLogger(__name__)

DEFAULT_MIN_IOU = MatchParams.model_fields["min_iou"].default


def region_conf_maps(rendered: RenderedView) -> tuple[np.ndarray, np.ndarray]:
    """Keys (m,) int64 of the regions in view and their confidence maps (m, h, w) float32."""
    keys = np.unique(rendered.key_map[rendered.key_map >= 0]).astype(np.int64)
    maps = np.zeros((len(keys),) + rendered.key_map.shape, np.float32)
    for j, key in enumerate(keys):
        on = rendered.key_map == key
        maps[j][on] = rendered.conf_map[on]
    return keys, maps


def soft_iou_matrix(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Dense soft IoU ``sum(min)/sum(max)`` between maps a (n, h, w) and b (m, h, w) -> (n, m)."""
    a = np.asarray(a, np.float32).reshape(len(a), -1)
    b = np.asarray(b, np.float32).reshape(len(b), -1)
    out = np.zeros((len(a), len(b)), np.float32)
    for j in range(len(b)):
        inter = np.minimum(a, b[j]).sum(axis=1)
        union = np.maximum(a, b[j]).sum(axis=1)
        out[:, j] = np.where(union > 0, inter / np.maximum(union, 1e-12), 0.0)
    return out


@dataclass
class MatchResult:
    """Soft IoU of every frame region against every rendered region, and the kept assignment."""

    iou: np.ndarray  # (n, m) float32
    rendered_keys: np.ndarray  # (m,) int64
    frame_indices: np.ndarray  # (k,) int64, matched frame regions
    keys: np.ndarray  # (k,) int64, the map key each is matched to
    pair_iou: np.ndarray  # (k,) float32

    @property
    def pairs(self) -> list[tuple[int, int]]:
        return [(int(i), int(k)) for i, k in zip(self.frame_indices, self.keys, strict=True)]


def _check_conf_maps(frame_conf: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    frame_conf = np.asarray(frame_conf)
    if frame_conf.ndim != 3 or frame_conf.shape[1:] != shape:
        raise ValueError(f"frame confidence maps must be (n, {shape[0]}, {shape[1]}), got {frame_conf.shape}")
    frame_conf = frame_conf.astype(np.float32, copy=False)
    if not ((frame_conf >= 0) & (frame_conf <= 1)).all():  # NaN fails both comparisons
        raise ValueError("frame confidence maps must be finite and within [0, 1]")
    return frame_conf


def match_regions(
    frame_conf: np.ndarray,
    rendered: RenderedView,
    min_iou: float = DEFAULT_MIN_IOU,
    *,
    allowed: Callable[[np.ndarray], np.ndarray] | None = None,
    rendered_conf_weighted: bool = True,
) -> MatchResult:
    """Match the frame's n regions to the m map regions in view (soft IoU, Jonker-Volgenant).

    ``allowed`` maps the rendered keys (m,) to an (n, m) boolean matrix of pairs that may match
    (e.g. an embedding-similarity gate); other pairs are treated as IoU 0 by the assignment.
    The rendered regions enter weighted by their rendered confidence, or as masks (pixels with a key
    and confidence > 0) with ``rendered_conf_weighted=False`` (see the module docstring).
    """
    if not 0.0 <= min_iou <= 1.0:
        raise ValueError(f"min_iou must be within [0, 1], got {min_iou}")
    return _match_checked(
        _check_conf_maps(frame_conf, rendered.key_map.shape),
        rendered,
        min_iou,
        allowed,
        rendered_conf_weighted,
    )


def _match_checked(
    frame_conf: np.ndarray,
    rendered: RenderedView,
    min_iou: float,
    allowed: Callable[[np.ndarray], np.ndarray] | None,
    rendered_conf_weighted: bool = True,
) -> MatchResult:
    n = len(frame_conf)
    flat_keys = rendered.key_map.reshape(-1)
    flat_conf = rendered.conf_map.reshape(-1).astype(np.float32)
    labelled = np.flatnonzero((flat_keys >= 0) & (flat_conf > 0))
    if n == 0 or len(labelled) == 0:
        rkeys = np.unique(flat_keys[labelled]).astype(np.int64)
        empty = np.zeros(0, np.int64)
        return MatchResult(
            np.zeros((n, len(rkeys)), np.float32), rkeys, empty, empty, np.zeros(0, np.float32)
        )
    order = labelled[np.argsort(flat_keys[labelled], kind="stable")]
    sorted_keys = flat_keys[order]
    starts = np.flatnonzero(np.r_[True, sorted_keys[1:] != sorted_keys[:-1]])
    rkeys = sorted_keys[starts].astype(np.int64)
    A = frame_conf.reshape(n, -1)
    sum_a = A.sum(axis=1)
    if rendered_conf_weighted:
        b = flat_conf[order]
        inter = np.add.reduceat(np.minimum(A[:, order], b[None, :]), starts, axis=1)
        sum_b = np.add.reduceat(b, starts)
    else:  # masks: min(a, 1) = a, and each key's mask area is its pixel count
        inter = np.add.reduceat(A[:, order], starts, axis=1)
        sum_b = np.diff(np.r_[starts, len(order)]).astype(np.float32)
    union = sum_a[:, None] + sum_b[None, :] - inter
    iou = np.where(union > 0, inter / np.maximum(union, 1e-12), 0.0).astype(np.float32)
    score = iou if allowed is None else np.where(allowed(rkeys), iou, 0.0)
    rows, cols = linear_sum_assignment(-score)
    keep = (score[rows, cols] >= min_iou) & (score[rows, cols] > 0)
    rows, cols = rows[keep], cols[keep]
    return MatchResult(iou, rkeys, rows.astype(np.int64), rkeys[cols], iou[rows, cols])


def _joins(
    winner: np.ndarray,
    covered: np.ndarray,
    rendered_keys: np.ndarray,
    key_of: np.ndarray,
    pixels_won: np.ndarray,
    embeddings: np.ndarray,
    embedded: np.ndarray,
    dictionary: RegionDictionary,
    p: MatchParams,
) -> list[tuple[int, int]]:
    """(frame region, key) for frame regions the assignment left unmatched that lie mostly inside
    one rendered region (``join_min_coverage`` of their pixels) whose embedding agrees with theirs
    (``join_min_cos``; a region without an embedding, :mod:`openfusion.mapping.region_gate`,
    cannot show that it agrees and joins nothing: coverage alone would glue another object to a
    region wherever a render lags the map): a part of an object the map already holds as one region (an encoder that
    split the object, or a map region that merged two segments the encoder keeps apart). The
    assignment is one-to-one, so without this each such part would start a new region every frame.
    """
    if p.join_min_coverage is None:
        return []
    out = []
    for i in np.flatnonzero((key_of < 0) & (pixels_won > 0) & embedded):
        under = rendered_keys[covered & (winner == i)]
        under = under[under >= 0]
        if len(under) == 0:
            continue
        keys, counts = np.unique(under, return_counts=True)
        best = int(counts.argmax())
        key = int(keys[best])
        if counts[best] < p.join_min_coverage * pixels_won[i] or key not in dictionary:
            continue
        v = embeddings[i] / max(float(np.linalg.norm(embeddings[i])), 1e-12)
        if float(v @ dictionary.embedding(key)) >= p.join_min_cos:
            out.append((int(i), key))
    return out


def _splits(
    winner: np.ndarray,
    covered: np.ndarray,
    rendered_keys: np.ndarray,
    key_of: np.ndarray,
    pixels_won: np.ndarray,
    dictionary: RegionDictionary,
    p: MatchParams,
) -> list[tuple[int, int]]:
    """(frame region, rendered key) pairs where one frame region holds two map objects: a map region
    no frame region took this frame lies mostly (``split_min_cover`` of its rendered pixels) inside
    the frame region, over at least ``split_min_share`` of the frame region's pixels, and its
    embedding disagrees with the key the frame region took (cosine below ``split_max_cos``). The
    one-to-one assignment gives a mask that merged two objects to one of them; the other's pixels
    then fuse their own map key instead of weakening it (the embedding is observed by the matched
    key only). A fragment of the same object (embeddings agree) is left to the merge pass.
    """
    on = covered & (rendered_keys >= 0)
    if not on.any():
        return []
    matched = set(int(k) for k in key_of[key_of >= 0])
    rk, r_area = np.unique(rendered_keys[rendered_keys >= 0], return_counts=True)
    area_of = dict(zip(rk.tolist(), r_area.tolist(), strict=True))
    pairs, counts = np.unique(np.stack([winner[on], rendered_keys[on]]), axis=1, return_counts=True)
    out = []
    for (i, key), o in zip(pairs.T.tolist(), counts.tolist(), strict=True):
        own = int(key_of[i])
        if key == own or key in matched or own < 0 or key not in dictionary:
            continue
        if o < p.split_min_cover * area_of[key] or o < p.split_min_share * pixels_won[i]:
            continue
        if float(dictionary.embedding(own) @ dictionary.embedding(key)) < p.split_max_cos:
            out.append((int(i), int(key)))
    return out


@dataclass
class PlannedUpdate:
    """Per-pixel keys/confidences to fuse, and what happened to each frame region."""

    key_map: np.ndarray  # (h, w) int32, -1 = leave voxels alone
    conf_map: np.ndarray  # (h, w) float32
    matched: list[tuple[int, int]] = field(default_factory=list)  # (frame region index, key)
    new_keys: list[tuple[int, int]] = field(default_factory=list)  # (frame region index, new key)
    skipped: list[int] = field(default_factory=list)  # frame regions that won no pixel
    match: MatchResult | None = None
    dictionary_version: int = 0


def plan_update(
    obs: Any,
    rendered: RenderedView,
    dictionary: RegionDictionary,
    params: MatchParams | None = None,
) -> PlannedUpdate:
    """Match the observation to the rendered map and update the dictionary (one version batch).

    ``obs`` is any object with ``conf_maps`` (n, h, w), ``embeddings`` (n, d), ``labels`` (list or
    None) and optionally ``embedding_space`` (checked against the dictionary's). ``params``
    (:class:`~openfusion.mapping.params.MatchParams`, defaults when None) holds every option below.

    Each pixel takes the frame region with the highest confidence there (pixels below
    ``min_pixel_conf`` take none). Regions that win no pixel are skipped. A matched region
    updates its key's running-mean embedding and count; an unmatched one gets a new key. A region
    without an embedding (``obs.embedded`` False, :mod:`openfusion.mapping.region_gate`) still
    takes pixels and fuses its matched key there, but updates no embedding, joins no region and
    starts none.
    With ``min_embedding_cos``, a key whose embedding averages ``min_embedding_cos_views`` views
    or more matches only regions whose embeddings reach that cosine to it (younger keys: geometry
    alone, as in the paper). Matching compares the frame's soft maps with the rendered confidences
    (or with the rendered key masks, ``rendered_conf_weighted=False``).

    A pixel's planned confidence is its region's confidence there (minus the runner-up's with
    ``contested_margin``) times the mask-edge weight
    ``min(1, (d + 1) / (mask_edge_px + 1))``, d = distance in pixels to the nearest border between
    winning regions (see the module docstring; 0 turns the weighting off). Border pixels cut off from
    their region's interior by a depth edge of the rendered view fuse nothing where the map shows
    another region, or no region and they lie behind the mask's body (``depth_cut_rel``,
    ``crease_rel``, ``depth_cut_new_rel``; the module docstring).
    """
    conf_maps = _check_conf_maps(obs.conf_maps, rendered.key_map.shape)
    embeddings = np.asarray(obs.embeddings, np.float32)
    n = len(conf_maps)
    if embeddings.shape != (n, dictionary.dim):
        raise ValueError(f"embeddings must be ({n}, {dictionary.dim}), got {embeddings.shape}")
    dictionary.check_space(getattr(obs, "embedding_space", None))
    labels = getattr(obs, "labels", None)
    if labels is not None and len(labels) != n:
        raise ValueError(f"labels has {len(labels)} entries for {n} regions")
    embedded = getattr(obs, "embedded", None)
    if embedded is None:
        embedded = np.ones(n, bool)
    else:
        embedded = np.asarray(embedded)
        if embedded.dtype != bool or embedded.shape != (n,):
            raise ValueError(f"embedded must be ({n},) bool, got {embedded.dtype} {embedded.shape}")
    p = params if params is not None else MatchParams()
    h, w = rendered.key_map.shape
    # A render made before a merge reached its renderer (services) may still show merged-away
    # keys: they count as the region they were merged into.
    resolved = dictionary.resolve_keys(rendered.key_map)
    if resolved is not rendered.key_map:
        rendered = replace(rendered, key_map=resolved.astype(np.int32, copy=False))
    if n == 0:
        return PlannedUpdate(
            np.full((h, w), -1, np.int32), np.zeros((h, w), np.float32), dictionary_version=dictionary.version
        )
    winner = conf_maps.argmax(axis=0)
    best_conf = np.take_along_axis(conf_maps, winner[None], axis=0)[0]
    covered = best_conf >= max(p.min_pixel_conf, 1e-12)
    pixels_won = np.bincount(winner[covered], minlength=n)
    gate = None
    if p.min_embedding_cos is not None:
        min_embedding_cos = p.min_embedding_cos
        unit = embeddings / np.maximum(np.linalg.norm(embeddings, axis=1, keepdims=True), 1e-12)

        def gate(rkeys: np.ndarray) -> np.ndarray:
            allowed = np.zeros((n, len(rkeys)), bool)
            for j, key in enumerate(rkeys.tolist()):  # a young key, or a region without an embedding: geometry alone
                if key in dictionary:
                    young = dictionary.count(key) < p.min_embedding_cos_views
                    allowed[:, j] = young | (unit @ dictionary.embedding(key) >= min_embedding_cos) | ~embedded
            return allowed

    match = _match_checked(conf_maps, rendered, p.min_iou, gate, p.rendered_conf_weighted)
    key_of = np.full(n, -1, np.int64)
    plan = PlannedUpdate(np.full((h, w), -1, np.int32), np.zeros((h, w), np.float32), match=match)
    with dictionary.batch():
        obs_idx, obs_keys = [], []
        for i, key in zip(match.frame_indices, match.keys, strict=True):
            if pixels_won[i] == 0:
                continue
            if int(key) not in dictionary:
                logger.warning("rendered key %d is not in the dictionary; region %d gets a new key", key, i)
                continue
            obs_idx.append(int(i))
            obs_keys.append(int(key))
        seen = [j for j, i in enumerate(obs_idx) if embedded[i]]  # a region without an embedding keeps the key's
        if seen:
            dictionary.observe_many(
                np.array([obs_keys[j] for j in seen], np.int64),
                embeddings[[obs_idx[j] for j in seen]],
                [labels[obs_idx[j]] for j in seen] if labels is not None else None,
            )
        if obs_idx:
            key_of[obs_idx] = obs_keys
            plan.matched.extend(zip(obs_idx, obs_keys, strict=True))
        for i, key in _joins(winner, covered, rendered.key_map, key_of, pixels_won, embeddings, embedded,
                             dictionary, p):
            if embedded[i]:
                dictionary.observe(key, embeddings[i], label=labels[i] if labels is not None else None)
            key_of[i] = key
            plan.matched.append((i, key))
        for i in range(n):
            if key_of[i] >= 0:
                continue
            if pixels_won[i] == 0 or not embedded[i]:  # no embedding: it cannot start a region
                plan.skipped.append(i)
                continue
            key = dictionary.add(embeddings[i], label=labels[i] if labels is not None else None)
            key_of[i] = key
            plan.new_keys.append((i, key))
    pixel_keys = key_of[winner]
    if p.split_min_share is not None:
        for i, key in _splits(winner, covered, rendered.key_map, key_of, pixels_won, dictionary, p):
            part = covered & (winner == i) & (rendered.key_map == key)
            pixel_keys = np.where(part, key, pixel_keys)
    use = covered & (pixel_keys >= 0)
    pixel_conf = best_conf
    if p.contested_margin and n > 1:
        pixel_conf = best_conf - np.partition(conf_maps, n - 2, axis=0)[n - 2]
    labels_px = np.where(covered, winner, -1)
    if p.mask_edge_px > 0:
        edge_w = mask_edge_weights(labels_px, p.mask_edge_px)
        pixel_conf = pixel_conf * edge_w
        if p.depth_cut_rel > 0:
            spill = depth_cut_spill(
                labels_px, edge_w < 1, rendered.depth_m, p.depth_cut_rel, p.crease_rel, p.mask_edge_px
            )
            # Where the map already holds another region; on new surface only behind the mask's body
            # (a mask's first view of a slanted or nearer surface, or of its own, loses nothing).
            cut = spill & (rendered.key_map >= 0) & (rendered.key_map != pixel_keys)
            if p.depth_cut_new_rel > 0:
                # On surface the map has not labelled yet, only spill that lies behind its mask's body
                # (a foreground mask dilated over the background), by the larger jump depth_cut_new_rel.
                cut |= (rendered.key_map < 0) & behind_body(
                    labels_px, spill, rendered.depth_m, p.depth_cut_new_rel, p.depth_cut_rel, math.ceil(p.mask_edge_px)
                )
            pixel_conf = np.where(cut, np.float32(0), pixel_conf)
    plan.key_map[use] = pixel_keys[use]
    plan.conf_map[use] = pixel_conf[use]
    plan.dictionary_version = dictionary.version
    return plan
