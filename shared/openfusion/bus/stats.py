"""Thread-safe counters of one service, published as its :class:`HealthStats`."""

from __future__ import annotations

import collections
import os
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from openfusion.wire.schemas import HealthStats


class ServiceStats:
    """Thread-safe counters of one service: processed items (fps), latency, drops, errors and
    named counters; :meth:`snapshot` makes the :class:`HealthStats` message."""

    def __init__(self, *, window_s: float = 5.0, latency_samples: int = 1024) -> None:
        self._lock = threading.Lock()
        self._window_s = window_s
        self._done: collections.deque[float] = collections.deque()
        self._latencies_ms: collections.deque[float] = collections.deque(maxlen=latency_samples)
        self.started = time.monotonic()
        self.processed = 0
        self.drops = 0
        self.errors = 0
        self.counters: dict[str, float] = {}
        #: Called by :meth:`snapshot` for :attr:`HealthStats.robots` (geometry: each robot's stream).
        self.robots_provider: Callable[[], dict[str, Any]] | None = None

    def record(self, latency_s: float | None = None) -> None:
        """One item processed (counts towards fps), optionally with its latency in seconds."""
        now = time.monotonic()
        with self._lock:
            self.processed += 1
            self._done.append(now)
            while self._done and self._done[0] < now - self._window_s:
                self._done.popleft()
            if latency_s is not None:
                self._latencies_ms.append(latency_s * 1000.0)

    def add_drops(self, n: int = 1) -> None:
        with self._lock:
            self.drops += n

    def add_error(self, n: int = 1) -> None:
        with self._lock:
            self.errors += n

    def incr(self, name: str, by: float = 1.0) -> None:
        with self._lock:
            self.counters[name] = self.counters.get(name, 0.0) + by

    def set(self, name: str, value: float) -> None:
        with self._lock:
            self.counters[name] = float(value)

    def fps(self) -> float:
        now = time.monotonic()
        with self._lock:
            while self._done and self._done[0] < now - self._window_s:
                self._done.popleft()
            span = min(self._window_s, now - self.started)
            return len(self._done) / span if span > 0 else 0.0

    def snapshot(self, *, service: str, map_id: str) -> HealthStats:
        fps = self.fps()
        robots = self.robots_provider() if self.robots_provider is not None else {}
        with self._lock:
            lat = np.asarray(self._latencies_ms, dtype=np.float64)
            p50, p99 = (float(np.percentile(lat, 50)), float(np.percentile(lat, 99))) if lat.size else (0.0, 0.0)
            return HealthStats(
                service=service,
                map_id=map_id,
                pid=os.getpid(),
                stamp_ns=time.time_ns(),
                uptime_s=time.monotonic() - self.started,
                fps=fps,
                latency_ms_p50=p50,
                latency_ms_p99=p99,
                drops=self.drops,
                errors=self.errors,
                counters=dict(self.counters),
                robots=robots,
            )
