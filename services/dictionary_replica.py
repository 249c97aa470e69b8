"""The copy of the region dictionary that geometry (for checkpoints) and query (for rankings)
keep: a snapshot, then the semantic service's deltas; a gap or a stale version means "fetch a
snapshot". Snapshots and deltas are the wire types the dictionary itself produces
(:meth:`openfusion.mapping.RegionDictionary.snapshot` / ``delta_since``), so nothing is converted.
"""

from __future__ import annotations

import logging
import threading

import numpy as np

from openfusion.bus import QueryError, ServiceRunner
from openfusion.mapping import EmbeddingSpaceError, RegionDictionary, StaleVersionError
from openfusion.wire.endpoints import Endpoint
from openfusion.wire.schemas import DictionaryDelta, DictionaryRequest, DictionarySnapshot

logger = logging.getLogger(__name__)


class DictionaryReplica:
    """A thread-safe copy of the semantic service's dictionary, kept by deltas."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._changed = threading.Condition(self._lock)
        self.dictionary: RegionDictionary | None = None
        self._epoch = 0  # +1 whenever the dictionary is replaced (a snapshot may repeat a version number)

    def __len__(self) -> int:
        return len(self.dictionary) if self.dictionary is not None else 0

    @property
    def embedding_space(self) -> str | None:
        return self.dictionary.embedding_space if self.dictionary is not None else None

    @property
    def version(self) -> int | None:
        with self._lock:
            return self.dictionary.version if self.dictionary is not None else None

    @property
    def state(self) -> tuple[int, int] | None:
        """(replacement epoch, version): equal states hold the same dictionary (None: none yet)."""
        with self._lock:
            return None if self.dictionary is None else (self._epoch, self.dictionary.version)

    def reset(self, dictionary: RegionDictionary | None) -> None:
        with self._lock:
            self._epoch += 1
            self.dictionary = dictionary
            self._changed.notify_all()

    def apply_snapshot(self, msg: DictionarySnapshot) -> dict[int, int]:
        """Replace the copy by the snapshot; returns its merge table (``{merged key: survivor}``),
        which a holder of voxels relabels with (it may have missed the delta of those merges)."""
        dictionary = RegionDictionary.from_snapshot(msg)
        with self._lock:
            self._epoch += 1
            self.dictionary = dictionary
            self._changed.notify_all()
        return dictionary.merge_table()

    def wait_for_version(self, version: int, timeout_s: float) -> bool:
        """Block until this copy is at ``version`` or newer (True) or ``timeout_s`` passed (False)."""
        with self._lock:
            return self._changed.wait_for(
                lambda: self.dictionary is not None and self.dictionary.version >= version, timeout=timeout_s)

    def apply_delta(self, msg: DictionaryDelta) -> bool:
        """Apply a delta; False when it cannot be applied (no base, a gap, another space): resync."""
        with self._lock:
            if self.dictionary is None:
                if msg.prev_version != 0:
                    return False
                self._epoch += 1
                self.dictionary = RegionDictionary(msg.embedding_space, msg.dim)
            try:
                self.dictionary.apply_delta(msg)
            except (StaleVersionError, EmbeddingSpaceError) as exc:
                logger.info("dictionary replica out of sync (%s); a snapshot is needed", exc)
                return False
            self._changed.notify_all()
        return True

    def resolve_keys(self, keys: np.ndarray) -> np.ndarray:
        """``keys`` with every key this replica saw merged away replaced by its survivor."""
        with self._lock:
            return self.dictionary.resolve_keys(keys) if self.dictionary is not None else keys

    def snapshot(self) -> DictionarySnapshot | None:
        with self._lock:
            return self.dictionary.snapshot() if self.dictionary is not None else None

    def top_k(self, vector: np.ndarray, k: int) -> list[tuple[int, float]]:
        with self._lock:
            if self.dictionary is None:
                return []
            keys, scores = self.dictionary.top_k(vector, k)
        return [(int(a), float(b)) for a, b in zip(keys, scores, strict=True)]

    def top_k_at_state(self, vector: np.ndarray, k: int) -> tuple[tuple[int, int] | None, list[tuple[int, float]]]:
        """:meth:`top_k` and the :attr:`state` it was computed at (None: no dictionary)."""
        with self._lock:
            if self.dictionary is None:
                return None, []
            version = (self._epoch, self.dictionary.version)
            keys, scores = self.dictionary.top_k(vector, k)
        return version, [(int(a), float(b)) for a, b in zip(keys, scores, strict=True)]

    def embeddings_for(self, keys: list[int]) -> np.ndarray:
        """(len(keys), dim) unit embeddings of ``keys`` (zero rows for keys it does not hold)."""
        with self._lock:
            d = self.dictionary
            if d is None:
                return np.zeros((len(keys), 0), np.float32)
            return np.stack([d.embedding(int(k)) if int(k) in d else np.zeros(d.dim, np.float32) for k in keys]
                            ) if keys else np.zeros((0, d.dim), np.float32)

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
