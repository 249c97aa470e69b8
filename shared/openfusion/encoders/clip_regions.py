"""The ``clip-regions`` backend: class-agnostic proposals + CLIP embeddings of masked region crops.

Proposals come from graph segmentation on color + depth (:mod:`.graph_segmentation`) or a SAM-style
ONNX ``mask-proposer`` (``mask_model_path``). Crops are preprocessed in numpy/PIL
(:mod:`.crops`; torchvision is not needed) and embedded in batches with the image tower of a
transformers ``CLIPModel``; queries use its text tower (:class:`ClipTextEncoder`).

Weights load by hub name (``openai/clip-vit-base-patch32`` -> space ``clip-vit-b-32``) when they
are in the local Hugging Face cache or the machine is online, or from a local folder written by
``save_pretrained`` (model + tokenizer). One model per (weights, device) is loaded per process and
shared by the region and text encoders.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from openfusion.encoders.base import (
    DEFAULT_OUTPUT_SCALE,
    EncoderConfigError,
    TextEncoder,
    check_texts,
    normalize_rows,
)
from openfusion.encoders.crops import CLIP_MEAN, CLIP_STD, CropSpec
from openfusion.encoders.device import select_device
from openfusion.encoders.proposal_encoder import ProposalRegionEncoder
from openfusion.encoders.proposers import make_proposer

logger = logging.getLogger(__name__)

DEFAULT_CLIP_MODEL = "openai/clip-vit-base-patch32"

#: Hub names -> embedding-space ids (every map records its named space).
KNOWN_CLIP_SPACES = {
    "openai/clip-vit-base-patch32": "clip-vit-b-32",
    "openai/clip-vit-base-patch16": "clip-vit-b-16",
    "openai/clip-vit-large-patch14": "clip-vit-l-14",
    "openai/clip-vit-large-patch14-336": "clip-vit-l-14-336",
}

#: Optional file in a local model folder naming its embedding space: {"embedding_space": "..."}.
SPACE_FILE = "openfusion_encoder.json"


@dataclass
class LoadedClip:
    model: Any  # transformers CLIPModel (eval mode, on device)
    tokenizer: Any  # transformers CLIPTokenizer
    embedding_space: str
    dim: int
    crop_spec: CropSpec
    device: str
    max_text_length: int


_CACHE: dict[tuple[str, str, str], LoadedClip] = {}
_LOCK = threading.Lock()


def _features(out: Any) -> Any:
    """transformers returns a tensor (v4) or an output object with the projected pooler_output (v5)."""
    return out if hasattr(out, "shape") else out.pooler_output


def _resolve_space(model: str, folder: Path | None, config: Any, embedding_space: str | None) -> str:
    if embedding_space:
        return str(embedding_space)
    if folder is not None and (folder / SPACE_FILE).is_file():
        try:
            space = json.loads((folder / SPACE_FILE).read_text(encoding="utf-8")).get("embedding_space")
        except (OSError, json.JSONDecodeError, AttributeError) as exc:
            raise EncoderConfigError(f"{folder / SPACE_FILE}: cannot read embedding_space: {exc}") from exc
        if space:
            return str(space)
    for name in (model, getattr(config, "_name_or_path", "") or "", getattr(config, "name_or_path", "") or ""):
        if name in KNOWN_CLIP_SPACES:
            return KNOWN_CLIP_SPACES[name]
    raise EncoderConfigError(
        f"cannot tell the embedding space of CLIP weights {model!r}: pass embedding_space=... or write "
        f"{SPACE_FILE} with {{\"embedding_space\": ...}} in the model folder (known hub names: "
        f"{', '.join(KNOWN_CLIP_SPACES)})"
    )


def clip_source(model: str) -> tuple[Path | None, str]:
    """(local folder or None, what ``from_pretrained`` reads) of a CLIP model given as a hub name
    or a ``save_pretrained`` folder; anything else is a clear :class:`EncoderConfigError`."""
    folder = Path(model).expanduser()
    if folder.is_dir():
        return folder, str(folder)
    if "/" not in str(model) or str(model).startswith((".", "/", "~")):
        raise EncoderConfigError(f"CLIP weights {model!r}: no such folder, and not a hub name like {DEFAULT_CLIP_MODEL}")
    return None, str(model)


def load_clip(model: str = DEFAULT_CLIP_MODEL, *, device: str = "auto", embedding_space: str | None = None) -> LoadedClip:
    """Load (once per process) CLIP weights + tokenizer by hub name or local folder."""
    dev = select_device(device)
    key = (str(model), dev, str(embedding_space or ""))
    with _LOCK:
        cached = _CACHE.get(key)
        if cached is not None:
            return cached
        import torch
        from transformers import CLIPModel, CLIPTokenizer

        folder, source = clip_source(model)
        t0 = time.perf_counter()
        try:
            # eager attention on CPU: the ONNX export traces this model, and the int8 path is the
            # CPU's fast one; on CUDA scaled-dot-product attention (fused kernels, fp16 in clip-dense).
            attention = "sdpa" if dev == "cuda" else "eager"
            clip = CLIPModel.from_pretrained(source, attn_implementation=attention, dtype=torch.float32)
            tokenizer = CLIPTokenizer.from_pretrained(source)
        except OSError as exc:
            raise EncoderConfigError(
                f"cannot load CLIP weights {model!r}: {exc}. Without internet the weights must be in the "
                "local Hugging Face cache or a local folder (save_pretrained of model + tokenizer)."
            ) from exc
        clip = clip.eval().to(dev)
        space = _resolve_space(str(model), folder, clip.config, embedding_space)
        dim = int(clip.config.projection_dim)
        mean, std = CLIP_MEAN, CLIP_STD
        pre = folder / "preprocessor_config.json" if folder is not None else None
        if pre is not None and pre.is_file():
            cfg = json.loads(pre.read_text(encoding="utf-8"))
            mean = tuple(cfg.get("image_mean", mean))  # type: ignore[assignment]
            std = tuple(cfg.get("image_std", std))  # type: ignore[assignment]
        spec = CropSpec(size=int(clip.config.vision_config.image_size), mean=mean, std=std)
        loaded = LoadedClip(
            model=clip,
            tokenizer=tokenizer,
            embedding_space=space,
            dim=dim,
            crop_spec=spec,
            device=dev,
            max_text_length=int(clip.config.text_config.max_position_embeddings),
        )
        _CACHE[key] = loaded
        logger.info("loaded CLIP %s (space %s, %d-d) on %s in %.1f s", model, space, dim, dev, time.perf_counter() - t0)
        return loaded


class TorchClipCropEmbedder:
    """CLIP image tower over preprocessed crops (torch, no grad)."""

    def __init__(self, clip: LoadedClip, *, padding: float = 0.1, mask_background: bool = True) -> None:
        self.clip = clip
        self.embedding_space = clip.embedding_space
        self.dim = clip.dim
        self.crop_spec = CropSpec(
            size=clip.crop_spec.size,
            mean=clip.crop_spec.mean,
            std=clip.crop_spec.std,
            padding=padding,
            mask_background=mask_background,
        )

    def embed_crops(self, crops: np.ndarray) -> np.ndarray:
        import torch

        if crops.shape[0] == 0:
            return np.zeros((0, self.dim), np.float32)
        with torch.inference_mode():
            x = torch.from_numpy(np.ascontiguousarray(crops)).to(self.clip.device)
            feats = _features(self.clip.model.get_image_features(pixel_values=x))
            return feats.float().cpu().numpy()


class ClipRegionEncoder(ProposalRegionEncoder):
    """Graph-segmentation (or ONNX mask) proposals + CLIP embeddings of masked crops; name ``clip-regions``."""

    def __init__(
        self,
        model: str = DEFAULT_CLIP_MODEL,
        *,
        device: str = "auto",
        embedding_space: str | None = None,
        output_scale: float = DEFAULT_OUTPUT_SCALE,
        mask_model_path: str | Path | None = None,
        proposer_options: dict[str, Any] | None = None,
        batch_size: int = 32,
        crop_padding: float = 0.1,
        mask_background: bool = True,
    ) -> None:
        self.clip = load_clip(model, device=device, embedding_space=embedding_space)
        proposer = make_proposer(mask_model_path, proposer_options, device=self.clip.device)
        embedder = TorchClipCropEmbedder(self.clip, padding=crop_padding, mask_background=mask_background)
        super().__init__(proposer, embedder, name="clip-regions", output_scale=output_scale, batch_size=batch_size)


class ClipTextEncoder(TextEncoder):
    """CLIP text tower: texts -> (k, d) unit-norm embeddings in the CLIP space."""

    def __init__(
        self,
        model: str = DEFAULT_CLIP_MODEL,
        *,
        device: str = "auto",
        embedding_space: str | None = None,
        batch_size: int = 64,
    ) -> None:
        self.clip = load_clip(model, device=device, embedding_space=embedding_space)
        self.embedding_space = self.clip.embedding_space
        self.dim = self.clip.dim
        self.batch_size = int(batch_size)

    def encode(self, texts: list[str]) -> np.ndarray:
        import torch

        texts = check_texts(texts)
        if not texts:
            return np.zeros((0, self.dim), np.float32)
        parts = []
        with torch.inference_mode():
            for i in range(0, len(texts), self.batch_size):
                tok = self.clip.tokenizer(
                    texts[i : i + self.batch_size],
                    padding=True,
                    truncation=True,
                    max_length=self.clip.max_text_length,
                    return_tensors="pt",
                )
                tok = {k: v.to(self.clip.device) for k, v in tok.items() if k in ("input_ids", "attention_mask")}
                parts.append(_features(self.clip.model.get_text_features(**tok)).float().cpu().numpy())
        return normalize_rows(np.concatenate(parts), what="CLIP text embeddings")
