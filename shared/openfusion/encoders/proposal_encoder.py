"""Region encoder = class-agnostic proposals + an embedder of masked region crops.

Shared by ``clip-regions`` (torch CLIP image tower) and ``onnx`` crop-embedder models: a proposer
gives (n, h, w) masks at the output resolution, :func:`~openfusion.encoders.crops.region_crops`
cuts one crop per mask out of the full-resolution color image, and the embedder maps the crop batch
to (n, d) embeddings (normalised here).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Protocol

import numpy as np

from openfusion.encoders.base import (
    DEFAULT_OUTPUT_SCALE,
    MIN_EMBEDDING_NORM,
    EncoderError,
    ImageQueryEncoder,
    RegionEncoder,
    RegionObservation,
    blank_frame,
    check_rgb,
)
from openfusion.encoders.crops import CropSpec, preprocess_image, region_crops
from openfusion.frame import Frame
from openfusion.mapping.region_gate import regions_wanted

logger = logging.getLogger(__name__)


class RegionProposer(Protocol):
    """Frame -> (n, h, w) float32 masks in [0, 1] on an ``out_hw`` grid."""

    name: str

    def propose(self, frame: Frame, out_hw: tuple[int, int]) -> np.ndarray: ...


class CropEmbedder(Protocol):
    """(m, 3, S, S) preprocessed crops -> (m, d) float32 (not necessarily normalised)."""

    embedding_space: str
    dim: int
    crop_spec: CropSpec

    def embed_crops(self, crops: np.ndarray) -> np.ndarray: ...


class ProposalRegionEncoder(RegionEncoder, ImageQueryEncoder):
    """Regions from ``proposer``, embeddings from ``embedder`` applied to masked crops (batched).

    ``batch_size`` bounds how many crops go through the embedder at once (memory).
    Also an :class:`ImageQueryEncoder`: ``encode_image`` embeds a whole image the same way.
    """

    def __init__(
        self,
        proposer: RegionProposer,
        embedder: CropEmbedder,
        *,
        name: str,
        output_scale: float = DEFAULT_OUTPUT_SCALE,
        batch_size: int = 32,
    ) -> None:
        super().__init__(output_scale=output_scale)
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        self.name = name
        self.proposer = proposer
        self.embedder = embedder
        self.embedding_space = embedder.embedding_space
        self.dim = embedder.dim
        self.batch_size = int(batch_size)
        self.stats: dict[str, int] = {"frames": 0, "regions": 0, "dropped_zero_embedding": 0}

    def _embed(self, crops: np.ndarray) -> np.ndarray:
        parts = [
            np.asarray(self.embedder.embed_crops(crops[i : i + self.batch_size]), dtype=np.float32)
            for i in range(0, crops.shape[0], self.batch_size)
        ]
        emb = np.concatenate(parts, axis=0) if parts else np.zeros((0, self.dim), np.float32)
        if emb.shape != (crops.shape[0], self.dim):
            raise EncoderError(f"embedder returned {emb.shape}, expected ({crops.shape[0]}, {self.dim})")
        return emb

    def warm_up(self, vocabulary: Sequence[str] = ()) -> None:
        """The proposer once on a blank 640x480 frame and the embedder once on a full batch of
        blank crops (the torch graph's or the onnx session's first run, at the batch size frames
        use); nothing is counted in ``stats``."""
        self.proposer.propose(blank_frame(), self.output_size(480, 640))
        s = int(self.embedder.crop_spec.size)
        self._embed(np.zeros((self.batch_size, 3, s, s), np.float32))

    def encode(self, frame: Frame) -> RegionObservation:
        return self.encode_where(frame, None, None)

    def encode_where(self, frame: Frame, wanted_px: np.ndarray | None, min_share: float | None) -> RegionObservation:
        """Proposals of ``frame``; crops embedded only for the regions
        :func:`~openfusion.mapping.region_gate.regions_wanted` keeps (the others are not cropped
        nor embedded: ``embedded`` False, a zero row). ``stats["regions_not_embedded"]`` counts them."""
        check_rgb(frame.color)
        out_hw = self.output_size(*frame.color.shape[:2])
        masks = np.asarray(self.proposer.propose(frame, out_hw), dtype=np.float32)
        if masks.ndim != 3 or masks.shape[1:] != out_hw:
            raise EncoderError(f"proposer {self.proposer.name!r} returned masks {masks.shape}, expected (n, {out_hw[0]}, {out_hw[1]})")
        masks = masks[np.any(masks > 0, axis=(1, 2))]  # an empty mask has no crop (region_boxes: None)
        wanted = regions_wanted(masks, wanted_px, min_share)
        crops, kept = region_crops(frame.color, masks[wanted], self.embedder.crop_spec)
        emb_wanted = self._embed(crops)
        emb = np.zeros((len(masks), self.dim), np.float32)
        embedded = np.zeros(len(masks), bool)
        rows = np.flatnonzero(wanted)[kept]
        emb[rows] = emb_wanted
        embedded[rows] = True
        unwanted = ~wanted
        emb_ok = np.isfinite(emb).all(axis=1)
        norms = np.linalg.norm(np.where(emb_ok[:, None], emb, 0.0), axis=1)
        ok = (emb_ok & (norms > MIN_EMBEDDING_NORM)) | unwanted
        if not ok.all():
            self.stats["dropped_zero_embedding"] += int((~ok).sum())
            logger.warning("frame %s: %d region(s) with zero/non-finite embeddings dropped", frame.frame_id, int((~ok).sum()))
        emb, embedded = emb[ok], embedded[ok]
        emb[embedded] /= norms[ok][embedded, None]
        self.stats["frames"] += 1
        self.stats["regions"] += int(embedded.sum())
        self.stats["regions_not_embedded"] = self.stats.get("regions_not_embedded", 0) + int((~embedded).sum())
        return RegionObservation(
            conf_maps=np.ascontiguousarray(np.clip(masks[ok], 0.0, 1.0), dtype=np.float32),
            embeddings=np.ascontiguousarray(emb, dtype=np.float32),
            embedding_space=self.embedding_space,
            labels=None,
            embedded=None if embedded.all() else embedded,
        )

    def encode_image(self, rgb: np.ndarray) -> np.ndarray:
        batch = preprocess_image(rgb, self.embedder.crop_spec)
        e = self._embed(batch)[0]
        n = float(np.linalg.norm(e))
        if not np.isfinite(n) or n < MIN_EMBEDDING_NORM:
            raise EncoderError("the image embedding has zero or non-finite norm")
        return (e / n).astype(np.float32)
