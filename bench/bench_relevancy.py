#!/usr/bin/env python3
"""Calibrate ``match`` per embedding space and measure its precision and recall on the word lists.

For each text encoder (``minilm``, ``hash``): the synthetic scene's categories are embedded as
the gt encoder embeds regions (v8: name and captions, ``openfusion.encoders.captions``; the rows
of earlier methods: the name alone, as they were shipped). The threshold margin is chosen on the
development lists of ``openfusion.testing.word_lists`` pooled (:data:`DEVELOPMENT`: the eight
seen lists): the best F1 of precision and recall, the middle of the margins that reach it (v6
took the highest recall at precision >= 0.96; docs/CLI.md says why that changed). ``cv P/R``:
leave one development list out, choose on the others, measure on it; the left-out lists counted
together. Then each list's figures (in sample), and those of :data:`JUDGED` lists (written blind
before the method was measured on them: ``HELD_OUT_8`` judges v8): a new list is one line in
either dict. Each space gets rows measured in the same run: the library's method (v8: LERF
negatives, six query categories, the head rule, captioned regions), v8's regions without the head
rule and plain LERF on them calibrated by the same rule, and v7 and v3 as they were shipped (name
regions, their thresholds). The calibrated margin of the library's method must equal the one
stored in ``openfusion.mapping.relevancy.CALIBRATIONS``. A second table gives, per judged list,
what no threshold can beat: the share of positives whose closest region is a right one, and the
best recall at precision >= 0.95 over all thresholds. ``--alternatives`` prints the development
figures (pooled and left out) of the grid v8 was chosen on (captions' weight x name cosine), then,
on name regions, the head rule's variants and vocabulary contrasts of v5-v7 and the formulations
measured while v3 was chosen (prompt templates, more categories, a genericness term, a per-map
normalisation).

    HF_HUB_OFFLINE=1 .venv/bin/python bench/bench_relevancy.py
    HF_HUB_OFFLINE=1 .venv/bin/python bench/bench_relevancy.py --failures --alternatives
"""

from __future__ import annotations

import argparse
from dataclasses import replace

import numpy as np

from openfusion.encoders import make_text_encoder
from openfusion.encoders.captions import region_text_embeddings
from openfusion.eval.classes import NYU40_CLASSES
from openfusion.mapping.match_figures import DEFAULT_TOP_K, HitFigures, evaluate_hits
from openfusion.mapping.query_head import query_head
from openfusion.mapping.relevancy import (
    CALIBRATIONS,
    SpaceCalibration,
    calibration_for,
    evaluate_match,
    margins,
    match_mask,
    relevancy_texts,
    text_margins,
)
from openfusion.sources.synthetic import CATEGORIES
from openfusion.testing.word_lists import CALIBRATION, HELD_OUT, HELD_OUT_2, HELD_OUT_3, HELD_OUT_4
from openfusion.testing.word_lists_blind import HELD_OUT_5, HELD_OUT_6, HELD_OUT_7, HELD_OUT_8

#: The development lists (pooled, they choose; each is left out once in ``cv``), in the order of
#: the table's columns. A new list is one more line here.
DEVELOPMENT: dict[str, tuple[tuple[str, tuple[str, ...]], ...]] = {
    "CALIBRATION": CALIBRATION,
    "HELD_OUT": HELD_OUT,
    "HELD_OUT_2": HELD_OUT_2,
    "HELD_OUT_3": HELD_OUT_3,
    "HELD_OUT_4": HELD_OUT_4,
    "HELD_OUT_5": HELD_OUT_5,
    "HELD_OUT_6": HELD_OUT_6,
    "HELD_OUT_7": HELD_OUT_7,
}
#: Judged lists (written blind before the method was measured on them, never chosen on).
JUDGED: dict[str, tuple[tuple[str, tuple[str, ...]], ...]] = {"HELD_OUT_8": HELD_OUT_8}
DEV_POOL = tuple(q for wl in DEVELOPMENT.values() for q in wl)
#: The columns of the hits table: the five lists written before the blind ones (pooled; v9's
#: share was not chosen on any list), then each blind list (never tuned on).
HIT_COLUMNS: dict[str, tuple[tuple[str, tuple[str, ...]], ...]] = {
    "CAL..HO4 pooled": CALIBRATION + HELD_OUT + HELD_OUT_2 + HELD_OUT_3 + HELD_OUT_4,
    "HELD_OUT_5": HELD_OUT_5, "HELD_OUT_6": HELD_OUT_6, "HELD_OUT_7": HELD_OUT_7, "HELD_OUT_8": HELD_OUT_8,
}
MARGINS = np.round(np.arange(-0.3, 0.9, 0.0025), 4)
CATS = list(CATEGORIES)
#: v3 as it was shipped: chosen on the first three lists (margins per space).
V3_SHIPPED_MARGIN = {"minilm-l6-v2": 0.04, "hash-trigram-256": 0.3275}
#: v7 as it was shipped (name regions, head rule name cosine 0.8): margins per space.
V7_SHIPPED_MARGIN = {"minilm-l6-v2": 0.0525, "hash-trigram-256": 0.1875}


