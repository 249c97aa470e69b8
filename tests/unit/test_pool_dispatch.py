"""Which encoder worker the semantic service's pool sends the next frame to
(openfusion.services.semantic.pool.pick_worker): the worker with room that should finish the
frame first, from when it should be free and its measured time per frame. So frames come back in
the order they went out: a frame never waits behind a worker that frees up after another worker
could have started and finished a newer one (its result would be dropped as stale: results are
applied in frame order).

Bad input tried: a worker whose own limit is one request (capacity 1) never gets a second; no
worker at all; workers not measured yet."""

from __future__ import annotations

from openfusion.services.semantic.pool import WorkerLoad, pick_worker

NOW = 100.0


def load(worker_id: str, in_flight: int, *, sent: int = 0, free_at: float = NOW, frame_s: float | None = 0.25,
         capacity: int = 2) -> WorkerLoad:
    return WorkerLoad(worker_id, in_flight, capacity, sent, free_at, frame_s)


def test_an_idle_worker_takes_the_frame_fewest_sent_first() -> None:
    workers = [load("w1", 1, sent=3, free_at=NOW + 0.1), load("w2", 0, sent=5), load("w3", 0, sent=2)]
    assert pick_worker(workers, NOW) == "w3"


def test_when_all_are_busy_the_frame_goes_where_it_finishes_first() -> None:
    # w2 should be free first, so a frame queued there finishes before one queued anywhere else.
    workers = [load("w1", 1, free_at=NOW + 0.2), load("w2", 1, free_at=NOW + 0.05), load("w3", 1, free_at=NOW + 0.1)]
    assert pick_worker(workers, NOW) == "w2"


def test_frames_sent_one_after_another_come_back_in_order() -> None:
    """Dispatch four frames to two equally fast workers, one of them busy: each frame's expected
    finish is later than the one before (no overtaking), and a faster idle worker wins."""
    state = {"w1": [1, NOW + 0.2], "w2": [0, NOW]}
    finishes = []
    for _ in range(4):
        chosen = pick_worker([load(w, n, free_at=f) for w, (n, f) in state.items()], NOW)
        assert chosen is not None
        n, free_at = state[chosen]
        finish = max(NOW, free_at if n else NOW) + 0.25
        state[chosen] = [n + 1, finish]
        finishes.append(finish)
        if n + 1 >= 2 and all(v[0] >= 2 for v in state.values()):
            break
    assert finishes == sorted(finishes) and len(finishes) == 3
    fast = [load("slow", 0, frame_s=0.5), load("fast", 0, frame_s=0.1, sent=9)]
    assert pick_worker(fast, NOW) == "fast"


def test_limits_are_kept_and_unmeasured_workers_count_as_typical() -> None:
    assert pick_worker([], NOW) is None
    assert pick_worker([load("w1", 1, capacity=1)], NOW) is None
    assert pick_worker([load("w1", 1, capacity=1), load("w2", 1, free_at=NOW + 5)], NOW) == "w2"
    # one worker: the second frame travels while the first is encoded (two in flight), not a third
    assert pick_worker([load("w1", 1, free_at=NOW + 0.2)], NOW) == "w1"
    assert pick_worker([load("w1", 2, free_at=NOW + 0.4)], NOW) is None
    # a new worker (not measured) counts with the median time: idle, it goes before a busy one
    assert pick_worker([load("new", 0, frame_s=None, sent=0), load("w1", 1, free_at=NOW + 0.2, sent=1)], NOW) == "new"
