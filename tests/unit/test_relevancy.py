"""Relevancy (LERF: minimum of pairwise softmaxes against the negative phrases, region side, and
the contrast categories, query side; v5: the query's head word must describe the region too) and
``match`` (openfusion.mapping.relevancy): the math, the head rule, the calibration table and its
record in map files, and precision/recall of ``match`` on the word lists
(openfusion.testing.word_lists: eight development lists, pooled they chose the thresholds, and
HELD_OUT_8, written blind, which judges v8) in the MiniLM and hash spaces, the scene's regions
embedded as the gt encoder embeds them (name and captions, openfusion.encoders.captions). The figures asserted are those docs/CLI.md reports
(``bench/bench_relevancy.py``).

Bad input tried: a non-positive temperature, no negatives, a saved calibration for another space,
with a threshold outside [0, 1], unreadable, or made for an earlier method (an older map's
record, v3's included: ignored with a logged reason, the library's table answers); phrase
vectors that do not match the calibration's phrases."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from openfusion.encoders import make_text_encoder
from openfusion.encoders.captions import region_text_embeddings
from openfusion.mapping.match_figures import evaluate_hits
from openfusion.mapping.relevancy import (
    BEST_SHARE,
    CALIBRATIONS,
    DEFAULT_NEGATIVES,
    DEFAULT_QUERY_CATEGORIES,
    HEAD_NAME_COS,
    METHOD,
    RelevancyScorer,
    SpaceCalibration,
    calibration_for,
    evaluate_match,
    list_margins,
    margins,
    match_mask,
    relevancy,
    relevancy_texts,
    text_margins,
)
from openfusion.sources.synthetic import CATEGORIES
from openfusion.testing.word_lists import CALIBRATION, HELD_OUT, HELD_OUT_2, HELD_OUT_3, HELD_OUT_4
from openfusion.testing.word_lists_blind import HELD_OUT_5, HELD_OUT_6, HELD_OUT_7, HELD_OUT_8


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
    assert 0.5 < minilm.threshold < 1 and minilm.margin == pytest.approx(0.085, abs=1e-3)
    assert minilm.head_name_cos == HEAD_NAME_COS and CALIBRATIONS["hash-trigram-256"].head_name_cos == HEAD_NAME_COS
    assert minilm.best_share == BEST_SHARE == CALIBRATIONS["hash-trigram-256"].best_share == 0.7
    assert SpaceCalibration.from_dict(minilm.to_dict()) == replace(minilm, note="")  # a map file keeps all but the note
    other = calibration_for("clip-vit-b-32")  # uncalibrated: plain LERF at 0.5, no text-to-text categories
    assert not other.calibrated and other.threshold == 0.5 and other.embedding_space == "clip-vit-b-32"
    assert other.query_categories == () and other.head_name_cos is None and other.best_share == BEST_SHARE
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
    # a map saved under v3 (six categories, margin 0.04, no head rule): ignored, v6's table answers
    caplog.clear()
    v3 = {**v2, "method": "lerf+query-categories-v3", "threshold": 0.69,
          "query_categories": list(DEFAULT_QUERY_CATEGORIES)}
    assert calibration_for("minilm-l6-v2", v3) is minilm and minilm.head_name_cos is not None
    assert "made for method 'lerf+query-categories-v3'" in caplog.text
    # maps saved under v5 (name cosine 0.7), v6 (threshold at precision >= 0.96) or v7 (name
    # regions, margin 0.0525): ignored the same way
    for old, name_cos, threshold in (("v5", 0.7, 0.928), ("v6", 0.8, 0.928), ("v7", 0.8, 0.741)):
        caplog.clear()
        record = {**minilm.to_dict(), "method": f"lerf+query-categories+head-{old}", "head_name_cos": name_cos,
                  "threshold": threshold}
        assert calibration_for("minilm-l6-v2", record) is minilm and minilm.head_name_cos == HEAD_NAME_COS
        assert f"made for method 'lerf+query-categories+head-{old}'" in caplog.text
    # a map saved under v8 (no share of the best: "chair" matched the table): ignored the same way
    caplog.clear()
    v8 = {**minilm.to_dict(), "method": "lerf+query-categories+head+captions-v8"}
    del v8["best_share"]
    assert calibration_for("minilm-l6-v2", v8) is minilm and minilm.best_share == BEST_SHARE
    assert "made for method 'lerf+query-categories+head+captions-v8'" in caplog.text
    # a share outside (0, 1] is unreadable
    caplog.clear()
    assert calibration_for("minilm-l6-v2", {**minilm.to_dict(), "best_share": 0.0}) is minilm
    assert calibration_for("minilm-l6-v2", {**minilm.to_dict(), "best_share": 1.5}) is minilm
    assert "unreadable" in caplog.text


def _scene(encoder_name: str, texts: list[str]):  # noqa: ANN202
    """The synthetic room's categories as regions, ``texts`` and their head-rule parts embedded."""
    encoder = make_text_encoder(encoder_name, **({} if encoder_name == "hash" else {"device": "cpu"}))
    wanted = list(dict.fromkeys(t for text in texts for t in [text, *relevancy_texts(text)]))
    return RelevancyScorer(encoder), list(CATEGORIES), region_text_embeddings(encoder.encode, CATEGORIES), dict(
        zip(wanted, encoder.encode(wanted), strict=True))


