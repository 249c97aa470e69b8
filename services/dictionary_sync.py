"""The region dictionary on the bus: conversions between the library's snapshots/deltas
(:mod:`openfusion.mapping.dictionary`) and the bus messages, and the replica that geometry and
query keep in sync (snapshot + deltas; a gap or a stale version means "fetch a snapshot").
"""

from __future__ import annotations

import logging
import threading

import numpy as np

from openfusion.bus import QueryError, ServiceRunner
from openfusion.mapping import DictionaryDelta as LibDelta
from openfusion.mapping import DictionarySnapshot as LibSnapshot
from openfusion.mapping import EmbeddingSpaceError, RegionDictionary, StaleVersionError
from openfusion.wire.endpoints import Endpoint
from openfusion.wire.schemas import DictionaryDelta, DictionaryRequest, DictionarySnapshot

logger = logging.getLogger(__name__)


def _labels_out(labels: list[str | None]) -> list[str]:
    return [label or "" for label in labels]


def _labels_in(labels: list[str]) -> list[str | None]:
    return [label or None for label in labels]


def snapshot_message(dictionary: RegionDictionary) -> DictionarySnapshot:
    snap = dictionary.snapshot()
    return DictionarySnapshot(
        embedding_space=snap.embedding_space, dim=snap.dim, version=snap.version, next_key=snap.next_key,
        keys=snap.keys.astype(np.int32), embeddings=snap.mean_embeddings.astype(np.float32),
        counts=snap.counts.astype(np.int64), labels=_labels_out(snap.labels),
    )


def dictionary_from_snapshot(msg: DictionarySnapshot) -> RegionDictionary:
    """A dictionary equal to the message (ValueError when its arrays are inconsistent)."""
    return RegionDictionary.from_snapshot(LibSnapshot(
        embedding_space=msg.embedding_space, dim=msg.dim, version=msg.version, next_key=msg.next_key,
        keys=msg.keys.astype(np.int64), mean_embeddings=np.asarray(msg.embeddings, np.float32),
        counts=msg.counts.astype(np.int64), labels=_labels_in(msg.labels),
    ))


def delta_message(dictionary: RegionDictionary, *, since_version: int) -> DictionaryDelta | None:
    """The changes after ``since_version`` as a message, or None when nothing changed."""
    if dictionary.version <= since_version:
        return None
    d = dictionary.delta_since(since_version)
    merged_into = dict((int(b), int(a)) for b, a in d.merges.reshape(-1, 2))
    removed = [int(k) for k in d.removed_keys]
    return DictionaryDelta(
        embedding_space=d.embedding_space, dim=d.dim, version=d.to_version, prev_version=d.from_version,
        next_key=d.next_key, keys=d.keys.astype(np.int32), embeddings=d.mean_embeddings.astype(np.float32),
        counts=d.counts.astype(np.int64), labels=_labels_out(d.labels),
        removed_keys=np.array(removed, np.int32), merged_into=np.array([merged_into.get(k, -1) for k in removed], np.int32),
    )


def library_delta(msg: DictionaryDelta) -> LibDelta:
    merges = [(int(r), int(m)) for r, m in zip(msg.removed_keys, msg.merged_into, strict=True) if m >= 0]
    return LibDelta(
        embedding_space=msg.embedding_space, dim=msg.dim, from_version=msg.prev_version, to_version=msg.version,
        next_key=msg.next_key, keys=msg.keys.astype(np.int64), mean_embeddings=np.asarray(msg.embeddings, np.float32),
        counts=msg.counts.astype(np.int64), labels=_labels_in(msg.labels),
        removed_keys=msg.removed_keys.astype(np.int64), merges=np.array(merges, np.int64).reshape(-1, 2),
    )


class DictionaryReplica:
    """A thread-safe copy of the semantic service's dictionary, kept by deltas."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.dictionary: RegionDictionary | None = None

    def __len__(self) -> int:
        return len(self.dictionary) if self.dictionary is not None else 0

    @property
    def embedding_space(self) -> str | None:
        return self.dictionary.embedding_space if self.dictionary is not None else None

    def reset(self, dictionary: RegionDictionary | None) -> None:
        with self._lock:
            self.dictionary = dictionary

    def apply_snapshot(self, msg: DictionarySnapshot) -> None:
        dictionary = dictionary_from_snapshot(msg)
        with self._lock:
            self.dictionary = dictionary

    def apply_delta(self, msg: DictionaryDelta) -> bool:
        """Apply a delta; False when it cannot be applied (no base, a gap, another space): resync."""
        with self._lock:
            if self.dictionary is None:
                if msg.prev_version != 0:
                    return False
                self.dictionary = RegionDictionary(msg.embedding_space, msg.dim)
            try:
                self.dictionary.apply_delta(library_delta(msg))
            except (StaleVersionError, EmbeddingSpaceError) as exc:
                logger.info("dictionary replica out of sync (%s); a snapshot is needed", exc)
                return False
        return True

    def merges_of(self, msg: DictionaryDelta) -> dict[int, int]:
        """{merged key: key it was merged into} of a delta (the volume relabels those voxels)."""
        return {int(r): int(m) for r, m in zip(msg.removed_keys, msg.merged_into, strict=True) if m >= 0}

    def snapshot_message(self) -> DictionarySnapshot | None:
        with self._lock:
            return snapshot_message(self.dictionary) if self.dictionary is not None else None

    def top_k(self, vector: np.ndarray, k: int) -> list[tuple[int, float]]:
        with self._lock:
            if self.dictionary is None:
                return []
            keys, scores = self.dictionary.top_k(vector, k)
        return [(int(a), float(b)) for a, b in zip(keys, scores, strict=True)]

    def labels_for(self, keys: list[int]) -> dict[int, str]:
        """Label text of each of ``keys`` ("" when none or unknown)."""
        with self._lock:
            d = self.dictionary
            return {int(k): (d.label(int(k)) if d is not None and int(k) in d else None) or "" for k in keys}

    @staticmethod
    def fetch_snapshot(
        runner: ServiceRunner, endpoint: Endpoint[DictionaryRequest, DictionarySnapshot], *, timeout_s: float = 3.0
    ) -> DictionarySnapshot | None:
        """A snapshot from ``endpoint`` (the semantic service's or geometry's), None when it does not answer."""
        try:
            return runner.call(endpoint, DictionaryRequest(), timeout_s=timeout_s)
        except QueryError as exc:
            logger.info("no dictionary snapshot from %s: %s", endpoint.path, exc.reason)
            return None
