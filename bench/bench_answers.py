#!/usr/bin/env python3
"""What v9's ``match`` costs per query: one text answered from dictionaries of growing size.

v9 judges ``match`` among the :data:`~openfusion.mapping.answers.MATCH_POOL` (32) regions closest
to the text instead of the ``top_k`` (5) returned, so each query ranks, fetches the embeddings of
and scores 32 regions instead of 5. This bench times
:func:`openfusion.mapping.answers.answer_text` (the library call every query path makes: the
query service, ``openfusion query --map-dir``, the in-process run) for a plain text and a relation
query, ``top_k`` 5, on dictionaries of 100 to 20,000 random regions (384-d, MiniLM's size), with
the text's vectors embedded beforehand (the encoder call is the same in both and dominates a real
query: about 10 ms for MiniLM on one core). The baseline, measured in the same run on the same
dictionary: v8 (no share of the best, the 5 returned regions scored).

    .venv/bin/python bench/bench_answers.py           # about 30 s
    .venv/bin/python bench/bench_answers.py --quick   # sizes 100 and 2,000
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

import numpy as np

from openfusion.mapping import answers
from openfusion.mapping.answers import answer_text, texts_to_embed
from openfusion.mapping.relations import RegionBoxes
from openfusion.mapping.relevancy import CALIBRATIONS, RelevancyScorer

DIM = 384
TEXTS = ("something to sit on", "the chair next to the table")


def _setup(n: int, rng: np.random.Generator):  # noqa: ANN202
    emb = rng.normal(size=(n, DIM)).astype(np.float32)
    emb /= np.linalg.norm(emb, axis=1, keepdims=True)
    lo = rng.uniform(0, 5, size=(n, 3)).astype(np.float32)
    boxes = RegionBoxes(keys=np.arange(n, dtype=np.int32), bbox_min=lo, bbox_max=lo + 0.5)
    wanted = texts_to_embed(list(TEXTS))
    vectors = {t: (emb[i % n] + 0.3 * rng.normal(size=DIM)).astype(np.float32) for i, t in enumerate(wanted)}

    def rank(vector: np.ndarray, k: int) -> list[tuple[int, float]]:
        scores = emb @ (vector / np.linalg.norm(vector))
        top = np.argpartition(-scores, min(k, n) - 1)[:k]
        top = top[np.argsort(-scores[top], kind="stable")]
        return [(int(i), float(scores[i])) for i in top]

    def embeddings(keys: list[int]) -> np.ndarray:
        return emb[keys]

    return vectors, rank, embeddings, boxes


def _time(fn, repeats: int) -> float:  # noqa: ANN001
    fn()
    best = float("inf")
    for _ in range(3):
        start = time.perf_counter()
        for _ in range(repeats):
            fn()
        best = min(best, (time.perf_counter() - start) / repeats)
    return best * 1000.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--full", action="store_true", help="(bench/run_all.py) the default run")
    args = parser.parse_args()
    sizes = (100, 2_000) if args.quick else (100, 1_000, 5_000, 20_000)
    rng = np.random.default_rng(0)
    cal = CALIBRATIONS["minilm-l6-v2"]
    phrases = rng.normal(size=(len(cal.phrases), DIM)).astype(np.float32)
    v9 = RelevancyScorer.of_vectors(cal, phrases)
    v8 = RelevancyScorer.of_vectors(replace(cal, best_share=None), phrases)
    print("answer_text, top_k 5, 384-d regions, text vectors given (ms per query, best of 3)")
    print("| regions | text | v8 (5 scored) | v9 (32 scored) | ratio |")
    print("|---|---|---|---|---|")
    for n in sizes:
        vectors, rank, embeddings, boxes = _setup(n, rng)
        for text in TEXTS:
            def run(scorer: RelevancyScorer, text: str = text, setup=(vectors, rank, embeddings, boxes)) -> None:  # noqa: ANN001
                answer_text(text, setup[0], rank=setup[1], embeddings=setup[2], scorer=scorer, boxes=setup[3], top_k=5)

            pool = answers.MATCH_POOL
            answers.MATCH_POOL = 0  # v8: only the regions returned are scored
            try:
                base = _time(lambda: run(v8), 20)
            finally:
                answers.MATCH_POOL = pool
            new = _time(lambda: run(v9), 20)
            print(f"| {n:,} | {text!r} | {base:.2f} | {new:.2f} | {new / base:.2f}x |")


if __name__ == "__main__":
    main()
