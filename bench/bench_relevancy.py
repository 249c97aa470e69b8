#!/usr/bin/env python3
"""Calibrate ``match`` per embedding space and measure its precision and recall on held-out words.

For each text encoder (``minilm``, ``hash``): the synthetic scene's categories are embedded as
the gt encoder embeds regions (the category name). The threshold margin is chosen on the
development lists of ``openfusion.testing.word_lists`` pooled (``CALIBRATION``, ``HELD_OUT``,
``HELD_OUT_2``: all seen before, none judges): the highest recall at precision >= 0.96 (0.01 kept
in hand for the target 0.95), the middle of the margins that reach it (when none reaches 0.96:
the highest precision, then recall). ``cv P/R``: leave one development list out, choose on the
other two, measure on it; the three left-out lists counted together. Precision and recall are
judged on ``HELD_OUT_3`` (written and committed before any measurement on it), with the stored
calibration (:func:`openfusion.mapping.relevancy.evaluate_match`); each development list is
shown too (in-sample). Each space gets three rows measured in the same run, each calibrated by
the same rule: the library's method (LERF negatives and six query categories, v3), the five
categories of v2, and plain LERF (no query categories). The calibrated margin of the library's
method must equal the one stored in ``openfusion.mapping.relevancy.CALIBRATIONS``.
``--alternatives`` prints the development figures of the other formulations measured while
choosing (prompt templates, more categories, a genericness term, a per-map normalisation).

    HF_HUB_OFFLINE=1 .venv/bin/python bench/bench_relevancy.py
    HF_HUB_OFFLINE=1 .venv/bin/python bench/bench_relevancy.py --failures --alternatives
"""

from __future__ import annotations

import argparse
from dataclasses import replace

import numpy as np

from openfusion.encoders import make_text_encoder
from openfusion.mapping.relevancy import (
    CALIBRATIONS,
    SpaceCalibration,
    calibration_for,
    evaluate_match,
)
from openfusion.sources.synthetic import CATEGORIES
from openfusion.testing.word_lists import CALIBRATION, HELD_OUT, HELD_OUT_2, HELD_OUT_3, HELD_OUT_4

CHOOSE_AT_PRECISION = 0.96
#: The development lists (chosen on) and the judged one, in the order of the table's columns.
DEVELOPMENT = {"CALIBRATION": CALIBRATION, "HELD_OUT": HELD_OUT, "HELD_OUT_2": HELD_OUT_2}
DEV_POOL = CALIBRATION + HELD_OUT + HELD_OUT_2
MARGINS = np.round(np.arange(-0.3, 0.9, 0.0025), 4)
CATS = list(CATEGORIES)


def _margin_to_threshold(margin: float, temperature: float) -> float:
    return float(1.0 / (1.0 + np.exp(-margin / temperature)))


def _unit(a: np.ndarray) -> np.ndarray:
    a = np.atleast_2d(np.asarray(a, np.float64))
    return a / np.maximum(np.linalg.norm(a, axis=1, keepdims=True), 1e-12)


class Space:
    """One encoder's embeddings of the scene, the lists and the phrases (each text once)."""

    def __init__(self, name: str) -> None:
        self.encoder = make_text_encoder(name, **({} if name == "hash" else {"device": "cpu"}))
        self._cache: dict[str, np.ndarray] = {}

    def vectors(self, texts: list[str]) -> np.ndarray:
        missing = [t for t in dict.fromkeys(texts) if t not in self._cache]
        if missing:
            self._cache.update(zip(missing, np.asarray(self.encoder.encode(missing), np.float64), strict=True))
        return np.stack([self._cache[t] for t in texts]) if texts else np.zeros((0, self.encoder.dim))

    def figures(self, word_list, cal: SpaceCalibration, queries: np.ndarray | None = None):  # noqa: ANN001, ANN201
        q = self.vectors([t for t, _ in word_list]) if queries is None else queries
        return evaluate_match(word_list, q, CATS, self.vectors(CATS), self.vectors(list(cal.negatives)),
                              temperature=cal.temperature, threshold=cal.threshold,
                              query_category_vectors=self.vectors(list(cal.query_categories)))


def margin_matrix(space: Space, cal: SpaceCalibration, word_list=DEV_POOL, queries=None):  # noqa: ANN001, ANN201
    """(cosines, margins) of each query of ``word_list`` against each category: relevancy >= the
    threshold of margin m exactly when the margin >= m (``relevancy`` is a sigmoid of it)."""
    q = _unit(space.vectors([t for t, _ in word_list]) if queries is None else queries)
    r, n = _unit(space.vectors(CATS)), _unit(space.vectors(list(cal.negatives)))
    bar = np.broadcast_to((n @ r.T).max(0)[None, :], (len(q), len(r)))
    if cal.query_categories:
        bar = np.maximum(bar, (q @ _unit(space.vectors(list(cal.query_categories))).T).max(1)[:, None])
    return q @ r.T, q @ r.T - bar