def _first_match(scorer: RelevancyScorer, cats: list[str], regions: np.ndarray, vectors, text: str):  # noqa: ANN001, ANN202
    """What a user meets: the first region by cosine whose relevancy is a match (None: no match)."""
    rel = scorer.text_relevancy(text, vectors, regions)
    cos = (vectors[text] / np.linalg.norm(vectors[text])) @ (regions / np.linalg.norm(regions, axis=1)[:, None]).T
    return next((cats[j] for j in np.argsort(-cos, kind="stable") if scorer.is_match(rel[j])), None)


def test_the_head_rule_asks_the_head_word_to_describe_the_region() -> None:
    """MiniLM embeds "wall clock" next to the wall and "a ceiling fan" next to the ceiling, close
    enough to match them; with the head rule they match nothing and "a seat at the desk" is a chair; a core that is nearly a
    region's own name keeps it ("trash can", whose head "can" alone is no bin; cosine 0.7);
    "a couple of" is dropped like a determiner; texts with no noun head are scored whole. (At
    v8's name cosine "window blinds" and "pillow fight" keep the window and the pillow:
    test_match_on_the_minilm_word_lists.)"""
    cases = {"a ceiling fan": None, "a desk fan": None, "wall clock": None,
             "monitor lizard": None, "a seat at the desk": "chair", "a light for the desk": "lamp",
             "trash can": "trash can", "office chair": "office chair", "the trash cans": "trash can",
             "something to sit on": "chair", "a place to sleep": "bed", "couch": "sofa", "zebra": None,
             "a couple of pillows": "pillow"}
    scorer, cats, regions, vectors = _scene("minilm", list(cases))
    got = {text: _first_match(scorer, cats, regions, vectors, text) for text in cases}
    assert got == cases
    # v3's scoring (the whole text only) answered the modifier's region
    compounds = ("a ceiling fan", "wall clock", "a desk fan", "monitor lizard")
    whole = {t: cats[int(np.argmax(scorer.relevancy(vectors[t], regions)[0]))] for t in compounds}
    assert whole == {"a ceiling fan": "ceiling", "wall clock": "wall", "a desk fan": "desk", "monitor lizard": "monitor"}
    assert all(scorer.is_match(scorer.relevancy(vectors[t], regions)).any() for t in compounds)


def test_text_margins_are_the_texts_without_a_head_rule_and_capped_by_the_head_with_it() -> None:
    rng = np.random.default_rng(2)
    r, n, c = rng.normal(size=(5, 8)), rng.normal(size=(4, 8)), rng.normal(size=(2, 8))
    vectors = {t: rng.normal(size=8) for t in ("the wall clock", "wall clock", "clock", "a seat at the desk", "seat")}
    assert relevancy_texts("the wall clock") == ["wall clock", "clock"] and relevancy_texts("chair") == []
    whole = margins(vectors["the wall clock"], r, n, c)[0]
    np.testing.assert_allclose(text_margins("the wall clock", vectors, r, n, c), whole)
    capped = text_margins("the wall clock", vectors, r, n, c, head_name_cos=2.0)  # no region is the name
    np.testing.assert_allclose(capped, np.minimum(whole, margins(vectors["clock"], r, n, c)[0]))
    # the core at least as close as the name cosine to every region: the text's margins
    np.testing.assert_allclose(text_margins("the wall clock", vectors, r, n, c, head_name_cos=-1.0), whole)
    # a post-modified text scores as its core
    np.testing.assert_allclose(text_margins("a seat at the desk", vectors, r, n, c, head_name_cos=0.7),
                               margins(vectors["seat"], r, n, c)[0])


