"""Relevancy (LERF: minimum of pairwise softmaxes against the negative phrases, region side, and
the contrast categories, query side) and ``match`` (openfusion.mapping.relevancy): the math, the
calibration table and its record in map files, and precision/recall of ``match`` on the word
lists (openfusion.testing.word_lists: chosen on CALIBRATION, HELD_OUT and HELD_OUT_2 pooled,
judged on HELD_OUT_3)
in the MiniLM and hash spaces. The figures asserted are those docs/CLI.md reports
(``bench/bench_relevancy.py``).

Bad input tried: a non-positive temperature, no negatives, a saved calibration for another space,
with a threshold outside [0, 1], unreadable, or made for the previous method (an older map's
record: ignored with a logged reason, the library's table answers); phrase vectors that do not
match the calibration's phrases."""

from __future__ import annotations

import numpy as np
import pytest

from openfusion.encoders import make_text_encoder
from openfusion.mapping.relevancy import (
    CALIBRATIONS,
    DEFAULT_NEGATIVES,
    DEFAULT_QUERY_CATEGORIES,
    METHOD,
    RelevancyScorer,
    calibration_for,
    evaluate_match,
    relevancy,
)
from openfusion.sources.synthetic import CATEGORIES
from openfusion.testing.word_lists import (
    CALIBRATION,
    HELD_OUT,
    HELD_OUT_2,
    HELD_OUT_3,
    HELD_OUT_4,
    HELD_OUT_5,
    HELD_OUT_6,
)


def test_relevancy_is_the_minimum_over_negatives_of_the_pairwise_softmax() -> None:
    rng = np.random.default_rng(0)
    q, r, n = rng.normal(size=(2, 8)), rng.normal(size=(5, 8)), rng.normal(size=(4, 8))
    unit = lambda a: a / np.linalg.norm(a, axis=1, keepdims=True)  # noqa: E731
    got = relevancy(q, r, n, temperature=0.1)
    qr, nr = unit(q) @ unit(r).T, unit(n) @ unit(r).T
    want = np.min(np.exp(qr[:, None, :] / 0.1) / (np.exp(qr[:, None, :] / 0.1) + np.exp(nr[None] / 0.1)), axis=1)
    np.testing.assert_allclose(got, want, rtol=1e-9)
    assert got.shape == (2, 5) and np.all((got > 0) & (got < 1))
    # as close as the best negative: 0.5 exactly, whatever the temperature
    np.testing.assert_allclose(relevancy(n[:1], r, n, temperature=3.0)[0] <= 0.5, True)
    assert relevancy(n[:1], n[:1], n[:1], temperature=0.05)[0, 0] == pytest.approx(0.5)
    # a lower temperature spreads the same margins further from 0.5
    assert abs(relevancy(q, r, n, temperature=0.01) - 0.5).min() >= abs(got - 0.5).min()
    with pytest.raises(ValueError, match="temperature"):
        relevancy(q, r, n, temperature=0.0)
    with pytest.raises(ValueError, match="negative"):
        relevancy(q, r, np.zeros((0, 8)), temperature=0.1)


def test_query_categories_are_pairwise_softmaxes_on_the_query_side() -> None:
    rng = np.random.default_rng(1)
    q, r, n, c = rng.normal(size=(3, 8)), rng.normal(size=(5, 8)), rng.normal(size=(4, 8)), rng.normal(size=(2, 8))
    unit = lambda a: a / np.linalg.norm(a, axis=1, keepdims=True)  # noqa: E731
    qr, nr, qc = unit(q) @ unit(r).T, unit(n) @ unit(r).T, unit(q) @ unit(c).T
    sm = lambda a, b: np.exp(a / 0.1) / (np.exp(a / 0.1) + np.exp(b / 0.1))  # noqa: E731
    want = np.minimum(sm(qr[:, None, :], nr[None]).min(axis=1), sm(qr[:, None, :], qc[:, :, None]).min(axis=1))
    got = relevancy(q, r, n, temperature=0.1, query_category_vectors=c)
    np.testing.assert_allclose(got, want, rtol=1e-9)
    assert np.all(got <= relevancy(q, r, n, temperature=0.1) + 1e-12)  # a category only lowers relevancy
    # a query that is its own category is as close to it as to any region can be: at most 0.5
    assert relevancy(c[:1], r, n, temperature=0.1, query_category_vectors=c).max() <= 0.5
    np.testing.assert_allclose(relevancy(q, r, n, temperature=0.1, query_category_vectors=np.zeros((0, 8))),
                               relevancy(q, r, n, temperature=0.1))


