"""What the query service keeps between queries, so a query pays only for what changed.

Profile of a text query at 10,000 regions before these caches (in-process, MiniLM on torch, one
intra-op thread, 2-core host; ``bench/bench_services.py`` measures the same over Zenoh): text
encoding ~11 ms, nearby regions of the five hits ~6 ms (box distances to every region, then the
relation rules, per hit), sorting the summaries into boxes ~1 ms, top-k of 10,000 ~1.7 ms,
relevancy of the 32-region match pool < 0.5 ms, reply encoding < 0.5 ms. So:

- :class:`TextEmbeddings`: the embeddings of texts already asked (an LRU by text, bounded by
  ``text_cache_size``): a robot or a page asks the same few texts again and again. The encoder is
  fixed for the life of the service, so entries never go stale; the ONNX runtime tower
  (``query.text_backend``) makes a text not yet seen cost ~3 ms instead of ~11.
- :class:`SummaryDerived`: what is computed from one set of region summaries alone: the boxes of
  answerable regions (sorted once) and each region's nearby list (memoised per key). It hangs on
  the :class:`~services.query.region_hits.RegionSummaries` object, so new summaries (a fetch) start
  from an empty one: invalidation is the replacement itself. Summaries fetched again from an
  unchanged map (the background refresh runs every second while queries come) are compared
  array by array with the last ones and, when equal, keep their caches.
- :class:`RankCache`: the candidate lists (top-k by cosine) per text, valid for ONE dictionary
  state (the replica's epoch and version): a delta bumps the version, a snapshot the epoch, and
  the next lookup empties it.

The answers are the library's (:func:`openfusion.mapping.answers.answer_text`) on the same inputs:
caching changes when work is done, never what is answered (tests/unit/test_query_caches.py).
"""

from __future__ import annotations

import collections
import threading
from collections.abc import Callable, Hashable

import numpy as np

from openfusion.mapping.relations import Nearby, RegionBoxes, nearby_regions

#: Texts whose embeddings are kept (384 floats each for MiniLM: 1,024 texts ~1.5 MB).
DEFAULT_TEXT_CACHE_SIZE = 1024


class TextEmbeddings:
    """Embeddings by text, least recently used first out; thread-safe. ``encode(texts)`` (the
    service's text encoder) is called once per miss batch, all missing texts in one call."""

    def __init__(self, encode: Callable[[list[str]], np.ndarray], *, max_texts: int = DEFAULT_TEXT_CACHE_SIZE) -> None:
        if max_texts < 0:
            raise ValueError(f"max_texts must be >= 0, got {max_texts}")
        self._encode = encode
        self.max_texts = int(max_texts)
        self._lru: collections.OrderedDict[str, np.ndarray] = collections.OrderedDict()
        self._lock = threading.Lock()
        self.hits = 0
        self.misses = 0

    def __len__(self) -> int:
        with self._lock:
            return len(self._lru)

    def encode(self, texts: list[str]) -> np.ndarray:
        """(len(texts), dim) float32 rows, as ``encode(texts)`` returns them."""
        found: dict[str, np.ndarray] = {}
        with self._lock:
            for text in texts:
                vec = self._lru.get(text)
                if vec is not None:
                    self._lru.move_to_end(text)
                    found[text] = vec
            self.hits += len(found)
        missing = list(dict.fromkeys(t for t in texts if t not in found))
        if missing:
            fresh = np.asarray(self._encode(missing), np.float32).reshape(len(missing), -1)
            fresh.setflags(write=False)  # rows are shared by later replies: nobody writes into them
            with self._lock:
                self.misses += len(missing)
                for text, vec in zip(missing, fresh, strict=True):
                    found[text] = vec
                    if self.max_texts:
                        self._lru[text] = vec
                        self._lru.move_to_end(text)
                while len(self._lru) > self.max_texts:
                    self._lru.popitem(last=False)
        return np.stack([found[t] for t in texts]) if texts else np.zeros((0, 0), np.float32)


class SummaryDerived:
    """Boxes and nearby lists computed from one set of region summaries (immutable once built).

    ``boxes_of(min_points)`` builds the :class:`RegionBoxes` once per ``min_points``;
    ``nearby(key, boxes, up_axis)`` memoises :func:`~openfusion.mapping.relations.nearby_regions`
    per (boxes, key, up axis). Thread-safe: two queries may compute the same entry at once; both
    get the same value (a pure function of the same inputs)."""

    def __init__(self, build_boxes: Callable[[int], RegionBoxes]) -> None:
        self._build_boxes = build_boxes
        self._boxes: dict[int, RegionBoxes] = {}
        self._nearby: dict[tuple[int, int, str], list[Nearby]] = {}
        self._lock = threading.Lock()
        self.nearby_hits = 0
        self.nearby_misses = 0

    def boxes_of(self, min_points: int) -> RegionBoxes:
        with self._lock:
            boxes = self._boxes.get(min_points)
        if boxes is None:
            boxes = self._build_boxes(min_points)
            with self._lock:
                boxes = self._boxes.setdefault(min_points, boxes)
        return boxes

    def nearby(self, key: int, boxes: RegionBoxes, *, up_axis: str) -> list[Nearby]:
        """:func:`nearby_regions` of ``key`` in ``boxes`` (one of :meth:`boxes_of`'s), memoised."""
        memo_key = (id(boxes), int(key), up_axis)
        with self._lock:
            found = self._nearby.get(memo_key)
            if found is not None:
                self.nearby_hits += 1
                return list(found)
        found = nearby_regions(int(key), boxes, up_axis=up_axis)
        with self._lock:
            self.nearby_misses += 1
            self._nearby[memo_key] = found
        return list(found)


class RankCache:
    """Candidate lists ``[(key, cosine), …]`` by (text, n) for one dictionary state.

    :meth:`get` / :meth:`put` name the state they hold for (the replica's (epoch, version)); a
    lookup at another state empties the cache first (a delta or snapshot changed embeddings, added
    or merged regions). None: no dictionary, nothing cached. Bounded: past ``max_entries`` the
    oldest entry goes."""

    def __init__(self, *, max_entries: int = DEFAULT_TEXT_CACHE_SIZE) -> None:
        self.max_entries = int(max_entries)
        self._version: Hashable = None
        self._entries: collections.OrderedDict[tuple[str, int], list[tuple[int, float]]] = collections.OrderedDict()
        self._lock = threading.Lock()
        self.invalidations = 0

    def _at(self, version: Hashable) -> None:
        if version != self._version:
            if self._entries:
                self.invalidations += 1
            self._entries.clear()
            self._version = version

    def get(self, version: Hashable, text: str, n: int) -> list[tuple[int, float]] | None:
        if version is None:
            return None
        with self._lock:
            self._at(version)
            found = self._entries.get((text, n))
            return None if found is None else list(found)

    def put(self, version: Hashable, text: str, n: int, ranked: list[tuple[int, float]]) -> None:
        if version is None or not self.max_entries:
            return
        with self._lock:
            self._at(version)  # computed at an older state than the last lookup's: churn, never a stale hit
            self._entries[(text, n)] = list(ranked)
            while len(self._entries) > self.max_entries:
                self._entries.popitem(last=False)

    def __len__(self) -> int:
        with self._lock:
            return len(self._entries)
