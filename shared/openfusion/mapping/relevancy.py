"""Relevancy in [0, 1] and a calibrated ``match`` for ranked regions (the LERF formulation).

A raw cosine ``score`` has a scale that depends on the text encoder ("zebra" answers the plant
with 0.41 in MiniLM), so no fixed score threshold means "this is what you asked for". Following
LERF (Kerr et al. 2023), each region's relevancy to a query is measured against canonical
negative phrases: for each negative ``n``, a softmax over the pair (query·region, n·region)
gives the query's probability; the relevancy is the minimum over the negatives::

    relevancy(q, r) = min_i exp(q·r / T) / (exp(q·r / T) + exp(n_i·r / T))
                    = sigmoid((q·r - max_i n_i·r) / T)

(cosines of unit vectors). It is 0.5 exactly when the query is as close to the region as the
closest negative phrase, above 0.5 when the query beats every negative.

Temperature ``T``: LERF applies no temperature to CLIP cosines (``T = 1``), which squeezes every
relevancy into about [0.4, 0.6] and makes the number hard to read. We keep the formulation and
choose ``T`` per embedding space so that relevancy spreads over [0, 1]: MiniLM's margins
(query·region minus the best negative) run from about -0.1 (unrelated) to +0.5 (the class name
itself), so ``T = 0.05`` maps a margin of +0.2 (a synonym) to 0.98 and 0 to 0.5. ``T`` does not
change which regions match (a threshold on relevancy is a threshold on the margin); it only sets
how the number reads.

``match``: relevancy at or above a threshold calibrated per embedding space on the word lists of
:mod:`openfusion.testing.word_lists` (``CALIBRATION``; precision and recall reported on the
``HELD_OUT`` list, see ``bench/bench_relevancy.py`` and docs/CLI.md). The calibrations live in
:data:`CALIBRATIONS`, keyed by embedding-space id; :func:`save_map` records the one of the map's
space in the map file's header, and a saved map answers with the calibration it was saved with.
A space without a calibration gets :data:`FALLBACK` (``match`` = the query beats every negative,
relevancy 0.5), and says so in :attr:`SpaceCalibration.calibrated`.

Negatives: LERF's "object", "things", "stuff", "texture". Larger sets (generic words such as
"something", "an item"; broad out-of-room categories such as "animal", "vehicle", "food",
"landscape") and a greedy search over 42 candidate phrases did not raise recall at precision 0.95
on the calibration list for MiniLM, so the LERF set stays (measured by ``bench/bench_relevancy.py
--search``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

#: LERF's canonical negative phrases.
DEFAULT_NEGATIVES: tuple[str, ...] = ("object", "things", "stuff", "texture")


class _Encoder(Protocol):
    embedding_space: str

    def encode(self, texts: list[str]) -> np.ndarray: ...


@dataclass(frozen=True)
class SpaceCalibration:
    """How relevancy and ``match`` are computed in one embedding space."""

    embedding_space: str
    temperature: float
    threshold: float  # relevancy at or above it is a match
    negatives: tuple[str, ...] = DEFAULT_NEGATIVES
    calibrated: bool = True  # False: FALLBACK values for a space nobody calibrated
    note: str = ""

    @property
    def margin(self) -> float:
        """The threshold as a cosine margin over the best negative: ``T * logit(threshold)``."""
        t = min(max(self.threshold, 1e-9), 1 - 1e-9)
        return self.temperature * math.log(t / (1 - t))

    def to_dict(self) -> dict[str, Any]:
        return {"embedding_space": self.embedding_space, "temperature": self.temperature,
                "threshold": self.threshold, "negatives": list(self.negatives), "calibrated": self.calibrated}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> SpaceCalibration:
        temperature, threshold = float(data["temperature"]), float(data["threshold"])
        negatives = tuple(str(n) for n in data.get("negatives", DEFAULT_NEGATIVES))
        if not temperature > 0 or not 0.0 <= threshold <= 1.0 or not negatives:
            raise ValueError(f"bad relevancy calibration {data!r}")
        return cls(str(data["embedding_space"]), temperature, threshold, negatives,
                   bool(data.get("calibrated", True)))


def _threshold_for_margin(margin: float, temperature: float) -> float:
    return round(1.0 / (1.0 + math.exp(-margin / temperature)), 4)


#: Calibrations by embedding-space id (``bench/bench_relevancy.py`` measures them; the figures are
#: in docs/CLI.md). MiniLM: the margin 0.0725 gives the highest recall at precision >= 0.95 on the
#: calibration list. Hash trigrams are not semantic: the best threshold (margin 0.34, precision
#: 0.96 and recall 0.57 on the calibration list) keeps near-exact words only (the query shares
#: most trigrams with the region's text); its margins run over [-0.2, 0.9], hence T = 0.1.
CALIBRATIONS: dict[str, SpaceCalibration] = {
    "minilm-l6-v2": SpaceCalibration(
        "minilm-l6-v2", 0.05, _threshold_for_margin(0.0725, 0.05),
        note="margin 0.0725 over the best of the LERF negatives"),
    "hash-trigram-256": SpaceCalibration(
        "hash-trigram-256", 0.1, _threshold_for_margin(0.34, 0.1),
        note="lexical: near-exact words only"),
}

#: A space without calibration: the query must beat every negative phrase (LERF's 0.5).
FALLBACK = SpaceCalibration("", 0.05, 0.5, calibrated=False, note="uncalibrated space")


def calibration_for(space: str, saved: dict[str, Any] | None = None) -> SpaceCalibration:
    """The calibration of ``space``: ``saved`` (a map file's record) when it names that space,
    else the library's table, else :data:`FALLBACK` for that space."""
    if saved:
        try:
            cal = SpaceCalibration.from_dict(saved)
        except (KeyError, TypeError, ValueError):
            cal = None
        if cal is not None and cal.embedding_space == space:
            return cal
    known = CALIBRATIONS.get(space)
    if known is not None:
        return known
    return SpaceCalibration(space, FALLBACK.temperature, FALLBACK.threshold, FALLBACK.negatives, calibrated=False,
                            note=FALLBACK.note)


def _unit_rows(a: np.ndarray) -> np.ndarray:
    a = np.asarray(a, np.float64)
    if a.ndim == 1:
        a = a[None, :]
    norm = np.linalg.norm(a, axis=1, keepdims=True)
    return a / np.maximum(norm, 1e-12)


def relevancy(
    query_vectors: np.ndarray, region_embeddings: np.ndarray, negative_vectors: np.ndarray, *, temperature: float
) -> np.ndarray:
    """(q, r) relevancy of each query against each region (module docstring): the minimum over
    the negatives of the pairwise softmax, i.e. ``sigmoid((q·r - max_i n_i·r) / T)``. Vectors
    are normalised here; an empty region set gives a (q, 0) array."""
    if temperature <= 0:
        raise ValueError(f"temperature must be positive, got {temperature}")
    Q, R, N = _unit_rows(query_vectors), _unit_rows(region_embeddings), _unit_rows(negative_vectors)
    if R.shape[0] == 0 or np.asarray(region_embeddings).size == 0:
        return np.zeros((Q.shape[0], 0), np.float64)
    if len(N) == 0:
        raise ValueError("at least one negative phrase is needed")
    margin = Q @ R.T - (N @ R.T).max(axis=0)[None, :]
    return 1.0 / (1.0 + np.exp(-margin / float(temperature)))


class RelevancyScorer:
    """Relevancy and ``match`` for one text encoder's space: the negatives embedded once."""

    def __init__(self, encoder: _Encoder, calibration: SpaceCalibration | None = None) -> None:
        self.calibration = calibration or calibration_for(encoder.embedding_space)
        self._negatives = np.asarray(encoder.encode(list(self.calibration.negatives)), np.float32)

    @classmethod
    def of_vectors(cls, calibration: SpaceCalibration, negative_vectors: np.ndarray) -> RelevancyScorer:
        """A scorer from negatives the caller embedded (with its query texts, in one encoder call)."""
        scorer = object.__new__(cls)
        scorer.calibration = calibration
        scorer._negatives = np.asarray(negative_vectors, np.float32)
        if len(scorer._negatives) != len(calibration.negatives):
            raise ValueError(f"{len(calibration.negatives)} negative phrases but {len(scorer._negatives)} vectors")
        return scorer

    def relevancy(self, query_vectors: np.ndarray, region_embeddings: np.ndarray) -> np.ndarray:
        """(q, r) relevancy (:func:`relevancy`) with this space's negatives and temperature."""
        return relevancy(query_vectors, region_embeddings, self._negatives, temperature=self.calibration.temperature)

    def is_match(self, relevancy_values: np.ndarray | float) -> np.ndarray:
        return np.asarray(relevancy_values) >= self.calibration.threshold


@dataclass
class MatchFigures:
    """Precision and recall of ``match`` on a word list (:func:`evaluate_match`)."""

    precision: float
    recall: float
    positives: int  # queries that name something in the scene
    negatives: int  # queries that name nothing in it
    reported: int  # queries whose answer holds a match
    correct: int  # ... whose first matching region is one of the named categories
    failures: list[tuple[str, str | None]] = field(default_factory=list)  # (query, first match or None)


def evaluate_match(
    word_list: Sequence[tuple[str, Sequence[str]]],
    query_vectors: np.ndarray,
    categories: Sequence[str],
    category_vectors: np.ndarray,
    negative_vectors: np.ndarray,
    *,
    temperature: float,
    threshold: float,
) -> MatchFigures:
    """Precision and recall of ``match`` as a user meets it: each query ranks the scene's
    categories by cosine (one region per category, embedded as the gt encoder embeds regions);
    the query's answer is the first ranked region that is a match, or "no match".

    precision = answers whose first match is one of the query's categories / queries answered
    with a match (a match for "zebra" counts against it); recall = those right answers /
    queries that name something in the scene."""
    scores = _unit_rows(query_vectors) @ _unit_rows(category_vectors).T
    rel = relevancy(query_vectors, category_vectors, negative_vectors, temperature=temperature)
    reported = correct = positives = 0
    failures: list[tuple[str, str | None]] = []
    for i, (text, wanted) in enumerate(word_list):
        positives += bool(wanted)
        order = np.argsort(-scores[i], kind="stable")
        first = next((categories[j] for j in order if rel[i, j] >= threshold), None)
        reported += first is not None
        right = first is not None and first in wanted
        correct += right
        if (wanted and not right) or (not wanted and first is not None):
            failures.append((text, first))
    return MatchFigures(
        precision=correct / reported if reported else 1.0,
        recall=correct / positives if positives else 1.0,
        positives=positives,
        negatives=len(word_list) - positives,
        reported=reported,
        correct=correct,
        failures=failures,
    )
