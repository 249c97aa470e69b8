"""What a region encoder is — its embedding space, dimension and whether it reads instance
images — without loading its weights.

A semantic service that only dispatches frames to the encoder pool (``semantic.local_encoder``
off) needs the map's embedding space and dimension, not the model: building the encoder there
loaded the whole checkpoint (a ViT-L/14 is 1.7 GB) on the machine the pool exists to spare.
:func:`region_encoder_identity` answers from what is cheap: ``gt`` from its text encoder (MiniLM's
space and size are constants, the hash encoder has no model), ``clip-regions`` and ``clip-dense``
from the checkpoint's ``config.json`` (read by ``transformers`` without the weights; the space is
resolved the same way :func:`~openfusion.encoders.clip_regions.load_clip` does). ``onnx`` keeps its
metadata inside the model file, so it returns None and the caller builds the encoder.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from openfusion.encoders.base import (
    DEFAULT_OUTPUT_SCALE,
    EncoderConfigError,
    EncoderError,
    RegionObservation,
    output_size_for,
)
from openfusion.frame import Frame


@dataclass(frozen=True)
class EncoderIdentity:
    """A region encoder's name, space and size, standing in for an encoder nobody encodes with."""

    name: str
    embedding_space: str
    dim: int
    needs_instances: bool
    output_scale: float = DEFAULT_OUTPUT_SCALE

    def output_size(self, height_px: int, width_px: int) -> tuple[int, int]:
        return output_size_for(height_px, width_px, self.output_scale)

    def encode(self, frame: Frame) -> RegionObservation:
        raise EncoderError(
            f"frame {frame.frame_id}: no local {self.name!r} encoder was loaded (semantic.local_encoder is off: "
            "the encoder pool's workers encode)"
        )


def region_encoder_identity(name: str, **options: Any) -> EncoderIdentity | None:
    """The identity of ``make_region_encoder(name, **options)`` without building it; None where
    that needs the model itself (``onnx``). Options the identity does not depend on are ignored."""
    if name == "gt":
        return _gt_identity(options)
    if name in ("clip-regions", "clip-dense"):
        return _clip_identity(name, options)
    return None


def _gt_identity(options: dict[str, Any]) -> EncoderIdentity | None:
    text = options.get("text_encoder", "minilm")
    scale = float(options.get("output_scale", DEFAULT_OUTPUT_SCALE))
    if text in ("minilm", "gt"):
        from openfusion.encoders.text_minilm import MINILM_DIM, MINILM_SPACE

        return EncoderIdentity("gt", MINILM_SPACE, MINILM_DIM, needs_instances=True, output_scale=scale)
    if text == "hash":  # no model behind it: building it is the cheap way
        from openfusion.encoders.text_hash import HashTextEncoder

        hashed = HashTextEncoder(**dict(options.get("text_options") or {}))
        return EncoderIdentity("gt", hashed.embedding_space, hashed.dim, needs_instances=True, output_scale=scale)
    return None


def _clip_identity(name: str, options: dict[str, Any]) -> EncoderIdentity:
    from transformers import CLIPConfig

    from openfusion.encoders.clip_regions import DEFAULT_CLIP_MODEL, _resolve_space, clip_source

    model = str(options.get("model") or DEFAULT_CLIP_MODEL)
    folder, source = clip_source(model)
    try:
        config = CLIPConfig.from_pretrained(source)
    except OSError as exc:
        raise EncoderConfigError(
            f"cannot read the CLIP config of {model!r}: {exc}. Without internet the model must be in the local "
            "Hugging Face cache or a local folder (save_pretrained of model + tokenizer)."
        ) from exc
    space = _resolve_space(model, folder, config, options.get("embedding_space"))
    scale = float(options.get("output_scale", DEFAULT_OUTPUT_SCALE))
    return EncoderIdentity(name, space, int(config.projection_dim), needs_instances=False, output_scale=scale)
