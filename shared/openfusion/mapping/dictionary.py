"""Region dictionary: key -> embedding (running mean), observation count, label text.

Storage is dense (rows of a float32 matrix), so ranking 10,000 regions against a query is one
matrix-vector product. Keys are allocated from 0 upwards and never reused (a merged-away key stays
dead), so a key seen in the volume always means the same region.

Versioning: ``version`` increments once per change batch (one :meth:`RegionDictionary.batch`
block, or one call of a mutating method outside a batch). ``delta_since(v)`` returns what changed
after version ``v`` (upserted rows, removed keys and what each was merged into), ``apply_delta``
replays it on a replica, and ``snapshot`` / ``from_snapshot`` copy the whole dictionary. Snapshots
and deltas are the wire's own types (:class:`openfusion.wire.schemas.DictionarySnapshot`,
:class:`~openfusion.wire.schemas.DictionaryDelta`): one type per concept, the same in the library,
on the bus and in replicas, with no conversion in between. On the wire a label is ``""`` when a
region has none; the dictionary's API speaks ``None``.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator

import numpy as np

from openfusion.blas import single_thread_blas
from openfusion.mapping.errors import EmbeddingSpaceError, StaleVersionError
from openfusion.wire.schemas import DictionaryDelta, DictionarySnapshot

logger = logging.getLogger(__name__)

def _unit(v: np.ndarray) -> np.ndarray:
    norm = np.linalg.norm(v, axis=-1, keepdims=True)
    return (v / np.maximum(norm, 1e-12)).astype(np.float32)


class RegionDictionary:
    """Region embeddings of one map, in one named embedding space of dimension ``dim``."""

    def __init__(self, embedding_space: str, dim: int, *, initial_capacity: int = 256) -> None:
        if not embedding_space or not isinstance(embedding_space, str):
            raise ValueError(f"embedding_space must be a non-empty string, got {embedding_space!r}")
        if not isinstance(dim, (int, np.integer)) or dim < 1:
            raise ValueError(f"dim must be a positive int, got {dim!r}")
        self.embedding_space = embedding_space
        self.dim = int(dim)
        cap = max(int(initial_capacity), 1)
        self._means = np.zeros((cap, self.dim), np.float32)
        # Unit embeddings stored transposed (d, capacity): ``q @ units_t[:, :n]`` is a BLAS gemv
        # that ranks 10,000 x 512 in well under a millisecond (the row-major product was ~15x slower).
        self._units_t = np.zeros((self.dim, cap), np.float32)
        self._counts = np.zeros(cap, np.int64)
        self._keys = np.zeros(cap, np.int64)
        self._labels: list[str | None] = []
        self._row_of: dict[int, int] = {}
        self._size = 0
        self.next_key = 0
        self.version = 0
        self._history_start = 0  # deltas can be produced from this version on
        self._changed_at: dict[int, int] = {}  # key -> version of its last change
        self._removed_at: dict[int, int] = {}  # key -> version it was removed
        self._merges: list[tuple[int, int, int]] = []  # (merged, into, version)
        self._merged_into: dict[int, int] = {}  # merged key -> key it was merged into (all history)
        self._batch_depth = 0
        self._batch_dirty = False

    # ------------------------------------------------------------------ basics
    def __len__(self) -> int:
        return self._size

    def __contains__(self, key: object) -> bool:
        return isinstance(key, (int, np.integer)) and int(key) in self._row_of

    @property
    def keys(self) -> np.ndarray:
        """Live keys (k,) int64, in row order."""
        return self._keys[: self._size].copy()

    def unit_embeddings(self) -> np.ndarray:
        """(k, d) unit-norm embeddings in row order (a read-only view)."""
        view = self._units_t[:, : self._size].T
        view.flags.writeable = False
        return view

    def embedding(self, key: int) -> np.ndarray:
        """Unit-norm embedding of ``key``."""
        return self._units_t[:, self._row(key)].copy()

    def mean_embedding(self, key: int) -> np.ndarray:
        return self._means[self._row(key)].copy()

    def count(self, key: int) -> int:
        return int(self._counts[self._row(key)])

    def support_of(self, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(counts int64 (k,), agreement float32 (k,))`` of each key: how many embeddings its entry
        averages, and the length of that mean of unit vectors (1: every view agreed; a mean of views
        of two objects is shorter). A key not in the dictionary: 0 and 0."""
        keys = np.asarray(keys).reshape(-1)
        counts, agreement = np.zeros(len(keys), np.int64), np.zeros(len(keys), np.float32)
        for i, k in enumerate(keys.tolist()):
            row = self._row_of.get(int(k))
            if row is not None:
                counts[i] = self._counts[row]
                agreement[i] = np.linalg.norm(self._means[row])
        return counts, agreement

    def label(self, key: int) -> str | None:
        return self._labels[self._row(key)]

    def _row(self, key: int) -> int:
        try:
            return self._row_of[int(key)]
        except KeyError:
            raise KeyError(f"region key {key} is not in the dictionary") from None

    def check_space(self, embedding_space: str | None, dim: int | None = None) -> None:
        """Raise :class:`EmbeddingSpaceError` when the space (or dimension) differs from this map's."""
        if embedding_space is not None and embedding_space != self.embedding_space:
            raise EmbeddingSpaceError(
                f"embedding space {embedding_space!r} does not match the map's {self.embedding_space!r}"
            )
        if dim is not None and dim != self.dim:
            raise EmbeddingSpaceError(f"embedding dimension {dim} does not match the map's {self.dim}")

    def _check_vector(self, vector: np.ndarray, what: str = "embedding") -> np.ndarray:
        v = np.asarray(vector, dtype=np.float32).reshape(-1)
        if v.shape[0] != self.dim:
            raise EmbeddingSpaceError(f"{what} has dimension {v.shape[0]}, the map's space has {self.dim}")
        if not np.isfinite(v).all():
            raise ValueError(f"{what} contains NaN or inf")
        if float(np.linalg.norm(v)) < 1e-12:
            raise ValueError(f"{what} has zero norm")
        return v

    # ------------------------------------------------------------------ change batches
    @contextlib.contextmanager
    def batch(self) -> Iterator[RegionDictionary]:
        """Group changes into one version increment."""
        self._batch_depth += 1
        try:
            yield self
        finally:
            self._batch_depth -= 1
            if self._batch_depth == 0 and self._batch_dirty:
                self._batch_dirty = False

    def _begin_change(self) -> int:
        """Version number the current change belongs to."""
        if self._batch_depth > 0:
            if not self._batch_dirty:
                self.version += 1
                self._batch_dirty = True
            return self.version
        self.version += 1
        return self.version

    def _grow(self) -> None:
        cap = len(self._keys) * 2
        means = np.zeros((cap, self.dim), np.float32)
        means[: self._size] = self._means[: self._size]
        self._means = means
        units_t = np.zeros((self.dim, cap), np.float32)
        units_t[:, : self._size] = self._units_t[:, : self._size]
        self._units_t = units_t
        for name in ("_counts", "_keys"):
            old = getattr(self, name)
            new = np.zeros(cap, np.int64)
            new[: self._size] = old[: self._size]
            setattr(self, name, new)

    # ------------------------------------------------------------------ mutation
    def add(self, embedding: np.ndarray, *, label: str | None = None, count: int = 1) -> int:
        """New region with this embedding; returns its key."""
        v = self._check_vector(embedding)
        if count < 1:
            raise ValueError(f"count must be >= 1, got {count}")
        version = self._begin_change()
        key = self.next_key
        self.next_key += 1
        self._insert_row(key, v, int(count), label)
        self._changed_at[key] = version
        return key

    def _insert_row(self, key: int, mean: np.ndarray, count: int, label: str | None) -> None:
        if self._size == len(self._keys):
            self._grow()
        row = self._size
        self._means[row] = mean
        self._units_t[:, row] = _unit(mean)
        self._counts[row] = count
        self._keys[row] = key
        self._labels.append(label)
        self._row_of[key] = row
        self._size += 1

    def observe(self, key: int, embedding: np.ndarray, *, label: str | None = None) -> None:
        """A matched observation: running mean of embeddings, count + 1 (label set if none yet)."""
        row = self._row(key)
        v = self._check_vector(embedding)
        version = self._begin_change()
        n = self._counts[row]
        mean = self._means[row] + (v - self._means[row]) / np.float32(n + 1)
        self._means[row] = mean
        self._units_t[:, row] = _unit(mean)
        self._counts[row] = n + 1
        if label is not None and self._labels[row] is None:
            self._labels[row] = label
        self._changed_at[int(key)] = version

    def observe_many(
        self, keys: np.ndarray, embeddings: np.ndarray, labels: list[str | None] | None = None
    ) -> None:
        """Vectorised :meth:`observe` for distinct ``keys`` (k,) with ``embeddings`` (k, d); one version."""
        keys = np.asarray(keys, np.int64).reshape(-1)
        if len(keys) == 0:
            return
        if len(np.unique(keys)) != len(keys):
            raise ValueError("observe_many needs distinct keys")
        E = np.asarray(embeddings, np.float32)
        if E.shape != (len(keys), self.dim):
            raise EmbeddingSpaceError(f"embeddings must be ({len(keys)}, {self.dim}), got {E.shape}")
        norms = np.linalg.norm(E, axis=1)
        if not (np.isfinite(norms).all() and (norms > 1e-12).all()):
            raise ValueError("embeddings must be finite and non-zero")
        rows = np.array([self._row(int(k)) for k in keys], np.int64)
        version = self._begin_change()
        n = self._counts[rows].astype(np.float32)
        mean = self._means[rows] + (E - self._means[rows]) / (n + 1)[:, None]
        self._means[rows] = mean
        self._units_t[:, rows] = _unit(mean).T
        self._counts[rows] += 1
        for i, key in enumerate(keys):
            if labels is not None and labels[i] is not None and self._labels[rows[i]] is None:
                self._labels[rows[i]] = labels[i]
            self._changed_at[int(key)] = version

    def set_label(self, key: int, label: str | None) -> None:
        row = self._row(key)
        version = self._begin_change()
        self._labels[row] = label
        self._changed_at[int(key)] = version

    def _remove_row(self, key: int) -> None:
        row = self._row_of.pop(key)
        last = self._size - 1
        if row != last:
            self._means[row] = self._means[last]
            self._units_t[:, row] = self._units_t[:, last]
            self._counts[row] = self._counts[last]
            self._keys[row] = self._keys[last]
            self._labels[row] = self._labels[last]
            self._row_of[int(self._keys[row])] = row
        self._labels.pop()
        self._size -= 1

    def remove(self, key: int) -> None:
        """Delete a region (its voxels should be cleared with ``volume.relabel_keys({key: -1})``)."""
        self._row(key)
        version = self._begin_change()
        self._remove_row(int(key))
        self._changed_at.pop(int(key), None)
        self._removed_at[int(key)] = version

    def merge(self, a: int, b: int, *, embedding: str = "weighted") -> int:
        """Merge region ``b`` into ``a`` (counts summed); ``b`` disappears.

        ``embedding``: ``"weighted"`` (default) the count-weighted mean of the two running means,
        ``"mean"`` their plain mean, ``"first"`` ``a``'s (the alternatives exist to measure the
        choice; :mod:`openfusion.mapping.merging` says why weighted). Returns ``a``. The caller
        relabels voxels with ``volume.relabel_keys({b: a})`` (``SemanticMapper.merge_regions``
        and :func:`openfusion.mapping.merging.merge_regions` do both).
        """
        a, b = int(a), int(b)
        if a == b:
            raise ValueError(f"cannot merge region {a} with itself")
        if embedding not in ("weighted", "mean", "first"):
            raise ValueError(f"embedding must be 'weighted', 'mean' or 'first', got {embedding!r}")
        ra, rb = self._row(a), self._row(b)
        version = self._begin_change()
        na, nb = self._counts[ra], self._counts[rb]
        if embedding == "weighted":
            mean = (self._means[ra] * na + self._means[rb] * nb) / np.float32(na + nb)
        elif embedding == "mean":
            mean = (self._means[ra] + self._means[rb]) / np.float32(2)
        else:
            mean = self._means[ra].copy()
        self._means[ra] = mean
        self._units_t[:, ra] = _unit(mean)
        self._counts[ra] = na + nb
        if self._labels[ra] is None:
            self._labels[ra] = self._labels[rb]
        self._changed_at[a] = version
        self._remove_row(b)
        self._changed_at.pop(b, None)
        self._removed_at[b] = version
        self._merges.append((b, a, version))
        self._merged_into[b] = a
        return a

    def survivor_of(self, key: int) -> int | None:
        """The live key ``key`` ended in: itself when live, the region it was merged into (following
        later merges) when merged here or in a delta this replica applied, else None."""
        key = int(key)
        seen = 0
        while key not in self._row_of:
            nxt = self._merged_into.get(key)
            if nxt is None or seen > len(self._merged_into):
                return None
            key, seen = nxt, seen + 1
        return key

    def resolve_keys(self, keys: np.ndarray) -> np.ndarray:
        """``keys`` (any shape, int) with every merged-away key replaced by its survivor (others kept)."""
        arr = np.asarray(keys)
        if not self._merged_into or arr.size == 0:
            return arr
        out = arr.copy()
        for old in np.unique(arr[np.isin(arr, list(self._merged_into))]):
            new = self.survivor_of(int(old))
            if new is not None:
                out[arr == old] = new
        return out

    # ------------------------------------------------------------------ queries
    def top_k(self, vector: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Keys (k,) and cosine scores (k,) of the ``k`` regions most similar to ``vector``, best first;
        equal scores rank by observation count (most first), then key."""
        if k < 1:
            raise ValueError(f"k must be >= 1, got {k}")
        v = _unit(self._check_vector(vector, "query vector"))
        n = self._size
        if n == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.float32)
        with single_thread_blas():
            scores = v @ self._units_t[:, :n]
        k = min(int(k), n)
        if k < n:
            part = np.argpartition(-scores, k - 1)[:k]
            # Regions tying with the k-th score all compete for the last places (on count, below).
            tied = np.flatnonzero(scores >= scores[part].min())
            if len(tied) > k:
                part = tied
        else:
            part = np.arange(n)
        # Best score first; equal scores: the most observed region first (a fragment seen once
        # should not outrank the object's main region), then the older key.
        order = part[np.lexsort((self._keys[part], -self._counts[part], -scores[part]))][:k]
        return self._keys[order].copy(), scores[order].astype(np.float32)

    def similarities(self, vectors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(keys (k,), cosine matrix (k, c)) of every region against ``c`` vectors."""
        V = np.asarray(vectors, np.float32)
        if V.ndim != 2 or V.shape[1] != self.dim:
            raise EmbeddingSpaceError(f"vectors must be (c, {self.dim}), got {V.shape}")
        return self.keys, (_unit(V) @ self._units_t[:, : self._size]).T

    # ------------------------------------------------------------------ deltas / snapshots
    def merge_table(self) -> dict[int, int]:
        """``{merged-away key: the live key it ended in}`` for every merge this dictionary knows
        (keys whose survivor was later deleted are left out: their voxels are gone too)."""
        table = {old: self.survivor_of(old) for old in self._merged_into}
        return {old: new for old, new in table.items() if new is not None}

    def snapshot(self) -> DictionarySnapshot:
        """The whole dictionary at its current version (running-mean embeddings, not normalised),
        with its merge table (a replica that missed a merge delta learns the merge from it)."""
        n = self._size
        merges = self.merge_table()
        return DictionarySnapshot(
            embedding_space=self.embedding_space,
            dim=self.dim,
            version=self.version,
            next_key=self.next_key,
            keys=self._keys[:n].astype(np.int32),
            embeddings=self._means[:n].copy(),
            counts=self._counts[:n].copy(),
            labels=[label or "" for label in self._labels],
            merged_keys=np.array(sorted(merges), np.int32),
            merged_into=np.array([merges[k] for k in sorted(merges)], np.int32),
        )

    @classmethod
    def from_snapshot(cls, snapshot: DictionarySnapshot) -> RegionDictionary:
        """A replica equal to the snapshot; raises ``ValueError`` on keys beyond ``next_key``, counts
        below 1 or non-finite embeddings (the message itself checks shapes and uniqueness)."""
        keys = np.asarray(snapshot.keys, np.int64).reshape(-1)
        means = np.asarray(snapshot.embeddings, np.float32)
        counts = np.asarray(snapshot.counts, np.int64).reshape(-1)
        k = len(keys)
        if k and (keys.min() < 0 or keys.max() >= snapshot.next_key):
            raise ValueError("snapshot keys must be >= 0 and below next_key")
        if k and (counts.min() < 1 or not np.isfinite(means).all()):
            raise ValueError("snapshot counts must be >= 1 and embeddings finite")
        d = cls(snapshot.embedding_space, int(snapshot.dim), initial_capacity=max(k, 1))
        for i in range(k):
            d._insert_row(int(keys[i]), means[i], int(counts[i]), snapshot.labels[i] or None)
        d.next_key = int(snapshot.next_key)
        d.version = int(snapshot.version)
        d._history_start = d.version
        d._changed_at = {int(key): d.version for key in keys}
        d._merged_into = {int(a): int(b) for a, b in zip(snapshot.merged_keys, snapshot.merged_into, strict=True)}
        return d

    def delta_since(self, version: int) -> DictionaryDelta | None:
        """Everything that changed after ``version`` (None when nothing did); raises
        :class:`StaleVersionError` if this dictionary's history does not reach back that far (the
        replica should fetch a snapshot)."""
        version = int(version)
        if version > self.version:
            raise StaleVersionError(f"version {version} is newer than the dictionary's {self.version}")
        if version < self._history_start:
            raise StaleVersionError(
                f"history starts at version {self._history_start}; cannot build a delta from {version}"
            )
        if version == self.version:
            return None
        changed = sorted(k for k, v in self._changed_at.items() if v > version)
        rows = np.array([self._row_of[k] for k in changed], np.int64)
        removed = sorted(k for k, v in self._removed_at.items() if v > version)
        merged_into = {b: a for b, a, v in self._merges if v > version}
        return DictionaryDelta(
            embedding_space=self.embedding_space,
            dim=self.dim,
            version=self.version,
            prev_version=version,
            next_key=self.next_key,
            keys=np.array(changed, np.int32),
            embeddings=self._means[rows].copy() if len(rows) else np.zeros((0, self.dim), np.float32),
            counts=self._counts[rows].copy() if len(rows) else np.zeros(0, np.int64),
            labels=[self._labels[r] or "" for r in rows],
            removed_keys=np.array(removed, np.int32),
            merged_into=np.array([merged_into.get(k, -1) for k in removed], np.int32),
        )

    def apply_delta(self, delta: DictionaryDelta) -> None:
        """Replay a delta on a replica. Raises :class:`StaleVersionError` when versions between this
        replica and the delta are missing, :class:`EmbeddingSpaceError` for another space."""
        self.check_space(delta.embedding_space, int(delta.dim))
        if delta.prev_version > self.version:
            raise StaleVersionError(
                f"delta starts at version {delta.prev_version} but the replica is at {self.version}; "
                "fetch a snapshot"
            )
        if delta.version <= self.version:
            return  # already applied
        keys = np.asarray(delta.keys, np.int64).reshape(-1)
        means = np.asarray(delta.embeddings, np.float32)
        counts = np.asarray(delta.counts, np.int64).reshape(-1)
        to_version = int(delta.version)
        for key, into in zip(np.asarray(delta.removed_keys, np.int64), np.asarray(delta.merged_into, np.int64),
                             strict=True):
            if int(key) in self._row_of:
                self._remove_row(int(key))
                self._changed_at.pop(int(key), None)
            self._removed_at[int(key)] = to_version
            if into >= 0:
                self._merges.append((int(key), int(into), to_version))
                self._merged_into[int(key)] = int(into)
        for i, key in enumerate(keys):
            key = int(key)
            label = delta.labels[i] or None
            if key in self._row_of:
                row = self._row_of[key]
                self._means[row] = means[i]
                self._units_t[:, row] = _unit(means[i])
                self._counts[row] = counts[i]
                self._labels[row] = label
            else:
                self._insert_row(key, means[i], int(counts[i]), label)
            self._changed_at[key] = to_version
        self.next_key = max(self.next_key, int(delta.next_key))
        self.version = to_version

    @staticmethod
    def merges_of(delta: DictionaryDelta) -> dict[int, int]:
        """``{merged key: key it was merged into}`` of a delta (the volume relabels those voxels)."""
        return {int(r): int(m) for r, m in zip(delta.removed_keys, delta.merged_into, strict=True) if m >= 0}
