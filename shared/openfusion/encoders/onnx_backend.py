"""The ``onnx`` backend: encoders exported to ONNX (contract: docs/ENCODERS.md), run by onnxruntime.

- :class:`OnnxRegionEncoder`: a ``region-model`` (image -> conf_maps + embeddings), e.g. a SEEM-like
  model exported whole.
- A ``crop-embedder`` (crops -> embeddings, e.g. a CLIP image tower) is paired with a proposer:
  graph segmentation by default or an :class:`OnnxMaskProposer` (SAM-style ``mask-proposer`` model).
- :class:`OnnxTextEncoder`: a ``text-model`` with its ``tokenizer.json`` (HF ``tokenizers``).

Use :func:`make_onnx_region_encoder` (registry name ``onnx``) to get the right one for a file.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from openfusion.encoders.base import (
    DEFAULT_OUTPUT_SCALE,
    MIN_EMBEDDING_NORM,
    EncoderConfigError,
    EncoderError,
    RegionEncoder,
    RegionObservation,
    TextEncoder,
    blank_frame,
    check_rgb,
    check_texts,
    normalize_rows,
)
from openfusion.encoders.crops import CropSpec
from openfusion.encoders.graph_segmentation import GraphSegmentationProposer
from openfusion.encoders.masks import resize_maps_bilinear
from openfusion.encoders.onnx_contract import EncoderContractError, OnnxModel, load_onnx_model
from openfusion.encoders.proposal_encoder import ProposalRegionEncoder, RegionProposer
from openfusion.frame import Frame

logger = logging.getLogger(__name__)


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return (1.0 / (1.0 + np.exp(-np.clip(x, -60.0, 60.0)))).astype(np.float32)


def _image_input(model: OnnxModel, frame: Frame) -> dict[str, np.ndarray]:
    """The ``image`` (and ``depth``) feeds for a frame: resized to the model's input size, normalised."""
    color = check_rgb(frame.color)
    H, W = color.shape[:2]
    in_h = model.static_dim("image", 2) or model.meta_int("input_height") or H
    in_w = model.static_dim("image", 3) or model.meta_int("input_width") or W
    if (in_h, in_w) != (H, W):
        color = np.asarray(Image.fromarray(color).resize((in_w, in_h), Image.Resampling.BILINEAR))
    mean = np.asarray(model.meta_float3("mean"), np.float32)
    std = np.asarray(model.meta_float3("std"), np.float32)
    x = (color.astype(np.float32) / 255.0 - mean) / std
    feeds = {"image": np.ascontiguousarray(x.transpose(2, 0, 1)[None])}
    if model.has_input("depth"):
        d = frame.depth_m()
        if d.shape != (in_h, in_w):
            d = np.asarray(Image.fromarray(d, mode="F").resize((in_w, in_h), Image.Resampling.NEAREST))
        feeds["depth"] = np.ascontiguousarray(d[None, None].astype(np.float32))
    return feeds


