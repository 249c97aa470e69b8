#!/usr/bin/env python3
"""Calibrate ``match`` per embedding space and measure its precision and recall on held-out words.

For each text encoder (``minilm``, ``hash``): the synthetic scene's categories are embedded as
the gt encoder embeds regions (the category name). The threshold margin is chosen on
``openfusion.testing.word_lists.CALIBRATION`` only: the highest recall at precision >= 0.97 (0.02
kept in hand for the held-out target 0.95), the middle of the margins that reach it (when none
reaches 0.97: the highest precision, then recall). Precision and recall are then measured with the
stored calibration on ``HELD_OUT_2`` (the list the target is judged on) and ``HELD_OUT``
(:func:`openfusion.mapping.relevancy.evaluate_match`). Each space gets two rows, measured in the
same run: the library's method (LERF negatives and query categories) and plain LERF (no query
categories, the method before), each calibrated by the same rule. The calibrated margin of the
library's method must equal the one stored in ``openfusion.mapping.relevancy.CALIBRATIONS``.
``--alternatives`` prints the calibration-list figures of the other formulations measured while
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
from openfusion.testing.word_lists import CALIBRATION, HELD_OUT, HELD_OUT_2

CHOOSE_AT_PRECISION = 0.97
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


def margin_matrix(space: Space, cal: SpaceCalibration, queries: np.ndarray | None = None):  # noqa: ANN201
    """(cosines, margins) of each CALIBRATION query against each category: relevancy >= the
    threshold of margin m exactly when the margin >= m (``relevancy`` is a sigmoid of it)."""
    q = _unit(space.vectors([t for t, _ in CALIBRATION]) if queries is None else queries)
    r, n = _unit(space.vectors(CATS)), _unit(space.vectors(list(cal.negatives)))
    bar = np.broadcast_to((n @ r.T).max(0)[None, :], (len(q), len(r)))
    if cal.query_categories:
        bar = np.maximum(bar, (q @ _unit(space.vectors(list(cal.query_categories))).T).max(1)[:, None])
    return q @ r.T, q @ r.T - bar


def sweep(cosines: np.ndarray, margins: np.ndarray, grid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Precision and recall on CALIBRATION for every margin of ``grid`` at once, scored as
    :func:`evaluate_match` scores (the first region by cosine whose margin reaches the threshold):
    along each query's cosine order the running maximum of the margins says where the first
    match is for any threshold (hand-written because evaluating 480 thresholds one by one takes
    minutes on a busy machine)."""
    correct = np.zeros(len(grid))
    reported = np.zeros(len(grid))
    positives = 0
    for i, (_text, wanted) in enumerate(CALIBRATION):
        order = np.argsort(-cosines[i], kind="stable")
        running = np.maximum.accumulate(margins[i, order])
        first = np.searchsorted(running, grid, side="left")  # index into order; len(order): no match
        found = first < len(order)
        reported += found
        right = np.array([CATS[order[j]] in wanted for j in range(len(order))] + [False])
        correct += right[first]
        positives += bool(wanted)
    precision = np.where(reported > 0, correct / np.maximum(reported, 1), 1.0)
    return precision, correct / positives