def counts(cosines: np.ndarray, margins: np.ndarray, grid: np.ndarray, word_list=DEV_POOL):  # noqa: ANN001, ANN201
    """(right answers, answers with a match, positives) on ``word_list`` for every margin of
    ``grid`` at once, scored as :func:`evaluate_match` scores (the first region by cosine whose
    margin reaches the threshold): along each query's cosine order the running maximum of the
    margins says where the first match is for any threshold (hand-written because evaluating 480
    thresholds one by one takes minutes on a busy machine)."""
    correct = np.zeros(len(grid))
    reported = np.zeros(len(grid))
    positives = 0
    for i, (_text, wanted) in enumerate(word_list):
        order = np.argsort(-cosines[i], kind="stable")
        running = np.maximum.accumulate(margins[i, order])
        first = np.searchsorted(running, grid, side="left")  # index into order; len(order): no match
        reported += first < len(order)
        right = np.array([CATS[order[j]] in wanted for j in range(len(order))] + [False])
        correct += right[first]
        positives += bool(wanted)
    return correct, reported, positives


def sweep(cosines: np.ndarray, margins: np.ndarray, grid: np.ndarray, word_list=DEV_POOL):  # noqa: ANN001, ANN201
    """(precision, recall) on ``word_list`` for every margin of ``grid`` (:func:`counts`)."""
    correct, reported, positives = counts(cosines, margins, grid, word_list)
    return np.where(reported > 0, correct / np.maximum(reported, 1), 1.0), correct / positives