def test_calibrations_are_per_space_and_a_saved_one_wins_only_for_its_space_and_method(
    caplog: pytest.LogCaptureFixture,
) -> None:
    minilm = calibration_for("minilm-l6-v2")
    assert minilm is CALIBRATIONS["minilm-l6-v2"] and minilm.calibrated and minilm.negatives == DEFAULT_NEGATIVES
    assert minilm.query_categories == DEFAULT_QUERY_CATEGORIES and minilm.method == METHOD
    assert minilm.phrases == [*DEFAULT_NEGATIVES, *DEFAULT_QUERY_CATEGORIES]
    assert 0.5 < minilm.threshold < 1 and minilm.margin == pytest.approx(0.04, abs=1e-3)
    other = calibration_for("clip-vit-b-32")  # uncalibrated: plain LERF at 0.5, no text-to-text categories
    assert not other.calibrated and other.threshold == 0.5 and other.embedding_space == "clip-vit-b-32"
    assert other.query_categories == ()
    saved = {**minilm.to_dict(), "threshold": 0.9}
    assert calibration_for("minilm-l6-v2", saved).threshold == 0.9
    assert calibration_for("minilm-l6-v2", saved).query_categories == DEFAULT_QUERY_CATEGORIES
    caplog.set_level("INFO", logger="openfusion.mapping.relevancy")
    assert calibration_for("hash-trigram-256", saved) is CALIBRATIONS["hash-trigram-256"]
    assert "for space 'minilm-l6-v2'" in caplog.text
    assert calibration_for("minilm-l6-v2", {**saved, "threshold": 1.5}) is minilm
    assert calibration_for("minilm-l6-v2", {"nonsense": 1}) is minilm
    assert "unreadable" in caplog.text
    # a record from a map saved before the query categories (no "method" field): plain LERF
    # figures that would misjudge the new relevancy, so the library's calibration answers
    caplog.clear()
    legacy = {"embedding_space": "minilm-l6-v2", "temperature": 0.05, "threshold": 0.8079,
              "negatives": list(DEFAULT_NEGATIVES), "calibrated": True}
    assert calibration_for("minilm-l6-v2", legacy) is minilm
    assert "made for method 'lerf-v1'" in caplog.text
    # a record of v2 (five categories, margin 0.0725): another method, ignored the same way
    caplog.clear()
    v2 = {**legacy, "method": "lerf+query-categories-v2", "query_categories": list(DEFAULT_QUERY_CATEGORIES[:5])}
    assert calibration_for("minilm-l6-v2", v2) is minilm
    assert "made for method 'lerf+query-categories-v2'" in caplog.text


def test_the_word_lists_are_disjoint_and_name_only_scene_categories() -> None:
    """A held-out list judges only texts nothing was chosen on: no text (case and spacing
    ignored) is in two lists or twice in one, and every category named is one of the scene's."""
    lists = {"CALIBRATION": CALIBRATION, "HELD_OUT": HELD_OUT, "HELD_OUT_2": HELD_OUT_2, "HELD_OUT_3": HELD_OUT_3,
             "HELD_OUT_4": HELD_OUT_4, "HELD_OUT_5": HELD_OUT_5,
             "HELD_OUT_6": HELD_OUT_6}
    seen: dict[str, str] = {}
    for name, word_list in lists.items():
        for text, wanted in word_list:
            key = " ".join(text.lower().split())
            assert key not in seen, f"{text!r} of {name} is in {seen[key]} too"
            seen[key] = name
            assert set(wanted) <= set(CATEGORIES), (name, text, wanted)
    assert sum(map(len, lists.values())) == len(seen)


