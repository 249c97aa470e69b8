"""Procedural textures of the synthetic world: one 256 x 256 brightness atlas per texture kind.

``_TEXTURES`` names the kinds a ``Part`` may use (plain, wood, fabric, noise, planks, paint);
``_texture_atlas()`` makes their multipliers (around 1) from a fixed seed, so they are the same
for every world. ``_TEXEL_M`` is the size of one texel on a surface (1 cm); the atlas tiles.
"""

from __future__ import annotations

import numpy as np

# texture kinds (index into per-geometry texture weights)
_TEXTURES = ("plain", "wood", "fabric", "noise", "planks", "paint")

_TEX_SIZE = 256
_TEXEL_M = 0.01


def _smooth_noise(rng: np.random.Generator, cells: int) -> np.ndarray:
    """Tileable value noise on the atlas grid with ``cells`` x ``cells`` random values."""
    coarse = rng.random((cells, cells))
    idx = np.arange(_TEX_SIZE) * cells / _TEX_SIZE
    i0 = np.floor(idx).astype(int)
    f = idx - i0
    f = f * f * (3 - 2 * f)
    i1 = (i0 + 1) % cells
    rows = coarse[i0] * (1 - f)[:, None] + coarse[i1] * f[:, None]
    return rows[:, i0] * (1 - f)[None, :] + rows[:, i1] * f[None, :]


def _texture_atlas() -> np.ndarray:
    """(n_textures, 256, 256) float32 brightness multipliers around 1, one per texture kind.

    Axis order is (u, v): u runs along x (or y on walls facing x), v along y or z.
    """
    rng = np.random.default_rng(20240611)
    white = rng.random((_TEX_SIZE, _TEX_SIZE)) - 0.5
    blocks = np.kron(rng.random((_TEX_SIZE // 2, _TEX_SIZE // 2)) - 0.5, np.ones((2, 2)))
    low = _smooth_noise(rng, 8) - 0.5
    v = np.arange(_TEX_SIZE)[None, :]
    u = np.arange(_TEX_SIZE)[:, None]
    grain = np.sin(2 * np.pi * v / 3.2 + 6.0 * low)
    plank_id = u // 18
    plank_tone = (rng.random(_TEX_SIZE) - 0.5)[plank_id]
    seams = np.where(u % 18 == 0, -0.25, 0.0)
    out = {
        "plain": 1 + 0.03 * white,
        "wood": 1 + 0.05 * grain + 0.04 * white + 0.06 * low,
        "fabric": 1 + 0.10 * white + 0.05 * low,
        "noise": 1 + 0.30 * blocks + 0.1 * low,
        "planks": 1 + 0.16 * plank_tone + 0.05 * grain + 0.03 * white + seams,
        "paint": 1 + 0.02 * white + 0.05 * low,
    }
    return np.stack([np.broadcast_to(out[name], (_TEX_SIZE, _TEX_SIZE)) for name in _TEXTURES]).astype(np.float32)
