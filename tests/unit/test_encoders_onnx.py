"""The onnx backend: contract validation at load time and end-to-end runs of tiny random models."""

from __future__ import annotations

import json

import numpy as np
import pytest

from openfusion.encoders import EncoderError, make_region_encoder, make_text_encoder
from openfusion.encoders.clip_export import set_onnx_metadata
from openfusion.encoders.onnx_backend import OnnxRegionEncoder, _image_input
from openfusion.encoders.onnx_contract import EncoderContractError
from openfusion.testing.images import grid_boxes, make_box_frame
from openfusion.testing.models import build_tiny_region_onnx, build_tiny_text_onnx


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    d = tmp_path_factory.mktemp("onnx")
    return {
        "dir": d,
        "region": build_tiny_region_onnx(d / "region.onnx"),
        "region_logits": build_tiny_region_onnx(d / "region_logits.onnx", conf_logits=True, with_valid=False),
        "region_novalid": build_tiny_region_onnx(d / "region_novalid.onnx", with_valid=False),
        "text": build_tiny_text_onnx(d / "text"),
    }


@pytest.fixture(scope="module")
def frame():
    return make_box_frame(
        grid_boxes(height_px=480, width_px=640, rows=3, cols=4, categories=["x"], gap_px=10, seed=1)
    )


def test_region_model_end_to_end(models, frame):
    """A 640x480 frame through a 48x64-input model: maps come back at 160x120 in [0,1], embeddings
    unit-norm in the space the metadata names, and regions flagged invalid by the model are dropped."""
    enc = make_region_encoder("onnx", model_path=models["region"], device="cpu")
    assert isinstance(enc, OnnxRegionEncoder)
    assert (enc.name, enc.embedding_space, enc.dim) == ("onnx", "tiny-onnx-random", 16)
    assert enc.model.providers == ["CPUExecutionProvider"]
    obs = enc.encode(frame)
    obs.validate(dim=16)
    assert obs.conf_maps.shape[1:] == (120, 160)
    valid = enc.model.session.run(["valid"], _image_input(enc.model, frame))[0].reshape(-1)
    assert obs.num_regions == int(valid.sum()) and 0 < obs.num_regions < 6
    all_regions = make_region_encoder("onnx", model_path=models["region_novalid"], device="cpu").encode(frame)
    assert all_regions.num_regions == 6
    np.testing.assert_allclose(obs.conf_maps, all_regions.conf_maps[valid.astype(bool)], atol=1e-6)


def test_logit_outputs_are_turned_into_probabilities(models, frame):
    """conf_maps_are=logits: the encoder applies the sigmoid, so the same network exported with
    logits or probabilities gives the same confidence maps."""
    probs = make_region_encoder("onnx", model_path=models["region_novalid"], device="cpu").encode(frame)
    logits = make_region_encoder("onnx", model_path=models["region_logits"], device="cpu").encode(frame)
    np.testing.assert_allclose(logits.conf_maps, probs.conf_maps, atol=1e-5)
    np.testing.assert_allclose(logits.embeddings, probs.embeddings, atol=1e-5)


def test_text_model_end_to_end(models):
    """Text model + tokenizer.json: unit rows, and padding in a batch does not change a text's vector
    (the attention mask reaches the model)."""
    enc = make_text_encoder("onnx", model_path=models["text"], device="cpu")
    assert (enc.embedding_space, enc.dim) == ("tiny-onnx-random", 16)
    e = enc.encode(["chair", "a red office chair by the door"])
    assert e.shape == (2, 16) and e.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(e, axis=1), 1.0, atol=1e-5)
    np.testing.assert_allclose(enc.encode(["chair"])[0], e[0], atol=1e-5)
    assert not np.allclose(e[0], e[1])


def test_text_model_must_match_the_region_model(models):
    """A text model of another dimension or space than the region model is refused at load time."""
    with pytest.raises(EncoderContractError, match="dim 16 does not match the region encoder's 512"):
        make_text_encoder("onnx", model_path=models["text"], expect_dim=512)
    with pytest.raises(EncoderContractError, match="does not match the region encoder's 'clip-vit-b-32'"):
        make_text_encoder("onnx", model_path=models["text"], expect_space="clip-vit-b-32")


def test_wrong_output_name_is_named_in_the_error(tmp_path):
    """A model exporting 'masks' instead of 'conf_maps' fails at load, naming the missing output."""
    p = build_tiny_region_onnx(tmp_path / "bad.onnx", output_names=("masks", "embeddings"))
    with pytest.raises(EncoderContractError, match=r"output 'conf_maps' missing; the model's outputs are masks, embeddings"):
        make_region_encoder("onnx", model_path=p)


def test_wrong_rank_is_named_in_the_error(tmp_path):
    """Embeddings without the batch axis ([N,d] instead of [1,N,d]) are a rank error."""
    p = build_tiny_region_onnx(tmp_path / "bad.onnx", squeeze_embeddings=True)
    with pytest.raises(EncoderContractError, match=r"output 'embeddings' has rank 2 .* expected rank 3"):
        make_region_encoder("onnx", model_path=p)


def test_wrong_dim_is_named_in_the_error(tmp_path):
    """metadata dim that disagrees with the exported embedding size is refused (before any frame)."""
    p = build_tiny_region_onnx(tmp_path / "bad.onnx", metadata={"dim": 99})
    with pytest.raises(EncoderContractError, match=r"'embeddings' axis 2 is 16, expected 99 \(metadata dim\)"):
        make_region_encoder("onnx", model_path=p)


