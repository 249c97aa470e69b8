"""The per-voxel semantic update rule (see ``openfusion.mapping.volume`` for where it is applied).

Keys are handled in their stored form (key + 1, 0 = never labelled), as the volume keeps them.
"""

from __future__ import annotations

import numpy as np


def fuse_semantics(
    old_key1: np.ndarray,
    old_conf: np.ndarray,
    new_key1: np.ndarray,
    new_conf: np.ndarray,
    *,
    history_weight: float,
) -> tuple[np.ndarray, np.ndarray, tuple[int, int, int, int]]:
    """The per-voxel update rule on stored keys (key + 1, 0 = none); see the module docstring.

    Returns the new stored keys, confidences and counts (labelled, reinforced, weakened, switched).
    """
    old_conf = old_conf.astype(np.float32, copy=False)
    new_conf = new_conf.astype(np.float32, copy=False)
    none = old_key1 <= 0
    same = (old_key1 == new_key1) & ~none
    other = ~none & ~same
    diff = old_conf - new_conf
    switched = other & (diff < 0)
    weakened = other & ~switched
    out_key1 = np.where(none | switched, new_key1, old_key1).astype(np.int32)
    w = np.float32(history_weight)
    out_conf = np.select(
        [none, same, switched, weakened],
        [new_conf, (w * old_conf + new_conf) / (w + 1), -diff, diff],
        default=old_conf,
    ).astype(np.float32)
    counts = (int(none.sum()), int(same.sum()), int(weakened.sum()), int(switched.sum()))
    return out_key1, out_conf, counts
