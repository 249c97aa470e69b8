"""The ONNX model contract (docs/ENCODERS.md) and its load-time validation.

Four kinds of model, named by the metadata key ``kind``:

=============== =============================================== ==========================================
kind            inputs                                          outputs
=============== =============================================== ==========================================
region-model    image f32 [1,3,H,W] (+ depth f32 [1,1,H,W])     conf_maps f32 [1,N,h,w], embeddings f32
                                                                [1,N,d] (+ valid [1,N] bool/f32/i64)
crop-embedder   crops f32 [B,3,S,S]                             embeddings f32 [B,d]
mask-proposer   image f32 [1,3,H,W] (+ depth f32 [1,1,H,W])     masks f32 [1,N,h,w] (+ scores f32 [1,N])
text-model      input_ids i64 [B,L] (+ attention_mask i64 [B,L]) text_embeddings f32 [B,d]
=============== =============================================== ==========================================

Metadata comes from the model's ``metadata_props`` and, overriding it, an optional sidecar JSON
file next to the model (``<name>.json`` for ``<name>.onnx``). Everything is checked when the model
is loaded; a mismatch raises :class:`EncoderContractError` naming the model, the tensor and what
was expected.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from openfusion.encoders.base import EncoderError
from openfusion.encoders.device import onnx_providers, select_device
from openfusion.errors import UserError

logger = logging.getLogger(__name__)

KINDS = ("region-model", "crop-embedder", "mask-proposer", "text-model")

_FLOAT = ("tensor(float)",)
_INT64 = ("tensor(int64)",)
_VALID_TYPES = ("tensor(bool)", "tensor(float)", "tensor(int64)", "tensor(int32)")


@dataclass(frozen=True)
class TensorSpec:
    rank: int
    types: tuple[str, ...]
    required: bool = True


#: name -> spec for the inputs and outputs of each kind.
CONTRACT: dict[str, dict[str, dict[str, TensorSpec]]] = {
    "region-model": {
        "inputs": {"image": TensorSpec(4, _FLOAT), "depth": TensorSpec(4, _FLOAT, required=False)},
        "outputs": {
            "conf_maps": TensorSpec(4, _FLOAT),
            "embeddings": TensorSpec(3, _FLOAT),
            "valid": TensorSpec(2, _VALID_TYPES, required=False),
        },
    },
    "crop-embedder": {
        "inputs": {"crops": TensorSpec(4, _FLOAT)},
        "outputs": {"embeddings": TensorSpec(2, _FLOAT)},
    },
    "mask-proposer": {
        "inputs": {"image": TensorSpec(4, _FLOAT), "depth": TensorSpec(4, _FLOAT, required=False)},
        "outputs": {"masks": TensorSpec(4, _FLOAT), "scores": TensorSpec(2, _FLOAT, required=False)},
    },
    "text-model": {
        "inputs": {"input_ids": TensorSpec(2, _INT64), "attention_mask": TensorSpec(2, _INT64, required=False)},
        "outputs": {"text_embeddings": TensorSpec(2, _FLOAT)},
    },
}

#: metadata keys each kind must define (after merging the sidecar).
REQUIRED_METADATA: dict[str, tuple[str, ...]] = {
    "region-model": ("embedding_space", "dim", "mean", "std"),
    "crop-embedder": ("embedding_space", "dim", "mean", "std"),
    "mask-proposer": ("mean", "std"),
    "text-model": ("embedding_space", "dim"),
}


class EncoderContractError(EncoderError, UserError):
    """An ONNX model (or model pair) does not follow the contract in docs/ENCODERS.md."""


@dataclass
class OnnxModel:
    """A loaded, validated model: the onnxruntime session, merged metadata and tensor shapes."""

    path: Path
    kind: str
    session: Any
    metadata: dict[str, Any]
    input_shapes: dict[str, list[int | str | None]]
    output_shapes: dict[str, list[int | str | None]]
    providers: list[str] = field(default_factory=list)

    def static_dim(self, tensor: str, axis: int) -> int | None:
        """The fixed size of ``tensor``'s axis, or None when it is dynamic."""
        shape = self.input_shapes.get(tensor) or self.output_shapes.get(tensor)
        if shape is None:
            return None
        v = shape[axis]
        return int(v) if isinstance(v, int) and v > 0 else None

    def has_input(self, name: str) -> bool:
        return name in self.input_shapes

    def has_output(self, name: str) -> bool:
        return name in self.output_shapes

    def meta_float3(self, key: str) -> tuple[float, float, float]:
        return _parse_float3(self.metadata[key], key, self.path)

    def meta_int(self, key: str, default: int | None = None) -> int | None:
        if key not in self.metadata or self.metadata[key] in ("", None):
            return default
        try:
            return int(self.metadata[key])
        except (TypeError, ValueError) as exc:
            raise EncoderContractError(f"{self.path.name}: metadata {key!r}={self.metadata[key]!r} is not an integer") from exc

    def meta_str(self, key: str, default: str | None = None) -> str | None:
        v = self.metadata.get(key, default)
        return None if v is None else str(v)