def test_metadata_problems_are_named(tmp_path, models):
    """Missing kind, missing normalisation, a broken sidecar and a wrong kind each get their own message."""
    p = build_tiny_region_onnx(tmp_path / "m.onnx", metadata={"kind": ""})
    with pytest.raises(EncoderContractError, match="metadata 'kind' is missing"):
        make_region_encoder("onnx", model_path=p)
    p = build_tiny_region_onnx(tmp_path / "n.onnx")
    (tmp_path / "n.json").write_text(json.dumps({"mean": ""}))
    with pytest.raises(EncoderContractError, match=r"metadata key\(s\) mean missing"):
        make_region_encoder("onnx", model_path=p)
    (tmp_path / "n.json").write_text("{not json")
    with pytest.raises(EncoderContractError, match="sidecar is not valid JSON"):
        make_region_encoder("onnx", model_path=p)
    (tmp_path / "n.json").write_text(json.dumps({"std": [0.5, 0.0, 0.5]}))
    with pytest.raises(EncoderContractError, match="std must be > 0"):
        make_region_encoder("onnx", model_path=p)
    with pytest.raises(EncoderContractError, match="expected region-model or crop-embedder"):
        make_region_encoder("onnx", model_path=models["text"])


def test_sidecar_supplies_and_overrides_metadata(tmp_path, frame):
    """A model exported without our metadata works once a sidecar JSON gives it."""
    p = build_tiny_region_onnx(tmp_path / "plain.onnx", metadata={"embedding_space": "", "kind": ""})
    (tmp_path / "plain.json").write_text(json.dumps({"kind": "region-model", "embedding_space": "my-space"}))
    enc = make_region_encoder("onnx", model_path=p, device="cpu")
    assert enc.embedding_space == "my-space"
    enc.encode(frame).validate(dim=16)


def test_unreadable_or_missing_files_are_clear_errors(tmp_path):
    """A path typo or a file that is not ONNX is reported with the path, not an onnxruntime traceback."""
    with pytest.raises(EncoderContractError, match="not found"):
        make_region_encoder("onnx", model_path=tmp_path / "nope.onnx")
    junk = tmp_path / "junk.onnx"
    junk.write_bytes(b"not a model")
    with pytest.raises(EncoderContractError, match="cannot load the model"):
        make_region_encoder("onnx", model_path=junk)
    with pytest.raises(EncoderError, match="model_path"):
        make_region_encoder("onnx")


def test_text_model_problems_are_named(tmp_path, models):
    """Text model: wrong output name, and a missing tokenizer file."""
    bad = build_tiny_text_onnx(tmp_path / "t1", output_name="embeddings")
    with pytest.raises(EncoderContractError, match="output 'text_embeddings' missing"):
        make_text_encoder("onnx", model_path=bad)
    ok = build_tiny_text_onnx(tmp_path / "t2")
    (tmp_path / "t2" / "tokenizer.json").unlink()
    with pytest.raises(EncoderContractError, match="tokenizer file .* not found"):
        make_text_encoder("onnx", model_path=ok)


def test_extra_model_input_is_refused(tmp_path):
    """An input the runtime cannot feed (here 'scale') is not part of the contract: refuse at load."""
    import onnx
    from onnx import TensorProto, helper

    inp = helper.make_tensor_value_info("crops", TensorProto.FLOAT, ["b", 3, 8, 8])
    extra = helper.make_tensor_value_info("scale", TensorProto.FLOAT, [1])
    out = helper.make_tensor_value_info("embeddings", TensorProto.FLOAT, ["b", 192])
    graph = helper.make_graph(
        [
            helper.make_node("Flatten", ["crops"], ["flat"], axis=1),
            helper.make_node("Mul", ["flat", "scale"], ["embeddings"]),
        ],
        "g",
        [inp, extra],
        [out],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 9  # what onnxruntime >= 1.17 reads
    p = tmp_path / "extra.onnx"
    onnx.save(model, str(p))
    set_onnx_metadata(p, {"kind": "crop-embedder", "embedding_space": "s", "dim": 192, "crop_size": 8, "mean": "0,0,0", "std": "1,1,1"})
    with pytest.raises(EncoderContractError, match=r"input\(s\) 'scale' are not part of the contract"):
        make_region_encoder("onnx", model_path=p)


def test_warm_up_runs_the_model_once_on_a_640x480_frame_and_changes_no_answer(models, frame):
    """onnxruntime allocates its arenas on the first run; ``warm_up`` makes that run on a blank
    camera-size frame before a worker announces itself, counts nothing, and the answers after it are
    those of an encoder that never warmed up."""
    cold = make_region_encoder("onnx", model_path=models["region"], device="cpu")
    enc = make_region_encoder("onnx", model_path=models["region"], device="cpu")
    runs: list[tuple[int, ...]] = []
    session = enc.model.session

    class CountingSession:
        def run(self, names, feeds):
            runs.append(feeds["image"].shape)
            return session.run(names, feeds)

        def __getattr__(self, name):
            return getattr(session, name)

    enc.model.session = CountingSession()
    enc.warm_up(["chair"])
    assert len(runs) == 1 and runs[0][0] == 1
    assert enc.stats == {"frames": 0, "regions": 0, "dropped_invalid": 0}
    warm, plain = enc.encode(frame), cold.encode(frame)
    np.testing.assert_array_equal(warm.conf_maps, plain.conf_maps)
    np.testing.assert_array_equal(warm.embeddings, plain.embeddings)
    assert enc.stats == cold.stats
