"""The frames chosen for the encoder while it is busy (:class:`CandidateWindow`): each frame is
decided as it comes by the :class:`~openfusion.mapping.coverage.CoverageScorer`, a chosen one
waits, and the encoder is given the waiting frame of highest gain when it is free. The semantic
service uses it with its local encoder or the encoder pool (the overview:
:mod:`openfusion.mapping.selection`)."""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from typing import Generic, TypeVar

from openfusion.mapping.coverage import CoverageScorer, ViewEvidence, ViewScore

T = TypeVar("T")


@dataclass(eq=False)
class Candidate(Generic[T]):
    """A frame waiting for the encoder: its prepared view, its last score and what the caller
    needs to encode it (``payload``: the frame, or the message and its instance image). Compared
    by identity: two robots' frames may share an id and a stamp, and comparing their arrays
    field by field raised (the window removes the one it gives out)."""

    evidence: ViewEvidence
    score: ViewScore
    payload: T
    arrival: int


@dataclass
class WindowChange(Generic[T]):
    """What one call to the window did: the frame taken (None: none), and the frames that left
    without being encoded: ``no_gain`` (not chosen: their gain is under the bar) and ``evicted``
    (chosen, but a full window let them go for frames of higher gain)."""

    taken: Candidate[T] | None = None
    no_gain: list[Candidate[T]] = field(default_factory=list)
    evicted: list[Candidate[T]] = field(default_factory=list)


class CandidateWindow(Generic[T]):
    """The frames chosen for the encoder while it is busy; :meth:`take` gives it the best one.

    :meth:`offer` decides a frame as it comes, with the same rule as one process
    (:meth:`CoverageScorer.decide`: scored against what the frames chosen before it cover, chosen
    when its gain reaches the bar, and then recorded as chosen at once, so the next frame is
    judged as if this one were encoded; the surface it will label is held for it until the encoding
    side releases it (:meth:`release`), as one process would have labelled it before the next frame).
    A frame that adds too little is dropped there
    (``no_gain``); a chosen one waits here. So the frames the services encode are the frames one
    process would, only later, as long as the window holds the backlog: a window over
    ``select_window`` lets its lowest-gain frame go (``evicted``; what it showed stays recorded as
    chosen, so the cost of an overload is surface left for a later view). :meth:`take` gives the
    encoder the waiting frame of highest gain (ties: the newest). Thread-safe; ``take`` can wait."""

    def __init__(self, scorer: CoverageScorer, capacity: int | None = None) -> None:
        self.scorer = scorer
        self.capacity = int(capacity if capacity is not None else scorer.params.select_window)
        if self.capacity < 1:
            raise ValueError(f"the window must hold at least one frame, got {self.capacity}")
        self._items: list[Candidate[T]] = []
        self._run: list[tuple[ViewEvidence, T, int]] = []  # frames waiting for their run's decision
        self._arrivals = 0
        self._cond = threading.Condition()
        self._closed = False

    def __len__(self) -> int:
        with self._cond:
            return len(self._items)

    def offer(self, evidence: ViewEvidence, payload: T) -> WindowChange[T]:
        """Decide one frame: wait in the window (chosen) or drop it (``no_gain``); a full window
        lets its lowest-gain frame go (``evicted``). With ``select_lookahead`` K > 1 frames are
        decided K at a time (:meth:`CoverageScorer.decide_best`, as in one process): a frame waits
        undecided until its run is complete (or :meth:`flush`)."""
        with self._cond:
            arrival = self._arrivals
            self._arrivals += 1
            lookahead = self.scorer.params.select_lookahead
            if lookahead <= 1:
                score, chosen = self.scorer.decide(evidence, hold=True)
                return self._place([Candidate(evidence, score, payload, arrival)], 0 if chosen else None)
            self._run.append((evidence, payload, arrival))
            if len(self._run) < lookahead:
                return WindowChange()
            return self._decide_run()

    def flush(self) -> WindowChange[T]:
        """Decide the frames of an incomplete run now (the frames stopped coming for a while)."""
        with self._cond:
            return self._decide_run() if self._run else WindowChange()

    @property
    def undecided(self) -> int:
        """Frames waiting for the rest of their run (``select_lookahead``)."""
        with self._cond:
            return len(self._run)

    def _decide_run(self) -> WindowChange[T]:
        run, self._run = self._run, []
        scores, best = self.scorer.decide_best([ev for ev, _, _ in run], hold=True)
        return self._place([Candidate(ev, sc, pl, arr) for (ev, pl, arr), sc in zip(run, scores, strict=True)], best)

    def _place(self, cands: list[Candidate[T]], chosen: int | None) -> WindowChange[T]:
        """(lock held) The chosen candidate waits, the others are dropped (``no_gain``)."""
        change: WindowChange[T] = WindowChange()
        change.no_gain.extend(c for i, c in enumerate(cands) if i != chosen)
        if chosen is None:
            return change
        self._items.append(cands[chosen])
        if len(self._items) > self.capacity:
            worst = min(self._items, key=lambda c: (c.score.gain, c.arrival))
            self._items.remove(worst)
            self.release(worst.evidence)
            change.evicted.append(worst)
        self._cond.notify_all()
        return change

    def take(self, timeout_s: float = 0.0) -> WindowChange[T]:
        """The waiting frame of highest gain, waiting up to ``timeout_s`` for one."""
        change: WindowChange[T] = WindowChange()
        deadline = time.monotonic() + max(0.0, timeout_s)
        with self._cond:
            while not self._items:
                remaining = deadline - time.monotonic()
                if remaining <= 0 or self._closed:
                    return change
                self._cond.wait(remaining)
            best = max(self._items, key=lambda c: (c.score.gain, c.arrival))
            self._items.remove(best)
            change.taken = best
            return change

    def drain(self) -> list[Candidate[T]]:
        """Remove and return every candidate, decided or not (a new playback, a shutdown)."""
        with self._cond:
            out, self._items = self._items, []
            for ev, payload, arrival in self._run:
                out.append(Candidate(ev, self.scorer.score(ev), payload, arrival))
            self._run = []
            for cand in out:
                self.release(cand.evidence)
            return out

    def release(self, evidence: ViewEvidence) -> None:
        """A chosen frame was encoded (its update sent) or let go: the surface it was to show is
        no longer held for it (:meth:`CoverageScorer.hold`). The encoding side calls it for a frame
        :meth:`take` gave; the window for the frames it lets go."""
        self.scorer.release(evidence.frame_id, evidence.stamp_s, evidence.robot)

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()
