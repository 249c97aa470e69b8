"""Text encoders: MiniLM (semantic, offline) and the hashed-trigram baseline."""

from __future__ import annotations

import numpy as np
import pytest

from openfusion.encoders import EncoderError, make_region_encoder, make_text_encoder
from openfusion.encoders.captions import region_text_embeddings
from openfusion.testing.images import PixelRect, make_box_frame

CATALOGUE = [
    "chair", "table", "sofa", "bed", "bookshelf", "cabinet", "lamp", "monitor",
    "plant", "door", "picture", "wall", "floor", "ceiling",
]  # fmt: skip


@pytest.fixture(scope="module")
def minilm():
    return make_text_encoder("minilm", device="cpu")


def test_minilm_ranks_chair_closest_to_office_chair(minilm):
    """A region labelled "office chair" must be scored as the class "chair" (the gt protocol relies on
    the text space putting raw categories near their benchmark class)."""
    classes = minilm.encode(CATALOGUE)
    query = minilm.encode(["office chair"])[0]
    scores = classes @ query
    assert CATALOGUE[int(np.argmax(scores))] == "chair"
    ranked = [CATALOGUE[i] for i in np.argsort(-scores)]
    assert ranked.index("chair") == 0 and scores.max() > 0.7


def test_minilm_output_contract(minilm):
    """(k, 384) float32 unit rows in space minilm-l6-v2; same text -> same vector across batches."""
    assert minilm.embedding_space == "minilm-l6-v2" and minilm.dim == 384
    e = minilm.encode(["a lamp", "lamp", "a red sofa"])
    assert e.shape == (3, 384) and e.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(e, axis=1), 1.0, atol=1e-5)
    np.testing.assert_allclose(minilm.encode(["lamp"])[0], e[1], atol=1e-5)
    assert minilm.encode([]).shape == (0, 384)


def test_text_encoders_reject_bad_input(minilm):
    """A bare string (a common slip: encode("chair")), empty strings and non-strings are refused clearly."""
    for enc in (minilm, make_text_encoder("hash")):
        with pytest.raises(EncoderError, match="single string"):
            enc.encode("chair")
        with pytest.raises(EncoderError, match="text 1 is empty"):
            enc.encode(["chair", "  "])
        with pytest.raises(EncoderError, match="text 0 is int"):
            enc.encode([3])


def test_gt_embeddings_are_minilm_of_raw_category(minilm):
    """The gt encoder embeds the RAW category ("office chair": its name and captions), cached per
    category, in MiniLM space; ``region_text="name"``: the name alone."""
    frame = make_box_frame([PixelRect(1, "office chair", 0, 0, 32, 32), PixelRect(2, "office chair", 32, 32, 64, 64)],
                           height_px=64, width_px=64)
    enc = make_region_encoder("gt", text_encoder=minilm)
    obs = enc.encode(frame)
    assert obs.embedding_space == "minilm-l6-v2"
    np.testing.assert_allclose(obs.embeddings, np.repeat(region_text_embeddings(minilm.encode, ["office chair"]), 2,
                                                         axis=0), atol=1e-5)
    assert list(enc._embedding_cache) == ["office chair"]
    named = make_region_encoder("gt", text_encoder=minilm, region_text="name").encode(frame)
    np.testing.assert_allclose(named.embeddings, np.repeat(minilm.encode(["office chair"]), 2, axis=0), atol=1e-5)


def test_hash_encoder_is_lexical_and_deterministic():
    """The hashed baseline places shared-word phrases close and is stable across processes (blake2b)."""
    enc = make_text_encoder("hash", dim=256)
    e = enc.encode(["office chair", "chair", "ceiling", "office chair"])
    assert enc.embedding_space == "hash-trigram-256"
    assert e[0] @ e[1] > e[0] @ e[2]
    np.testing.assert_array_equal(e[0], e[3])
    np.testing.assert_allclose(np.linalg.norm(e, axis=1), 1.0, atol=1e-6)


