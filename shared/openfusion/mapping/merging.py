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
   voxels), at least ``merge_min_contact_voxels`` of its voxels and at least
   ``merge_min_contact_fraction`` of them touch the other region. The fraction is relative to the
   smaller region so a small fragment lying against a big one counts as one with it, while a big
   region touching another along one edge needs that edge to be long enough.
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

Cost: ``O(n)`` in the labelled voxels ``n`` (13 lookups for radius 1 in a dense index over their
bounding box; ``O(n log n)`` binary search when that box is too big). Written with numpy rather than an Open3D neighbour search because Open3D's
``VoxelBlockGrid`` has no per-voxel neighbour query and its point-cloud KD-tree would need the
points first; the sorted voxel index does the same in a few passes over flat arrays.
"""

from __future__ import annotations

import itertools
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from openfusion.mapping.params import MergeParams


@dataclass
class RegionContacts:
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

    @classmethod
    def empty(cls) -> RegionContacts:
        z = np.zeros(0, np.int64)
        return cls(z, z.copy(), z.copy(), z.copy(), z.copy(), z.copy())

    def surface_of(self) -> dict[int, int]:
        return {int(k): int(n) for k, n in zip(self.keys, self.surface_voxels, strict=True)}


def _half_offsets(radius: int) -> np.ndarray:
    """Offsets of the (2r+1)^3 cube without 0, one of each +-pair (lexicographically positive)."""
    rng = range(-radius, radius + 1)
    out = [d for d in itertools.product(rng, rng, rng) if d > (0, 0, 0)]
    return np.array(out, np.int64)


#: Up to this many cells of the voxels' bounding box, neighbours are looked up in a dense array
#: (64 MiB of int32; a furnished 6 x 5 x 3 m room at 2 cm is 11 M cells), else by binary search.
DENSE_LOOKUP_MAX_CELLS = 16_000_000


def _neighbour_pairs(
    lin: np.ndarray, key: np.ndarray, dims: np.ndarray, radius: int
) -> list[tuple[np.ndarray, np.ndarray]]:
    """For every half-offset, (i, j): voxel ``j`` is voxel ``i``'s neighbour and has another key.
    ``lin``: linear voxel index in a box of ``dims`` that keeps every offset inside it."""
    out = []
    steps = [int((d[0] * dims[1] + d[1]) * dims[2] + d[2]) for d in _half_offsets(radius)]
    if int(np.prod(dims)) <= DENSE_LOOKUP_MAX_CELLS:
        index = np.full(int(np.prod(dims)), -1, np.int32 if len(lin) < 2**31 else np.int64)
        index[lin] = np.arange(len(lin))
        for step in steps:
            j = index[lin + step]
            i = np.flatnonzero(j >= 0)
            j = j[i].astype(np.int64)
            differ = key[j] != key[i]
            if differ.any():
                out.append((i[differ], j[differ]))
        return out
    order = np.argsort(lin, kind="stable")
    lin_sorted = lin[order]
    key_sorted = key[order]
    for step in steps:
        target = lin + step
        pos = np.minimum(np.searchsorted(lin_sorted, target), len(lin_sorted) - 1)
        i = np.flatnonzero((lin_sorted[pos] == target) & (key_sorted[pos] != key))
        if len(i):
            out.append((i, order[pos[i]]))
    return out


def region_contacts(voxels: np.ndarray, keys: np.ndarray, *, radius_vox: int = 1) -> RegionContacts:
    """Contacts between regions from labelled voxels: integer voxel coordinates ``voxels`` (n, 3)
    and their region ``keys`` (n,), each voxel once (see the module docstring)."""
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
    region_keys, surface = np.unique(key, return_counts=True)
    r = int(radius_vox)
    lo = vox.min(axis=0) - r
    dims = vox.max(axis=0) - lo + 1 + r
    rel = vox - lo
    lin = (rel[:, 0] * dims[1] + rel[:, 1]) * dims[2] + rel[:, 2]
    src: list[np.ndarray] = []
    other: list[np.ndarray] = []
    for i, j in _neighbour_pairs(lin, key, dims, r):
        src += [i, j]
        other += [key[j], key[i]]
    if not src:
        z = np.zeros(0, np.int64)
        return RegionContacts(region_keys, surface, z, z.copy(), z.copy(), z.copy())
    s = np.concatenate(src)
    o = np.concatenate(other)
    span = int(key.max()) + 1
    # Each (voxel, other region) once: a voxel touching b through several neighbours counts once.
    touching = np.unique(s * span + o)
    voxel_of, other_of = touching // span, touching % span
    pair_codes, counts = np.unique(key[voxel_of] * span + other_of, return_counts=True)
    owner, against = pair_codes // span, pair_codes % span
    count_of = dict(zip(zip(owner.tolist(), against.tolist(), strict=True), counts.tolist(), strict=True))
    lower = owner < against
    a, b = owner[lower], against[lower]
    ca = counts[lower]
    cb = np.array([count_of.get((int(y), int(x)), 0) for x, y in zip(a, b, strict=True)], np.int64)
    return RegionContacts(region_keys, surface, a, b, ca.astype(np.int64), cb)


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
    ok = known & (small_contact >= p.merge_min_contact_voxels) & (frac >= p.merge_min_contact_fraction)
    idx = np.flatnonzero(ok)
    if len(idx) == 0:
        return plan
    ea = np.stack([dictionary.embedding(int(x)) for x in a[idx]])
    eb = np.stack([dictionary.embedding(int(y)) for y in b[idx]])
    agree = np.einsum("ij,ij->i", ea, eb) >= p.merge_min_cos
    idx = idx[agree]
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


@dataclass
class MergeResult:
    """One merge pass: the plan, voxels relabelled and its time in milliseconds."""

    plan: MergePlan
    voxels_relabelled: int = 0
    contacts_ms: float = 0.0
    total_ms: float = 0.0

    @property
    def merged(self) -> int:
        return len(self.plan.merged_into)


def apply_merges(dictionary: Any, merged_into: dict[int, int], *, embedding: str = "weighted") -> None:
    """Merge every ``b`` into ``merged_into[b]`` in the dictionary as one version (one delta)."""
    if not merged_into:
        return
    with dictionary.batch():
        for b, a in sorted(merged_into.items()):
            dictionary.merge(a, b, embedding=embedding)


def merge_regions(volume: Any, dictionary: Any, params: MergeParams | None = None) -> MergeResult:
    """One merge pass on an in-process map: contacts from ``volume``, merges in ``dictionary``,
    voxels relabelled to the surviving keys."""
    p = params if params is not None else MergeParams()
    t0 = time.perf_counter()
    contacts = volume.region_contacts(radius_vox=p.merge_contact_radius_vox)
    t1 = time.perf_counter()
    plan = plan_merges(dictionary, contacts, p)
    apply_merges(dictionary, plan.merged_into, embedding=p.merge_embedding)
    relabelled = volume.relabel_keys(plan.merged_into) if plan.merged_into else 0
    t2 = time.perf_counter()
    return MergeResult(plan, relabelled, contacts_ms=(t1 - t0) * 1e3, total_ms=(t2 - t0) * 1e3)


class MergeSchedule:
    """Every ``merge_every`` semantic frames (0 = never): :meth:`due` after each semantic frame."""

    def __init__(self, params: MergeParams) -> None:
        self.params = params
        self._since = 0

    def due(self) -> bool:
        """Count one semantic frame; True when a merge pass is due now."""
        if self.params.merge_every <= 0:
            return False
        self._since += 1
        if self._since >= self.params.merge_every:
            self._since = 0
            return True
        return False
