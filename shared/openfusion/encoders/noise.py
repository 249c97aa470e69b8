"""Noise model for ground-truth regions: stresses the fusion with realistic encoder errors.

Applied at the output resolution, in this order, each step with its own random draws from one
seeded generator (deterministic given the seed and frame id):

1. **drop**: each region is removed with probability ``drop_prob`` (missed detections).
2. **embedding noise**: each embedding e is replaced by ``c*e + sqrt(1-c^2)*u`` with u a random
   unit vector orthogonal to e, so cos(e', e) == ``embedding_cosine`` exactly.
3. **merge**: each region, with probability ``merge_prob``, is merged with one adjacent region
   (their masks touch); the merged map is the pixel-wise max, and it keeps the embedding and
   label of one of the two, chosen at random (under-segmentation).
4. **split**: each region not produced by a merge, with probability ``split_prob``, is cut into
   two halves across its longer axis through its centroid; both halves keep its embedding and
   label (over-segmentation).
5. **boundary noise**: each region is eroded or dilated (even odds) by ``boundary_px`` pixels
   of the output grid with a disk (grey morphology on the soft confidence map).

Regions left with less than ``min_area_px`` of confidence mass after the steps are removed
(counted as ``vanished``). A :class:`NoiseReport` says what happened to each frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from openfusion.encoders.masks import dilate_soft, erode_soft


@dataclass(frozen=True)
class NoiseProfile:
    """Rates of each kind of noise (see the module docstring)."""

    name: str
    drop_prob: float = 0.0
    boundary_px: int = 0
    split_prob: float = 0.0
    merge_prob: float = 0.0
    embedding_cosine: float = 1.0

    def __post_init__(self) -> None:
        for attr in ("drop_prob", "split_prob", "merge_prob"):
            v = getattr(self, attr)
            if not (0.0 <= v <= 1.0):
                raise ValueError(f"noise {attr} must be in [0, 1], got {v}")
        if self.boundary_px < 0:
            raise ValueError(f"noise boundary_px must be >= 0, got {self.boundary_px}")
        if not (-1.0 <= self.embedding_cosine <= 1.0):
            raise ValueError(f"noise embedding_cosine must be in [-1, 1], got {self.embedding_cosine}")

    @property
    def is_off(self) -> bool:
        return (
            self.drop_prob == 0.0
            and self.boundary_px == 0
            and self.split_prob == 0.0
            and self.merge_prob == 0.0
            and self.embedding_cosine == 1.0
        )


#: Named profiles. "standard" is the default stress test of the fusion (docs/EVAL.md).
NOISE_PROFILES: dict[str, NoiseProfile] = {
    "off": NoiseProfile("off"),
    "light": NoiseProfile("light", drop_prob=0.1, boundary_px=1, split_prob=0.05, merge_prob=0.05, embedding_cosine=0.95),
    "standard": NoiseProfile(
        "standard", drop_prob=0.2, boundary_px=2, split_prob=0.1, merge_prob=0.1, embedding_cosine=0.9
    ),
    "heavy": NoiseProfile("heavy", drop_prob=0.4, boundary_px=4, split_prob=0.2, merge_prob=0.2, embedding_cosine=0.8),
}


def get_noise_profile(noise: str | NoiseProfile | None) -> NoiseProfile:
    """A profile by name (or the profile itself); None means "off"."""
    if noise is None:
        return NOISE_PROFILES["off"]
    if isinstance(noise, NoiseProfile):
        return noise
    profile = NOISE_PROFILES.get(str(noise).strip().lower())
    if profile is None:
        raise ValueError(f"unknown noise profile {noise!r}; known: {', '.join(NOISE_PROFILES)}")
    return profile


@dataclass
class NoiseReport:
    """What the noise model did to one frame's regions (counts of regions / events)."""

    input_regions: int = 0
    dropped: int = 0
    embedding_perturbed: int = 0
    merged: int = 0  # merge events (each consumed two regions and produced one)
    split: int = 0  # split events (each consumed one region and produced two)
    eroded: int = 0
    dilated: int = 0
    vanished: int = 0
    output_regions: int = 0
    merge_candidates: int = 0  # regions that had an adjacent partner when merges were drawn


def perturb_embeddings(embeddings: np.ndarray, cosine: float, rng: np.random.Generator) -> np.ndarray:
    """Unit rows at exactly ``cosine`` to the given unit rows (random orthogonal component)."""
    e = embeddings.astype(np.float64)
    if cosine >= 1.0 or e.shape[0] == 0:
        return embeddings.astype(np.float32, copy=True)
    g = rng.standard_normal(e.shape)
    g -= np.sum(g * e, axis=1, keepdims=True) * e
    norms = np.linalg.norm(g, axis=1, keepdims=True)
    # A draw parallel to e has probability zero; redraw defensively so the result is exact.
    while np.any(norms < 1e-12):
        bad = (norms < 1e-12).ravel()
        g[bad] = rng.standard_normal((int(bad.sum()), e.shape[1]))
        g[bad] -= np.sum(g[bad] * e[bad], axis=1, keepdims=True) * e[bad]
        norms = np.linalg.norm(g, axis=1, keepdims=True)
    u = g / norms
    out = cosine * e + math.sqrt(max(0.0, 1.0 - cosine * cosine)) * u
    out /= np.linalg.norm(out, axis=1, keepdims=True)
    return out.astype(np.float32)


