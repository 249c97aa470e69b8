"""Relevancy (LERF: minimum over the negative phrases of a pairwise softmax) and ``match``
(openfusion.mapping.relevancy): the math, the calibration table and its record in map files, and
precision/recall of ``match`` on the held-out word list (openfusion.testing.word_lists) in the
MiniLM and hash spaces. The figures asserted are those docs/CLI.md reports
(``bench/bench_relevancy.py``).

Bad input tried: a non-positive temperature, no negatives, a saved calibration for another space
or with a threshold outside [0, 1] (ignored: the library's table answers)."""

from __future__ import annotations

import numpy as np
import pytest

from openfusion.encoders import make_text_encoder
from openfusion.mapping.relevancy import (
    CALIBRATIONS,
    DEFAULT_NEGATIVES,
    RelevancyScorer,
    calibration_for,
    evaluate_match,
    relevancy,
)
from openfusion.sources.synthetic import CATEGORIES
from openfusion.testing.word_lists import CALIBRATION, HELD_OUT


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


def test_calibrations_are_per_space_and_a_saved_one_wins_only_for_its_space() -> None:
    minilm = calibration_for("minilm-l6-v2")
    assert minilm is CALIBRATIONS["minilm-l6-v2"] and minilm.calibrated and minilm.negatives == DEFAULT_NEGATIVES
    assert 0.5 < minilm.threshold < 1 and minilm.margin == pytest.approx(0.0725, abs=1e-3)
    other = calibration_for("clip-vit-b-32")
    assert not other.calibrated and other.threshold == 0.5 and other.embedding_space == "clip-vit-b-32"
    saved = {**minilm.to_dict(), "threshold": 0.9}
    assert calibration_for("minilm-l6-v2", saved).threshold == 0.9
    assert calibration_for("hash-trigram-256", saved) is CALIBRATIONS["hash-trigram-256"]
    assert calibration_for("minilm-l6-v2", {**saved, "threshold": 1.5}) is minilm
    assert calibration_for("minilm-l6-v2", {"nonsense": 1}) is minilm


def _figures(encoder_name: str, word_list):  # noqa: ANN001, ANN202
    encoder = make_text_encoder(encoder_name, **({} if encoder_name == "hash" else {"device": "cpu"}))
    cal = calibration_for(encoder.embedding_space)
    cats = list(CATEGORIES)
    return evaluate_match(word_list, encoder.encode([q for q, _ in word_list]), cats, encoder.encode(cats),
                          encoder.encode(list(cal.negatives)), temperature=cal.temperature, threshold=cal.threshold)


def test_match_on_the_minilm_word_lists() -> None:
    """Calibration list: precision >= 0.95 (the target the threshold was chosen for), recall 0.955.
    Held-out list (never used to choose): precision 0.932, recall 0.872 (docs/CLI.md; the
    issue's targets are 0.95 / 0.90: not reached, see the docs for the misses)."""
    cal = _figures("minilm", CALIBRATION)
    assert cal.precision >= 0.95 and cal.recall >= 0.95
    held = _figures("minilm", HELD_OUT)
    assert held.precision >= 0.93 and held.recall >= 0.87, held.failures
    wrong = dict(held.failures)
    assert "kangaroo" not in wrong and "zebra" not in dict(cal.failures)  # unrelated words: no match


def test_match_on_the_hash_word_lists() -> None:
    """The lexical space matches near-exact words only: held-out precision 0.929, recall 0.553."""
    held = _figures("hash", HELD_OUT)
    assert held.precision >= 0.92 and held.recall >= 0.55
    assert "somewhere to sit" in dict(held.failures)  # no meaning in trigrams


def test_the_scorer_embeds_the_negatives_once_and_matches_at_the_threshold() -> None:
    text = make_text_encoder("hash")
    scorer = RelevancyScorer(text)
    regions = text.encode(["chair", "table"])
    rel = scorer.relevancy(text.encode(["chair", "zebra"]), regions)
    assert rel.shape == (2, 2)
    assert scorer.is_match(rel[0, 0]) and not scorer.is_match(rel[1]).any()