def _parse_float3(value: Any, key: str, path: Path) -> tuple[float, float, float]:
    try:
        parts = [float(v) for v in value.split(",")] if isinstance(value, str) else [float(v) for v in value]
    except (TypeError, ValueError) as exc:
        raise EncoderContractError(f"{path.name}: metadata {key!r}={value!r} is not 3 numbers") from exc
    if len(parts) != 3:
        raise EncoderContractError(f"{path.name}: metadata {key!r} must have 3 values (R,G,B), got {len(parts)}")
    return parts[0], parts[1], parts[2]


def sidecar_path(model_path: Path) -> Path:
    """``<name>.json`` beside ``<name>.onnx``."""
    return model_path.with_suffix(".json")


def read_metadata(model_path: Path, session: Any) -> dict[str, Any]:
    """Model metadata_props merged with (overridden by) the sidecar JSON when present."""
    meta: dict[str, Any] = dict(session.get_modelmeta().custom_metadata_map)
    side = sidecar_path(model_path)
    if side.is_file():
        try:
            extra = json.loads(side.read_text(encoding="utf-8"))
        except (OSError, json.JSONDecodeError) as exc:
            raise EncoderContractError(f"{side}: sidecar is not valid JSON: {exc}") from exc
        if not isinstance(extra, dict):
            raise EncoderContractError(f"{side}: sidecar must be a JSON object")
        meta.update(extra)
    return meta


def load_onnx_model(path: str | Path, *, expected_kind: str | tuple[str, ...], device: str = "auto") -> OnnxModel:
    """Open ``path`` with onnxruntime on ``device`` and validate it against the contract."""
    import onnxruntime as ort

    model_path = Path(path).expanduser()
    if not model_path.is_file():
        raise EncoderContractError(f"ONNX model not found: {model_path}")
    providers = onnx_providers(select_device(device))
    try:
        session = ort.InferenceSession(str(model_path), providers=providers)
    except Exception as exc:  # onnxruntime raises several unrelated types for a bad file
        raise EncoderContractError(f"{model_path}: onnxruntime cannot load the model: {exc}") from exc
    meta = read_metadata(model_path, session)
    kinds = (expected_kind,) if isinstance(expected_kind, str) else tuple(expected_kind)
    kind = str(meta.get("kind", "")).strip()
    if kind not in kinds:
        hint = "missing" if not kind else repr(kind)
        raise EncoderContractError(
            f"{model_path.name}: metadata 'kind' is {hint}; expected {' or '.join(kinds)} (docs/ENCODERS.md)"
        )
    inputs = {i.name: (i.shape, i.type) for i in session.get_inputs()}
    outputs = {o.name: (o.shape, o.type) for o in session.get_outputs()}
    spec = CONTRACT[kind]
    _check_tensors(model_path, kind, "input", inputs, spec["inputs"], allow_extra=False)
    _check_tensors(model_path, kind, "output", outputs, spec["outputs"], allow_extra=True)
    missing = [k for k in REQUIRED_METADATA[kind] if k not in meta or meta[k] in ("", None)]
    if missing:
        raise EncoderContractError(
            f"{model_path.name} ({kind}): metadata key(s) {', '.join(missing)} missing "
            f"(set them in the model's metadata_props or in {sidecar_path(model_path).name})"
        )
    model = OnnxModel(
        path=model_path,
        kind=kind,
        session=session,
        metadata=meta,
        input_shapes={k: list(v[0]) for k, v in inputs.items()},
        output_shapes={k: list(v[0]) for k, v in outputs.items()},
        providers=list(session.get_providers()),
    )
    _check_dims(model)
    logger.info("loaded %s %s on %s", kind, model_path.name, ",".join(model.providers))
    return model