class OnnxRegionEncoder(RegionEncoder):
    """A ``region-model`` ONNX file: image -> (conf_maps, embeddings[, valid]).

    Confidence maps are converted to probabilities (sigmoid when metadata says ``logits``), resized
    bilinearly to :meth:`output_size`, and regions are dropped when ``valid`` is false, when their
    peak confidence is below ``min_peak_conf`` or when their embedding has zero norm.
    """

    name = "onnx"

    def __init__(
        self,
        model: OnnxModel,
        *,
        output_scale: float = DEFAULT_OUTPUT_SCALE,
        min_peak_conf: float = 0.05,
    ) -> None:
        super().__init__(output_scale=output_scale)
        if model.kind != "region-model":
            raise EncoderContractError(f"{model.path.name}: expected a region-model, got {model.kind}")
        self.model = model
        self.embedding_space = str(model.metadata["embedding_space"])
        self.dim = int(model.metadata["dim"])
        self.logits = model.meta_str("conf_maps_are", "probability") == "logits"
        self.min_peak_conf = float(min_peak_conf)
        self.stats: dict[str, int] = {"frames": 0, "regions": 0, "dropped_invalid": 0}

    def warm_up(self, vocabulary: Sequence[str] = ()) -> None:
        """One run of the model on a blank 640x480 frame (onnxruntime's first run allocates its
        memory arenas); the result is thrown away and nothing is counted in ``stats``."""
        self.model.session.run(None, _image_input(self.model, blank_frame()))

    def encode(self, frame: Frame) -> RegionObservation:
        out_hw = self.output_size(*frame.color.shape[:2])
        names = ["conf_maps", "embeddings"] + (["valid"] if self.model.has_output("valid") else [])
        outs = self.model.session.run(names, _image_input(self.model, frame))
        conf, emb = np.asarray(outs[0]), np.asarray(outs[1])
        name = self.model.path.name
        if conf.ndim != 4 or conf.shape[0] != 1 or emb.ndim != 3 or emb.shape[0] != 1:
            raise EncoderContractError(f"{name}: conf_maps {conf.shape} / embeddings {emb.shape} are not [1,N,h,w] / [1,N,d]")
        if emb.shape[1] != conf.shape[1]:
            raise EncoderContractError(f"{name}: {conf.shape[1]} conf_maps but {emb.shape[1]} embeddings")
        if emb.shape[2] != self.dim:
            raise EncoderContractError(f"{name}: embeddings are {emb.shape[2]}-d, metadata dim is {self.dim}")
        conf = conf[0].astype(np.float32)
        emb = emb[0].astype(np.float32)
        if self.logits:
            conf = _sigmoid(conf)
        conf = np.clip(np.nan_to_num(conf, nan=0.0), 0.0, 1.0)
        keep = np.ones(conf.shape[0], bool)
        if len(outs) > 2:
            keep &= np.asarray(outs[2]).reshape(-1).astype(bool)
        conf = resize_maps_bilinear(conf, out_hw) if conf.shape[1:] != out_hw else conf
        keep &= conf.reshape(conf.shape[0], -1).max(axis=1, initial=0.0) >= self.min_peak_conf
        finite = np.isfinite(emb).all(axis=1)
        norms = np.linalg.norm(np.where(finite[:, None], emb, 0.0), axis=1)
        keep &= finite & (norms > MIN_EMBEDDING_NORM)
        self.stats["dropped_invalid"] += int((~keep).sum())
        self.stats["frames"] += 1
        self.stats["regions"] += int(keep.sum())
        return RegionObservation(
            conf_maps=np.ascontiguousarray(np.clip(conf[keep], 0.0, 1.0), dtype=np.float32),
            embeddings=np.ascontiguousarray(emb[keep] / norms[keep, None], dtype=np.float32),
            embedding_space=self.embedding_space,
            labels=None,
        )


class OnnxCropEmbedder:
    """A ``crop-embedder`` ONNX file: (B, 3, S, S) crops -> (B, d) embeddings."""

    def __init__(self, model: OnnxModel, *, padding: float = 0.1, mask_background: bool = True) -> None:
        if model.kind != "crop-embedder":
            raise EncoderContractError(f"{model.path.name}: expected a crop-embedder, got {model.kind}")
        self.model = model
        self.embedding_space = str(model.metadata["embedding_space"])
        self.dim = int(model.metadata["dim"])
        size = model.meta_int("crop_size") or model.static_dim("crops", 2)
        assert size is not None  # guaranteed by the contract check
        self.crop_spec = CropSpec(
            size=int(size),
            mean=model.meta_float3("mean"),
            std=model.meta_float3("std"),
            padding=padding,
            mask_background=mask_background,
        )
        self._fixed_batch = model.static_dim("crops", 0)

    def embed_crops(self, crops: np.ndarray) -> np.ndarray:
        if crops.shape[0] == 0:
            return np.zeros((0, self.dim), np.float32)
        if self._fixed_batch is None:
            return np.asarray(self.model.session.run(["embeddings"], {"crops": crops})[0], np.float32)
        parts = []
        b = self._fixed_batch
        for i in range(0, crops.shape[0], b):
            chunk = crops[i : i + b]
            pad = b - chunk.shape[0]
            if pad:
                chunk = np.concatenate([chunk, np.zeros((pad, *chunk.shape[1:]), np.float32)])
            parts.append(np.asarray(self.model.session.run(["embeddings"], {"crops": chunk})[0], np.float32)[: b - pad])
        return np.concatenate(parts)