def test_the_scorer_needs_one_vector_per_phrase() -> None:
    cal = CALIBRATIONS["minilm-l6-v2"]
    with pytest.raises(ValueError, match="10 phrases but 4 vectors"):
        RelevancyScorer.of_vectors(cal, np.ones((4, 8)))


def _figures(encoder_name: str, word_list):  # noqa: ANN001, ANN202
    encoder = make_text_encoder(encoder_name, **({} if encoder_name == "hash" else {"device": "cpu"}))
    cal = calibration_for(encoder.embedding_space)
    cats = list(CATEGORIES)
    return evaluate_match(word_list, encoder.encode([q for q, _ in word_list]), cats, encoder.encode(cats),
                          encoder.encode(list(cal.negatives)), temperature=cal.temperature, threshold=cal.threshold,
                          query_category_vectors=encoder.encode(list(cal.query_categories)))


def _figures_at(encoder_name: str, word_list, precision: float, recall: float):  # noqa: ANN001, ANN202
    """:func:`_figures`, asserted to be the documented precision and recall (within 0.01)."""
    figures = _figures(encoder_name, word_list)
    assert figures.precision == pytest.approx(precision, abs=0.01) and figures.recall == pytest.approx(
        recall, abs=0.01), (figures.precision, figures.recall)
    return figures


def test_match_on_the_minilm_word_lists() -> None:
    """HELD_OUT_3 (written and committed before any measurement on it, the judged list):
    precision 0.810, recall 0.817 -- the issue's targets (0.95 / 0.90) are missed (docs/CLI.md
    says why). The development lists pooled, which chose the threshold (best recall at precision
    >= 0.96): 0.965 / 0.915."""
    judged = _figures_at("minilm", HELD_OUT_3, 0.810, 0.817)
    # the second judged list (written for a v4 that was not shipped; v3 never chose anything on it)
    _figures_at("minilm", HELD_OUT_4, 0.825, 0.808)
    dev = _figures_at("minilm", CALIBRATION + HELD_OUT + HELD_OUT_2, 0.965, 0.915)
    failures = dict(judged.failures) | dict(dev.failures)
    # unrelated words: no match, also those the LERF negatives alone let through ("car" -> plant)
    # and the one "appliance" took off ("refrigerator" -> cabinet)
    for text in ("zebra", "car", "kangaroo", "camel", "refrigerator", "owl", "democracy"):
        assert text not in failures, (text, failures.get(text))
    # paraphrases and synonyms find a region they name
    for text in ("something to sit on", "couch", "a place to sleep", "something green that grows"):
        assert text not in failures, (text, failures.get(text))


def test_match_on_the_hash_word_lists() -> None:
    """The lexical space matches near-exact words only: HELD_OUT_3 precision 0.942, recall 0.471;
    the development lists pooled 0.967 / 0.559."""
    judged = _figures_at("hash", HELD_OUT_3, 0.942, 0.471)
    _figures_at("hash", HELD_OUT_4, 0.906, 0.485)
    dev = _figures_at("hash", CALIBRATION + HELD_OUT + HELD_OUT_2, 0.967, 0.559)
    assert "something to rest on" in dict(judged.failures)  # no meaning in trigrams
    assert "zebra" not in dict(dev.failures)


def test_the_scorer_embeds_the_negatives_once_and_matches_at_the_threshold() -> None:
    text = make_text_encoder("hash")
    scorer = RelevancyScorer(text)
    regions = text.encode(["chair", "table"])
    rel = scorer.relevancy(text.encode(["chair", "zebra"]), regions)
    assert rel.shape == (2, 2)
    assert scorer.is_match(rel[0, 0]) and not scorer.is_match(rel[1]).any()
