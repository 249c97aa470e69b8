"""An encoder's space and size without its weights (openfusion.encoders.identity), and the
semantic service that uses it when only the encoder pool encodes.

Bad input tried: a CLIP model name that is neither a folder nor a hub name (a clear
``EncoderConfigError``, as when loading the weights)."""

from __future__ import annotations

import pytest

from openfusion.encoders import EncoderConfigError, EncoderError, make_region_encoder
from openfusion.encoders.identity import EncoderIdentity, region_encoder_identity
from openfusion.services.semantic.service import SemanticConfig, SemanticService
from openfusion.testing.bus import loopback_config, unique_map_id
from openfusion.testing.images import grid_boxes, make_box_frame
from openfusion.testing.models import build_tiny_clip


@pytest.fixture(scope="module")
def clip_dir(tmp_path_factory):
    return build_tiny_clip(tmp_path_factory.mktemp("clip") / "tiny-clip", projection_dim=24)


@pytest.fixture
def no_weights(monkeypatch):
    """Loading CLIP weights fails: whatever passes did not load them."""
    import transformers

    def refuse(*_args, **_kwargs):
        raise AssertionError("the weights were loaded")

    monkeypatch.setattr(transformers.CLIPModel, "from_pretrained", refuse)


@pytest.fixture(scope="module")
def built(clip_dir):
    """The real encoders, weights loaded (before ``no_weights``)."""
    return {name: make_region_encoder(name, model=str(clip_dir), device="cpu") for name in ("clip-dense", "clip-regions")}


@pytest.mark.parametrize("name", ["clip-dense", "clip-regions"])
def test_clip_identity_is_the_encoders_space_and_size_without_its_weights(clip_dir, built, name, no_weights):
    built = built[name]
    identity = region_encoder_identity(name, model=str(clip_dir), device="cpu", backend="onnx-int8")
    assert identity == EncoderIdentity(name, built.embedding_space, built.dim, needs_instances=False)
    assert (identity.embedding_space, identity.dim) == ("tiny-clip-random", 24)
    assert identity.output_size(480, 640) == built.output_size(480, 640)


def test_gt_identity_comes_from_its_text_encoder() -> None:
    assert region_encoder_identity("gt", noise="standard", seed=3) == EncoderIdentity(
        "gt", "minilm-l6-v2", 384, needs_instances=True)
    hashed = make_region_encoder("gt", text_encoder="hash", text_options={"dim": 48})
    identity = region_encoder_identity("gt", text_encoder="hash", text_options={"dim": 48})
    assert (identity.embedding_space, identity.dim) == (hashed.embedding_space, hashed.dim)
    assert region_encoder_identity("onnx", model_path="region.onnx") is None  # only the model file says


def test_a_bad_clip_name_is_a_clear_error() -> None:
    with pytest.raises(EncoderConfigError, match="no such folder, and not a hub name"):
        region_encoder_identity("clip-dense", model="not-a-folder")


def _semantic(clip_dir, **values) -> SemanticService:  # noqa: ANN001, ANN003
    base = loopback_config(unique_map_id("ident")).model_dump()
    cfg = SemanticConfig.model_validate({**base, "semantic": {"encoder": "clip-dense", "model_path": str(clip_dir),
                                                              "encoder_pool": True, **values}})
    return SemanticService(cfg)


def test_semantic_service_with_only_the_pool_encoding_loads_no_model(clip_dir, no_weights) -> None:
    """``local_encoder`` off: the dictionary is in the model's space and size, nothing loaded;
    a frame given to it anyway is a clear error (the service never does: no worker, no frame)."""
    service = _semantic(clip_dir, local_encoder=False)
    assert (service.dictionary.embedding_space, service.dictionary.dim) == ("tiny-clip-random", 24)
    frame = make_box_frame(grid_boxes(height_px=48, width_px=64, rows=1, cols=2, categories=["x"]),
                           height_px=48, width_px=64, frame_id=7)
    with pytest.raises(EncoderError, match="frame 7: no local 'clip-dense' encoder"):
        service.encoder.encode(frame)


def test_semantic_service_with_a_local_fallback_loads_it(clip_dir) -> None:
    service = _semantic(clip_dir, local_encoder=True)
    assert not isinstance(service.encoder, EncoderIdentity)
    assert service.encoder.embedding_space == "tiny-clip-random"
