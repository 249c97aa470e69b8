"""The semantic service's periodic merge passes, off the frame loop (:class:`MergeWorker`).

A merge pass asks geometry for the region contacts (``geometry/contacts``), a whole-map read-out
that geometry runs on its read-out worker, one job at a time. On a loaded 2-core box that took
2.3 s in the middle of a 3 s recording (90 frames at 30 fps, measured in the services with
``--select latest``). Run on the frame loop, the pass stopped the encoder for that long: with
``select=latest`` every frame that came meanwhile was replaced by the next one, so a third of the
room was never encoded (f-mIoU 0.61 instead of 0.94 in that run); with ``select=coverage`` the
candidate window filled meanwhile. So a pass that falls due after a frame (``merge_every``) runs
on a thread of its own and the loop goes on with the next frame. Passes never overlap: a pass
asked for on ``semantic/merge`` (geometry, before it saves) waits for a periodic one still running,
then runs its own.

The pass itself is the service's (:meth:`SemanticService._merge`); the dictionary is changed
under the service's dictionary lock, as the frame loop's updates are, so deltas go out in version
order.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import TypeVar

logger = logging.getLogger(__name__)

R = TypeVar("R")


class MergeWorker:
    """Runs merge passes one at a time: :meth:`request` on the worker's thread (not the caller's),
    :meth:`run_now` on the caller's. ``on_error`` is called when a requested pass raises (the
    pass's own failures, such as geometry not answering, are counted by the pass and return
    normally)."""

    def __init__(self, *, on_error: Callable[[], None] | None = None) -> None:
        self._on_error = on_error
        self._due = threading.Event()
        self._pending: Callable[[], object] | None = None
        self._pass_lock = threading.Lock()
        self._stopping = threading.Event()
        self._thread: threading.Thread | None = None

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def start(self) -> None:
        if self.running:
            return
        self._stopping.clear()
        self._thread = threading.Thread(target=self._run, name="semantic-merge", daemon=True)
        self._thread.start()

    def request(self, run_pass: Callable[[], object]) -> None:
        """A periodic pass is due: run it on the worker's thread (at once, on this one, when the
        worker does not run: a test driving the service without its loop). Requests that come
        while a pass runs make one more pass after it, not one each."""
        if not self.running:
            self.run_now(run_pass)
            return
        self._pending = run_pass
        self._due.set()

    def run_now(self, run_pass: Callable[[], R]) -> R:
        """One pass on the caller's thread, after any pass still running."""
        with self._pass_lock:
            return run_pass()

    def stop(self, timeout_s: float) -> None:
        """Stop after the pass in hand (a pass asked for and not started is not run)."""
        self._stopping.set()
        self._due.set()
        if self._thread is not None:
            self._thread.join(timeout_s)

    def _run(self) -> None:
        while True:
            self._due.wait()
            if self._stopping.is_set():
                return
            self._due.clear()
            run_pass, self._pending = self._pending, None
            if run_pass is None:
                continue
            try:
                self.run_now(run_pass)
            except Exception:  # one pass's failure never ends the worker: logged, counted, next pass
                logger.exception("semantic: a merge pass failed; mapping goes on")
                if self._on_error is not None:
                    self._on_error()