def _margin_to_threshold(margin: float, temperature: float) -> float:
    return float(1.0 / (1.0 + np.exp(-margin / temperature)))


def _unit(a: np.ndarray) -> np.ndarray:
    a = np.atleast_2d(np.asarray(a, np.float64))
    return a / np.maximum(np.linalg.norm(a, axis=1, keepdims=True), 1e-12)


class Space:
    """One encoder's embeddings of the scene, the lists and the phrases (each text once); the
    scene's regions embedded as the gt encoder does (``captioned``) or by name (v7 and before)."""

    def __init__(self, name: str, *, captioned: bool = True, weight: float | None = None) -> None:
        self.encoder = make_text_encoder(name, **({} if name == "hash" else {"device": "cpu"}))
        self._cache: dict[str, np.ndarray] = {}
        self.captioned, self.weight = captioned, weight

    def view(self, *, captioned: bool = True, weight: float | None = None) -> Space:
        """The same encoder and cache, with other regions (name only, or another captions' weight)."""
        other = object.__new__(Space)
        other.encoder, other._cache, other.captioned, other.weight = self.encoder, self._cache, captioned, weight
        return other

    def regions(self) -> np.ndarray:
        """(categories, d) region embeddings of the scene (:data:`CATS` order)."""
        kw = {} if self.weight is None else {"name_weight": self.weight}
        return region_text_embeddings(self.vectors, CATS, captions=None if self.captioned else {}, **kw)

    def vectors(self, texts: list[str]) -> np.ndarray:
        missing = [t for t in dict.fromkeys(texts) if t not in self._cache]
        if missing:
            self._cache.update(zip(missing, np.asarray(self.encoder.encode(missing), np.float64), strict=True))
        return np.stack([self._cache[t] for t in texts]) if texts else np.zeros((0, self.encoder.dim))

    def parts(self, word_list) -> dict[str, np.ndarray]:  # noqa: ANN001
        """The vectors of every text's head-rule parts (core noun phrase, head word)."""
        texts = [p for t, _ in word_list for p in relevancy_texts(t)]
        return dict(zip(texts, self.vectors(texts), strict=True))

    def figures(self, word_list, cal: SpaceCalibration, queries: np.ndarray | None = None):  # noqa: ANN001, ANN201
        q = self.vectors([t for t, _ in word_list]) if queries is None else queries
        return evaluate_match(word_list, q, CATS, self.regions(), self.vectors(list(cal.negatives)),
                              temperature=cal.temperature, threshold=cal.threshold,
                              query_category_vectors=self.vectors(list(cal.query_categories)),
                              head_name_cos=cal.head_name_cos, part_vectors=self.parts(word_list),
                              best_share=cal.best_share)

    def hits(self, word_list, cal: SpaceCalibration, top_k: int = DEFAULT_TOP_K) -> HitFigures:  # noqa: ANN001
        """Hit precision / recall / clean answers of ``match`` over the ``top_k`` returned hits."""
        cosines, m = margin_matrix(self, cal, word_list)
        return evaluate_hits(word_list, cosines, m, CATS, threshold=cal.threshold, temperature=cal.temperature,
                             best_share=cal.best_share, top_k=top_k)


