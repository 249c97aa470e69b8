"""Which encoder worker the semantic service's pool sends the next frame to
(openfusion.services.semantic.pool.pick_worker): idle workers first, and when every worker is
busy, one frame in line at the worker that should be free first, so a newer frame never overtakes
it (its result would be dropped as stale: results are applied in frame order).

Bad input tried: a worker whose own limit is one request (capacity 1) never gets a second; no
worker at all."""

from __future__ import annotations

from openfusion.services.semantic.pool import WorkerLoad, pick_worker


def load(worker_id: str, in_flight: int, *, sent: int = 0, oldest_s: float = 0.0, capacity: int = 2) -> WorkerLoad:
    return WorkerLoad(worker_id, in_flight, capacity, sent, oldest_s)


def test_an_idle_worker_takes_the_frame_fewest_sent_first() -> None:
    workers = [load("w1", 1, sent=3, oldest_s=1.0), load("w2", 0, sent=5), load("w3", 0, sent=2)]
    assert pick_worker(workers) == "w3"


def test_when_all_are_busy_the_frame_waits_at_the_worker_free_first() -> None:
    # w2's frame went out first, so w2 frees up first: the frame in line starts right after it,
    # before any newer frame could start elsewhere.
    workers = [load("w1", 1, oldest_s=10.2), load("w2", 1, oldest_s=10.0), load("w3", 1, oldest_s=10.1)]
    assert pick_worker(workers) == "w2"


def test_only_one_frame_waits_in_line_across_the_pool() -> None:
    workers = [load("w1", 1, oldest_s=10.2), load("w2", 2, oldest_s=10.0), load("w3", 1, oldest_s=10.1)]
    assert pick_worker(workers) is None  # the next worker to free up takes the newest frame then


def test_limits_are_kept() -> None:
    assert pick_worker([]) is None
    assert pick_worker([load("w1", 1, capacity=1)]) is None
    assert pick_worker([load("w1", 1, capacity=1), load("w2", 1, oldest_s=5.0)]) == "w2"
    # one worker: the second frame travels while the first is encoded (two in flight)
    assert pick_worker([load("w1", 1)]) == "w1" and pick_worker([load("w1", 2)]) is None
