#!/usr/bin/env python3
"""Calibrate ``match`` per embedding space and measure its precision and recall on held-out words.

For each text encoder (``minilm``, ``hash``): the synthetic scene's categories are embedded as
the gt encoder embeds regions (the category name); the threshold margin is the one that gives the
highest recall at precision >= 0.95 on ``openfusion.testing.word_lists.CALIBRATION`` (when none
reaches 0.95: the highest precision, then recall); precision and recall are then measured on
``HELD_OUT`` with that threshold (:func:`openfusion.mapping.relevancy.evaluate_match`). The table
prints the calibrated margin and relevancy threshold next to the one stored in
``openfusion.mapping.relevancy.CALIBRATIONS`` (the two must agree) and the held-out figures.
``--search`` also tries larger negative sets (greedy, on the calibration list only).

    HF_HUB_OFFLINE=1 .venv/bin/python bench/bench_relevancy.py
    HF_HUB_OFFLINE=1 .venv/bin/python bench/bench_relevancy.py --search --failures
"""

from __future__ import annotations

import argparse

import numpy as np

from openfusion.encoders import make_text_encoder
from openfusion.mapping.relevancy import (
    CALIBRATIONS,
    DEFAULT_NEGATIVES,
    calibration_for,
    evaluate_match,
)
from openfusion.sources.synthetic import CATEGORIES
from openfusion.testing.word_lists import CALIBRATION, HELD_OUT

TARGET_PRECISION = 0.95
MARGINS = np.round(np.arange(-0.1, 0.6, 0.0025), 4)
#: Candidate negative phrases for ``--search``.
POOL = ("something", "an item", "a thing", "animal", "vehicle", "food", "landscape", "weather",
        "musical instrument", "person", "building", "a photo", "an image", "a room", "furniture", "nature",
        "sports", "a machine", "a tool", "clothing", "a toy", "fruit", "water", "sky", "metal", "wood",
        "plastic", "color", "shape", "outdoors", "indoors", "a city", "a place", "equipment", "material",
        "surface", "the background", "noise", "an animal", "a vehicle", "a plant", "a picture of something")


def _margin_to_threshold(margin: float, temperature: float) -> float:
    return 1.0 / (1.0 + np.exp(-margin / temperature))


def calibrate(encoder, negatives, temperature: float):  # noqa: ANN001, ANN201
    """(margin, figures on CALIBRATION) with the best recall at precision >= 0.95 (else best precision)."""
    cats = list(CATEGORIES)
    cat_vec, neg_vec = encoder.encode(cats), encoder.encode(list(negatives))
    q_vec = encoder.encode([q for q, _ in CALIBRATION])
    best = None
    for m in MARGINS:
        f = evaluate_match(CALIBRATION, q_vec, cats, cat_vec, neg_vec, temperature=temperature,
                           threshold=_margin_to_threshold(m, temperature))
        key = (f.precision >= TARGET_PRECISION, f.recall if f.precision >= TARGET_PRECISION else f.precision,
               f.recall)
        if best is None or key > best[0]:
            best = (key, float(m), f)
    return best[1], best[2]


def held_out(encoder, negatives, temperature: float, threshold: float):  # noqa: ANN001, ANN201
    cats = list(CATEGORIES)
    return evaluate_match(HELD_OUT, encoder.encode([q for q, _ in HELD_OUT]), cats, encoder.encode(cats),
                          encoder.encode(list(negatives)), temperature=temperature, threshold=threshold)


def search(encoder, temperature: float) -> None:  # noqa: ANN001
    negatives = list(DEFAULT_NEGATIVES)
    _m, f = calibrate(encoder, negatives, temperature)
    print(f"  search from {negatives}: calibration P {f.precision:.3f} R {f.recall:.3f}")
    for _ in range(4):
        trials = [(calibrate(encoder, [*negatives, p], temperature)[1], p) for p in POOL if p not in negatives]
        g, phrase = max(trials, key=lambda t: (t[0].precision >= TARGET_PRECISION, t[0].recall, t[0].precision))
        if (g.precision >= TARGET_PRECISION, g.recall) <= (f.precision >= TARGET_PRECISION, f.recall):
            print("  no candidate phrase raises calibration recall at precision 0.95: keep the set")
            return
        negatives.append(phrase)
        f = g
        print(f"  + {phrase!r}: calibration P {g.precision:.3f} R {g.recall:.3f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--encoders", default="minilm,hash")
    parser.add_argument("--quick", action="store_true", help="(bench/run_all.py) the same run: it takes seconds")
    parser.add_argument("--full", action="store_true", help="(bench/run_all.py) the same run")
    parser.add_argument("--search", action="store_true", help="try larger negative sets (calibration list only)")
    parser.add_argument("--failures", action="store_true", help="list the held-out queries answered wrongly")
    args = parser.parse_args()
    print(f"{len(CALIBRATION)} calibration queries, {len(HELD_OUT)} held-out queries, {len(CATEGORIES)} categories")
    header = (f"{'space':<18} {'T':>5} {'margin':>7} {'thresh':>7} {'stored':>7}  {'cal P':>6} {'cal R':>6}  "
              f"{'held P':>6} {'held R':>6}  (pos/neg held out)")
    print(header)
    for name in args.encoders.split(","):
        encoder = make_text_encoder(name, **({} if name == "hash" else {"device": "cpu"}))
        stored = calibration_for(encoder.embedding_space)
        margin, cal = calibrate(encoder, stored.negatives, stored.temperature)
        threshold = float(_margin_to_threshold(margin, stored.temperature))
        held = held_out(encoder, stored.negatives, stored.temperature, stored.threshold)
        known = "" if encoder.embedding_space in CALIBRATIONS else " (not in CALIBRATIONS)"
        print(f"{encoder.embedding_space:<18} {stored.temperature:>5.2f} {margin:>+7.4f} {threshold:>7.4f} "
              f"{stored.threshold:>7.4f}  {cal.precision:>6.3f} {cal.recall:>6.3f}  {held.precision:>6.3f} "
              f"{held.recall:>6.3f}  ({held.positives}/{held.negatives}){known}")
        if args.failures:
            for text, first in held.failures:
                print(f"    held out wrong: {text!r} -> {first or 'no match'}")
        if args.search:
            search(encoder, stored.temperature)


if __name__ == "__main__":
    main()
