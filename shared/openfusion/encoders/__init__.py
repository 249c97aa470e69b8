"""Region and text encoders (docs/ARCHITECTURE.md "Encoders", docs/ENCODERS.md).

Backends: ``gt`` (ground-truth regions, measures fusion not vision), ``onnx`` (exported models run
by onnxruntime), ``clip-regions`` (graph-segmentation proposals + CLIP crop embeddings). Build them
with :func:`make_region_encoder` / :func:`make_text_encoder`; pick devices with :func:`select_device`.

Names are imported on first use (PEP 562), so ``from openfusion.encoders import make_text_encoder``
does not load SciPy (the noise profiles) for a process that only encodes a query text.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from openfusion.lazy import lazy_exports

if TYPE_CHECKING:
    from openfusion.encoders.base import (
        DEFAULT_OUTPUT_SCALE,
        EncoderConfigError,
        EncoderError,
        ImageQueryEncoder,
        RegionEncoder,
        RegionObservation,
        TextEncoder,
        normalize_rows,
        output_size_for,
    )
    from openfusion.encoders.device import onnx_providers, select_device
    from openfusion.encoders.noise import NOISE_PROFILES, NoiseProfile, NoiseReport, get_noise_profile
    from openfusion.encoders.registry import (
        REGION_ENCODER_NAMES,
        TEXT_ENCODER_NAMES,
        make_region_encoder,
        make_text_encoder,
    )

_EXPORTS: dict[str, str] = {
    "DEFAULT_OUTPUT_SCALE": "openfusion.encoders.base",
    "EncoderConfigError": "openfusion.encoders.base",
    "EncoderError": "openfusion.encoders.base",
    "ImageQueryEncoder": "openfusion.encoders.base",
    "RegionEncoder": "openfusion.encoders.base",
    "RegionObservation": "openfusion.encoders.base",
    "TextEncoder": "openfusion.encoders.base",
    "normalize_rows": "openfusion.encoders.base",
    "output_size_for": "openfusion.encoders.base",
    "onnx_providers": "openfusion.encoders.device",
    "select_device": "openfusion.encoders.device",
    "NOISE_PROFILES": "openfusion.encoders.noise",
    "NoiseProfile": "openfusion.encoders.noise",
    "NoiseReport": "openfusion.encoders.noise",
    "get_noise_profile": "openfusion.encoders.noise",
    "REGION_ENCODER_NAMES": "openfusion.encoders.registry",
    "TEXT_ENCODER_NAMES": "openfusion.encoders.registry",
    "make_region_encoder": "openfusion.encoders.registry",
    "make_text_encoder": "openfusion.encoders.registry",
}

__all__ = [
    "DEFAULT_OUTPUT_SCALE",
    "NOISE_PROFILES",
    "REGION_ENCODER_NAMES",
    "TEXT_ENCODER_NAMES",
    "EncoderConfigError",
    "EncoderError",
    "ImageQueryEncoder",
    "NoiseProfile",
    "NoiseReport",
    "RegionEncoder",
    "RegionObservation",
    "TextEncoder",
    "get_noise_profile",
    "make_region_encoder",
    "make_text_encoder",
    "normalize_rows",
    "onnx_providers",
    "output_size_for",
    "select_device",
]


__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