def margin_matrix(space: Space, cal: SpaceCalibration, word_list=DEV_POOL, queries=None):  # noqa: ANN001, ANN201
    """(cosines, margins) of each query of ``word_list`` against each category: relevancy >= the
    threshold of margin m exactly when the margin >= m (``relevancy`` is a sigmoid of it). With
    ``queries`` (other vectors for the texts): no head rule."""
    texts = [t for t, _ in word_list]
    q = _unit(space.vectors(texts) if queries is None else queries)
    r, n = space.regions(), space.vectors(list(cal.negatives))
    c = space.vectors(list(cal.query_categories)) if cal.query_categories else None
    m = margins(q, r, n, c)
    if cal.head_name_cos is not None and queries is None:
        vectors = space.parts(word_list) | dict(zip(texts, q, strict=True))
        m = np.stack([text_margins(t, vectors, r, n, c, head_name_cos=cal.head_name_cos) for t in texts])
    return q @ _unit(r).T, m


def counts(cosines: np.ndarray, margins: np.ndarray, grid: np.ndarray, word_list=DEV_POOL,  # noqa: ANN001, ANN201
           best_share: float | None = None):
    """(right answers, answers with a match, positives) on ``word_list`` for every margin of
    ``grid`` at once, scored as :func:`evaluate_match` scores (the first region by cosine whose
    margin reaches the threshold, and with ``best_share`` that share of the text's best margin):
    along each query's cosine order the running maximum of the margins says where the first match
    is for any threshold (hand-written because evaluating 480 thresholds one by one takes minutes
    on a busy machine)."""
    correct = np.zeros(len(grid))
    reported = np.zeros(len(grid))
    positives = 0
    for i, (_text, wanted) in enumerate(word_list):
        order = np.argsort(-cosines[i], kind="stable")
        row = margins[i, order]
        if best_share is not None:  # below the share of the best: never a match, whatever the threshold
            best = row.max()
            row = np.where(row >= (best * best_share if best > 0 else best) - 1e-12, row, -np.inf)
        running = np.maximum.accumulate(row)
        first = np.searchsorted(running, grid, side="left")  # index into order; len(order): no match
        reported += first < len(order)
        right = np.array([CATS[order[j]] in wanted for j in range(len(order))] + [False])
        correct += right[first]
        positives += bool(wanted)
    return correct, reported, positives


def sweep(cosines: np.ndarray, margins: np.ndarray, grid: np.ndarray, word_list=DEV_POOL,  # noqa: ANN001, ANN201
          best_share: float | None = None):
    """(precision, recall) on ``word_list`` for every margin of ``grid`` (:func:`counts`)."""
    correct, reported, positives = counts(cosines, margins, grid, word_list, best_share)
    return np.where(reported > 0, correct / np.maximum(reported, 1), 1.0), correct / positives