def _adjacency(conf_maps: np.ndarray) -> np.ndarray:
    """(n, n) bool: regions whose support (conf > 0) touch or overlap (8-neighbourhood)."""
    n = conf_maps.shape[0]
    support = conf_maps > 0
    grown = ndimage.binary_dilation(support, structure=np.ones((1, 3, 3), bool))
    touch = grown.reshape(n, -1).astype(np.float32) @ support.reshape(n, -1).T.astype(np.float32)
    adj = (touch > 0) | (touch.T > 0)
    np.fill_diagonal(adj, False)
    return adj


def _split_halves(conf: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Cut a map across its longer axis through its confidence-weighted centroid."""
    total = float(conf.sum())
    if total <= 0:
        return None
    ys, xs = np.nonzero(conf > 0)
    if ys.size < 2:
        return None
    h_extent = ys.max() - ys.min()
    w_extent = xs.max() - xs.min()
    h, w = conf.shape
    if w_extent >= h_extent:
        cx = float((conf.sum(axis=0) * np.arange(w)).sum() / total)
        first = np.arange(w)[None, :] < cx
        first = np.broadcast_to(first, conf.shape)
    else:
        cy = float((conf.sum(axis=1) * np.arange(h)).sum() / total)
        first = np.broadcast_to(np.arange(h)[:, None] < cy, conf.shape)
    a = np.where(first, conf, 0.0).astype(np.float32)
    b = np.where(first, 0.0, conf).astype(np.float32)
    if a.sum() <= 0 or b.sum() <= 0:
        return None
    return a, b


def apply_region_noise(
    conf_maps: np.ndarray,
    embeddings: np.ndarray,
    labels: list[str],
    profile: NoiseProfile,
    rng: np.random.Generator,
    *,
    min_area_px: float = 1.0,
) -> tuple[np.ndarray, np.ndarray, list[str], NoiseReport]:
    """Apply ``profile`` to one frame's regions; returns new (conf_maps, embeddings, labels, report)."""
    n0 = conf_maps.shape[0]
    report = NoiseReport(input_regions=n0)
    h, w = conf_maps.shape[1:]
    dim = embeddings.shape[1]
    if profile.is_off or n0 == 0:
        report.output_regions = n0
        return conf_maps, embeddings, list(labels), report

    # 1. drop
    keep = rng.random(n0) >= profile.drop_prob
    report.dropped = int((~keep).sum())
    maps = [conf_maps[i] for i in np.flatnonzero(keep)]
    embs = embeddings[keep]
    labs = [labels[i] for i in np.flatnonzero(keep)]

    # 2. embedding noise
    if profile.embedding_cosine < 1.0 and len(maps):
        embs = perturb_embeddings(embs, profile.embedding_cosine, rng)
        report.embedding_perturbed = len(maps)

    # 3. merge adjacent pairs
    merged_flags = [False] * len(maps)
    if profile.merge_prob > 0 and len(maps) >= 2:
        adj = _adjacency(np.stack(maps))
        report.merge_candidates = int(adj.any(axis=1).sum())
        consumed = np.zeros(len(maps), bool)
        new_maps, new_embs, new_labs, new_flags = [], [], [], []
        draws = rng.random(len(maps))
        for i in rng.permutation(len(maps)):
            if consumed[i] or draws[i] >= profile.merge_prob:
                continue
            partners = np.flatnonzero(adj[i] & ~consumed)
            partners = partners[partners != i]
            if partners.size == 0:
                continue
            j = int(rng.choice(partners))
            consumed[i] = consumed[j] = True
            keep_from = i if rng.random() < 0.5 else j
            new_maps.append(np.maximum(maps[i], maps[j]))
            new_embs.append(embs[keep_from])
            new_labs.append(labs[keep_from])
            new_flags.append(True)
            report.merged += 1
        for i in range(len(maps)):
            if not consumed[i]:
                new_maps.append(maps[i])
                new_embs.append(embs[i])
                new_labs.append(labs[i])
                new_flags.append(False)
        maps, labs, merged_flags = new_maps, new_labs, new_flags
        embs = np.stack(new_embs) if new_embs else np.zeros((0, dim), np.float32)

    # 4. split
    if profile.split_prob > 0 and maps:
        draws = rng.random(len(maps))
        new_maps, new_embs, new_labs = [], [], []
        for i, m in enumerate(maps):
            halves = None
            if not merged_flags[i] and draws[i] < profile.split_prob:
                halves = _split_halves(m)
            if halves is None:
                new_maps.append(m)
                new_embs.append(embs[i])
                new_labs.append(labs[i])
            else:
                report.split += 1
                for half in halves:
                    new_maps.append(half)
                    new_embs.append(embs[i])
                    new_labs.append(labs[i])
        maps, labs = new_maps, new_labs
        embs = np.stack(new_embs) if new_embs else np.zeros((0, dim), np.float32)

    # 5. boundary noise
    if profile.boundary_px > 0 and maps:
        dilate = rng.random(len(maps)) < 0.5
        for i in range(len(maps)):
            if dilate[i]:
                maps[i] = dilate_soft(maps[i], profile.boundary_px)
                report.dilated += 1
            else:
                maps[i] = erode_soft(maps[i], profile.boundary_px)
                report.eroded += 1

    out_maps = np.stack(maps).astype(np.float32) if maps else np.zeros((0, h, w), np.float32)
    mass = out_maps.reshape(out_maps.shape[0], h * w).sum(axis=1)  # explicit size: works for 0 regions
    alive = mass >= min_area_px
    report.vanished = int((~alive).sum())
    out_maps = np.ascontiguousarray(np.clip(out_maps[alive], 0.0, 1.0))
    out_embs = np.ascontiguousarray(embs[alive].astype(np.float32))
    out_labs = [lab for lab, a in zip(labs, alive, strict=True) if a]
    report.output_regions = int(out_maps.shape[0])
    return out_maps, out_embs, out_labs, report