def calibrate(space: Space, cal: SpaceCalibration, queries: np.ndarray | None = None):  # noqa: ANN201
    """(margin, figures on CALIBRATION) by the rule of the module docstring."""
    precision, recall = sweep(*margin_matrix(space, cal, queries), MARGINS)
    ok = precision >= CHOOSE_AT_PRECISION
    if not ok.any():
        i = max(range(len(MARGINS)), key=lambda k: (precision[k], recall[k]))
    else:
        tied = np.flatnonzero(ok & (recall == recall[ok].max()))
        i = int(tied[len(tied) // 2])
    m = float(MARGINS[i])
    figures = space.figures(CALIBRATION, replace(cal, threshold=_margin_to_threshold(m, cal.temperature)), queries)
    assert abs(figures.recall - recall[i]) < 1e-9, "sweep and evaluate_match disagree"
    return m, figures


def alternatives(space: Space, stored: SpaceCalibration) -> None:
    """Calibration-list figures (the threshold rule of the module docstring) of other formulations."""
    texts = [t for t, _ in CALIBRATION]

    def templated(template_sets: list[str], items: list[str]) -> np.ndarray:
        return _unit(np.stack([_unit(space.vectors([tp.format(t) for tp in template_sets])).mean(0) for t in items]))

    def show(label: str, precision: np.ndarray, recall: np.ndarray) -> None:
        ok = precision >= CHOOSE_AT_PRECISION
        if not ok.any():
            print(f"    {label:<52} no margin reaches precision {CHOOSE_AT_PRECISION}")
            return
        i = int(np.flatnonzero(ok & (recall == recall[ok].max()))[0])
        print(f"    {label:<52} margin {MARGINS[i]:+.4f}  cal P {precision[i]:.3f} R {recall[i]:.3f}")

    def row(label: str, cal: SpaceCalibration, queries: np.ndarray | None = None) -> None:
        show(label, *sweep(*margin_matrix(space, cal, queries), MARGINS))

    plain = replace(stored, query_categories=())
    row("plain LERF (4 negatives)", plain)
    row("chosen: + query categories " + "/".join(stored.query_categories), stored)
    row("  + weather, musical instrument, something", replace(
        stored, query_categories=(*stored.query_categories, "weather", "musical instrument", "something")))
    for label, tmpl in (("query 'a photo of a {}.'", ["a photo of a {}."]),
                        ("query ensemble '{}', 'a photo of a {}.'", ["{}", "a photo of a {}."]),
                        ("query ensemble of 4 templates", ["{}", "a photo of a {}.", "a {} in a room.",
                                                            "there is a {} here."])):
        row("plain LERF, " + label, plain, templated(tmpl, texts))
        row("chosen, " + label, stored, templated(tmpl, texts))
    # a genericness term (CSLS-like) and a per-map normalisation, taken off plain LERF's margin:
    # the query's best cosine to a negative phrase, or its mean cosine over the scene's regions
    cosines, margins = margin_matrix(space, plain)
    q, n = _unit(space.vectors(texts)), _unit(space.vectors(list(stored.negatives)))
    for label, shift in (("plain LERF - 0.5 * max_i q.n_i", 0.5 * (q @ n.T).max(1)),
                         ("plain LERF - 0.5 * mean_r q.r (map)", 0.5 * cosines.mean(1))):
        show(label, *sweep(cosines, margins - shift[:, None], MARGINS))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--encoders", default="minilm,hash")
    parser.add_argument("--quick", action="store_true", help="(bench/run_all.py) the same run: about a minute of CPU")
    parser.add_argument("--full", action="store_true", help="(bench/run_all.py) the same run")
    parser.add_argument("--alternatives", action="store_true", help="other formulations (calibration list only)")
    parser.add_argument("--failures", action="store_true", help="list the held-out queries answered wrongly")
    args = parser.parse_args()
    print(f"{len(CALIBRATION)} calibration, {len(HELD_OUT_2)} held-out-2 and {len(HELD_OUT)} held-out queries, "
          f"{len(CATEGORIES)} categories; threshold: best recall at calibration precision >= {CHOOSE_AT_PRECISION}")
    print(f"{'space':<18} {'method':<17} {'T':>5} {'margin':>7} {'stored':>7}  {'cal P':>6} {'cal R':>6}  "
          f"{'ho2 P':>6} {'ho2 R':>6}  {'ho1 P':>6} {'ho1 R':>6}")
    for name in args.encoders.split(","):
        space = Space(name)
        stored = calibration_for(space.encoder.embedding_space)
        for method, cal in (("query categories", stored), ("plain LERF", replace(stored, query_categories=()))):
            margin, on_cal = calibrate(space, cal)
            if method == "plain LERF":
                cal = replace(cal, threshold=_margin_to_threshold(margin, cal.temperature))
            ho2, ho1 = space.figures(HELD_OUT_2, cal), space.figures(HELD_OUT, cal)
            known = "" if space.encoder.embedding_space in CALIBRATIONS else " (not in CALIBRATIONS)"
            stored_m = f"{cal.margin:>+7.4f}" if method != "plain LERF" else f"{'':>7}"
            print(f"{space.encoder.embedding_space:<18} {method:<17} {cal.temperature:>5.2f} {margin:>+7.4f} "
                  f"{stored_m}  {on_cal.precision:>6.3f} {on_cal.recall:>6.3f}  {ho2.precision:>6.3f} "
                  f"{ho2.recall:>6.3f}  {ho1.precision:>6.3f} {ho1.recall:>6.3f}{known}")
            if args.failures:
                for label, figs in (("held-out-2", ho2), ("held-out", ho1)):
                    for text, first in figs.failures:
                        print(f"    {label} wrong: {text!r} -> {first or 'no match'}")
        if args.alternatives:
            alternatives(space, stored)


if __name__ == "__main__":
    main()
