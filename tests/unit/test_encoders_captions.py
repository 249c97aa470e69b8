"""Captioned regions (openfusion.encoders.captions): what the gt encoder embeds for a region of a
known category, the table's shape, and what a user notices in the MiniLM space (paraphrases of
use and place find their region only with captions).

Bad input tried: an unknown ``region_text`` (the encoder and the service settings refuse it with
the known values)."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from openfusion.encoders import make_region_encoder, make_text_encoder
from openfusion.encoders.captions import CAPTION_NAME_WEIGHT, CAPTIONS, region_text_embeddings
from openfusion.encoders.gt import GroundTruthRegionEncoder
from openfusion.encoders.text_hash import HashTextEncoder
from openfusion.sources.synthetic_categories import CATEGORIES
from services.encoder.options import EncoderOptions


class _CountingEncoder:
    """A text encoder that records its calls (texts per call)."""

    def __init__(self) -> None:
        self.inner = HashTextEncoder(dim=64)
        self.calls: list[list[str]] = []

    def encode(self, texts: list[str]) -> np.ndarray:
        self.calls.append(list(texts))
        return self.inner.encode(texts)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def test_every_category_of_the_room_has_six_captions_and_nothing_else_has() -> None:
    assert set(CAPTIONS) == set(CATEGORIES)
    for name, captions in CAPTIONS.items():
        assert len(captions) == 6 and len(set(captions)) == 6, name
        assert all(4 <= len(c.split()) <= 14 for c in captions), name


def test_a_region_is_its_captions_mean_plus_half_its_name_and_an_unknown_category_its_name() -> None:
    enc = _CountingEncoder()
    got = region_text_embeddings(enc.encode, ["sofa", "wooden chair", "sofa"])
    assert len(enc.calls) == 1 and len(enc.calls[0]) == len(set(enc.calls[0])) == 2 + 6  # each text once, one call
    name, caps = enc.inner.encode(["sofa"])[0], enc.inner.encode(list(CAPTIONS["sofa"]))
    want = _unit(np.mean([_unit(c) for c in caps], axis=0) + CAPTION_NAME_WEIGHT * _unit(name))
    np.testing.assert_allclose(got[0], want, atol=1e-6)
    np.testing.assert_allclose(got[2], got[0])
    np.testing.assert_allclose(got[1], _unit(enc.inner.encode(["wooden chair"])[0]), atol=1e-6)
    assert got.dtype == np.float32 and np.allclose(np.linalg.norm(got, axis=1), 1.0, atol=1e-6)
    # names only: the table is ignored
    np.testing.assert_allclose(region_text_embeddings(enc.encode, ["sofa"], captions={})[0], _unit(name), atol=1e-6)


def test_the_gt_encoder_embeds_captions_by_default_and_names_on_request() -> None:
    text = HashTextEncoder(dim=64)
    captioned = GroundTruthRegionEncoder(text).category_embeddings(["bed", "wooden chair"])
    named = make_region_encoder("gt", text_encoder=text, region_text="name").category_embeddings(["bed", "wooden chair"])
    np.testing.assert_allclose(named, text.encode(["bed", "wooden chair"]), atol=1e-6)
    np.testing.assert_allclose(captioned[1], named[1], atol=1e-6)  # no captions for it: its name
    assert float(captioned[0] @ named[0]) < 0.99  # the bed's captions moved it
    with pytest.raises(ValueError, match="region_text must be one of"):
        GroundTruthRegionEncoder(text, region_text="captions")
    with pytest.raises(ValidationError, match="unknown region_text 'label'"):
        EncoderOptions(region_text="label")
    assert EncoderOptions().region_text == "caption"


def test_paraphrases_of_use_and_place_find_their_region_with_captions_and_not_with_names() -> None:
    """What the captions are for (MiniLM, the room's 19 categories): texts with no word of their
    region's name. With names alone their closest region is the wrong one."""
    minilm = make_text_encoder("minilm", device="cpu")
    cases = {"a place to keep my clothes": "cabinet", "a place to do my homework": "desk",
             "the thing above my head": "ceiling", "the glass that lets light in": "window"}
    queries = minilm.encode(list(cases))
    cats = list(CATEGORIES)
    captioned = region_text_embeddings(minilm.encode, cats)
    named = region_text_embeddings(minilm.encode, cats, captions={})
    assert [cats[int(np.argmax(captioned @ q))] for q in queries] == list(cases.values())
    assert all(cats[int(np.argmax(named @ q))] != want for q, want in zip(queries, cases.values(), strict=True))