def test_the_word_lists_are_disjoint_and_name_only_scene_categories() -> None:
    """A held-out list judges only texts nothing was chosen on: no text (case and spacing
    ignored) is in two lists or twice in one, and every category named is one of the scene's."""
    lists = {"CALIBRATION": CALIBRATION, "HELD_OUT": HELD_OUT, "HELD_OUT_2": HELD_OUT_2, "HELD_OUT_3": HELD_OUT_3,
             "HELD_OUT_4": HELD_OUT_4, "HELD_OUT_5": HELD_OUT_5,
             "HELD_OUT_6": HELD_OUT_6,
             "HELD_OUT_7": HELD_OUT_7, "HELD_OUT_8": HELD_OUT_8}
    seen: dict[str, str] = {}
    for name, word_list in lists.items():
        for text, wanted in word_list:
            key = " ".join(text.lower().split())
            assert key not in seen, f"{text!r} of {name} is in {seen[key]} too"
            seen[key] = name
            assert set(wanted) <= set(CATEGORIES), (name, text, wanted)
    assert sum(map(len, lists.values())) == len(seen)


def test_a_match_is_at_least_the_share_of_the_best_margin() -> None:
    """v9: among one query's regions, a match beats the threshold AND has at least ``best_share``
    of the best margin; the best always matches when it beats the threshold; without a share (v8)
    the threshold alone decides; a best margin <= 0 leaves the best (and its ties) alone."""
    t = 0.05
    threshold = 1 / (1 + np.exp(-0.085 / t))  # margin 0.085
    m = np.array([0.466, 0.413, 0.226, 0.092, 0.05])  # "chair": chair, office chair, sofa, table, floor
    assert match_mask(m, threshold=threshold, temperature=t, best_share=0.7).tolist() == [
        True, True, False, False, False]
    assert match_mask(m, threshold=threshold, temperature=t, best_share=None).tolist() == [
        True, True, True, True, False]
    assert match_mask(m[3:], threshold=threshold, temperature=t, best_share=0.7).tolist() == [True, False]
    assert match_mask(np.array([-0.1, -0.1, -0.2]), threshold=0.0, temperature=t, best_share=0.7).tolist() == [
        True, True, False]
    assert match_mask(np.zeros(0), threshold=threshold, temperature=t, best_share=0.7).shape == (0,)
    scorer = RelevancyScorer.of_vectors(CALIBRATIONS["minilm-l6-v2"], np.eye(10, 8))
    assert scorer.matches(m).tolist() == [True, True, False, False, False]
    np.testing.assert_allclose(scorer.relevancy_of(np.array([0.0])), [0.5])


#: Hit precision / recall / clean answers of ``match`` over the top 5 hits (MiniLM), v8 then v9,
#: on the five lists written before the blind ones (pooled) and each blind list: docs/CLI.md
#: ("v9") and bench/bench_relevancy.py print the same table. v9's share was chosen on the
#: built-in room (bench/bench_match_rule.py), on no list.
HITS_V8_V9 = {
    "CAL..HO4": ((0.573, 0.882, 0.483), (0.916, 0.877, 0.855)),
    "HELD_OUT_5": ((0.577, 0.771, 0.438), (0.869, 0.752, 0.743)),
    "HELD_OUT_6": ((0.584, 0.777, 0.466), (0.787, 0.767, 0.709)),
    "HELD_OUT_7": ((0.647, 0.748, 0.449), (0.852, 0.748, 0.682)),
    "HELD_OUT_8": ((0.574, 0.800, 0.448), (0.841, 0.790, 0.724)),
}