def _check_tensors(
    path: Path,
    kind: str,
    what: str,
    present: dict[str, tuple[list, str]],
    spec: dict[str, TensorSpec],
    *,
    allow_extra: bool,
) -> None:
    for name, ts in spec.items():
        if name not in present:
            if ts.required:
                raise EncoderContractError(
                    f"{path.name} ({kind}): {what} {name!r} missing; the model's {what}s are {', '.join(present) or 'none'}"
                )
            continue
        shape, dtype = present[name]
        if len(shape) != ts.rank:
            raise EncoderContractError(
                f"{path.name} ({kind}): {what} {name!r} has rank {len(shape)} {list(shape)}, expected rank {ts.rank}"
            )
        if dtype not in ts.types:
            raise EncoderContractError(
                f"{path.name} ({kind}): {what} {name!r} has type {dtype}, expected {' or '.join(ts.types)}"
            )
    if not allow_extra:
        extra = [n for n in present if n not in spec]
        if extra:
            raise EncoderContractError(
                f"{path.name} ({kind}): {what}(s) {', '.join(map(repr, extra))} are not part of the contract "
                f"(allowed: {', '.join(spec)})"
            )


def _expect(model: OnnxModel, tensor: str, axis: int, want: int | None, what: str) -> None:
    got = model.static_dim(tensor, axis)
    if want is not None and got is not None and got != want:
        raise EncoderContractError(
            f"{model.path.name} ({model.kind}): {tensor!r} axis {axis} is {got}, expected {want} ({what})"
        )


def _check_dims(model: OnnxModel) -> None:
    kind = model.kind
    dim = model.meta_int("dim")
    if dim is not None and dim < 1:
        raise EncoderContractError(f"{model.path.name}: metadata dim must be >= 1, got {dim}")
    if kind in ("region-model", "crop-embedder", "mask-proposer"):
        std = model.meta_float3("std")
        model.meta_float3("mean")
        if min(std) <= 0:
            raise EncoderContractError(f"{model.path.name}: metadata std must be > 0, got {std}")
    if kind in ("region-model", "mask-proposer"):
        _expect(model, "image", 0, 1, "batch of one frame")
        _expect(model, "image", 1, 3, "RGB channels")
        _expect(model, "image", 2, model.meta_int("input_height"), "metadata input_height")
        _expect(model, "image", 3, model.meta_int("input_width"), "metadata input_width")
        if model.has_input("depth"):
            _expect(model, "depth", 1, 1, "one depth channel")
    if kind == "region-model":
        _expect(model, "embeddings", 2, dim, "metadata dim")
        n_conf, n_emb = model.static_dim("conf_maps", 1), model.static_dim("embeddings", 1)
        if n_conf is not None and n_emb is not None and n_conf != n_emb:
            raise EncoderContractError(
                f"{model.path.name} (region-model): {n_conf} conf_maps but {n_emb} embeddings per frame"
            )
        kind_of_conf = model.meta_str("conf_maps_are", "probability")
        if kind_of_conf not in ("probability", "logits"):
            raise EncoderContractError(
                f"{model.path.name}: metadata conf_maps_are must be 'probability' or 'logits', got {kind_of_conf!r}"
            )
    if kind == "mask-proposer":
        kind_of_masks = model.meta_str("masks_are", "probability")
        if kind_of_masks not in ("probability", "logits"):
            raise EncoderContractError(
                f"{model.path.name}: metadata masks_are must be 'probability' or 'logits', got {kind_of_masks!r}"
            )
    if kind == "crop-embedder":
        _expect(model, "crops", 1, 3, "RGB channels")
        size = model.meta_int("crop_size")
        _expect(model, "crops", 2, size, "metadata crop_size")
        _expect(model, "crops", 3, size, "metadata crop_size")
        if size is None and (model.static_dim("crops", 2) is None or model.static_dim("crops", 3) is None):
            raise EncoderContractError(f"{model.path.name} (crop-embedder): give metadata crop_size or a static crop shape")
        _expect(model, "embeddings", 1, dim, "metadata dim")
    if kind == "text-model":
        _expect(model, "text_embeddings", 1, dim, "metadata dim")
        _expect(model, "input_ids", 1, model.meta_int("max_length"), "metadata max_length")
