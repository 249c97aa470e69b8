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
    fibonacci_directions,
    scoring_size,
)
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
    score_s: float = 0.0  # rendering at the scored size + scoring


class FrameSelector:
    """Selection where the encoder is free for every frame (the in-process pipeline, the eval):
    each frame is scored as it comes and encoded when it adds enough (``select=coverage``), or
    always (``every`` / ``latest``, which are the same in one process). The services use the same
    :class:`CoverageScorer` through a :class:`CandidateWindow`, since their encoder is busy while
    frames come."""

    def __init__(self, params: SelectParams | None, render: Callable[[np.ndarray, CameraIntrinsics], Any]) -> None:
        self.params = params if params is not None else SelectParams()
        self.scorer = CoverageScorer(self.params)
        self.render = render
        self.stats = SelectionStats()
        self.last_score: ViewScore | None = None

    @property
    def scoring(self) -> bool:
        return self.params.select == "coverage"

    def wants(self, frame: Frame) -> bool:
        """Whether ``frame`` goes to the encoder; with ``coverage`` it is then recorded as selected."""
        if not self.scoring:
            return True
        t0 = time.perf_counter()
        score, chosen = self.scorer.decide(self.scorer.prepare_frame(frame, self.render))
        self.last_score = score
        self.stats.frames_scored += 1
        self.stats.skipped_no_gain += int(not chosen)
        self.stats.score_s += time.perf_counter() - t0
        return chosen

    def encoded(self, frame: Frame, key_map: np.ndarray) -> None:
        """Record the update a chosen frame's encoding planned (``key_map`` at the encoder's size)."""
        if self.scoring and key_map is not None:
            h, w = np.shape(key_map)
            self.scorer.observe_plan(key_map, frame.T_world_cam, frame.intrinsics.scaled(w, h), frame.stamp_ns)

    def merged(self, merged_into: Mapping[int, int], removed: Iterable[int] = ()) -> None:
        self.scorer.merge(merged_into, removed)
