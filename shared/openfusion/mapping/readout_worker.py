"""One worker thread for the whole-map read-outs of a process: at most one chunk in hand at a time.

Why: under a memory budget the grid is the budget, and everything else a process holds is the
overhead. Geometry alone measured a flat overhead of 161 MiB; through the services it stood about
250 MiB over the budget and peaked at 637-761 MiB, each peak a moment where *bounded* read-outs
ran at once on different threads (a periodic checkpoint's slice, a merge pass's region-contacts
chunk, the region summaries, the end of a run's key-filtered points read-outs): each is bounded by
its chunk, but four of them together are four chunks, and glibc keeps each thread's freed chunk
in that thread's arena. So every read-out of the whole map runs as a job on one worker thread
(:func:`run`), one job at a time, in the order asked (FIFO), while the thread that asked waits for
its result: the overhead is one chunk whatever asks for what, on whatever thread, and the chunks
are allocated and freed in one arena.

What runs on it (each job decodes or copies at most one chunk)

- a checkpoint's slices and its last step (:func:`openfusion.mapping.mapstore.checkpoint`): one
  job per slice (copy, encode, write) and one for the last step (copy, encode, commit);
- region summaries and region contacts (:func:`openfusion.mapping.tilereadouts.refresh`: a save's
  summaries, a merge pass's contacts, the idle read-outs): one job per chunk (copy, read out, keep
  the parts); a refresh that holds its locks throughout (``hold``) is one job;
- surface points, meshes, labelled blocks and array dumps (:class:`~openfusion.mapping.volume.SemanticVolume`'s
  ``extract_points``, ``extract_mesh``, ``mesh_parts``, ``labelled_blocks``, ``to_arrays``: with
  paged-out tiles they walk the map chunk by chunk, :mod:`openfusion.mapping.wholemap`): one job per
  read-out (a query's key-filtered points, a mesh), holding the volume's lock as before;
- a save into a new store (:func:`openfusion.mapping.mapstore.save_store` without a store of the
  volume's own) and a version-1 file (the geometry service's ``.npz`` saves): one job.

A job that asks for another read-out runs it at once, inline (a checkpoint's region summaries; a
save's arrays), never queued behind itself.

Renders do not go through it: a render pages the tiles in view into the grid (inside the budget)
and reads resident blocks only (:meth:`SemanticVolume.ray_cast`), so it never waits for a
checkpoint or a read-out; integration does not either (page-outs under the budget are part of
integration, measured in the geometry-only overhead).

Deadlock analysis. A job takes, on the worker, the locks of the volume it reads and the caller's
lock it was given (a service's: ``lock=``), always in the order **service lock, then volume lock**
(:func:`openfusion.mapping.tilereadouts.both`), and the thread that asked waits, holding whatever
it holds, until the job is done. So:

1. A thread must never ask for a job while holding a lock that a job may take (a volume's or a
   service's lock): the job queued before its own, or its own, could wait for that lock forever.
   Every such lock is registered (:func:`register_lock`: every volume registers its lock, the
   geometry service its own; unregistered when the volume is collected) and :func:`run` refuses
   (:class:`WorkerOrderError`, at once, rather than a hang) a thread outside the worker that
   holds one of them. Read-outs therefore take their locks themselves, on the worker: the geometry
   service's points and mesh handlers no longer hold the service's lock around the read-out, and
   its ``.npz`` save runs as one job that takes the lock on the worker.
2. The worker itself holds no lock between jobs, and a job never waits for another job (nested
   read-outs run inline), so the worker always gets to the next job: no waiter starves.
3. Integration (a frame, a semantic update, a render) takes the service's lock then the volume's,
   never the worker: it waits at most for one chunk's copy (read-outs copy under the locks and
   read out outside them) or for one whole-map read-out of :mod:`.wholemap` (which holds the
   volume's lock throughout, as before: one at a time now).
4. A read-out waiting for its job holds neither the service's lock nor the volume's (rule 1), so
   it never blocks integration while it waits. The geometry service's ``_swap_lock`` (held by a
   save, a load, a reset and the idle read-outs) is taken before any of them, is never taken by a
   job, and may be held while waiting.
5. The end-of-run save (``control/save``): its merge pass asks the semantic service, which asks
   ``geometry/contacts`` (another thread of this process, whose contact chunks are jobs); the
   save's thread holds ``_swap_lock`` only meanwhile. Then the save's summaries and slices are jobs:
   it completes, interleaved chunk by chunk with whatever else asks, and ``saving`` stays up for
   its progress as before.
6. A load or a reset closes the old volume under the locks; a read-out job of the old volume that
   runs afterwards finds its volume closed and fails with an error answered to its asker (the
   service re-reads ``self.volume`` under its lock before each read-out).

Accounting: :data:`STATS` counts jobs, waits and the seconds waited; :data:`hooks` lets a test watch
every job start and end (``tests/unit/test_readout_worker.py`` counts the chunks in hand at once).
"""

