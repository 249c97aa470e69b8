"""Region merging: regions that are one object become one region.

Why: a region is born whenever an observed mask overlaps no rendered region enough (soft IoU
under ``MatchParams.min_iou``), so two views of one wall that overlap little on screen start two
regions, and nothing joined them again (issue #17: 16 regions for 13 objects without noise, 71
under the gt encoder's ``standard`` noise, more with every lap of a room).

The rule (parameters: :class:`~openfusion.mapping.params.MergeParams`, declared once):

1. **Contact** (:func:`region_contacts`, from the volume's labelled voxels): voxel ``v`` of region
   ``a`` *touches* region ``b`` when a voxel of ``b`` lies within ``merge_contact_radius_vox``
   voxels of ``v`` per axis (the 26-neighbourhood for radius 1, i.e. ``b`` dilated by one voxel).
   For each touching pair the numbers of voxels of ``a`` touching ``b`` and of ``b`` touching
   ``a`` are counted, with each region's number of labelled voxels.
2. **Candidates**: a pair is substantial contact when, for the *smaller* region (fewer labelled
   voxels), at least ``merge_min_contact_voxels`` of its voxels (all of them when it has fewer)
   and at least ``merge_min_contact_fraction`` of them touch the other region. The fraction is
   relative to the smaller region so a small fragment lying against a big one counts as one with
   it, while a big region touching another along one edge needs that edge to be long enough.
   Each region joins at most one region larger than itself (the one it touches most), so a small
   fragment between two big regions does not bridge them.
3. **Agreement**: the two unit embeddings have cosine ``>= merge_min_cos``. Two objects of the
   same class that do not touch (two chairs apart) never merge; touching objects of different
   classes (a chair at a table) do not agree.
4. **Groups**: accepted pairs are joined transitively (union-find, :class:`scipy` connected
   components); each group keeps the key with the most observations (ties: the oldest key) and
   the others are merged into it: :meth:`RegionDictionary.merge` (one dictionary version, so one
   delta on the wire carries every merge of a pass) and ``volume.relabel_keys`` (voxels follow).

Embedding of a merged region (``merge_embedding``): the observation-weighted mean of the two
running means (counts summed), normalised for ranking -- the running mean the region would have
had if every observation had been matched to it from the start. Measured against the plain mean
of the two and against keeping the survivor's embedding (docs/EVAL.md, "Merging regions").

Cost (:func:`block_contacts`): linear in the labelled blocks, working on the grid's own block
layout (each block padded with its neighbours' border voxels; blocks inside one region skipped).
Written with numpy because Open3D's ``VoxelBlockGrid`` has no neighbour query between voxels (its
KD-trees work on extracted points, which would cost a surface read-out first).
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable
from dataclasses import dataclass, field, fields
from typing import Any, Self

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from openfusion.mapping.params import MergeParams


class _Int64Columns:
    """A dataclass whose fields are equally long int64 columns (a table of facts)."""

    @classmethod
    def empty(cls) -> Self:
        """The table with no row."""
        return cls(*(np.zeros(0, np.int64) for _ in fields(cls)))  # type: ignore[arg-type]


@dataclass
class RegionContacts(_Int64Columns):
    """Adjacency facts of a map's regions (what geometry answers on ``geometry/contacts``).

    ``keys`` / ``surface_voxels``: every region with labelled voxels and how many it has.
    ``pair_a`` < ``pair_b``: regions that touch; ``contact_a``: voxels of ``a`` touching ``b``,
    ``contact_b``: voxels of ``b`` touching ``a``.
    """

    keys: np.ndarray  # (R,) int64
    surface_voxels: np.ndarray  # (R,) int64
    pair_a: np.ndarray  # (P,) int64
    pair_b: np.ndarray  # (P,) int64
    contact_a: np.ndarray  # (P,) int64
    contact_b: np.ndarray  # (P,) int64

    def surface_of(self) -> dict[int, int]:
        return {int(k): int(n) for k, n in zip(self.keys, self.surface_voxels, strict=True)}


#: Edge length (voxels) of the blocks :func:`region_contacts` groups loose voxels into (the grid's own
#: block resolution is used for a volume).
CONTACT_BLOCK_VOXELS = 8


def _block_rows(coords: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sorted linear codes of block coordinates, their rows, and the code's box (for lookups)."""
    lo = coords.min(axis=0) - 1
    dims = coords.max(axis=0) - lo + 2
    rel = coords - lo
    codes = (rel[:, 0] * dims[1] + rel[:, 1]) * dims[2] + rel[:, 2]
    order = np.argsort(codes)
    return codes[order], order, np.concatenate([lo, dims])


