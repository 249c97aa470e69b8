"""Build encoders by name: the one switch services and configs use.

Region encoders: ``gt``, ``onnx``, ``clip-regions``, ``clip-dense``. Text encoders: the same three names give the
text encoder that matches that region encoder's embedding space (``gt`` -> ``minilm``), plus
``minilm`` and ``hash`` (lexical baseline, no model). Backends import lazily, so importing
:mod:`openfusion.encoders` does not pull in torch, transformers or onnxruntime.
"""

from __future__ import annotations

from typing import Any

from openfusion.encoders.base import EncoderConfigError, RegionEncoder, TextEncoder

REGION_ENCODER_NAMES = ("gt", "onnx", "clip-regions", "clip-dense")
TEXT_ENCODER_NAMES = ("gt", "onnx", "clip-regions", "clip-dense", "minilm", "hash")
MINILM_BACKENDS = ("sentence-transformers", "onnxruntime")


def _normalise_name(name: str) -> str:
    return str(name).strip().lower().replace("_", "-")


def make_text_encoder(name: str, **options: Any) -> TextEncoder:
    """A text encoder by name.

    - ``minilm`` (alias ``gt``): MiniLM-L6-v2 sentence embeddings, space ``minilm-l6-v2``; options ``device``,
      ``backend``: ``sentence-transformers`` (default, torch) or ``onnxruntime`` (the same
      embeddings without importing torch at query time, :mod:`openfusion.encoders.text_minilm_onnx`;
      falls back to sentence-transformers, logged, when it is unavailable).
    - ``hash``: hashed character trigrams, space ``hash-trigram-<dim>``; option ``dim``.
    - ``onnx``: an ONNX text model (docs/ENCODERS.md); options ``model_path``, ``device``.
    - ``clip-regions`` (aliases ``clip``, ``clip-dense``): the CLIP text tower; options ``model``, ``device``,
      ``embedding_space``.
    """
    key = _normalise_name(name)
    if key in ("minilm", "gt"):
        backend = str(options.pop("backend", "sentence-transformers")).strip().lower()
        if backend not in MINILM_BACKENDS:
            raise EncoderConfigError(f"unknown MiniLM backend {backend!r}; known: {', '.join(MINILM_BACKENDS)}")
        if backend == "onnxruntime":
            from openfusion.encoders.text_minilm_onnx import make_minilm_onnx

            onnx_only = {k: options.pop(k) for k in ("model_dir", "cache_dir") if k in options}
            encoder = make_minilm_onnx(**options, **onnx_only)
            if encoder is not None:
                return encoder
        from openfusion.encoders.text_minilm import MiniLMTextEncoder

        return MiniLMTextEncoder(**options)
    if key == "hash":
        from openfusion.encoders.text_hash import HashTextEncoder

        return HashTextEncoder(**options)
    if key == "onnx":
        from openfusion.encoders.onnx_backend import OnnxTextEncoder

        return OnnxTextEncoder(**options)
    if key in ("clip-regions", "clip", "clip-dense"):
        from openfusion.encoders.clip_regions import ClipTextEncoder

        return ClipTextEncoder(**options)
    raise EncoderConfigError(f"unknown text encoder {name!r}; known: {', '.join(TEXT_ENCODER_NAMES)}")


def make_region_encoder(name: str, **options: Any) -> RegionEncoder:
    """A region encoder by name.

    - ``gt``: ground-truth instances; options ``text_encoder`` (a TextEncoder or a text encoder
      name, default ``minilm``), ``text_options`` (dict for that name), ``noise``, ``seed``,
      ``output_scale``, ``min_area_px``.
    - ``onnx``: an ONNX region model or crop embedder (docs/ENCODERS.md); options ``model_path``, ``device``, ...
    - ``clip-regions``: graph-segmentation proposals + CLIP crop embeddings; options ``model``, ``device``, ...
    - ``clip-dense``: the same proposals + region means of dense CLIP patch features from one pass over
      the frame (MaskCLIP); options as ``clip-regions`` plus ``backend`` (torch, onnx, onnx-int8),
      ``input_long_side_px``, ``dense_mode``, ``cache_dir``.
    """
    key = _normalise_name(name)
    if key == "gt":
        from openfusion.encoders.gt import GroundTruthRegionEncoder

        text = options.pop("text_encoder", "minilm")
        text_options = dict(options.pop("text_options", None) or {})
        if isinstance(text, str):
            text = make_text_encoder(text, **text_options)
        elif text_options:
            raise EncoderConfigError("text_options only apply when text_encoder is given by name")
        return GroundTruthRegionEncoder(text, **options)
    if key == "onnx":
        from openfusion.encoders.onnx_backend import make_onnx_region_encoder

        return make_onnx_region_encoder(**options)
    if key == "clip-regions":
        from openfusion.encoders.clip_regions import ClipRegionEncoder

        return ClipRegionEncoder(**options)
    if key == "clip-dense":
        from openfusion.encoders.clip_dense import ClipDenseRegionEncoder

        return ClipDenseRegionEncoder(**options)
    raise EncoderConfigError(f"unknown region encoder {name!r}; known: {', '.join(REGION_ENCODER_NAMES)}")
