"""The in-process semantic step: render -> match -> dictionary -> update.

The services run the same pieces on different machines: geometry renders and applies updates
(``SemanticVolume.render`` / ``apply_update``), semantic plans and owns the dictionary
(``plan_update``). :class:`SemanticMapper` chains them for the in-process pipeline and tests.
The view of the map a step matches against is a ray cast, or, given the frame's depth on a map of
more than ``MatchParams.step_probe_blocks`` blocks, a probe at that depth (the same images and
voxels, at a cost that does not grow with the map: :mod:`openfusion.mapping.surface_probe`).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from openfusion.frame import CameraIntrinsics, resize_nearest
from openfusion.mapping.dictionary import RegionDictionary
from openfusion.mapping.matching import PlannedUpdate, plan_update
from openfusion.mapping.params import MatchParams
from openfusion.mapping.volume import SemanticVolume, UpdateStats

logger = logging.getLogger(__name__)


@dataclass
class StepStats:
    """What one semantic step did, with its timings in milliseconds."""

    num_regions: int
    matched: int
    new: int
    skipped: int
    regions_in_view: int
    voxels_updated: int
    render_ms: float
    plan_ms: float
    update_ms: float
    dictionary_version: int


class SemanticMapper:
    """Owns nothing but wiring: a volume, a dictionary and the matching parameters
    (:class:`~openfusion.mapping.params.MatchParams`, passed to
    :func:`openfusion.mapping.matching.plan_update`)."""

    def __init__(
        self, volume: SemanticVolume, dictionary: RegionDictionary, *, params: MatchParams | None = None
    ) -> None:
        self.volume = volume
        self.dictionary = dictionary
        self.params = params if params is not None else MatchParams()
        self.last_plan: PlannedUpdate | None = None
        self.last_update: UpdateStats | None = None

    def step(
        self,
        obs: Any,
        T_world_cam: np.ndarray,
        intrinsics: CameraIntrinsics,
        *,
        depth_m: np.ndarray | None = None,
    ) -> StepStats:
        """Fuse one region observation taken at ``T_world_cam``.

        ``intrinsics`` may be those of the full frame: they are rescaled to the observation's size.
        ``depth_m`` (the frame's depth in metres, any size) enables the update's depth gate, which
        keeps silhouette labels off the background (see ``SemanticVolume.apply_update``).
        """
        conf_maps = np.asarray(obs.conf_maps)
        if conf_maps.ndim != 3:
            raise ValueError(f"obs.conf_maps must be (n, h, w), got {conf_maps.shape}")
        h, w = conf_maps.shape[1:]
        intr = (
            intrinsics if (intrinsics.width_px, intrinsics.height_px) == (w, h) else intrinsics.scaled(w, h)
        )
        t0 = time.perf_counter()
        probe_above = self.params.step_probe_blocks
        if depth_m is None or probe_above is None:
            rendered = self.volume.render(T_world_cam, intr)
        else:  # probed at its own depth on a large map (MatchParams.step_probe_blocks), else rendered
            depth_small = resize_nearest(np.asarray(depth_m, np.float32), (h, w))
            rendered = self.volume.candidate_view(T_world_cam, intr, depth_small, probe_above)
        t1 = time.perf_counter()
        plan = plan_update(obs, rendered, self.dictionary, self.params)
        t2 = time.perf_counter()
        update = self.volume.apply_update(
            T_world_cam, intr, plan.key_map, plan.conf_map, rendered=rendered, observed_depth_m=depth_m
        )
        t3 = time.perf_counter()
        self.last_plan, self.last_update = plan, update
        in_view = len(plan.match.rendered_keys) if plan.match is not None else 0
        return StepStats(
            num_regions=len(conf_maps),
            matched=len(plan.matched),
            new=len(plan.new_keys),
            skipped=len(plan.skipped),
            regions_in_view=in_view,
            voxels_updated=update.voxels_updated,
            render_ms=(t1 - t0) * 1e3,
            plan_ms=(t2 - t1) * 1e3,
            update_ms=(t3 - t2) * 1e3,
            dictionary_version=plan.dictionary_version,
        )

    def merge_regions(self, a: int, b: int) -> int:
        """Merge region ``b`` into ``a`` in the dictionary and relabel ``b``'s voxels; returns voxels changed."""
        self.dictionary.merge(a, b)
        return self.volume.relabel_keys({int(b): int(a)})
