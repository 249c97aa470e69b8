"""The geometry process's own resident memory, sampled once a second by a thread of its own (the
service's loop writes checkpoints, whose peaks a sample from the loop would miss) and published as
health counters (``rss_mb``, ``rss_peak_mb``, ``rss_anon_peak_mb``): what ``openfusion run``
reports as geometry's memory in ``run.json``. Linux ``/proc/self/status``; elsewhere the counters
stay absent.

``RssAnon`` is the process's own memory without file pages it maps: the tile store (LMDB) reads
tiles through a memory map, and those pages are the kernel's file cache (shared, dropped under
memory pressure), counted in RSS but not in RssAnon. The memory budget bounds the latter.
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

from openfusion.wire.counters import GeometryCounter

_STATUS = Path("/proc/self/status")


def process_memory_mib() -> tuple[float, float] | None:
    """(VmRSS, RssAnon) of this process in MiB, or None where ``/proc`` has no such lines."""
    try:
        text = _STATUS.read_text()
    except OSError:
        return None
    values: dict[str, float] = {}
    for line in text.splitlines():
        key, _, rest = line.partition(":")
        if key in ("VmRSS", "RssAnon"):
            values[key] = int(rest.split()[0]) / 1024.0
    if "VmRSS" not in values:
        return None
    return values["VmRSS"], values.get("RssAnon", values["VmRSS"])


SAMPLE_EVERY_S = 1.0


class MemoryPeaks:
    """The largest samples seen so far."""

    def __init__(self) -> None:
        self.rss_peak_mb = 0.0
        self.anon_peak_mb = 0.0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self, stats: Any) -> None:
        """Sample every :data:`SAMPLE_EVERY_S` into ``stats`` on a daemon thread until :meth:`stop`."""
        if self._thread is not None:
            return

        def run() -> None:
            while not self._stop.is_set():
                self.sample_into(stats)
                self._stop.wait(SAMPLE_EVERY_S)

        self._thread = threading.Thread(target=run, name="geometry-memory", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None

    def sample(self) -> tuple[float, float] | None:
        got = process_memory_mib()
        if got is not None:
            self.rss_peak_mb = max(self.rss_peak_mb, got[0])
            self.anon_peak_mb = max(self.anon_peak_mb, got[1])
        return got

    def sample_into(self, stats: Any) -> None:
        """Sample now and publish the sample and the peaks as health counters."""
        got = self.sample()
        if got is not None:
            stats.set(GeometryCounter.RSS_MB, got[0])
            stats.set(GeometryCounter.RSS_PEAK_MB, self.rss_peak_mb)
            stats.set(GeometryCounter.RSS_ANON_PEAK_MB, self.anon_peak_mb)


def publish_map_size(stats: Any, volume: Any) -> None:
    """The map's size and residency as health counters (all blocks, resident ones, the grid's MiB,
    tiles paged out and in)."""
    stats.set(GeometryCounter.NUM_BLOCKS, volume.num_blocks_total)
    stats.set(GeometryCounter.RESIDENT_BLOCKS, volume.num_blocks)
    stats.set(GeometryCounter.RESIDENT_MB, volume.resident_bytes / 2**20)
    stats.set(GeometryCounter.TILES_PAGED_OUT, volume.pager.stats.tiles_paged_out)
    stats.set(GeometryCounter.TILES_PAGED_IN, volume.pager.stats.tiles_paged_in)
