"""clip-regions backend on a tiny random-weight CLIP built here, and its ONNX export."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from openfusion.encoders import EncoderError, make_region_encoder, make_text_encoder
from openfusion.encoders.clip_export import export_clip_to_onnx
from openfusion.encoders.clip_regions import DEFAULT_CLIP_MODEL, SPACE_FILE, ClipRegionEncoder
from openfusion.encoders.masks import area_downsample_labels
from openfusion.testing.images import grid_boxes, make_box_frame
from openfusion.testing.models import build_tiny_clip, build_tiny_mask_proposer_onnx


@pytest.fixture(scope="module")
def clip_dir(tmp_path_factory):
    return build_tiny_clip(tmp_path_factory.mktemp("clip") / "tiny-clip")


@pytest.fixture(scope="module")
def frame():
    return make_box_frame(
        grid_boxes(height_px=240, width_px=320, rows=2, cols=3, categories=["x"], gap_px=8, seed=2),
        height_px=240,
        width_px=320,
    )


@pytest.fixture(scope="module")
def exported(clip_dir, tmp_path_factory):
    return export_clip_to_onnx(str(clip_dir), tmp_path_factory.mktemp("clip_onnx"))


def test_clip_regions_end_to_end(clip_dir, frame):
    """Regions follow the objects (each box is covered by one proposal, IoU > 0.8) and carry unit
    embeddings in the space named by the model folder."""
    enc = make_region_encoder("clip-regions", model=str(clip_dir), device="cpu")
    assert isinstance(enc, ClipRegionEncoder)
    assert (enc.name, enc.embedding_space, enc.dim) == ("clip-regions", "tiny-clip-random", 16)
    obs = enc.encode(frame)
    obs.validate(dim=16)
    assert obs.conf_maps.shape == (7, 60, 80)  # 6 boxes + background
    assert obs.labels is None
    gt = area_downsample_labels(frame.instance, np.arange(1, 7), (60, 80)) >= 0.5
    props = obs.conf_maps >= 0.5
    for g in gt:
        iou = (g & props).sum(axis=(1, 2)) / (g | props).sum(axis=(1, 2))
        assert iou.max() > 0.8
    # different crops -> different embeddings (the crops reach the model)
    assert np.abs(obs.embeddings @ obs.embeddings.T - np.eye(7)).max() < 1.0 - 1e-4


def test_clip_text_and_image_queries(clip_dir, frame):
    """Text tower: unit rows in the same space, independent of batch padding; image query: (d,) unit."""
    enc = make_text_encoder("clip-regions", model=str(clip_dir), device="cpu")
    assert (enc.embedding_space, enc.dim) == ("tiny-clip-random", 16)
    e = enc.encode(["chair", "a photo of the red table"])
    assert e.shape == (2, 16)
    np.testing.assert_allclose(np.linalg.norm(e, axis=1), 1.0, atol=1e-5)
    np.testing.assert_allclose(enc.encode(["chair"])[0], e[0], atol=1e-5)
    region = make_region_encoder("clip-regions", model=str(clip_dir), device="cpu")
    q = region.encode_image(frame.color)
    assert q.shape == (16,) and abs(float(np.linalg.norm(q)) - 1.0) < 1e-5


def test_clip_loading_errors_are_clear(clip_dir, tmp_path):
    """Unknown embedding space, a missing folder and weights that cannot be fetched: each says what to do."""
    anonymous = shutil.copytree(clip_dir, tmp_path / "anonymous-clip")
    (anonymous / SPACE_FILE).unlink()
    with pytest.raises(EncoderError, match="pass embedding_space="):
        make_region_encoder("clip-regions", model=str(anonymous), device="cpu")
    named = make_text_encoder("clip", model=str(anonymous), device="cpu", embedding_space="my-clip")
    assert named.embedding_space == "my-clip"
    with pytest.raises(EncoderError, match="no such folder"):
        make_region_encoder("clip-regions", model=str(tmp_path / "missing"), device="cpu")
    with pytest.raises(EncoderError, match="cannot load CLIP weights"):
        make_text_encoder("clip", model="openfusion-tests/no-such-clip-model", device="cpu")


def test_export_to_onnx_matches_torch(clip_dir, exported, frame):
    """The exported crop-embedder + text model run through the onnx backend give the same regions and
    embeddings as the torch backend (so users can deploy CLIP without torch)."""
    torch_enc = make_region_encoder("clip-regions", model=str(clip_dir), device="cpu")
    onnx_enc = make_region_encoder("onnx", model_path=exported["image"], device="cpu")
    assert (onnx_enc.embedding_space, onnx_enc.dim) == (torch_enc.embedding_space, torch_enc.dim)
    a, b = torch_enc.encode(frame), onnx_enc.encode(frame)
    np.testing.assert_array_equal(a.conf_maps, b.conf_maps)
    np.testing.assert_allclose(a.embeddings, b.embeddings, atol=1e-4)
    texts = ["chair", "a photo of the red table", "zzz " * 40]  # the last one is truncated
    t_torch = make_text_encoder("clip", model=str(clip_dir), device="cpu").encode(texts)
    t_onnx = make_text_encoder("onnx", model_path=exported["text"], device="cpu", expect_space="tiny-clip-random")
    np.testing.assert_allclose(t_onnx.encode(texts), t_torch, atol=1e-4)


def test_onnx_crop_embedder_with_mask_proposer(exported, frame, tmp_path):
    """A SAM-style ONNX mask model replaces graph segmentation: masks at the output size, <= N regions."""
    masks = build_tiny_mask_proposer_onnx(tmp_path / "masks.onnx", num_masks=5)
    enc = make_region_encoder(
        "onnx", model_path=exported["image"], mask_model_path=masks, device="cpu", proposer_options={"min_region_px": 1}
    )
    obs = enc.encode(frame)
    obs.validate(dim=16)
    assert obs.conf_maps.shape[1:] == (60, 80) and 1 <= obs.num_regions <= 5
    with pytest.raises(EncoderError, match="mask-proposer"):
        make_region_encoder("onnx", model_path=exported["image"], mask_model_path=exported["text"], device="cpu")


@pytest.mark.slow
def test_real_clip_if_cached(frame):
    """With openai CLIP ViT-B/32 in the local HF cache: space clip-vit-b-32, 512-d, sensible text ranking."""
    try:
        text = make_text_encoder("clip", model=DEFAULT_CLIP_MODEL, device="cpu")
    except EncoderError as exc:
        pytest.skip(f"real CLIP not available offline: {exc}")
    assert (text.embedding_space, text.dim) == ("clip-vit-b-32", 512)
    e = text.encode(["a chair", "an office chair", "a ceiling"])
    assert e[1] @ e[0] > e[1] @ e[2]
    obs = make_region_encoder("clip-regions", model=DEFAULT_CLIP_MODEL, device="cpu").encode(frame)
    obs.validate(dim=512)


def test_export_script_cli(clip_dir, tmp_path, capsys):
    """scripts/export_clip_onnx.py: exports a folder model (exit 0, files written) and reports a
    model it cannot load with exit 1 and a message instead of a traceback."""
    import importlib.util
    from pathlib import Path

    root = next(p for p in Path(__file__).resolve().parents if (p / "pyproject.toml").is_file())
    script = root / "scripts" / "export_clip_onnx.py"
    spec = importlib.util.spec_from_file_location("export_clip_onnx", script)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    assert module.main([str(clip_dir), str(tmp_path / "out")]) == 0
    assert {p.name for p in (tmp_path / "out").iterdir()} >= {"clip_image.onnx", "clip_text.onnx", "tokenizer.json"}
    assert module.main([str(tmp_path / "missing"), str(tmp_path / "out2")]) == 1
    assert "export failed" in capsys.readouterr().err


def test_warm_up_runs_proposer_and_embedder_once_and_changes_no_answer(clip_dir, frame):
    """A worker warms up before it announces itself: the embedder sees one full batch of crops
    (the batch shape frames use), the proposer one frame, and the encoder's answers and counters
    are those of an encoder that never warmed up."""
    cold = make_region_encoder("clip-regions", model=str(clip_dir), device="cpu")
    enc = make_region_encoder("clip-regions", model=str(clip_dir), device="cpu")
    batches: list[tuple[int, ...]] = []
    proposals: list[tuple[int, int]] = []
    embed, propose = enc.embedder.embed_crops, enc.proposer.propose

    def counting_embed(crops):
        batches.append(crops.shape)
        return embed(crops)

    def counting_propose(f, out_hw):
        proposals.append(f.color.shape[:2])
        return propose(f, out_hw)

    enc.embedder.embed_crops, enc.proposer.propose = counting_embed, counting_propose
    enc.warm_up(["chair"])
    size = enc.embedder.crop_spec.size
    assert batches == [(enc.batch_size, 3, size, size)] and proposals == [(480, 640)]
    assert enc.stats == {"frames": 0, "regions": 0, "dropped_zero_embedding": 0}
    warm, plain = enc.encode(frame), cold.encode(frame)
    np.testing.assert_allclose(warm.embeddings, plain.embeddings, atol=1e-6)
    np.testing.assert_array_equal(warm.conf_maps, plain.conf_maps)
    assert enc.stats == cold.stats
