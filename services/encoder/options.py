"""The region encoder's settings, declared once: the semantic service's local encoder and every
encoder worker of the pool take the same options (``SemanticSection`` and ``EncoderSection``
extend :class:`EncoderOptions`)."""

from __future__ import annotations

import logging
import time
from typing import Any

from pydantic import Field, ValidationInfo, field_validator

from openfusion.config import ConfigSection, one_of
from openfusion.encoders import NOISE_PROFILES, REGION_ENCODER_NAMES, make_region_encoder
from openfusion.encoders.base import CLIP_DENSE_BACKENDS, DEFAULT_DENSE_INPUT_LONG_SIDE_PX
from openfusion.encoders.gt import REGION_TEXTS
from openfusion.encoders.identity import EncoderIdentity, region_encoder_identity
from openfusion.sources.synthetic_categories import CATEGORIES

logger = logging.getLogger(__name__)


class EncoderOptions(ConfigSection):
    """Which region encoder, on which device, with which options."""

    encoder: str = Field("gt", description=f"region encoder: {', '.join(REGION_ENCODER_NAMES)}")
    model_path: str | None = Field(
        None, description="model file or folder of the onnx / clip-regions / clip-dense encoder"
    )
    device: str = Field(
        "auto", description="device of the onnx / clip-regions / clip-dense encoder: auto, cpu or cuda"
    )
    noise: str = Field("off", description=f"gt encoder noise profile: {', '.join(NOISE_PROFILES)}")
    seed: int = Field(0, description="seed of the gt encoder's noise")
    region_text: str = Field(
        "caption",
        description="what the gt encoder embeds for a region: caption (its name and six captions where "
        "openfusion.encoders.captions knows the category, else the name) or name",
    )
    encoder_delay_ms: float = Field(
        0.0,
        ge=0,
        le=60_000,
        description="add this many ms to every encoder call, sleeping: models a remote GPU "
        "encoder in tests and benches",
    )
    encoder_backend: str = Field("torch", description="clip-dense backend: torch, onnx or onnx-int8")
    dense_input_long_side_px: int = Field(
        DEFAULT_DENSE_INPUT_LONG_SIDE_PX,
        ge=16,
        le=4096,
        description="clip-dense: the frame's longer side at the tower's input, px (rounded to whole "
        "patches; fewer px is faster and coarser)",
    )
    encoder_onnx_spinning: bool = Field(
        True,
        description="clip-dense onnx backends: onnxruntime's idle threads busy-wait (faster when the "
        "encoder has the cores to itself; turn off beside other busy services on a small machine)",
    )

    @field_validator("encoder")
    @classmethod
    def _encoder(cls, value: str) -> str:
        return one_of(value, REGION_ENCODER_NAMES, "region encoder")

    @field_validator("encoder_backend")
    @classmethod
    def _encoder_backend(cls, value: str) -> str:
        return one_of(value, CLIP_DENSE_BACKENDS, "clip-dense backend")

    @field_validator("region_text")
    @classmethod
    def _region_text(cls, value: str) -> str:
        return one_of(value, REGION_TEXTS, "region_text")

    @field_validator("noise")
    @classmethod
    def _noise(cls, value: str, info: ValidationInfo) -> str:
        one_of(value, NOISE_PROFILES, "noise profile")
        encoder = info.data.get("encoder", "gt")
        if value != "off" and encoder != "gt":
            raise ValueError(f"noise applies to the gt encoder only, not to {encoder!r} (leave it off)")
        return value


def _encoder_options(section: EncoderOptions) -> dict[str, Any]:
    """The keyword options of ``make_region_encoder(section.encoder, ...)`` a section describes."""
    if section.encoder == "gt":
        return {"noise": section.noise, "seed": section.seed, "region_text": section.region_text}
    opts: dict[str, Any] = {"device": section.device}
    if section.model_path:
        opts["model_path" if section.encoder == "onnx" else "model"] = section.model_path
    if section.encoder == "clip-dense":
        opts["backend"] = section.encoder_backend
        opts["input_long_side_px"] = section.dense_input_long_side_px
        opts["onnx_spinning"] = section.encoder_onnx_spinning
    return opts


def region_encoder_from_section(section: EncoderOptions) -> Any:
    """The region encoder a section describes (semantic service, encoder worker, in-process run)."""
    encoder = make_region_encoder(section.encoder, **_encoder_options(section))
    if section.encoder_delay_ms > 0:
        from openfusion.encoders.delayed import DelayedRegionEncoder

        encoder = DelayedRegionEncoder(encoder, section.encoder_delay_ms)
    return encoder


def encoder_identity_from_section(section: EncoderOptions) -> EncoderIdentity | None:
    """The embedding space and size of the encoder a section describes, without its weights
    (:mod:`openfusion.encoders.identity`); None where only the model can say (``onnx``)."""
    return region_encoder_identity(section.encoder, **_encoder_options(section))


def warm_up_encoder(encoder: Any, service: str) -> None:
    """Warm ``encoder`` up (:meth:`~openfusion.encoders.base.RegionEncoder.warm_up`) with the
    built-in scene's categories before ``service`` announces itself. Measured: without it, each
    gt worker of a four-worker pool spent 1 to 3 s of its first frames embedding category names,
    a quarter of a 12 s playback (``bench/bench_pool.py``)."""
    warm_up = getattr(encoder, "warm_up", None)
    if warm_up is None:  # an encoder object that is not a RegionEncoder (tests' stand-ins)
        return
    started = time.monotonic()
    warm_up(CATEGORIES)
    logger.info("%s: encoder warmed up in %.2f s", service, time.monotonic() - started)