def _choose(precision: np.ndarray, recall: np.ndarray) -> int:
    """Index into MARGINS by the rule of the module docstring."""
    ok = precision >= CHOOSE_AT_PRECISION
    if not ok.any():
        return max(range(len(MARGINS)), key=lambda k: (precision[k], recall[k]))
    tied = np.flatnonzero(ok & (recall == recall[ok].max()))
    return int(tied[len(tied) // 2])


def calibrate(space: Space, cal: SpaceCalibration) -> float:
    """The margin chosen on the development lists pooled (module docstring)."""
    precision, recall = sweep(*margin_matrix(space, cal), MARGINS)
    i = _choose(precision, recall)
    m = float(MARGINS[i])
    figures = space.figures(DEV_POOL, replace(cal, threshold=_margin_to_threshold(m, cal.temperature)))
    assert abs(figures.recall - recall[i]) < 1e-9, "sweep and evaluate_match disagree"
    return m


def cross_validated(space: Space, cal: SpaceCalibration) -> tuple[float, float]:
    """Leave one development list out, choose on the other two, count on it; (precision, recall)
    of the three left-out lists together."""
    per_list = {name: counts(*margin_matrix(space, cal, wl), MARGINS, wl) for name, wl in DEVELOPMENT.items()}
    right = answered = positives = 0
    for left_out in DEVELOPMENT:
        rest = [c for name, c in per_list.items() if name != left_out]
        correct, reported, pos = (sum(c[k] for c in rest) for k in range(3))
        i = _choose(np.where(reported > 0, correct / np.maximum(reported, 1), 1.0), correct / pos)
        right += per_list[left_out][0][i]
        answered += per_list[left_out][1][i]
        positives += per_list[left_out][2]
    return right / max(answered, 1), right / positives


def alternatives(space: Space, stored: SpaceCalibration) -> None:
    """Development figures (pooled; the threshold rule of the module docstring) of other formulations."""
    texts = [t for t, _ in DEV_POOL]

    def templated(template_sets: list[str], items: list[str]) -> np.ndarray:
        return _unit(np.stack([_unit(space.vectors([tp.format(t) for tp in template_sets])).mean(0) for t in items]))

    def show(label: str, precision: np.ndarray, recall: np.ndarray) -> None:
        i = _choose(precision, recall)
        print(f"    {label:<58} margin {MARGINS[i]:+.4f}  dev P {precision[i]:.3f} R {recall[i]:.3f}")

    def row(label: str, cal: SpaceCalibration, queries: np.ndarray | None = None) -> None:
        show(label, *sweep(*margin_matrix(space, cal, DEV_POOL, queries), MARGINS))

    plain = replace(stored, query_categories=())
    row("plain LERF (4 negatives)", plain)
    row("chosen: + query categories " + "/".join(stored.query_categories), stored)
    for extra in (("weather", "musical instrument", "something"), ("electronics",), ("bathroom fixture",),
                  ("kitchen appliance",)):
        row("  + " + ", ".join(extra), replace(stored, query_categories=(*stored.query_categories, *extra)))
    for label, tmpl in (("query 'a photo of a {}.'", ["a photo of a {}."]),
                        ("query ensemble '{}', 'a photo of a {}.'", ["{}", "a photo of a {}."]),
                        ("query ensemble of 4 templates", ["{}", "a photo of a {}.", "a {} in a room.",
                                                            "there is a {} here."])):
        row("plain LERF, " + label, plain, templated(tmpl, texts))
        row("chosen, " + label, stored, templated(tmpl, texts))
    # a genericness term (CSLS-like) and a per-map normalisation, taken off plain LERF's margin:
    # the query's best cosine to a negative phrase, or its mean cosine over the scene's regions;
    # a term for the query's closeness to an in-room word, added to the chosen margin
    cosines, margins = margin_matrix(space, plain)
    q, n = _unit(space.vectors(texts)), _unit(space.vectors(list(stored.negatives)))
    for label, shift in (("plain LERF - 0.5 * max_i q.n_i", 0.5 * (q @ n.T).max(1)),
                         ("plain LERF - 0.5 * mean_r q.r (map)", 0.5 * cosines.mean(1))):
        show(label, *sweep(cosines, margins - shift[:, None], MARGINS))
    cosines, margins = margin_matrix(space, stored)
    for word in ("furniture", "household item"):
        show(f"chosen + 0.15 * q.'{word}'", *sweep(cosines, margins + 0.15 * (q @ _unit(space.vectors([word])).T),
                                                    MARGINS))
    # the two sides weighted apart: max(a * max_i n_i.r, max_j q.c_j + d)
    r = _unit(space.vectors(CATS))
    region_bar = (n @ r.T).max(0)[None, :]
    query_bar = (q @ _unit(space.vectors(list(stored.query_categories))).T).max(1)[:, None]
    for a, d in ((0.9, 0.0), (1.1, 0.05), (1.0, 0.025), (1.0, -0.025)):
        show(f"chosen, sides weighted: a = {a}, d = {d:+}", *sweep(
            cosines, cosines - np.maximum(a * region_bar, query_bar + d), MARGINS))


def _pr(figures) -> str:  # noqa: ANN001
    return f"{figures.precision:>6.3f} {figures.recall:>6.3f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--encoders", default="minilm,hash")
    parser.add_argument("--quick", action="store_true", help="(bench/run_all.py) the same run: about a minute of CPU")
    parser.add_argument("--full", action="store_true", help="(bench/run_all.py) the same run")
    parser.add_argument("--alternatives", action="store_true", help="other formulations (development lists only)")
    parser.add_argument("--failures", action="store_true", help="list the judged list's queries answered wrongly")
    args = parser.parse_args()
    print(f"judged: HELD_OUT_3 ({len(HELD_OUT_3)} queries), then HELD_OUT_4 ({len(HELD_OUT_4)}); development: " +
          ", ".join(f"{name} ({len(wl)})" for name, wl in DEVELOPMENT.items()) +
          f"; {len(CATEGORIES)} categories; threshold: best recall at pooled development precision >= "
          f"{CHOOSE_AT_PRECISION}")
    print(f"{'space':<18} {'method':<20} {'T':>5} {'margin':>7} {'stored':>7}  {'ho3 P':>6} {'ho3 R':>6}  "
          f"{'cv P':>6} {'cv R':>6}  {'dev P':>6} {'dev R':>6}  {'cal P':>6} {'cal R':>6}  {'ho1 P':>6} {'ho1 R':>6}  "
          f"{'ho2 P':>6} {'ho2 R':>6}")
    for name in args.encoders.split(","):
        space = Space(name)
        stored = calibration_for(space.encoder.embedding_space)
        v2 = replace(stored, query_categories=tuple(c for c in stored.query_categories if c != "appliance"))
        rows = (("v3 (library)", stored), ("v2: 5 categories", v2), ("plain LERF", replace(stored, query_categories=())))
        for method, cal in rows:
            margin = calibrate(space, cal)
            if cal is not stored:
                cal = replace(cal, threshold=_margin_to_threshold(margin, cal.temperature))
            known = "" if space.encoder.embedding_space in CALIBRATIONS else " (not in CALIBRATIONS)"
            stored_m = f"{cal.margin:>+7.4f}" if cal is stored else f"{'':>7}"
            cv_p, cv_r = cross_validated(space, cal)
            judged = space.figures(HELD_OUT_3, cal)
            judged_4 = space.figures(HELD_OUT_4, cal)
            dev = "  ".join(_pr(space.figures(wl, cal)) for wl in (DEV_POOL, *DEVELOPMENT.values()))
            print(f"{space.encoder.embedding_space:<18} {method:<20} {cal.temperature:>5.2f} {margin:>+7.4f} "
                  f"{stored_m}  {_pr(judged)}  {_pr(judged_4)}  {cv_p:>6.3f} {cv_r:>6.3f}  {dev}{known}")
            if args.failures and cal is stored:
                for list_name, figures in (("HELD_OUT_3", judged), ("HELD_OUT_4", judged_4)):
                    for text, first in figures.failures:
                        print(f"    {list_name} wrong: {text!r} -> {first or 'no match'}")
        if args.alternatives:
            alternatives(space, stored)


if __name__ == "__main__":
    main()
