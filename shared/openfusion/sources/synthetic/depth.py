"""The synthetic depth sensor: depth units, valid range and the Kinect-like noise model.

Depth images are uint16 millimetres (``DEPTH_SCALE = 1000``); depth outside
[``DEPTH_MIN_M``, ``DEPTH_MAX_M``] and surfaces seen at grazing angles (|cos| < ``GRAZING_COS``)
are holes. ``apply_depth_noise`` turns a clean render into a noisy one from a given ``rng``.
"""

from __future__ import annotations

import numpy as np

DEPTH_SCALE = 1000.0
DEPTH_MIN_M = 0.25
DEPTH_MAX_M = 8.0
GRAZING_COS = 0.15


def apply_depth_noise(
    depth_m: np.ndarray, view_cos: np.ndarray, rng: np.random.Generator, *, dropout: float = 0.002
) -> np.ndarray:
    """Kinect-like noisy depth (float32 m, 0 = hole) from a clean depth image.

    Axial noise sigma(z) = 0.0012 + 0.0019 (z - 0.4)^2 m; holes at grazing angles
    (|cos| < 0.15), at 60 % of pixels next to a depth jump larger than 4 cm + 3 % of z,
    ``dropout`` random pixels, and outside [0.25, 8.0] m.
    """
    z = depth_m
    valid = (z >= DEPTH_MIN_M) & (z <= DEPTH_MAX_M) & (view_cos >= GRAZING_COS)
    sigma = 0.0012 + 0.0019 * np.square(z - 0.4)
    noisy = z + sigma * rng.standard_normal(z.shape, dtype=np.float32)
    # depth discontinuities: compare with the 4 neighbours
    zp = np.where(z > 0, z, np.float32(100.0))
    jump = np.zeros(z.shape, dtype=bool)
    thr = 0.04 + 0.03 * zp
    dx = np.abs(np.diff(zp, axis=1)) > thr[:, 1:]
    dy = np.abs(np.diff(zp, axis=0)) > thr[1:, :]
    jump[:, 1:] |= dx
    jump[:, :-1] |= dx
    jump[1:, :] |= dy
    jump[:-1, :] |= dy
    r = rng.random(z.shape, dtype=np.float32)
    holes = (jump & (r < 0.6)) | (r > 1.0 - dropout)
    return np.where(valid & ~holes, noisy, np.float32(0.0)).astype(np.float32)
