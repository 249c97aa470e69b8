"""Region and text encoders (docs/ARCHITECTURE.md "Encoders", docs/ENCODERS.md).

Backends: ``gt`` (ground-truth regions, measures fusion not vision), ``onnx`` (exported models run
by onnxruntime), ``clip-regions`` (graph-segmentation proposals + CLIP crop embeddings). Build them
with :func:`make_region_encoder` / :func:`make_text_encoder`; pick devices with :func:`select_device`.
"""

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