@dataclass
class ContactCounts(_Int64Columns):
    """Contact counts of the voxels of some blocks, per group of blocks (:func:`contact_counts`):
    ``surface_*``: labelled voxels per (group, key); ``pair_*``: voxels of ``owner`` touching
    ``other`` per (group, owner, other), each (voxel, other region) counted once."""

    surface_group: np.ndarray  # (S,) int64
    surface_key: np.ndarray  # (S,) int64
    surface_count: np.ndarray  # (S,) int64
    pair_group: np.ndarray  # (P,) int64
    pair_owner: np.ndarray  # (P,) int64
    pair_other: np.ndarray  # (P,) int64
    pair_count: np.ndarray  # (P,) int64


def _runs(*columns: np.ndarray) -> tuple[list[np.ndarray], np.ndarray]:
    """Distinct rows of integer ``columns`` (sorted, first column major) and how often each occurs."""
    if len(columns[0]) == 0:
        return [c[:0] for c in columns], np.zeros(0, np.int64)
    order = np.lexsort(columns[::-1])
    cols = [c[order] for c in columns]
    change = np.zeros(len(order), bool)
    change[0] = True
    for c in cols:
        change[1:] |= c[1:] != c[:-1]
    starts = np.flatnonzero(change)
    counts = np.diff(np.append(starts, len(order)))
    return [c[starts] for c in cols], counts.astype(np.int64)