def test_match_over_every_returned_hit_before_and_after_the_share_of_the_best() -> None:
    """What a user reads: every hit marked ``match`` among the 5 returned. v8 marked about 4 in
    10 wrong on every list (furniture words match all the furniture); v9 (share of the best 0.7)
    keeps recall within 0.02 and raises hit precision by 0.2-0.34 on each list."""
    cal = calibration_for("minilm-l6-v2")
    cats = list(CATEGORIES)

    def enc(texts: list[str]) -> np.ndarray:
        return _encode("minilm", list(texts))

    regions = region_text_embeddings(enc, cats)
    lists = {"CAL..HO4": CALIBRATION + HELD_OUT + HELD_OUT_2 + HELD_OUT_3 + HELD_OUT_4, "HELD_OUT_5": HELD_OUT_5,
             "HELD_OUT_6": HELD_OUT_6, "HELD_OUT_7": HELD_OUT_7, "HELD_OUT_8": HELD_OUT_8}
    texts = list(dict.fromkeys(p for wl in lists.values() for q, _ in wl for p in (q, *relevancy_texts(q))))
    vectors = dict(zip(texts, enc(texts), strict=True))
    negatives, categories = enc(list(cal.negatives)), enc(list(cal.query_categories))
    for name, wl in lists.items():
        cosines, m = list_margins([q for q, _ in wl], np.stack([vectors[q] for q, _ in wl]), regions, negatives,
                                  query_category_vectors=categories, head_name_cos=cal.head_name_cos,
                                  part_vectors=vectors)
        for share, want in zip((None, cal.best_share), HITS_V8_V9[name], strict=True):
            f = evaluate_hits(wl, cosines, m, cats, threshold=cal.threshold, temperature=cal.temperature,
                              best_share=share)
            assert (f.hit_precision, f.recall, f.clean) == pytest.approx(want, abs=0.002), (name, share)
        if name == "CAL..HO4":
            wrong = dict(f.wrong)
            assert "chair" not in wrong and "something to sit on" not in wrong and "zebra" not in wrong
    with pytest.raises(ValueError, match="top_k"):
        evaluate_hits(wl, cosines, m, cats, threshold=0.5, temperature=0.05, best_share=None, top_k=0)


def test_the_scorer_needs_one_vector_per_phrase() -> None:
    cal = CALIBRATIONS["minilm-l6-v2"]
    with pytest.raises(ValueError, match="10 phrases but 4 vectors"):
        RelevancyScorer.of_vectors(cal, np.ones((4, 8)))


_ENCODERS: dict[str, object] = {}
_VECTORS: dict[tuple[str, str], np.ndarray] = {}


def _encode(encoder_name: str, texts: list[str]) -> np.ndarray:
    """``texts`` embedded by the named encoder, each text once per test module (MiniLM on the
    word lists is most of this module's time)."""
    encoder = _ENCODERS.get(encoder_name)
    if encoder is None:
        encoder = _ENCODERS[encoder_name] = make_text_encoder(
            encoder_name, **({} if encoder_name == "hash" else {"device": "cpu"}))
    missing = [t for t in dict.fromkeys(texts) if (encoder_name, t) not in _VECTORS]
    if missing:
        _VECTORS.update(((encoder_name, t), v) for t, v in zip(missing, encoder.encode(missing), strict=True))
    return np.stack([_VECTORS[encoder_name, t] for t in texts]) if texts else np.zeros((0, encoder.dim))


def _figures(encoder_name: str, word_list):  # noqa: ANN001, ANN202
    encoder = make_text_encoder(encoder_name, **({} if encoder_name == "hash" else {"device": "cpu"}))
    cal = calibration_for(encoder.embedding_space)
    cats = list(CATEGORIES)
    parts = list(dict.fromkeys(p for q, _ in word_list for p in relevancy_texts(q)))

    def enc(texts: list[str]) -> np.ndarray:
        return _encode(encoder_name, list(texts))

    return evaluate_match(word_list, enc([q for q, _ in word_list]), cats, region_text_embeddings(enc, cats),
                          enc(list(cal.negatives)), temperature=cal.temperature, threshold=cal.threshold,
                          query_category_vectors=enc(list(cal.query_categories)),
                          head_name_cos=cal.head_name_cos, part_vectors=dict(zip(parts, enc(parts), strict=True)),
                          best_share=cal.best_share)


def _figures_at(encoder_name: str, word_list, precision: float, recall: float):  # noqa: ANN001, ANN202
    """:func:`_figures`, asserted to be the documented precision and recall (within 0.01)."""
    figures = _figures(encoder_name, word_list)
    assert figures.precision == pytest.approx(precision, abs=0.01) and figures.recall == pytest.approx(
        recall, abs=0.01), (figures.precision, figures.recall)
    return figures


DEV_POOL = CALIBRATION + HELD_OUT + HELD_OUT_2 + HELD_OUT_3 + HELD_OUT_4 + HELD_OUT_5 + HELD_OUT_6 + HELD_OUT_7


