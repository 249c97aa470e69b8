"""clip-dense (one pass of a CLIP image tower, MaskCLIP value path, region means of patch
features) on a tiny random-weight CLIP built here: the construction against transformers' own
hidden states, the pooling against torch's bilinear upsampling, the ONNX and int8 backends against
torch, and a cost that does not depend on the number of regions. Bad input tried: an unknown
backend or dense mode, an input size below one patch, a proposer that finds nothing."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from openfusion.encoders import EncoderConfigError, make_region_encoder
from openfusion.encoders.clip_dense import (
    ClipDenseRegionEncoder,
    dense_input_size,
    pool_region_features,
    preprocess_dense,
)
from openfusion.encoders.delayed import DelayedRegionEncoder
from openfusion.services.encoder.options import region_encoder_from_section
from openfusion.services.semantic.service import SemanticSection
from openfusion.testing.images import grid_boxes, make_box_frame
from openfusion.testing.models import build_tiny_clip


@pytest.fixture(scope="module")
def clip_dir(tmp_path_factory):
    return build_tiny_clip(tmp_path_factory.mktemp("clip") / "tiny-clip")


def _frame(rows: int, cols: int, seed: int = 2):
    return make_box_frame(
        grid_boxes(height_px=240, width_px=320, rows=rows, cols=cols, categories=["x"], gap_px=8, seed=seed),
        height_px=240,
        width_px=320,
    )


@pytest.fixture(scope="module")
def encoder(clip_dir, tmp_path_factory) -> ClipDenseRegionEncoder:
    return make_region_encoder("clip-dense", model=str(clip_dir), device="cpu", input_long_side_px=64,
                               cache_dir=tmp_path_factory.mktemp("cache"))


def test_value_path_matches_the_towers_own_weights(encoder):
    """At the training size (no interpolation) the dense features equal the MaskCLIP value path
    computed by hand from transformers' hidden state entering the last block."""
    clip = encoder.clip.model
    size = clip.config.vision_config.image_size
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 255, (size, size, 3), dtype=np.uint8)
    pixels = preprocess_dense(rgb, (size, size), encoder.clip.crop_spec.mean, encoder.clip.crop_spec.std)
    dense = encoder._runner((size, size))(pixels)
    with torch.inference_mode():
        out = clip.vision_model(pixel_values=torch.from_numpy(pixels), output_hidden_states=True)
        x = out.hidden_states[-2]  # input of the last block
        last = clip.vision_model.encoder.layers[-1]
        v = last.self_attn.out_proj(last.self_attn.v_proj(last.layer_norm1(x)))
        want = clip.visual_projection(clip.vision_model.post_layernorm(v[:, 1:]))[0].numpy()
    patches = (size // encoder.patch_px) ** 2
    assert dense.shape == want.shape == (patches, encoder.dim)
    np.testing.assert_allclose(dense, want, rtol=1e-4, atol=1e-5)


def test_pooling_is_bilinear_upsampling_then_masked_mean() -> None:
    rng = np.random.default_rng(1)
    feats = rng.normal(size=(5, 7, 12)).astype(np.float32)
    masks = rng.random((3, 30, 40)).astype(np.float32)
    masks[2] = 0.0  # an empty mask is not a region
    emb, ok = pool_region_features(masks, feats)
    up = torch.nn.functional.interpolate(torch.from_numpy(feats).permute(2, 0, 1)[None], size=(30, 40),
                                         mode="bilinear", align_corners=False)[0].permute(1, 2, 0).numpy()
    want = np.einsum("nyx,yxd->nd", masks[:2], up)
    want /= np.linalg.norm(want, axis=1, keepdims=True)
    assert ok.tolist() == [True, True, False]
    np.testing.assert_allclose(emb[:2], want, atol=1e-5)
    assert not emb[2].any()


def test_regions_get_unit_embeddings_and_the_tower_runs_once_per_frame(encoder, monkeypatch):
    calls = []
    runner = encoder._runner(dense_input_size(240, 320, patch_px=encoder.patch_px, long_side_px=64))
    monkeypatch.setitem(encoder._runners, (48, 64), lambda px: calls.append(px.shape) or runner(px))
    few, many = encoder.encode(_frame(1, 2)), encoder.encode(_frame(3, 4))
    few.validate(dim=encoder.dim)
    many.validate(dim=encoder.dim)
    assert few.num_regions == 3 and many.num_regions == 13  # boxes + background
    assert calls == [(1, 3, 48, 64), (1, 3, 48, 64)]  # one pass each, whatever the number of regions
    # different regions see different image content
    assert np.abs(many.embeddings @ many.embeddings.T - np.eye(13)).max() < 1.0 - 1e-4


def test_onnx_and_int8_backends_agree_with_torch(clip_dir, encoder, tmp_path):
    frame = _frame(2, 3)
    ref = encoder.encode(frame)
    for backend, min_cos in (("onnx", 0.9999), ("onnx-int8", 0.98)):
        enc = make_region_encoder("clip-dense", model=str(clip_dir), device="cpu", backend=backend,
                                  input_long_side_px=64, cache_dir=tmp_path)
        obs = enc.encode(frame)
        np.testing.assert_array_equal(obs.conf_maps, ref.conf_maps)
        cos = np.sum(obs.embeddings * ref.embeddings, axis=1)
        assert cos.min() >= min_cos, (backend, cos)
    assert len(list((tmp_path / "clip-dense").glob("*-int8.onnx"))) == 1  # exported once, cached


def test_no_region_is_an_empty_observation_without_running_the_tower(encoder, monkeypatch):
    monkeypatch.setattr(encoder.proposer, "propose", lambda frame, hw: np.zeros((0, *hw), np.float32))
    monkeypatch.setattr(encoder, "patch_features", lambda rgb: pytest.fail("tower ran for no region"))
    obs = encoder.encode(_frame(1, 2))
    assert obs.num_regions == 0 and obs.conf_maps.shape == (0, 60, 80)


def test_bad_options_are_refused(clip_dir):
    with pytest.raises(EncoderConfigError, match="backend 'tensorrt'"):
        make_region_encoder("clip-dense", model=str(clip_dir), device="cpu", backend="tensorrt")
    with pytest.raises(EncoderConfigError, match="dense_mode"):
        make_region_encoder("clip-dense", model=str(clip_dir), device="cpu", dense_mode="query-key")
    with pytest.raises(EncoderConfigError, match="at least the patch size"):
        dense_input_size(480, 640, patch_px=32, long_side_px=16)
    with pytest.raises(ValueError, match="unknown clip-dense backend"):
        SemanticSection(encoder="clip-dense", encoder_backend="int4")


def test_encoder_delay_wraps_any_encoder(monkeypatch):
    """--encoder-delay-ms: the same observation, one sleep of that length per frame."""
    slept = []
    monkeypatch.setattr("openfusion.encoders.delayed.time.sleep", slept.append)
    enc = region_encoder_from_section(SemanticSection(encoder="gt", encoder_delay_ms=250))
    assert isinstance(enc, DelayedRegionEncoder) and enc.needs_instances
    frame = _frame(1, 2)
    obs = enc.encode(frame)
    assert slept == [0.25]
    np.testing.assert_array_equal(obs.conf_maps, enc.inner.encode(frame).conf_maps)
    assert not isinstance(region_encoder_from_section(SemanticSection(encoder="gt")), DelayedRegionEncoder)


def test_input_size_is_a_setting_of_the_section(clip_dir, monkeypatch):
    """semantic.dense_input_long_side_px reaches the encoder: the tower sees that many px on the
    frame's longer side (rounded to patches). Bad input tried: a size below 16 px."""
    enc = region_encoder_from_section(SemanticSection(encoder="clip-dense", model_path=str(clip_dir), device="cpu",
                                                      dense_input_long_side_px=96))
    assert enc.input_long_side_px == 96
    seen = []
    runner = enc._runner((72, 96))
    monkeypatch.setitem(enc._runners, (72, 96), lambda px: seen.append(px.shape) or runner(px))
    obs = enc.encode(_frame(1, 2))
    assert seen == [(1, 3, 72, 96)] and obs.num_regions == 3
    assert SemanticSection(encoder="clip-dense").dense_input_long_side_px == 448  # the measured default
    with pytest.raises(ValueError, match="dense_input_long_side_px"):
        SemanticSection(encoder="clip-dense", dense_input_long_side_px=8)


def test_pooling_products_run_on_one_blas_thread(monkeypatch):
    """The pooling's small products must not wake BLAS's worker threads (they busy-wait afterwards
    and slow the next tower pass); the limit is lifted again after."""
    import contextlib

    from threadpoolctl import threadpool_info

    from openfusion.blas import single_thread_blas
    from openfusion.encoders import clip_dense

    def blas_threads() -> set[int]:
        return {i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"}

    before = blas_threads()
    inside = []

    @contextlib.contextmanager
    def watched():
        with single_thread_blas():
            inside.append(blas_threads())
            yield

    monkeypatch.setattr(clip_dense, "single_thread_blas", watched)
    rng = np.random.default_rng(3)
    pool_region_features(rng.random((4, 30, 40)).astype(np.float32), rng.normal(size=(5, 7, 12)).astype(np.float32))
    assert inside == [{1}]
    assert blas_threads() == before


def test_onnx_spinning_is_a_setting(clip_dir, tmp_path):
    """onnxruntime's busy-waiting: on by default (its own default, as clip-regions' crop embedder),
    off with semantic.encoder_onnx_spinning=false."""
    for spinning, want in ((True, "1"), (False, "0")):
        enc = region_encoder_from_section(SemanticSection(
            encoder="clip-dense", model_path=str(clip_dir), device="cpu", encoder_backend="onnx-int8",
            dense_input_long_side_px=64, encoder_onnx_spinning=spinning))
        enc.cache_dir = tmp_path
        options = enc._runner((48, 64)).session.get_session_options()
        assert options.get_session_config_entry("session.intra_op.allow_spinning") == want


def test_warm_up_builds_the_onnx_session_of_a_640x480_frame_before_the_first_frame(clip_dir, tmp_path):
    """The onnx backends export and load the tower per input size on first use (seconds for a
    real model): ``warm_up`` does it for the usual 640x480 camera, so that frame size's first
    frame reuses the session and a worker announces itself only when it is ready."""
    enc = make_region_encoder("clip-dense", model=str(clip_dir), device="cpu", backend="onnx",
                              input_long_side_px=64, cache_dir=tmp_path)
    assert enc._runners == {}
    enc.warm_up(["chair"])
    assert len(enc._runners) == 1
    runner = next(iter(enc._runners.values()))
    frame = make_box_frame(grid_boxes(height_px=480, width_px=640, rows=2, cols=2, categories=["x"], gap_px=8),
                           height_px=480, width_px=640)
    assert len(enc.encode(frame).embeddings) > 0
    assert list(enc._runners.values()) == [runner]  # the same session, nothing exported again
