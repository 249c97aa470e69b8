"""The coverage record's small pieces: direction bins on a sphere, surface cubes packed into one
integer, and bit tables of ``1 << bin`` per key (:mod:`openfusion.mapping.coverage` keeps them per
region and per cube). Plain numpy; written here because no library packs these for a dict of ints.
"""

from __future__ import annotations

import math

import numpy as np

#: Cell coordinates are packed into one int64: 21 bits per axis around 0 (at 0.1 m cells +-100 km).
_CELL_BITS = 21
_CELL_OFFSET = 1 << (_CELL_BITS - 1)
_CELL_MASK = (1 << _CELL_BITS) - 1


def fibonacci_directions(n: int) -> np.ndarray:
    """``n`` unit vectors spread evenly over the sphere (float64 (n, 3)): the direction bins' centres."""
    if n < 1:
        raise ValueError(f"need at least one direction bin, got {n}")
    i = np.arange(n, dtype=np.float64) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    theta = math.pi * (1.0 + math.sqrt(5.0)) * i
    return np.stack([r * np.cos(theta), r * np.sin(theta), z], axis=1)


def pack_cells(points_world: np.ndarray, cell_m: float) -> np.ndarray:
    """int64 (n,) id of the ``cell_m`` cube holding each point (float (n, 3), metres)."""
    c = np.floor(points_world / cell_m).astype(np.int64) + _CELL_OFFSET
    c &= _CELL_MASK
    return (c[:, 0] << (2 * _CELL_BITS)) | (c[:, 1] << _CELL_BITS) | c[:, 2]


def group_bits_arrays(keys: np.ndarray, bins: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(distinct keys, the OR of ``1 << bin`` over each key's pairs), as int64 arrays."""
    if len(keys) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    order = np.argsort(keys, kind="stable")
    keys, bits = keys[order], np.left_shift(np.int64(1), bins[order])
    starts = np.flatnonzero(np.r_[True, keys[1:] != keys[:-1]])
    return keys[starts], np.bitwise_or.reduceat(bits, starts)


def group_bits(keys: np.ndarray, bins: np.ndarray) -> list[tuple[int, int]]:
    """``(key, bits)`` per distinct key: the OR of ``1 << bin`` over its pairs."""
    uniq, bits = group_bits_arrays(keys, bins)
    return list(zip(uniq.tolist(), bits.tolist(), strict=True))


def or_into(table: dict[int, int], keys: np.ndarray, bins: np.ndarray) -> None:
    """``table[k] |= 1 << bin`` for every (key, bin) pair, grouped per key."""
    for k, b in group_bits(keys, bins):
        table[k] = table.get(k, 0) | b
