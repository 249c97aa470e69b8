"""A candidate view as the frame selection sees it (:mod:`openfusion.mapping.coverage`): its
evidence, prepared once from the map's render at the scored size, and its score; the sizes of the
scored view and of the sample a chosen view marks as shown. Split from the scorer so that module
holds the record and the rules."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from openfusion.frame import CameraIntrinsics

#: A chosen view marks the surface it shows sampled MARK_DENSITY times denser (per side) than it is
#: scored, and at least MARK_MIN_WIDTH_PX wide: the cubes between sparser samples counted as never
#: shown in the next frame (4-10 % of every view looked new right after an encoded frame). The floor
#: is because those holes are in metres, not scored pixels: a 32 px score marked at 96 px left holes
#: in the floor, and the services (whose next candidates see the map before the chosen frame's labels
#: are in) chose 71 of 90 frames instead of 52 on the bench scene (docs/EVAL.md, "Scored at 32 px").
MARK_DENSITY = 3
MARK_MIN_WIDTH_PX = 192


def mark_width_px(scored_width_px: int) -> int:
    """Width of the sample a chosen view marks as shown (:data:`MARK_DENSITY`, :data:`MARK_MIN_WIDTH_PX`)."""
    return max(MARK_MIN_WIDTH_PX, MARK_DENSITY * int(scored_width_px))


def scoring_size(intrinsics: CameraIntrinsics, width_px: int) -> tuple[int, int]:
    """(height, width) of the scored view: ``width_px`` wide (at most the frame's), same aspect."""
    w = max(1, min(int(width_px), intrinsics.width_px))
    h = max(1, int(round(intrinsics.height_px * w / intrinsics.width_px)))
    return h, w


@dataclass(eq=False)  # one view's arrays: compared by identity
class ViewEvidence:
    """A candidate view, prepared once (:meth:`CoverageScorer.prepare`): per surface pixel of the
    scored view its direction bin, its surface cube and the region the map holds there."""

    frame_id: int
    stamp_s: float
    #: the stamp in map time (:mod:`openfusion.mapping.map_clock`): what staleness compares across robots
    map_s: float
    view_px: int  # pixels of the scored view (the shares' denominator)
    bins: np.ndarray  # (n,) int64, direction bin of each surface pixel
    cells: np.ndarray  # (n,) int64, packed surface cube of each surface pixel
    keys: np.ndarray  # (n,) int64, the map's region at each surface pixel (-1: none)
    confident: np.ndarray  # (n,) bool, key >= 0 with confidence >= select_low_conf
    robot: str = ""  # whose frame: the patience rule runs on each robot's own frames, a hold is keyed by it
    unsure_px: np.ndarray | None = None  # (h, w) bool: surface pixels without a confident region
    surface_idx: np.ndarray | None = field(default=None, repr=False)  # (n,) flat index of each surface pixel
    #: (h, w) bool, set when the view is chosen (:meth:`CoverageScorer.decide`): the pixels that add
    #: something, against the record before the view was marked (:meth:`CoverageScorer.wanted_px`)
    wanted_px: np.ndarray | None = field(default=None, repr=False)
    #: (n,) bool per surface pixel, set with ``wanted_px``: its reasons for the pixels the map held
    #: a confident region at (a new direction, stale), which no later update changes
    #: (:meth:`CoverageScorer.wanted_now`)
    wanted_base: np.ndarray | None = field(default=None, repr=False)
    #: per distinct confident key in view (sorted, as ``np.unique``): the views its embedding averages
    #: and their agreement (:attr:`CoverageScorer.embedding_support`, read when prepared); None: not asked
    support: tuple[np.ndarray, np.ndarray] | None = field(default=None, repr=False)
    # marking a chosen view: its depth sampled at mark_width_px and that grid's camera (None: scored pixels)
    mark_depth_m: np.ndarray | None = field(default=None, repr=False)
    mark_intrinsics: CameraIntrinsics | None = None
    T_world_cam: np.ndarray | None = field(default=None, repr=False)

    @property
    def surface_px(self) -> int:
        return int(len(self.bins))


@dataclass(frozen=True)
class ViewScore:
    """What encoding a view would add, in shares of its pixels (module docstring)."""

    frame_id: int
    stamp_s: float
    gain: float
    new_surface: float
    new_direction: float
    stale: float
    surface: float  # share of the view with valid depth
    regions: int  # regions in view big enough to count
    robot: str = ""