class OnnxMaskProposer:
    """A SAM-style ``mask-proposer`` ONNX file: image -> class-agnostic masks (+ scores)."""

    name = "onnx-masks"

    def __init__(
        self, model: OnnxModel, *, min_score: float = 0.0, max_regions: int = 48, min_region_px: int = 16
    ) -> None:
        if model.kind != "mask-proposer":
            raise EncoderContractError(f"{model.path.name}: expected a mask-proposer, got {model.kind}")
        self.model = model
        self.logits = model.meta_str("masks_are", "probability") == "logits"
        self.min_score = float(min_score)
        self.max_regions = int(max_regions)
        self.min_region_px = int(min_region_px)

    def propose(self, frame: Frame, out_hw: tuple[int, int]) -> np.ndarray:
        names = ["masks"] + (["scores"] if self.model.has_output("scores") else [])
        outs = self.model.session.run(names, _image_input(self.model, frame))
        masks = np.asarray(outs[0])
        if masks.ndim != 4 or masks.shape[0] != 1:
            raise EncoderContractError(f"{self.model.path.name}: masks {masks.shape} are not [1,N,h,w]")
        masks = masks[0].astype(np.float32)
        if self.logits:
            masks = _sigmoid(masks)
        masks = np.clip(np.nan_to_num(masks, nan=0.0), 0.0, 1.0)
        if masks.shape[1:] != out_hw:
            masks = resize_maps_bilinear(masks, out_hw)
        area = (masks >= 0.5).reshape(masks.shape[0], -1).sum(axis=1)
        scores = np.asarray(outs[1]).reshape(-1) if len(outs) > 1 else area.astype(np.float32)
        keep = np.flatnonzero((area >= self.min_region_px) & (scores >= self.min_score))
        keep = keep[np.argsort(-scores[keep], kind="stable")][: self.max_regions]
        return masks[keep]


def make_onnx_region_encoder(
    model_path: str | Path | None = None,
    *,
    device: str = "auto",
    output_scale: float = DEFAULT_OUTPUT_SCALE,
    mask_model_path: str | Path | None = None,
    proposer_options: dict[str, Any] | None = None,
    batch_size: int = 32,
    min_peak_conf: float = 0.05,
    crop_padding: float = 0.1,
    mask_background: bool = True,
) -> RegionEncoder:
    """Load ``model_path`` and return the encoder its ``kind`` calls for.

    A ``region-model`` becomes an :class:`OnnxRegionEncoder`. A ``crop-embedder`` is paired with a
    proposer: :class:`OnnxMaskProposer` for ``mask_model_path`` when given, else
    :class:`GraphSegmentationProposer` (``proposer_options`` go to whichever is used).
    """
    if model_path is None:
        raise EncoderConfigError("the onnx region encoder needs model_path=<file.onnx> (docs/ENCODERS.md)")
    model = load_onnx_model(model_path, expected_kind=("region-model", "crop-embedder"), device=device)
    if model.kind == "region-model":
        if mask_model_path is not None:
            raise EncoderConfigError(f"{model.path.name} is a region-model (it makes its own masks); mask_model_path does not apply")
        return OnnxRegionEncoder(model, output_scale=output_scale, min_peak_conf=min_peak_conf)
    embedder = OnnxCropEmbedder(model, padding=crop_padding, mask_background=mask_background)
    proposer: RegionProposer
    if mask_model_path is not None:
        mask_model = load_onnx_model(mask_model_path, expected_kind="mask-proposer", device=device)
        proposer = OnnxMaskProposer(mask_model, **(proposer_options or {}))
    else:
        proposer = GraphSegmentationProposer(**(proposer_options or {}))
    return ProposalRegionEncoder(proposer, embedder, name="onnx", output_scale=output_scale, batch_size=batch_size)