def test_minilm_single_text_path_gives_the_batch_path_embedding(minilm):
    """A query (one text) takes the direct tokenize+forward path; its embedding must equal the one
    the same text gets inside a batch (the path maps use for class names), or rankings would shift."""
    texts = ["the red chair", "something to sit on", "a lamp next to the sofa"]
    batch = minilm.encode(texts)
    singles = np.concatenate([minilm.encode([t]) for t in texts])
    assert minilm._direct_path_ok()  # the fast path is the one being compared
    np.testing.assert_allclose(singles, batch, atol=1e-5)
    assert np.allclose(np.linalg.norm(singles, axis=1), 1.0, atol=1e-5)


# ------------------------------------------------------------------- MiniLM through onnxruntime

PHRASES = [
    "chair", "a chair", "something to sit on near the window", "x", "A Potted PLANT!", "  monitor  ",
    "été café naïve", "the 3 red sofas, 2 lamps & 1 bookshelf", "office chair", "where can I put my cup?",
]  # fmt: skip
LONG = "the quick brown fox jumps over the lazy dog " * 30  # over max_seq_length (256 tokens): truncated


def test_minilm_onnx_gives_the_sentence_transformers_embeddings(minilm, minilm_onnx_cache):
    """The onnxruntime + tokenizers path embeds like sentence-transformers (to 1e-4) in the same
    space, batched and one text at a time."""
    from openfusion.encoders.text_minilm_onnx import MiniLMOnnxTextEncoder

    lean = make_text_encoder("minilm", backend="onnxruntime", device="cpu", cache_dir=minilm_onnx_cache)
    assert isinstance(lean, MiniLMOnnxTextEncoder)
    assert (lean.embedding_space, lean.dim) == (minilm.embedding_space, minilm.dim)
    want = minilm.encode(PHRASES)
    got = lean.encode(PHRASES)
    assert got.shape == want.shape and got.dtype == np.float32
    np.testing.assert_allclose(got, want, atol=1e-4, rtol=0)
    for i in (0, 2, len(PHRASES) - 1):
        np.testing.assert_allclose(lean.encode([PHRASES[i]])[0], want[i], atol=1e-4, rtol=0)
    np.testing.assert_allclose(lean.encode([LONG]), minilm.encode([LONG]), atol=1e-4, rtol=0)
    small_batches = make_text_encoder("minilm", backend="onnxruntime", device="cpu", batch_size=3,
                                      cache_dir=minilm_onnx_cache)
    np.testing.assert_allclose(small_batches.encode(PHRASES), want, atol=1e-4, rtol=0)
    assert lean.encode([]).shape == (0, 384)
    with pytest.raises(EncoderError, match="text 1 is empty"):
        lean.encode(["chair", " "])


def test_minilm_onnx_uses_its_cache_and_falls_back_when_the_export_fails(
    minilm_onnx_cache, tmp_path, monkeypatch, caplog
):
    """With the export in the cache, no export runs; when the export fails (e.g. no torch), the
    encoder is sentence-transformers', a log line says so, and no partial file is left behind."""
    from openfusion.encoders import text_minilm_onnx
    from openfusion.encoders.text_minilm import MiniLMTextEncoder

    def broken_export(model_dir, out):
        out.write_bytes(b"half a model")
        raise ImportError("No module named 'torch'")

    monkeypatch.setattr(text_minilm_onnx, "export_minilm_onnx", broken_export)
    cached = make_text_encoder("minilm", backend="onnxruntime", device="cpu", cache_dir=minilm_onnx_cache)
    assert isinstance(cached, text_minilm_onnx.MiniLMOnnxTextEncoder)
    with caplog.at_level("WARNING", logger="openfusion.encoders.text_minilm_onnx"):
        fallback = make_text_encoder("minilm", backend="onnxruntime", device="cpu", cache_dir=tmp_path)
    assert type(fallback) is MiniLMTextEncoder
    assert "using sentence-transformers" in caplog.text and "torch" in caplog.text
    assert not list((tmp_path / text_minilm_onnx.CACHE_SUBDIR).glob("*.onnx*"))
    with pytest.raises(EncoderError, match="unknown MiniLM backend"):
        make_text_encoder("minilm", backend="tensorflow")
