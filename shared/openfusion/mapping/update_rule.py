"""The per-voxel semantic update rule (see ``openfusion.mapping.volume`` for where it is applied).

Keys are handled in their stored form (key + 1, 0 = never labelled), as the volume keeps them.

The rule: confidence is accumulated evidence (clamped, like log-odds occupancy mapping)
    A voxel stores one key and a confidence ``conf`` in [0, 1] that counts the evidence for that
    key seen so far. With ``w = VolumeParams.conf_history_weight`` every observation (key ``k``,
    confidence ``c`` in (0, 1]) moves the confidence by one *evidence step* ``s * c``, where
    ``s = 1 / (w + 1)`` (default w = 3: s = 0.25):

    - never labelled:  key <- k,  conf <- s * c
    - same key:        conf <- min(1, conf + s * c)                   (evidence adds up, saturates at 1)
    - other key:       conf <- conf - s * c; if that is negative the new key wins:
                       key <- k, conf <- s * c - conf_old            (the remaining evidence)

    So a voxel seen n times at full confidence holds min(1, n * s) and needs as many contrary
    full-confidence observations to change key (at most w + 1 once saturated), however the
    contrary observations are spread in time; a voxel that changes key starts over with only the
    evidence left over. One or two contrary observations (a merged region, a mask edge that
    spilled over a neighbour, a key that drifted) no longer flip a voxel that was seen correctly
    many times. A confidence of exactly 0 keeps the key but carries no evidence (region matching
    leaves such pixels out of the key's mask; the next observation of any key takes the voxel).

    ``w = 0`` (s = 1) is the fastest-reacting form: one full-confidence observation saturates a
    voxel and one contrary one replaces its key.
"""

from __future__ import annotations

import math

import numpy as np


def evidence_step(history_weight: float) -> float:
    """Confidence one full-confidence observation adds or removes: ``1 / (history_weight + 1)``."""
    if not (math.isfinite(history_weight) and history_weight >= 0):
        raise ValueError(f"history_weight must be finite and >= 0, got {history_weight}")
    return 1.0 / (float(history_weight) + 1.0)


def fuse_semantics(
    old_key1: np.ndarray,
    old_conf: np.ndarray,
    new_key1: np.ndarray,
    new_conf: np.ndarray,
    *,
    history_weight: float,
) -> tuple[np.ndarray, np.ndarray, tuple[int, int, int, int]]:
    """The per-voxel update rule on stored keys (key + 1, 0 = none); see the module docstring.

    ``new_key1`` must be > 0 and ``new_conf`` in (0, 1] for every entry (the caller drops pixels
    without a key or with confidence 0). Returns the new stored keys, confidences and counts
    (labelled, reinforced, weakened, switched).
    """
    step = np.float32(evidence_step(history_weight))
    old_conf = old_conf.astype(np.float32, copy=False)
    delta = step * new_conf.astype(np.float32, copy=False)
    none = old_key1 <= 0
    same = (old_key1 == new_key1) & ~none
    other = ~none & ~same
    left = old_conf - delta
    switched = other & (left < 0)
    weakened = other & ~switched
    out_key1 = np.where(none | switched, new_key1, old_key1).astype(np.int32)
    out_conf = np.select(
        [none, same, switched, weakened],
        [delta, np.minimum(np.float32(1.0), old_conf + delta), -left, left],
        default=old_conf,
    ).astype(np.float32)
    counts = (int(none.sum()), int(same.sum()), int(weakened.sum()), int(switched.sum()))
    return out_key1, out_conf, counts