class OnnxTextEncoder(TextEncoder):
    """A ``text-model`` ONNX file + its tokenizer (HF ``tokenizers`` JSON).

    The tokenizer file is metadata ``tokenizer`` (relative to the model's folder), default
    ``tokenizer.json``. Texts are truncated/padded to ``max_length`` (metadata, or the static
    sequence length of ``input_ids``; padding to the longest text in the batch when neither).
    ``expect_space`` / ``expect_dim`` check that the model matches a region encoder.
    """

    def __init__(
        self,
        model_path: str | Path | None = None,
        *,
        device: str = "auto",
        expect_space: str | None = None,
        expect_dim: int | None = None,
    ) -> None:
        if model_path is None:
            raise EncoderConfigError("the onnx text encoder needs model_path=<file.onnx> (docs/ENCODERS.md)")
        from tokenizers import Tokenizer

        self.model = load_onnx_model(model_path, expected_kind="text-model", device=device)
        name = self.model.path.name
        self.embedding_space = str(self.model.metadata["embedding_space"])
        self.dim = int(self.model.metadata["dim"])
        if expect_space is not None and expect_space != self.embedding_space:
            raise EncoderContractError(
                f"{name}: text model space {self.embedding_space!r} does not match the region encoder's {expect_space!r}"
            )
        if expect_dim is not None and expect_dim != self.dim:
            raise EncoderContractError(f"{name}: text model dim {self.dim} does not match the region encoder's {expect_dim}")
        tok_path = self.model.path.parent / (self.model.meta_str("tokenizer", "tokenizer.json") or "tokenizer.json")
        if not tok_path.is_file():
            raise EncoderContractError(f"{name}: tokenizer file {tok_path} not found (metadata 'tokenizer')")
        try:
            self.tokenizer = Tokenizer.from_file(str(tok_path))
        except Exception as exc:  # tokenizers raises a bare Exception for a malformed file
            raise EncoderContractError(f"{tok_path}: not a valid tokenizers JSON file: {exc}") from exc
        self.max_length = self.model.meta_int("max_length") or self.model.static_dim("input_ids", 1)
        pad_id = self.model.meta_int("pad_id")
        if pad_id is None:
            padding = self.tokenizer.padding
            pad_id = int(padding["pad_id"]) if padding else 0
        self.pad_id = int(pad_id)
        # we pad ourselves (to max_length or the batch's longest); the tokenizer truncates so that
        # special tokens (e.g. CLIP's end-of-text, where CLIP pools) survive truncation
        self.tokenizer.no_padding()
        if self.max_length:
            self.tokenizer.enable_truncation(self.max_length)
        self._fixed_batch = self.model.static_dim("input_ids", 0)

    def _tokenize(self, texts: list[str]) -> tuple[np.ndarray, np.ndarray]:
        enc = self.tokenizer.encode_batch(texts)
        length = self.max_length or max(len(e.ids) for e in enc)
        ids = np.full((len(texts), length), self.pad_id, np.int64)
        mask = np.zeros((len(texts), length), np.int64)
        for i, e in enumerate(enc):
            n = min(len(e.ids), length)
            if n == 0:
                raise EncoderError(f"text {i} ({texts[i]!r}) produced no tokens")
            ids[i, :n] = e.ids[:n]
            mask[i, :n] = 1
        return ids, mask

    def encode(self, texts: list[str]) -> np.ndarray:
        texts = check_texts(texts)
        if not texts:
            return np.zeros((0, self.dim), np.float32)
        ids, mask = self._tokenize(texts)
        b = self._fixed_batch or len(texts)
        parts = []
        for i in range(0, len(texts), b):
            chunk_ids, chunk_mask = ids[i : i + b], mask[i : i + b]
            pad = b - chunk_ids.shape[0]
            if pad:
                chunk_ids = np.concatenate([chunk_ids, np.full((pad, ids.shape[1]), self.pad_id, np.int64)])
                chunk_mask = np.concatenate([chunk_mask, np.ones((pad, ids.shape[1]), np.int64)])
            feeds = {"input_ids": chunk_ids}
            if self.model.has_input("attention_mask"):
                feeds["attention_mask"] = chunk_mask
            out = np.asarray(self.model.session.run(["text_embeddings"], feeds)[0], np.float32)
            parts.append(out[: b - pad])
        emb = np.concatenate(parts)
        if emb.shape != (len(texts), self.dim):
            raise EncoderContractError(f"{self.model.path.name}: text_embeddings {emb.shape}, expected ({len(texts)}, {self.dim})")
        return normalize_rows(emb, what=f"{self.model.path.name} text embeddings")
