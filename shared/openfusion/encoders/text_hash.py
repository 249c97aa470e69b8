"""A lexical text encoder: hashed character trigrams (no model, no download, microseconds).

It is a baseline and a fast stand-in for plumbing tests and services that must start in
well under a second: "office chair" lands near "chair" because they share trigrams, but it
knows nothing about meaning ("sofa" is not near "couch"). Use ``minilm`` for semantics.
"""

from __future__ import annotations

import hashlib

import numpy as np

from openfusion.encoders.base import TextEncoder, check_texts, normalize_rows


def _trigram_features(text: str, dim: int) -> np.ndarray:
    padded = f"  {text.strip().lower()}  "
    vec = np.zeros(dim, np.float32)
    for i in range(len(padded) - 2):
        digest = hashlib.blake2b(padded[i : i + 3].encode("utf-8"), digest_size=8).digest()
        h = int.from_bytes(digest, "little")
        vec[h % dim] += 1.0 if (h >> 63) & 1 == 0 else -1.0
    return vec


class HashTextEncoder(TextEncoder):
    """Signed feature hashing of character trigrams into ``dim`` dimensions (space ``hash-trigram-<dim>``)."""

    def __init__(self, *, dim: int = 256) -> None:
        if dim < 8:
            raise ValueError(f"dim must be >= 8, got {dim}")
        self.dim = int(dim)
        self.embedding_space = f"hash-trigram-{self.dim}"

    def encode(self, texts: list[str]) -> np.ndarray:
        texts = check_texts(texts)
        if not texts:
            return np.zeros((0, self.dim), np.float32)
        feats = np.stack([_trigram_features(t, self.dim) for t in texts])
        # A text whose trigrams cancel out exactly is vanishingly rare; nudge it instead of failing.
        zero = np.linalg.norm(feats, axis=1) == 0
        feats[zero, 0] = 1.0
        return normalize_rows(feats, what="hashed text embeddings")