def test_match_on_the_minilm_word_lists() -> None:
    """v8 on the eight development lists, which chose its threshold (the best F1 pooled): pooled
    0.902 / 0.809, each list in sample as below (docs/CLI.md; leaving one list out, the bench:
    0.901 / 0.808; v7 as shipped, name regions: 0.892 / 0.745). Judged on HELD_OUT_8, written
    blind and committed before anything was measured on it: 0.875 / 0.733 (v7 as shipped on the
    same list: 0.880 / 0.629); with the head rule's commands dropped since (found on it, so in
    sample now): 0.882 / 0.781. The issue's targets (0.95 / 0.90) are missed."""
    dev = _figures_at("minilm", DEV_POOL, 0.902, 0.809)
    for word_list, p, r in ((CALIBRATION, 0.980, 0.960), (HELD_OUT, 0.976, 0.851), (HELD_OUT_2, 0.983, 0.906),
                            (HELD_OUT_3, 0.878, 0.827), (HELD_OUT_4, 0.880, 0.818), (HELD_OUT_5, 0.886, 0.743),
                            (HELD_OUT_6, 0.846, 0.748), (HELD_OUT_7, 0.839, 0.682), (HELD_OUT_8, 0.882, 0.781)):
        _figures_at("minilm", word_list, p, r)
    failures = dict(dev.failures)
    # unrelated words: no match, also those the LERF negatives alone let through ("car" -> plant),
    # the one "appliance" took off ("refrigerator" -> cabinet) and compounds the head rule takes
    # off ("a ceiling fan" -> ceiling, "pillow fight" -> pillow, "monitor lizard" -> monitor)
    for text in ("zebra", "car", "kangaroo", "camel", "refrigerator", "owl", "democracy", "a ceiling fan",
                 "a desk fan", "castle", "monitor lizard"):
        assert text not in failures, (text, failures.get(text))
    # paraphrases and synonyms find a region they name, the head rule's among them, and the
    # captions' (use and place: v7's name regions missed these)
    for text in ("something to sit on", "somewhere to sit", "couch", "a place to sleep", "houseplant",
                 "a seat at the desk", "a light for the desk", "where grandma takes her afternoon nap"):
        assert text not in failures, (text, failures.get(text))
    # what the balanced threshold lets through (docs/CLI.md): near-domain words and compounds
    assert [failures.get(t) for t in ("curtains", "a television", "window blinds", "pillow fight")] == [
        "window", "monitor", "window", "pillow"]


def test_match_on_the_hash_word_lists() -> None:
    """The lexical space matches near-exact words only: pooled 0.892 / 0.521, each list as below,
    HELD_OUT_8 judged (0.778 / 0.400 before the head rule dropped commands, at margin 0.18; v7 as
    shipped 0.822 / 0.352; now 0.800 / 0.457, in sample); "chair" still matches a region named
    "wooden chair" (a category without captions: its name alone)."""
    dev = _figures_at("hash", DEV_POOL, 0.892, 0.521)
    for word_list, p, r in ((CALIBRATION, 0.970, 0.640), (HELD_OUT, 0.879, 0.617), (HELD_OUT_2, 0.900, 0.562),
                            (HELD_OUT_3, 0.949, 0.538), (HELD_OUT_4, 0.853, 0.586), (HELD_OUT_5, 0.945, 0.495),
                            (HELD_OUT_6, 0.796, 0.417), (HELD_OUT_7, 0.824, 0.393), (HELD_OUT_8, 0.800, 0.457)):
        _figures_at("hash", word_list, p, r)
    assert "something to rest on" in dict(dev.failures)  # no meaning in trigrams
    assert "zebra" not in dict(dev.failures)
    text = make_text_encoder("hash")
    scorer = RelevancyScorer(text)
    vectors = dict(zip(["chair", "the chair"], text.encode(["chair", "the chair"]), strict=True))
    for query in vectors:
        assert scorer.is_match(scorer.text_relevancy(query, vectors, text.encode(["wooden chair"]))).all(), query


def test_the_scorer_embeds_the_negatives_once_and_matches_at_the_threshold() -> None:
    text = make_text_encoder("hash")
    scorer = RelevancyScorer(text)
    regions = text.encode(["chair", "table"])
    rel = scorer.relevancy(text.encode(["chair", "zebra"]), regions)
    assert rel.shape == (2, 2)
    assert scorer.is_match(rel[0, 0]) and not scorer.is_match(rel[1]).any()