def _choose(precision: np.ndarray, recall: np.ndarray) -> int:
    """Index into MARGINS by the rule of the module docstring: the highest F1 (the middle of the
    margins that reach it)."""
    f1 = np.where(precision + recall > 0, 2 * precision * recall / np.maximum(precision + recall, 1e-12), 0.0)
    tied = np.flatnonzero(f1 >= f1.max() - 1e-12)
    return int(tied[len(tied) // 2])


def calibrate(space: Space, cal: SpaceCalibration) -> float:
    """The margin chosen on the development lists pooled (module docstring)."""
    precision, recall = sweep(*margin_matrix(space, cal), MARGINS, best_share=cal.best_share)
    i = _choose(precision, recall)
    m = float(MARGINS[i])
    figures = space.figures(DEV_POOL, replace(cal, threshold=_margin_to_threshold(m, cal.temperature)))
    assert abs(figures.recall - recall[i]) < 1e-9, "sweep and evaluate_match disagree"
    return m


def _pooled_and_cv(matrix) -> tuple[int, tuple[float, float], tuple[float, float], dict]:  # noqa: ANN001
    """``matrix(word_list)`` -> (cosines, margins): the margin index chosen on the development
    lists pooled, its (precision, recall) there, the leave-one-list-out (precision, recall)
    (choose on the other lists, count on the one left out; the left-out lists counted together)
    and each list's counts."""
    per_list = {name: counts(*matrix(wl), MARGINS, wl) for name, wl in DEVELOPMENT.items()}
    correct, reported, pos = (sum(c[k] for c in per_list.values()) for k in range(3))
    precision = np.where(reported > 0, correct / np.maximum(reported, 1), 1.0)
    i = _choose(precision, correct / pos)
    right = answered = positives = 0
    for left_out in DEVELOPMENT:
        rest = [c for name, c in per_list.items() if name != left_out]
        c, r, p = (sum(x[k] for x in rest) for k in range(3))
        j = _choose(np.where(r > 0, c / np.maximum(r, 1), 1.0), c / p)
        right += per_list[left_out][0][j]
        answered += per_list[left_out][1][j]
        positives += per_list[left_out][2]
    return i, (precision[i], correct[i] / pos), (right / max(answered, 1), right / positives), per_list


def cross_validated(space: Space, cal: SpaceCalibration) -> tuple[float, float]:
    """Leave one development list out, choose on the others, count on it; (precision, recall)
    of the left-out lists together."""
    return _pooled_and_cv(lambda wl: margin_matrix(space, cal, wl))[2]


def variant_matrix(space: Space, cal: SpaceCalibration, word_list, *, name_cos: float = 2.0,  # noqa: ANN001, ANN201
                   cut: str = "core", compound: bool = True, delta: float = 0.0, vocab=None):  # noqa: ANN001
    """(cosines, margins) of a variant of the head rule (``alternatives``): ``cut`` "core" (v5:
    a post-modified text scores as its core), "min" (min of the text and its core), "none" (the
    text); ``compound``: the head word's margin (plus ``delta``) caps a core of several words
    except where cos(core, region) >= ``name_cos``; ``vocab`` (tau, qv): NYU40 class names as
    query-side contrasts where cos(name, region) < tau and cos(query, name) >= qv."""
    texts = [t for t, _ in word_list]
    r, n = space.regions(), space.vectors(list(cal.negatives))
    c = space.vectors(list(cal.query_categories))

    def of(t: str) -> np.ndarray:
        return margins(space.vectors([t]), r, n, c)[0]

    rows = []
    for t in texts:
        m, h = of(t), query_head(t)
        if h is not None:
            if h.cut and cut != "none":
                m = of(h.core) if cut == "core" else np.minimum(m, of(h.core))
            if compound and h.head != h.core:
                near = (_unit(space.vectors([h.core])) @ _unit(r).T)[0] >= name_cos
                m = np.where(near, m, np.minimum(m, of(h.head) + delta))
        rows.append(m)
    m = np.stack(rows)
    q = _unit(space.vectors(texts))
    if vocab is not None:
        tau, qv_min = vocab
        v = _unit(space.vectors([w for w in NYU40_CLASSES if not w.startswith("other")]))
        qv, vr = q @ v.T, v @ _unit(r).T
        bar = np.where((vr[None] < tau) & (qv[:, :, None] >= qv_min), qv[:, :, None], -9.0).max(1)
        m = np.minimum(m, q @ _unit(r).T - bar)
    return q @ _unit(r).T, m


def ceiling(space: Space, cal: SpaceCalibration, word_list) -> tuple[float, float]:  # noqa: ANN001
    """(share of positives whose closest region by cosine is one of theirs, best recall at
    precision >= 0.95 over every margin of the grid) on ``word_list``."""
    cosines, m = margin_matrix(space, cal, word_list)
    wanted = [w for _, w in word_list]
    pos = [i for i, w in enumerate(wanted) if w]
    top1 = float(np.mean([CATS[int(np.argmax(cosines[i]))] in wanted[i] for i in pos]))
    precision, recall = sweep(cosines, m, MARGINS, word_list, cal.best_share)
    ok = precision >= 0.95
    return top1, float(recall[ok].max()) if ok.any() else 0.0


def caption_alternatives(space: Space, stored: SpaceCalibration) -> None:
    """The grid v8 was chosen on (the best leave-one-list-out F1): the captions' weight against
    the name, and the head rule's name cosine (None: no head rule); regions by name last."""
    print("  v8's grid (captions' weight x name cosine; the best cv F1 chose v8):")
    for weight in (0.5, 0.7, 1.0, 1.5, None):
        view = space.view(weight=weight) if weight is not None else space.view(captioned=False)
        for name_cos in (0.6, 0.7, 0.8, None):
            cal = replace(stored, head_name_cos=name_cos)
            i, (p, r), (cp, cr), _ = _pooled_and_cv(lambda wl, v=view, c=cal: margin_matrix(v, c, wl))
            label = f"name weight {weight}" if weight is not None else "name regions"
            print(f"    {label + ', name cosine ' + str(name_cos):<58} margin {MARGINS[i]:+.4f}  dev P {p:.3f} "
                  f"R {r:.3f}  cv P {cp:.3f} R {cr:.3f}  cv F1 {2 * cp * cr / max(cp + cr, 1e-12):.3f}")


def alternatives(space: Space, stored: SpaceCalibration) -> None:
    """Development figures (pooled, and leave one list out; the threshold rule of the module
    docstring) of other formulations: the head rule's variants, then those measured for v3."""
    def show_matrix(label: str, matrix) -> None:  # noqa: ANN001
        i, (p, r), (cp, cr), _ = _pooled_and_cv(matrix)
        print(f"    {label:<58} margin {MARGINS[i]:+.4f}  dev P {p:.3f} R {r:.3f}  cv P {cp:.3f} R {cr:.3f}")

    v3 = replace(stored, head_name_cos=None)
    print("  on name regions (v3-v7):")
    show_matrix("v3: no head rule", lambda wl: margin_matrix(space, v3, wl))
    show_matrix(f"v7: head rule, name cosine {stored.head_name_cos}", lambda wl: margin_matrix(space, stored, wl))
    for label, kw in (("no name exception", {}), ("name cosine 0.6", {"name_cos": 0.6}),
                      ("name cosine 0.8", {"name_cos": 0.8}),
                      ("post-modified: min(text, core)", {"name_cos": 0.7, "cut": "min"}),
                      ("post-modifier only (no compound rule)", {"compound": False}),
                      ("compound rule only (no post-modifier cut)", {"name_cos": 0.7, "cut": "none"}),
                      ("head word + 0.05 slack", {"name_cos": 0.7, "delta": 0.05}),
                      ("+ NYU40 contrasts tau 0.4, qv 0.7", {"name_cos": 0.7, "vocab": (0.4, 0.7)}),
                      ("+ NYU40 contrasts tau 0.5, qv 0.6", {"name_cos": 0.7, "vocab": (0.5, 0.6)}),
                      ("+ NYU40 contrasts tau 0.6, qv 0.8", {"name_cos": 0.7, "vocab": (0.6, 0.8)})):
        show_matrix("v7 variant: " + label, lambda wl, kw=kw: variant_matrix(space, stored, wl, **kw))
    # a region's hubness (how close the household vocabulary sits to it: the mean cosine of its 10
    # nearest NYU40 names after the nearest, often its own) taken off its margins, centred
    r, n, c = space.regions(), space.vectors(list(stored.negatives)), space.vectors(list(stored.query_categories))
    v = _unit(space.vectors([w for w in NYU40_CLASSES if not w.startswith("other")]))
    hub = np.sort(v @ _unit(r).T, axis=0)[-11:-1].mean(0)
    for lam in (0.25, 1.0):
        show_matrix(f"v5 - {lam} * region hubness (NYU40)", lambda wl, lam=lam: (
            lambda cm: (cm[0], cm[1] - lam * (hub - hub.mean())[None]))(margin_matrix(space, stored, wl)))

    def templated(wl, template: str):  # noqa: ANN001, ANN202
        texts = [t for t, _ in wl]
        every = list(dict.fromkeys(x for t in texts for x in [t, *relevancy_texts(t)]))
        vectors = dict(zip(every, space.vectors([template.format(x) for x in every]), strict=True))
        q = _unit(np.stack([vectors[t] for t in texts]))
        return q @ _unit(r).T, np.stack([text_margins(t, vectors, r, n, c, head_name_cos=stored.head_name_cos)
                                         for t in texts])

    for template in ("a photo of a {}.", "a {} in a room."):
        show_matrix(f"v5, text, core and head as {template!r}", lambda wl, t=template: templated(wl, t))
    v3_alternatives(space, v3)


def v3_alternatives(space: Space, stored: SpaceCalibration) -> None:
    """Pooled development figures of the formulations measured while v3 was chosen (no head rule)."""
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
    r = _unit(space.regions())
    region_bar = (n @ r.T).max(0)[None, :]
    query_bar = (q @ _unit(space.vectors(list(stored.query_categories))).T).max(1)[:, None]
    for a, d in ((0.9, 0.0), (1.1, 0.05), (1.0, 0.025), (1.0, -0.025)):
        show(f"chosen, sides weighted: a = {a}, d = {d:+}", *sweep(
            cosines, cosines - np.maximum(a * region_bar, query_bar + d), MARGINS))


def _pr(figures) -> str:  # noqa: ANN001
    return f"{figures.precision:>6.3f} {figures.recall:>6.3f}"


def _short(name: str) -> str:
    return {"CALIBRATION": "cal", "HELD_OUT": "ho1"}.get(name, name.lower().replace("held_out_", "ho"))


def hit_alternatives(space: Space, stored: SpaceCalibration) -> None:
    """``match`` over the returned hits (top 5) of rules measured while v9 was chosen: the share
    of the best (v9's rule) over a grid, an additive gap to the best margin, and the map's other
    regions as negatives (a region matches when the query describes it better than the region
    that describes it best among the others, and beats the threshold)."""
    print("  match over the top 5 hits, v8's threshold (hit P / R / clean; the non-blind lists pooled, then each "
          "blind list):")

    def show(label: str, rule) -> None:  # noqa: ANN001
        cells = []
        for wl in HIT_COLUMNS.values():
            cosines, m = margin_matrix(space, stored, wl)
            f = evaluate_hits(wl, cosines, m, CATS, threshold=stored.threshold, temperature=stored.temperature,
                              best_share=None, mask=rule(cosines, m))
            cells.append(f"{f.hit_precision:.3f} {f.recall:.3f} {f.clean:.3f}")
        print(f"    {label:<44} " + "  ".join(cells))

    t = stored.margin
    for share in (None, 0.5, 0.6, 0.65, 0.7, 0.75, 0.8, 0.9, 1.0):
        show(f"share of the best {share}", lambda c, m, s=share: np.stack([match_mask(
            row, threshold=stored.threshold, temperature=stored.temperature, best_share=s) for row in m]))
    for gap in (0.05, 0.08, 0.1, 0.15, 0.2):
        show(f"within {gap} of the best margin", lambda c, m, g=gap: (m >= t) & (m >= m.max(1, keepdims=True) - g))
    r = _unit(space.regions())
    others = r @ r.T
    np.fill_diagonal(others, -1.0)
    best_other = others.max(0)  # how well the closest other region describes each region
    show("the map's other regions as negatives", lambda c, m: (m >= t) & (c > best_other[None, :]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--encoders", default="minilm,hash")
    parser.add_argument("--quick", action="store_true", help="(bench/run_all.py) the same run: about a minute of CPU")
    parser.add_argument("--full", action="store_true", help="(bench/run_all.py) the same run")
    parser.add_argument("--alternatives", action="store_true", help="other formulations (development lists only)")
    parser.add_argument("--failures", action="store_true", help="list the queries the library's method answers wrongly")
    args = parser.parse_args()
    columns = {**DEVELOPMENT, **JUDGED}
    print("development: " + ", ".join(f"{name} ({len(wl)})" for name, wl in DEVELOPMENT.items()) +
          "; judged: " + (", ".join(f"{name} ({len(wl)})" for name, wl in JUDGED.items()) or "none") +
          f"; {len(CATEGORIES)} categories; threshold: the best F1 on the development lists pooled "
          "(v9 keeps v8's); first match by cosine")
    print(f"{'space':<18} {'method':<22} {'T':>5} {'margin':>7} {'stored':>7}  {'cv P':>6} {'cv R':>6}  "
          f"{'dev P':>6} {'dev R':>6}  " + "  ".join(f"{_short(n) + ' P':>6} {_short(n) + ' R':>6}" for n in columns))
    ceilings: list[str] = []
    hit_rows: list[str] = []
    for name in args.encoders.split(","):
        space = Space(name)
        named = space.view(captioned=False)
        stored = calibration_for(space.encoder.embedding_space)
        v8 = replace(stored, best_share=None)  # v9 is v8 and the share of the best
        v3 = replace(v8, head_name_cos=None)
        rows: list[tuple[str, SpaceCalibration, bool, Space]] = [  # (method, calibration, choose its margin, regions)
            ("v9 (library)", stored, False, space), ("v8 (v9 without share)", v8, True, space),
            ("v8 regions, no head", v3, True, space),
            ("plain LERF, v8 regions", replace(v3, query_categories=()), True, space)]
        for label, table, head in (("v7 as shipped", V7_SHIPPED_MARGIN, 0.8), ("v3 as shipped", V3_SHIPPED_MARGIN, None)):
            if space.encoder.embedding_space in table:
                m = table[space.encoder.embedding_space]
                rows.append((label, replace(v8, head_name_cos=head,
                                            threshold=_margin_to_threshold(m, stored.temperature)), False, named))
        for method, cal, choose, regions in rows:
            if choose:
                margin = calibrate(regions, cal)
                if cal is v8:
                    assert abs(margin - stored.margin) < 1e-3, "v9 keeps v8's threshold: the best F1 of v8"
                cal = replace(cal, threshold=_margin_to_threshold(margin, cal.temperature))
                cv = "{:>6.3f} {:>6.3f}".format(*cross_validated(regions, cal))
            else:
                margin, cv = cal.margin, f"{'-':>6} {'-':>6}"
            known = "" if regions.encoder.embedding_space in CALIBRATIONS else " (not in CALIBRATIONS)"
            stored_m = f"{stored.margin:>+7.4f}" if method.startswith(("v9", "v8 (")) else f"{'':>7}"
            figures = {n: regions.figures(wl, cal) for n, wl in columns.items()}
            lists = "  ".join(_pr(f) for f in (regions.figures(DEV_POOL, cal), *figures.values()))
            print(f"{regions.encoder.embedding_space:<18} {method:<22} {cal.temperature:>5.2f} {margin:>+7.4f} "
                  f"{stored_m}  {cv}  {lists}{known}")
            if args.failures and cal is stored:
                for list_name, f in figures.items():
                    for text, first in f.failures:
                        print(f"    {list_name} wrong: {text!r} -> {first or 'no match'}")
            for list_name, wl in JUDGED.items():
                top1, best = ceiling(regions, cal, wl)
                ceilings.append(f"| {regions.encoder.embedding_space} | {method} | {list_name} | {top1:.3f} | {best:.3f} |")
            if method.startswith(("v9", "v8 (", "v7")):
                hits = [regions.hits(wl, cal) for wl in HIT_COLUMNS.values()]
                hit_rows.append(f"| {regions.encoder.embedding_space} | {method} | " + " | ".join(
                    f"{h.hit_precision:.3f} / {h.recall:.3f} / {h.clean:.3f}" for h in hits) + " |")
                if args.failures and cal is stored:
                    for list_name, wl in HIT_COLUMNS.items():
                        for text, bad in regions.hits(wl, cal).wrong:
                            print(f"    {list_name} wrongly matched: {text!r} -> {', '.join(bad)}")
        if args.alternatives:
            hit_alternatives(space, v8)
            caption_alternatives(space, v8)
            alternatives(named, replace(v8, head_name_cos=0.8))
    print("\nwhat no threshold can beat on the judged lists: positives whose closest region is right (recall's "
          "bound), best recall at precision >= 0.95 over all thresholds")
    print("| space | method | list | closest region right | best recall at P >= 0.95 |\n|---|---|---|---|---|")
    print("\n".join(ceilings))
    print(f"\nmatch over every returned hit (top {DEFAULT_TOP_K}): hit precision / recall / clean answers "
          "(openfusion.mapping.match_figures)")
    print("| space | method | " + " | ".join(HIT_COLUMNS) + " |\n|---|---|" + "---|" * len(HIT_COLUMNS))
    print("\n".join(hit_rows))


if __name__ == "__main__":
    main()
