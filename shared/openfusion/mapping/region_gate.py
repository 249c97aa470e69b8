"""Which regions of a chosen frame are worth an embedding: the per-region half of frame selection.

The frame selection (:mod:`openfusion.mapping.coverage`) decides which frames go to the encoder.
A chosen frame usually adds something in one part of the view (a new surface, one region seen from
a new direction) and shows regions elsewhere that earlier frames already described from the same
direction. OVI-MAP (CVPR 2026) runs its VLM per instance, only on the views that add viewing
directions to that instance; this is the same rule per region of a chosen frame:

- the selection's decision leaves a *wanted* mask of the scored view
  (:meth:`~openfusion.mapping.coverage.CoverageScorer.wanted_px`): surface without a confident
  region, pixels of a region seen from a direction bin it was not encoded from, pixels of a region
  gone stale;
- a region of the observation is embedded when at least ``min_share`` of its pixels (confidence
  >= 0.5 at the encoder's output size) are wanted (:func:`regions_wanted`); the others keep their
  confidence maps, so their pixels still update the voxels' region keys and confidences (the
  masks of every chosen frame, not only of the embedded regions, are fused), but they carry no
  embedding: they update no region's embedding and create no region
  (:func:`openfusion.mapping.matching.plan_update`).

Why a share of pixels and not any overlap: a region's mask spills a few pixels over its
neighbours (borders are soft, and the standard noise dilates them by 2 px), so any overlap would
embed every region next to something new. Measured in docs/EVAL.md ("Embeddings per region").

What it saves depends on the encoder: one that embeds region crops one by one (``clip-regions``,
an ONNX crop embedder) does not compute the skipped crops
(:class:`~openfusion.encoders.proposal_encoder.ProposalRegionEncoder.encode_where`); one that
describes the frame at once (``clip-dense``) saves nothing, and the gt encoder stands in for a
crop encoder. ``encoder_regions`` counts the regions embedded (the calls per object of the eval
report, OVI-MAP's measure).

Written here: a bit of numpy over the masks; no library decides this.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from openfusion.frame import resize_nearest

#: A pixel belongs to a region's mask for the share when its confidence reaches this.
MASK_CONF = 0.5


def regions_wanted(conf_maps: np.ndarray, wanted_px: np.ndarray | None, min_share: float | None) -> np.ndarray:
    """bool (n,): the regions of ``conf_maps`` (n, h, w) with at least ``min_share`` of their mask
    pixels (confidence >= :data:`MASK_CONF`) in ``wanted_px`` (bool, any size: resampled nearest to
    (h, w)). A region with an empty mask is wanted (nothing to judge it by). ``wanted_px`` or
    ``min_share`` None: every region. ValueError for a ``wanted_px`` that is not 2-D or a share
    outside [0, 1]."""
    n = int(np.shape(conf_maps)[0])
    if wanted_px is None or min_share is None or n == 0:
        return np.ones(n, bool)
    if not 0.0 <= float(min_share) <= 1.0:
        raise ValueError(f"min_share must be within [0, 1], got {min_share}")
    wanted = np.asarray(wanted_px)
    if wanted.ndim != 2 or wanted.size == 0:
        raise ValueError(f"wanted_px must be a 2-D mask, got shape {wanted.shape}")
    h, w = np.shape(conf_maps)[1:]
    wanted = resize_nearest(wanted.astype(bool, copy=False), (h, w)).reshape(-1)
    masks = (np.asarray(conf_maps) >= MASK_CONF).reshape(n, -1)
    size = masks.sum(axis=1)
    hit = (masks & wanted[None]).sum(axis=1)
    return (size == 0) | (hit >= float(min_share) * size)


def gate_observation(obs: Any, wanted_px: np.ndarray | None, min_share: float | None) -> Any:
    """``obs`` (a :class:`~openfusion.encoders.base.RegionObservation`) with ``embedded`` set by
    :func:`regions_wanted` and the embeddings of the regions not wanted zeroed (they were not paid
    for; nothing downstream may read them). Unchanged when every region is wanted."""
    wanted = regions_wanted(obs.conf_maps, wanted_px, min_share)
    if obs.embedded is not None:
        wanted &= np.asarray(obs.embedded, bool)
    if wanted.all():
        return obs
    embeddings = np.array(obs.embeddings, np.float32, copy=True)
    embeddings[~wanted] = 0.0
    return replace(obs, embeddings=embeddings, embedded=wanted)


def encode_where(encoder: Any, frame: Any, wanted_px: np.ndarray | None, min_share: float | None) -> Any:
    """``encoder.encode_where(...)`` (a :class:`~openfusion.encoders.base.RegionEncoder`), or, for
    an object that only has ``encode(frame)`` (a wrapper, a test double), its observation gated by
    :func:`gate_observation`: the one way every pipeline asks for a chosen frame's regions."""
    method = getattr(encoder, "encode_where", None)
    if method is not None:
        return method(frame, wanted_px, min_share)
    return gate_observation(encoder.encode(frame), wanted_px, min_share)
