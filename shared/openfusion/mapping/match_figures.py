"""Precision and recall of ``match`` over every returned hit, as a user reads an answer.

:func:`openfusion.mapping.relevancy.evaluate_match` counts the first region of an answer that is a
match (v3-v8 were chosen and judged that way). A person reads the whole answer: every hit marked
``match`` says "this is what you asked for". :func:`evaluate_hits` counts that, on a word list
(:mod:`openfusion.testing.word_lists`) against the built-in room's categories, one region each:

- the answer is the ``top_k`` regions closest by cosine (5, what ``openfusion query``, the page
  and the Python client return unless told), each with its ``match``
  (:func:`~openfusion.mapping.relevancy.match_mask`, judged among all the categories, as the
  query service judges it among its :data:`~openfusion.mapping.answers.MATCH_POOL` closest);
- **hit precision** = matched hits whose category is one the text names / matched hits (every
  match for "zebra" counts against it);
- **recall** = texts naming something in the room whose answer holds at least one right match /
  such texts;
- **clean** = texts naming something whose answer holds a right match and no wrong one / such
  texts (what a user who trusts every ``match`` gets right).

A list names the categories a text may be answered with ("go to the desk" -> desk or table), so a
match on any of them is right; the lists have one region per category, so they cannot see two
instances of one (the built-in room's own test and ``bench/bench_match_rule.py`` do).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from openfusion.mapping.relevancy import match_mask

#: Hits an answer holds unless the user asks for another number (the CLI's, page's and client's default).
DEFAULT_TOP_K = 5


@dataclass
class HitFigures:
    """:func:`evaluate_hits` on one word list."""

    hit_precision: float
    recall: float
    clean: float
    matched_hits: int  # hits marked match, over every text
    right_hits: int  # ... whose category the text names
    positives: int  # texts that name something in the room
    wrong: list[tuple[str, list[str]]] = field(default_factory=list)  # (text, wrongly matched categories)

    @property
    def f1(self) -> float:
        p, r = self.hit_precision, self.recall
        return 2 * p * r / (p + r) if p + r > 0 else 0.0


def evaluate_hits(
    word_list: Sequence[tuple[str, Sequence[str]]],
    cosines: np.ndarray,
    margins: np.ndarray,
    categories: Sequence[str],
    *,
    threshold: float,
    temperature: float,
    best_share: float | None,
    top_k: int = DEFAULT_TOP_K,
    mask: np.ndarray | None = None,
) -> HitFigures:
    """Hit precision, recall and clean answers (module docstring) of ``word_list`` from its
    (texts, categories) ``cosines`` and ``margins``
    (:func:`openfusion.mapping.relevancy.list_margins`) with a calibration's ``threshold``,
    ``temperature`` and ``best_share``; ``mask`` (texts, categories): which are matches, for a
    rule other than :func:`~openfusion.mapping.relevancy.match_mask` (the bench's alternatives)."""
    if top_k < 1:
        raise ValueError(f"top_k must be >= 1, got {top_k}")
    matched = right = positives = with_right = clean = 0
    wrong: list[tuple[str, list[str]]] = []
    for i, (text, wanted) in enumerate(word_list):
        ok = mask[i] if mask is not None else match_mask(margins[i], threshold=threshold, temperature=temperature,
                                                         best_share=best_share)
        shown = np.argsort(-np.asarray(cosines[i]), kind="stable")[:top_k]
        hits = [categories[j] for j in shown if ok[j]]
        good = [c for c in hits if c in wanted]
        bad = [c for c in hits if c not in wanted]
        matched += len(hits)
        right += len(good)
        if wanted:
            positives += 1
            with_right += bool(good)
            clean += bool(good) and not bad
        if bad:
            wrong.append((text, bad))
    return HitFigures(
        hit_precision=right / matched if matched else 1.0,
        recall=with_right / positives if positives else 1.0,
        clean=clean / positives if positives else 1.0,
        matched_hits=matched,
        right_hits=right,
        positives=positives,
        wrong=wrong,
    )
