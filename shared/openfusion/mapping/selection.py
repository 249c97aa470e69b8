"""Coverage-driven frame selection: encode the views that add something.

The region encoder is the most expensive step of the pipeline, and most frames of a camera at
30 fps show what the frame before showed. :class:`CoverageScorer` says, for a candidate frame,
what encoding it would add to the map, from the frame's pose and depth and the map as geometry
holds it (a render of the region keys and confidences at the frame's pose), plus a small record
of what earlier encoded frames covered; :meth:`CoverageScorer.decide` chooses a frame or not.
:class:`CandidateWindow` holds the chosen frames while the encoder is busy and gives it the best
one when it is free. The in-process pipeline, the evaluation
and the semantic service (with its local encoder or the encoder pool) all use these two classes
(:class:`FrameSelector` is the in-process driver), with the parameters of
:class:`~openfusion.mapping.params.SelectParams`.

The pieces, each in its own module: :mod:`openfusion.mapping.coverage` (the scorer: the score,
why its rules and defaults, what it remembers, what it costs), :mod:`openfusion.mapping.candidate_window`
(the window of chosen frames), and here :class:`FrameSelector` (the names of the other two are
re-exported here).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from openfusion.frame import CameraIntrinsics, Frame
from openfusion.mapping.candidate_window import Candidate, CandidateWindow, WindowChange
from openfusion.mapping.coverage import (
    MARK_DENSITY,
    SELECTED_KEPT,
    CoverageScorer,
    ViewEvidence,
    ViewScore,
    scoring_size,
)
from openfusion.mapping.coverage_bits import fibonacci_directions
from openfusion.mapping.params import SelectParams

__all__ = [
    "MARK_DENSITY",
    "SELECTED_KEPT",
    "Candidate",
    "CandidateWindow",
    "CoverageScorer",
    "FrameSelector",
    "SelectionStats",
    "ViewEvidence",
    "ViewScore",
    "WindowChange",
    "fibonacci_directions",
    "scoring_size",
]


@dataclass
class SelectionStats:
    """Counts and time of the selection in one process (run.json, the eval report)."""

    frames_scored: int = 0
    skipped_no_gain: int = 0
    score_s: float = 0.0  # the map's view at the scored size (probe or render) + scoring
    renders_reused: int = 0  # frames scored on their still camera's last render (select_still_s)


#: Chosen frames whose wanted pixels wait for :meth:`FrameSelector.embed_where` (a caller asks right
#: away; more than a look-ahead run's worth is a caller that never asks).
WANTED_KEPT = 32


class FrameSelector:
    """Selection where the encoder is free for every frame (the in-process pipeline, the eval):
    each frame is scored as it comes and encoded when it adds enough (``select=coverage``), or
    always (``every`` / ``latest``, which are the same in one process). With ``select_lookahead``
    K > 1 frames are decided K at a time (:meth:`CoverageScorer.decide_best`: at most the best of
    them is encoded), so a frame waits up to K - 1 frames for its decision: :meth:`offer` returns
    the frames to encode now, :meth:`flush` the last run's choice at the end of a source. The
    services use the same :class:`CoverageScorer` through a :class:`CandidateWindow`, since their
    encoder is busy while frames come."""

    def __init__(self, params: SelectParams | None, render: Callable[[np.ndarray, CameraIntrinsics], Any],
                 view: Callable[[np.ndarray, CameraIntrinsics, np.ndarray, int | None], Any] | None = None) -> None:
        """``render(T_world_cam, intrinsics)``: the map's render; ``view(T_world_cam, intrinsics,
        depth_m, probe_above_blocks)``: the map's view of a candidate, probed or rendered by the
        map's size (``SemanticVolume.candidate_view``, ``select_view``); without it every candidate
        is rendered."""
        self.params = params if params is not None else SelectParams()
        self.scorer = CoverageScorer(self.params)
        self.render = render
        self.view = view
        self.stats = SelectionStats()
        self.last_score: ViewScore | None = None
        self._run: list[tuple[Frame, ViewEvidence]] = []  # frames waiting for their run's decision
        # id(frame) -> (the frame, its evidence) for chosen frames not yet asked for their wanted pixels
        # (embed_where); holding the frame keeps its id from being reused; the oldest go past WANTED_KEPT
        self._wanted: dict[int, tuple[Frame, ViewEvidence]] = {}
        #: the labels' version for reusing a still camera's render: one more with every update and
        #: merge this selector is told of (:meth:`embed_where`, asked before each chosen frame's update
        #: is written, :meth:`encoded` after it, :meth:`merged`), which in one process are every change
        #: of the map's labels
        self._labels_version = 0

    @property
    def scoring(self) -> bool:
        return self.params.select == "coverage"

    def wants(self, frame: Frame) -> bool:
        """Whether ``frame`` goes to the encoder, decided on its own (``select_lookahead`` is not
        used: :meth:`offer` is); with ``coverage`` it is then recorded as selected."""
        if not self.scoring:
            return True
        t0 = time.perf_counter()
        ev = self._prepare(frame)
        score, chosen = self.scorer.decide(ev)
        if chosen:
            self._keep_wanted(frame, ev)
        self.last_score = score
        self.stats.frames_scored += 1
        self.stats.skipped_no_gain += int(not chosen)
        self.stats.score_s += time.perf_counter() - t0
        return chosen

    def offer(self, frame: Frame) -> list[Frame]:
        """One more frame: the frames to encode now, in order (this one, an earlier one whose run
        of ``select_lookahead`` frames is complete, or none)."""
        if not self.scoring:
            return [frame]
        if self.params.select_lookahead <= 1:
            return [frame] if self.wants(frame) else []
        t0 = time.perf_counter()
        self._run.append((frame, self._prepare(frame)))
        self.stats.frames_scored += 1
        out = self._decide_run() if len(self._run) >= self.params.select_lookahead else []
        self.stats.score_s += time.perf_counter() - t0
        return out

    def _prepare(self, frame: Frame) -> ViewEvidence:
        ev = self.scorer.prepare_frame(frame, self._view, labels_version=self._labels_version)
        self.stats.renders_reused = self.scorer.still.reused
        return ev

    def _view(self, T_world_cam: np.ndarray, K: CameraIntrinsics, depth_m: np.ndarray | None = None) -> Any:
        if depth_m is None or self.view is None:
            return self.render(T_world_cam, K)
        return self.view(T_world_cam, K, depth_m, self.params.probe_above_blocks)

    def flush(self) -> list[Frame]:
        """The end of the source: decide the frames still waiting."""
        t0 = time.perf_counter()
        out = self._decide_run() if self._run else []
        self.stats.score_s += time.perf_counter() - t0
        return out

    def _decide_run(self) -> list[Frame]:
        run, self._run = self._run, []
        scores, best = self.scorer.decide_best([ev for _, ev in run])
        self.last_score = scores[best] if best is not None else scores[-1]
        self.stats.skipped_no_gain += len(run) - (best is not None)
        if best is None:
            return []
        frame, ev = run[best]
        self._keep_wanted(frame, ev)
        return [frame]

    def _keep_wanted(self, frame: Frame, ev: ViewEvidence) -> None:
        self._wanted[id(frame)] = (frame, ev)
        while len(self._wanted) > WANTED_KEPT:
            del self._wanted[next(iter(self._wanted))]

    def embed_where(self, frame: Frame) -> tuple[np.ndarray | None, float | None]:
        """``(wanted_px, min_share)`` for :meth:`RegionEncoder.encode_where` of a frame this
        selector chose (:mod:`openfusion.mapping.region_gate`): ``(None, None)``, every region
        embedded, unless ``select=coverage`` chose it and ``select_embed_share`` is set. Asked once
        per chosen frame (what it keeps is dropped)."""
        self._labels_version += 1  # its update is next: no render kept from before it is reused after it
        kept = self._wanted.pop(id(frame), None)
        wanted = self.scorer.wanted_now(kept[1]) if kept is not None and kept[0] is frame else None
        if wanted is None or self.params.select_embed_share is None:
            return None, None
        return wanted, self.params.select_embed_share

    def encoded(self, frame: Frame, key_map: np.ndarray) -> None:
        """Record the update a chosen frame's encoding planned (``key_map`` at the encoder's size)."""
        self._labels_version += 1
        if self.scoring and key_map is not None:
            h, w = np.shape(key_map)
            self.scorer.observe_plan(key_map, frame.T_world_cam, frame.intrinsics.scaled(w, h), frame.stamp_ns)

    def merged(self, merged_into: Mapping[int, int], removed: Iterable[int] = ()) -> None:
        self._labels_version += 1
        self.scorer.merge(merged_into, removed)