from __future__ import annotations

import itertools
import queue
import threading
import time
import weakref
from collections.abc import Callable
from concurrent.futures import Future
from typing import Any, TypeVar

from openfusion.mapping.errors import MappingError

T = TypeVar("T")


class WorkerOrderError(MappingError, RuntimeError):
    """A thread asked for a read-out job while holding a lock a job may take (the module
    docstring's rule 1): a bug; refused instead of deadlocking."""


#: Jobs run, jobs that waited for another, seconds waited in all, the longest queue seen.
STATS: dict[str, float] = {"jobs": 0, "waits": 0, "wait_s": 0.0, "max_queue": 0}
#: Test hooks: each called with ``("start" | "end", what)`` on the worker around every job.
hooks: list[Callable[[str, str], None]] = []

_registry: dict[int, Any] = {}
_registry_lock = threading.Lock()
_ids = itertools.count()


def _owned(lock: Any) -> bool:
    """Whether the calling thread holds ``lock`` (an ``RLock``; other locks: unknown, False)."""
    is_owned = getattr(lock, "_is_owned", None)
    return bool(is_owned()) if is_owned is not None else False


def register_lock(lock: Any, owner: object | None = None) -> int:
    """``lock`` (an ``RLock``) may be taken by a job: :func:`run` refuses a thread holding it.
    ``owner``: unregistered when that object is collected. Returns a handle for :func:`unregister_lock`."""
    handle = next(_ids)
    with _registry_lock:
        _registry[handle] = lock
    if owner is not None:
        weakref.finalize(owner, unregister_lock, handle)
    return handle


def unregister_lock(handle: int) -> None:
    with _registry_lock:
        _registry.pop(handle, None)


class _Worker:
    def __init__(self) -> None:
        self.jobs: queue.SimpleQueue[tuple[str, Callable[[], Any], Future]] = queue.SimpleQueue()
        self.pending = 0
        self.busy_since: float | None = None
        self.thread = threading.Thread(target=self._loop, name="openfusion-readouts", daemon=True)
        self.thread.start()

    def _loop(self) -> None:
        while True:
            what, fn, fut = self.jobs.get()
            if not fut.set_running_or_notify_cancel():
                continue
            for hook in list(hooks):
                hook("start", what)
            try:
                result = fn()
            except BaseException as exc:  # handed to the asker, who raises it
                fut.set_exception(exc)
            else:
                fut.set_result(result)
            finally:
                for hook in list(hooks):
                    hook("end", what)
                with _worker_lock:
                    self.pending -= 1
            del fn, fut  # the job's closure (its chunk) is let go of before the next job


_worker: _Worker | None = None
_worker_lock = threading.Lock()


def on_worker() -> bool:
    """Whether the calling thread is the read-out worker."""
    w = _worker
    return w is not None and threading.current_thread() is w.thread


def check_caller(what: str) -> None:
    """Refuse (:class:`WorkerOrderError`) a thread outside the worker that holds a registered lock:
    :func:`run` does it, and read-outs that may need no job at all (nothing stale) do it on entry,
    so such a bug shows at once, not only on the day a job is needed."""
    if on_worker():
        return
    with _registry_lock:
        locks = list(_registry.values())
    for lock in locks:
        if _owned(lock):
            raise WorkerOrderError(
                f"read-out {what!r} asked for while holding a map or service lock that a read-out job may take "
                "(take locks inside the job: openfusion.mapping.readout_worker)"
            )


def run(what: str, fn: Callable[..., T], *args: Any, **kwargs: Any) -> T:
    """Run ``fn(*args, **kwargs)`` on the read-out worker and return its result (raise its
    exception); ``what`` names the job for the hooks. On the worker itself it runs at once."""
    global _worker
    if on_worker():
        return fn(*args, **kwargs)
    check_caller(what)
    fut: Future = Future()
    with _worker_lock:
        if _worker is None:
            _worker = _Worker()
        w = _worker
        queued = w.pending
        w.pending += 1
        STATS["jobs"] += 1
        STATS["max_queue"] = max(STATS["max_queue"], queued)
        if queued:
            STATS["waits"] += 1
    started = time.monotonic()
    w.jobs.put((what, lambda: fn(*args, **kwargs), fut))
    try:
        return fut.result()
    finally:
        if queued:
            STATS["wait_s"] += time.monotonic() - started
        del fut