def contact_counts(block_coords: np.ndarray, block_keys: np.ndarray, *, radius_vox: int = 1,
                   group: np.ndarray | None = None) -> ContactCounts:
    """The counts :func:`block_contacts` adds up, per group of blocks: block coordinates (N, 3)
    (x, y, z) and each block's voxel keys (N, R, R, R) indexed [z, y, x], -1 = no key (the layout of
    Open3D's voxel buffers); ``group`` (N,) int: which group each block's voxels count for, -1 for
    a block that only pads its neighbours (a halo around the blocks counted: a map read out tile
    by tile counts every voxel once, in the tile of its block).

    Each block is padded with ``radius_vox`` voxels of its 26 neighbour blocks; blocks whose padded
    neighbourhood holds a single key (the inside of a region: most of them) are skipped, and the
    rest compare every voxel with its neighbours by slicing the padded array. Cost: O(N R^3) to pad
    and screen, plus 26 (radius 1) array comparisons over the border blocks only.
    """
    coords = np.asarray(block_coords, np.int64).reshape(-1, 3)
    kb = np.asarray(block_keys)
    if radius_vox < 1:
        raise ValueError(f"radius_vox must be >= 1, got {radius_vox}")
    if kb.ndim != 4 or kb.shape[0] != len(coords) or not (kb.shape[1] == kb.shape[2] == kb.shape[3]):
        raise ValueError(f"block_keys must be (N, R, R, R) for {len(coords)} blocks, got {kb.shape}")
    R, r = kb.shape[1], int(radius_vox)
    if r >= R:
        raise ValueError(f"radius_vox ({r}) must be below the block resolution ({R})")
    groups = np.zeros(len(coords), np.int64) if group is None else np.asarray(group, np.int64).reshape(-1)
    if len(groups) != len(coords):
        raise ValueError(f"group must hold one entry per block ({len(coords)}), got {len(groups)}")
    kb = kb.astype(np.int32, copy=False)
    labelled = kb >= 0
    own = groups >= 0
    counted = labelled & own[:, None, None, None]
    if not counted.any():
        return ContactCounts.empty()
    blk, _, _, _ = np.nonzero(counted)
    (surface_group, surface_key), surface_count = _runs(groups[blk], kb[counted].astype(np.int64))
    n, S = len(coords), R + 2 * r
    padded = np.full((n, S, S, S), -1, np.int32)
    padded[:, r : r + R, r : r + R, r : r + R] = kb
    codes, order, box = _block_rows(coords)
    lo, dims = box[:3], box[3:]
    # Per axis offset -1 / 0 / +1: (destination slice in the padded block, source slice in the neighbour).
    spans = {-1: (slice(0, r), slice(R - r, R)), 0: (slice(r, r + R), slice(0, R)), 1: (slice(r + R, S), slice(0, r))}
    for dx, dy, dz in itertools.product((-1, 0, 1), repeat=3):
        if dx == dy == dz == 0:
            continue
        rel = coords + np.array([dx, dy, dz]) - lo
        target = (rel[:, 0] * dims[1] + rel[:, 1]) * dims[2] + rel[:, 2]
        pos = np.minimum(np.searchsorted(codes, target), n - 1)
        rows = np.flatnonzero(codes[pos] == target)
        if len(rows) == 0:
            continue
        nb = order[pos[rows]]
        (zd, zs), (yd, ys), (xd, xs) = spans[dz], spans[dy], spans[dx]
        padded[rows, zd, yd, xd] = kb[nb, zs, ys, xs]
    # Screen: blocks whose padded neighbourhood holds one key (or none) have no contact.
    big = np.iinfo(np.int32).max
    high = padded.reshape(n, -1).max(axis=1)
    low = np.where(padded >= 0, padded, big).reshape(n, -1).min(axis=1)
    border = np.flatnonzero((high > low) & counted.reshape(n, -1).any(axis=1))
    pb, centre = padded[border], kb[border]
    del padded
    span = int(max(int(kb.max()), 0)) + 1
    codes_out: list[np.ndarray] = []
    for dx, dy, dz in itertools.product(range(-r, r + 1), repeat=3):
        if dx == dy == dz == 0:
            continue
        other = pb[:, r + dz : r + dz + R, r + dy : r + dy + R, r + dx : r + dx + R]
        hit = np.flatnonzero(((centre >= 0) & (other >= 0) & (other != centre)).reshape(-1))
        if len(hit):
            codes_out.append(hit * span + other.reshape(-1)[hit].astype(np.int64))
    z = np.zeros(0, np.int64)
    if not codes_out:
        return ContactCounts(surface_group, surface_key, surface_count, z, z.copy(), z.copy(), z.copy())
    # Each (voxel, other region) once: a voxel touching b through several neighbours counts once.
    touching = np.unique(np.concatenate(codes_out))
    voxel, against = touching // span, touching % span
    owner = centre.reshape(-1)[voxel].astype(np.int64)
    grp = groups[border][voxel // R**3]
    (pg, po, pa), pc = _runs(grp, owner, against)
    return ContactCounts(surface_group, surface_key, surface_count, pg, po, pa, pc)


def contacts_of_counts(keys: np.ndarray, surface: np.ndarray, owner: np.ndarray, other: np.ndarray,
                       count: np.ndarray) -> RegionContacts:
    """:class:`RegionContacts` of summed counts: every region's labelled voxels (``keys``,
    ``surface``, one row per key, any order) and directed contacts (voxels of ``owner`` touching
    ``other``, one row per directed pair)."""
    keys = np.asarray(keys, np.int64)
    surface = np.asarray(surface, np.int64)
    order = np.argsort(keys, kind="stable")
    keys, surface = keys[order], surface[order]
    owner, other, count = (np.asarray(a, np.int64) for a in (owner, other, count))
    lower = owner < other
    a, b, ca = owner[lower], other[lower], count[lower]
    order = np.lexsort((b, a))
    a, b, ca = a[order], b[order], ca[order]
    # b's voxels touching a: the directed count (b, a), 0 when none (not possible for r >= 1).
    reverse = dict(zip(zip(owner.tolist(), other.tolist(), strict=True), count.tolist(), strict=True))
    cb = np.array([reverse.get((int(y), int(x)), 0) for x, y in zip(a, b, strict=True)], np.int64)
    return RegionContacts(keys, surface, a, b, ca, cb)


def block_contacts(block_coords: np.ndarray, block_keys: np.ndarray, *, radius_vox: int = 1) -> RegionContacts:
    """Contacts between regions (see the module docstring) from the grid's own layout: block
    coordinates (N, 3) (x, y, z) and each block's voxel keys (N, R, R, R) indexed [z, y, x], -1 =
    no key (the layout of Open3D's voxel buffers, ``VoxelStorage.labelled_blocks``). The counting
    is :func:`contact_counts`'; a map read out tile by tile adds up the same counts
    (:mod:`openfusion.mapping.tilereadouts`)."""
    c = contact_counts(block_coords, block_keys, radius_vox=radius_vox)
    if len(c.surface_key) == 0:
        return RegionContacts.empty()
    return contacts_of_counts(c.surface_key, c.surface_count, c.pair_owner, c.pair_other, c.pair_count)


def region_contacts(voxels: np.ndarray, keys: np.ndarray, *, radius_vox: int = 1) -> RegionContacts:
    """Contacts between regions from loose labelled voxels: integer voxel coordinates ``voxels``
    (n, 3) and their region ``keys`` (n,), each voxel once; grouped into blocks of
    :data:`CONTACT_BLOCK_VOXELS` for :func:`block_contacts`."""
    vox = np.asarray(voxels, np.int64).reshape(-1, 3)
    key = np.asarray(keys, np.int64).reshape(-1)
    if len(vox) != len(key):
        raise ValueError(f"voxels ({len(vox)}) and keys ({len(key)}) differ in length")
    if radius_vox < 1:
        raise ValueError(f"radius_vox must be >= 1, got {radius_vox}")
    if len(key) == 0:
        return RegionContacts.empty()
    if key.min() < 0:
        raise ValueError("keys must be >= 0 (labelled voxels only)")
    R = CONTACT_BLOCK_VOXELS
    block = np.floor_divide(vox, R)
    local = vox - block * R
    coords, row = np.unique(block, axis=0, return_inverse=True)
    kb = np.full((len(coords), R, R, R), -1, np.int32)
    kb[row.reshape(-1), local[:, 2], local[:, 1], local[:, 0]] = key
    return block_contacts(coords, kb, radius_vox=radius_vox)


@dataclass
class MergePlan:
    """What one merge pass decided: ``{merged key: surviving key}`` and the accepted pairs."""

    merged_into: dict[int, int] = field(default_factory=dict)
    pairs_touching: int = 0
    pairs_accepted: int = 0

    @property
    def groups(self) -> dict[int, list[int]]:
        """``{surviving key: [merged keys]}``."""
        out: dict[int, list[int]] = {}
        for b, a in sorted(self.merged_into.items()):
            out.setdefault(a, []).append(b)
        return out


def plan_merges(dictionary: Any, contacts: RegionContacts, params: MergeParams | None = None) -> MergePlan:
    """Which regions of ``dictionary`` to merge, from ``contacts`` (rules in the module docstring).
    Regions in ``contacts`` that the dictionary does not hold are ignored."""
    p = params if params is not None else MergeParams()
    plan = MergePlan(pairs_touching=len(contacts.pair_a))
    if len(contacts.pair_a) == 0:
        return plan
    surface = contacts.surface_of()
    a, b = contacts.pair_a, contacts.pair_b
    known = np.array([int(x) in dictionary and int(y) in dictionary for x, y in zip(a, b, strict=True)], bool)
    sa = np.array([surface.get(int(x), 0) for x in a], np.int64)
    sb = np.array([surface.get(int(y), 0) for y in b], np.int64)
    a_smaller = sa <= sb
    small_surface = np.where(a_smaller, sa, sb)
    small_contact = np.where(a_smaller, contacts.contact_a, contacts.contact_b)
    frac = small_contact / np.maximum(small_surface, 1)
    # A fragment smaller than the voxel floor counts when all of it touches.
    floor = np.minimum(p.merge_min_contact_voxels, small_surface)
    ok = known & (small_contact >= np.maximum(floor, 1)) & (frac >= p.merge_min_contact_fraction)
    idx = np.flatnonzero(ok)
    if len(idx) == 0:
        return plan
    ea = np.stack([dictionary.embedding(int(x)) for x in a[idx]])
    eb = np.stack([dictionary.embedding(int(y)) for y in b[idx]])
    agree = np.einsum("ij,ij->i", ea, eb) >= p.merge_min_cos
    idx = idx[agree]
    # Each region joins at most one region larger than itself (the one it touches most): a small
    # fragment between two big regions does not bridge them into one group.
    small_key = np.where(a_smaller, a, b)[idx]
    best_first = np.lexsort((-small_contact[idx], small_key))
    _, first = np.unique(small_key[best_first], return_index=True)
    idx = idx[best_first[first]]
    plan.pairs_accepted = len(idx)
    if len(idx) == 0:
        return plan
    nodes, inverse = np.unique(np.concatenate([a[idx], b[idx]]), return_inverse=True)
    m = len(idx)
    graph = coo_matrix((np.ones(m), (inverse[:m], inverse[m:])), shape=(len(nodes), len(nodes)))
    n_groups, group_of = connected_components(graph, directed=False)
    for g in range(n_groups):
        members = [int(k) for k in nodes[group_of == g]]
        survivor = min(members, key=lambda k: (-dictionary.count(k), k))
        for k in members:
            if k != survivor:
                plan.merged_into[k] = survivor
    return plan


class EmptyRegions:
    """Regions of the dictionary without a labelled voxel in ``passes`` passes in a row: dead (a
    region is matched only through its rendered voxels, so one that lost them all never comes
    back). The services use two passes, because a region's first update may still be on its way to
    geometry when the contacts are computed; in one process an update is written before the next
    pass, so one pass is enough."""

    def __init__(self, *, passes: int = 2) -> None:
        if passes < 1:
            raise ValueError(f"passes must be >= 1, got {passes}")
        self.passes = passes
        self._empty_for: dict[int, int] = {}

    def to_remove(self, dictionary: Any, contacts: RegionContacts, *, known: set[int] | None = None) -> list[int]:
        """``known``: the keys the dictionary held when the contacts were asked for (the services
        ask while frames go on); a region made since then is not taken for empty."""
        present = set(contacts.keys.tolist())
        empty_now = {int(k) for k in dictionary.keys.tolist()} - present
        if known is not None:
            empty_now &= known
        self._empty_for = {k: self._empty_for.get(k, 0) + 1 for k in empty_now}
        remove = sorted(k for k, n in self._empty_for.items() if n >= self.passes)
        for k in remove:
            del self._empty_for[k]
        return remove


@dataclass
class MergeResult:
    """One merge pass: the plan, voxels relabelled and its time in milliseconds."""

    plan: MergePlan
    removed: list[int] = field(default_factory=list)  # empty regions pruned (EmptyRegions)
    voxels_relabelled: int = 0
    contacts_ms: float = 0.0
    total_ms: float = 0.0

    @property
    def merged(self) -> int:
        return len(self.plan.merged_into)


def apply_merges(
    dictionary: Any, merged_into: dict[int, int], *, embedding: str = "weighted", removed: list[int] | None = None
) -> None:
    """Merge every ``b`` into ``merged_into[b]`` and remove the ``removed`` regions, in the
    dictionary as one version (one delta)."""
    if not merged_into and not removed:
        return
    with dictionary.batch():
        for b, a in sorted(merged_into.items()):
            dictionary.merge(a, b, embedding=embedding)
        for k in removed or ():
            if k in dictionary:
                dictionary.remove(k)


def merge_regions(
    volume: Any, dictionary: Any, params: MergeParams | None = None, *, empty: EmptyRegions | None = None
) -> MergeResult:
    """One merge pass on an in-process map: contacts from ``volume``, merges in ``dictionary``,
    voxels relabelled to the surviving keys; with ``empty`` (kept across passes) and
    ``merge_prune_empty``, regions without voxels in two passes in a row are removed."""
    p = params if params is not None else MergeParams()
    t0 = time.perf_counter()
    contacts = volume.region_contacts(radius_vox=p.merge_contact_radius_vox)
    t1 = time.perf_counter()
    plan = plan_merges(dictionary, contacts, p)
    removed = empty.to_remove(dictionary, contacts) if empty is not None and p.merge_prune_empty else []
    apply_merges(dictionary, plan.merged_into, embedding=p.merge_embedding, removed=removed)
    relabelled = volume.relabel_keys(plan.merged_into) if plan.merged_into else 0
    t2 = time.perf_counter()
    return MergeResult(plan, removed, relabelled, contacts_ms=(t1 - t0) * 1e3, total_ms=(t2 - t0) * 1e3)


class MergeSchedule:
    """Every ``merge_every`` semantic frames (0 = never): :meth:`due` after each semantic frame.
    ``min_interval_s`` (the services; 0 in process, so an evaluation does not depend on timing)
    also keeps two passes that far apart on ``clock``: a pass costs geometry a contacts read-out,
    and with a fast encoder pool ``merge_every`` frames come many times a second."""

    def __init__(self, params: MergeParams, *, min_interval_s: float = 0.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.params = params
        self.min_interval_s = float(min_interval_s)
        self._clock = clock
        self._since = 0
        self._last_s: float | None = None

    def due(self) -> bool:
        """Count one semantic frame; True when a merge pass is due now."""
        if self.params.merge_every <= 0:
            return False
        self._since += 1
        if self._since < self.params.merge_every:
            return False
        now = self._clock()
        if self._last_s is not None and now - self._last_s < self.min_interval_s:
            return False  # due by frames; comes with the first frame after the interval
        self._since = 0
        self._last_s = now
        return True
