"""The coverage score of a candidate frame: what encoding it would add to the map.

:class:`CoverageScorer` says, for a candidate frame, what encoding it would add, from the frame's
pose and depth and the map as geometry holds it (a render of the region keys and confidences at
the frame's pose), plus a small record of what earlier encoded frames covered;
:meth:`CoverageScorer.decide` chooses a frame or not. Where the encoder is busy while frames come
(the services), the chosen frames wait in a :class:`~openfusion.mapping.candidate_window.CandidateWindow`;
in one process :class:`~openfusion.mapping.selection.FrameSelector` drives the scorer (the overview:
:mod:`openfusion.mapping.selection`).

The score (one number, shares of the scored view's pixels)
    ``gain = new_surface + select_direction_weight * new_direction + stale``

    - **new surface**: surface pixels (the frame's own depth is valid) where the render shows no
      region or a confidence below ``select_low_conf``, and whose surface was not shown from the
      same direction bin by an encoded frame before. The second half matters: surface an encoder
      never labels (a floor gap, a region border whose fused confidence stays low, anything a
      real encoder misses) would otherwise make every view of it look new forever. Unlabelled
      surface is remembered per cube of ``select_cell_m`` with a bit per direction bin.
    - **new direction**: pixels of a region (labelled, confident) seen from a viewing direction
      bin the region was not encoded from (OVI-MAP's per-instance coverage of directions; our
      bins are ``select_direction_bins`` points of a Fibonacci sphere, the direction is the one
      from the surface to the camera). Only regions that fill at least
      ``select_min_region_share`` of the view count (OVI-MAP asks 1000 visible pixels).
    - **stale**: pixels of a region in view (same size rule) that no encoded frame showed for
      ``select_stale_s`` seconds of frame time: the floor that keeps a region that stays in view
      from going stale; a stale region that fills ``select_min_gain`` of a view is encoded again.
      Frame time here is the map's (:mod:`openfusion.mapping.map_clock`): robots whose clocks
      disagree by more than an hour are put on one time base at their first frame.

    A frame is encoded only when it adds something and ``gain >= select_min_gain / (1 + t /
    select_patience_s)``, ``t`` the frame time since the last frame chosen: the bar falls while
    nothing is encoded, so a little new surface that has waited (a glimpse behind an object that
    the next frames hide again) is encoded too, and a frame that adds nothing never is, even when
    the encoder is idle (counted ``skipped_no_gain``).

    **Look-ahead** (``select_lookahead`` K, off at 1): frames are decided K at a time
    (:meth:`CoverageScorer.decide_best`): of each run of K consecutive frames at most the one of
    highest gain is encoded, when it reaches the bar; a frame waits up to K - 1 frames for its
    decision. On a first sweep, where nearly every frame shows something new, this caps the calls
    at 1/K and takes the best view of each run instead of the first one over the bar; on a
    revisit, runs that add nothing still cost nothing. One process and the services' window decide
    the same runs (the window decides a run cut short when frames stop coming).

Why these rules and defaults (measured in docs/EVAL.md, "Frame selection")
    OVI-MAP (CVPR 2026) runs its VLM only on views that add viewing-direction coverage of an
    instance (at most 0.9 overlap with the covered bins, at least 1000 visible pixels, the top K by
    visible area) and cut VLM calls per instance from 18.7 to 8.6 at about the same accuracy; OVO
    keeps the top views per segment by mask area. We score whole frames because an encoder call
    takes a frame (its proposals or its dense features come from the whole image), so what a call
    buys is the sum over its regions; within a chosen frame only the regions that add something
    are embedded (:meth:`wanted_px`, :mod:`openfusion.mapping.region_gate`: OVI-MAP's rule per
    region, ``select_embed_share``), the others fuse their masks without an embedding. A call
    buys new surface first (weight 1: an unlabelled pixel is a miss in every metric), new
    directions of known regions at half weight (a second view of a labelled surface refines
    its embedding and its borders but is worth less than a first one), and staleness as a floor.
    The bins are coarse (24, about 47 degrees across): finer bins made a robot's small turns look
    new. The view is the map's keys probed at the frame's own depth, 32 px wide (``select_view``,
    :mod:`.surface_probe`): at 64 px, or ray-cast, the bench rooms map the same per encoder call
    at 2-3 times the scoring cost (docs/EVAL.md, "Scored at 32 px").

What is remembered (the scorer's state; it grows with the mapped surface, not with time)
    per region: a bit mask of the direction bins it was encoded from and the stamp of its last
    encoded view; per ``select_cell_m`` cube of surface an encoded frame showed: a bit mask of the
    bins it was shown from. Both follow merges (:meth:`CoverageScorer.merge`). A restarted semantic
    service starts with an empty record: every labelled region looks unseen from every direction
    once, so the first views after a restart are encoded again (the map itself is recovered).

Cost: :meth:`CoverageScorer.prepare` is numpy over the scored pixels (~0.3 ms at 64x48); a rescore
~0.1 ms; the map's view (``SemanticVolume.probe`` or ``render``, or a ``geometry/render`` request)
dominates. Written here, not taken from a library: none scores views against a semantic map.
"""

from __future__ import annotations

import bisect
import math
import threading
from collections.abc import Callable, Hashable, Iterable, Mapping
from typing import Any

import numpy as np

from openfusion.frame import CameraIntrinsics, Frame, resize_nearest
from openfusion.mapping.coverage_bits import fibonacci_directions, group_bits_arrays, or_into, pack_cells
from openfusion.mapping.held_views import HeldViews
from openfusion.mapping.map_clock import MapClock
from openfusion.mapping.params import SelectParams
from openfusion.mapping.still_views import StillViews
from openfusion.mapping.view_evidence import (
    MARK_DENSITY,
    ViewEvidence,
    ViewScore,
    mark_width_px,
    scoring_size,
)

__all__ = ["MARK_DENSITY", "SELECTED_KEPT", "CoverageScorer", "ViewEvidence", "ViewScore", "mark_width_px",
           "scoring_size"]

#: Frame times of chosen views kept for the patience rule (:meth:`CoverageScorer.min_gain_at`).
SELECTED_KEPT = 1024


class CoverageScorer:
    """The score of a view against what encoded frames already covered (module docstring).

    Thread-safe: the semantic service prepares candidates on one thread, takes them on another and
    records plans on a third."""

    def __init__(self, params: SelectParams | None = None) -> None:
        self.params = params if params is not None else SelectParams()
        p = self.params
        self.directions = fibonacci_directions(p.select_direction_bins)
        self._lock = threading.RLock()
        self._region_bins: dict[int, int] = {}
        self._region_last_s: dict[int, float] = {}
        self._region_views: dict[int, int] = {}  # encoded frames whose update wrote the region
        # _cell_tries[i][cube]: the direction bins the cube was shown from by at least i + 1 encoded frames
        self._cell_tries: list[dict[int, int]] = [{} for _ in range(p.select_tries)]
        self._held = HeldViews()  # views chosen but not encoded yet (the services' window; :meth:`hold`)
        #: views handed to an encoder, not applied yet -> the regions they will likely embed
        #: (:meth:`embedding_in_flight`, dropped at :meth:`release`; a pool holds a few at once)
        self._in_flight: dict[tuple[str, int, float], list[int]] = {}
        self._rays: dict[CameraIntrinsics, np.ndarray] = {}
        #: per robot, frame times of the views chosen (sorted; the newest SELECTED_KEPT): each robot's
        #: stamps are its own clock, and the patience rule is about the frames of one stream
        self._selected_s: dict[str, list[float]] = {}
        #: robots' stamps on one time base, for the regions' last-seen stamps (staleness)
        self.clock = MapClock()
        #: keys (int64 (k,)) -> (how many embeddings each region's dictionary entry averages, the
        #: length of that mean of unit vectors): :meth:`RegionDictionary.support_of`, set by the owner
        #: of the dictionary, for ``select_embed_min_views`` / ``select_embed_min_agreement`` (:meth:`wanted_px`)
        self.embedding_support: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None
        #: the last render of each robot's view, reused while its camera stands still (select_still_s)
        self.still = StillViews(still_s=p.select_still_s, still_m=p.select_still_m, still_deg=p.select_still_deg)

    # ------------------------------------------------------------------ record
    @property
    def regions_recorded(self) -> int:
        with self._lock:
            return len(self._region_bins)

    @property
    def cells_recorded(self) -> int:
        with self._lock:
            return len(self._cell_tries[0])

    def record_bytes(self) -> int:  # rough: python dict entries of two ints, ~100 B each
        with self._lock:
            return 100 * (sum(len(t) for t in self._cell_tries) + 3 * len(self._region_bins))

    def reset(self) -> None:
        with self._lock:
            self._region_bins.clear()
            self._region_last_s.clear()
            self._region_views.clear()
            self._selected_s.clear()
            self.clock.reset()
            self._held.clear()
            self._in_flight.clear()
            for table in self._cell_tries:
                table.clear()
        self.still.forget()

    def merge(self, merged_into: Mapping[int, int], removed: Iterable[int] = ()) -> None:
        """Follow the dictionary: region ``b`` merged into ``a`` gives ``a`` its direction bins and the
        later of the two last-seen stamps; removed regions are forgotten."""
        with self._lock:
            def root(k: int) -> int:
                seen = set()
                while k in merged_into and k not in seen:
                    seen.add(k)
                    k = int(merged_into[k])
                return k

            for b in merged_into:
                b, a = int(b), root(int(b))
                bits = self._region_bins.pop(b, 0)
                last = self._region_last_s.pop(b, None)
                views = self._region_views.pop(b, 0)
                if a < 0:
                    continue
                if bits:
                    self._region_bins[a] = self._region_bins.get(a, 0) | bits
                if views:
                    self._region_views[a] = self._region_views.get(a, 0) + views
                if last is not None:
                    self._region_last_s[a] = max(last, self._region_last_s.get(a, last))
            for k in removed:
                self._region_bins.pop(int(k), None)
                self._region_last_s.pop(int(k), None)
                self._region_views.pop(int(k), None)

    # ------------------------------------------------------------------ geometry of a view
    def _camera_rays(self, intrinsics: CameraIntrinsics) -> np.ndarray:
        """(h*w, 3) camera-frame rays with z = 1 through every pixel centre (integer coordinates, the
        convention of :meth:`CameraIntrinsics.scaled`; cached)."""
        rays = self._rays.get(intrinsics)
        if rays is None:
            h, w = intrinsics.height_px, intrinsics.width_px
            u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))  # pixel centres
            rays = np.stack([(u - intrinsics.cx) / intrinsics.fx, (v - intrinsics.cy) / intrinsics.fy,
                             np.ones_like(u)], axis=-1).reshape(-1, 3)
            if len(self._rays) > 16:
                self._rays.clear()
            self._rays[intrinsics] = rays
        return rays

    def _bins_of(self, rays_cam: np.ndarray, T_world_cam: np.ndarray) -> np.ndarray:
        """Direction bin (from the surface to the camera, world frame) of each camera ray."""
        to_camera = -(rays_cam @ np.asarray(T_world_cam, np.float64)[:3, :3].T)
        return np.argmax(to_camera @ self.directions.T, axis=1).astype(np.int64)

    def _cells_of(self, points_world: np.ndarray) -> np.ndarray:
        return pack_cells(points_world, self.params.select_cell_m)

    def prepare(
        self,
        *,
        frame_id: int,
        stamp_ns: int,
        T_world_cam: np.ndarray,
        intrinsics: CameraIntrinsics,
        depth_m: np.ndarray,
        key_map: np.ndarray,
        conf_map: np.ndarray,
        full_depth_m: np.ndarray | None = None,
        full_intrinsics: CameraIntrinsics | None = None,
        robot: str = "",
    ) -> ViewEvidence:
        """The evidence of one view: ``intrinsics`` of the scored view (:func:`scoring_size`),
        the frame's depth in metres at that size, and the map's key and confidence maps rendered at
        the frame's pose at that size. ``full_depth_m`` with its ``full_intrinsics`` (the frame's
        own): what the view marks as shown when it is chosen is sampled from it at
        :func:`mark_width_px`, denser than the score (a cube the scored pixels step over is shown
        all the same); only that sample is kept. Raises ValueError when the sizes disagree."""
        h, w = intrinsics.height_px, intrinsics.width_px
        for name, arr in (("depth_m", depth_m), ("key_map", key_map), ("conf_map", conf_map)):
            if np.shape(arr) != (h, w):
                raise ValueError(f"{name} is {np.shape(arr)}, the scored view is {(h, w)}")
        depth = np.asarray(depth_m, np.float64).reshape(-1)
        surface = np.isfinite(depth) & (depth > 0)
        rays = self._camera_rays(intrinsics)[surface]
        T = np.asarray(T_world_cam, np.float64)
        points = (rays * depth[surface, None]) @ T[:3, :3].T + T[:3, 3]
        keys = np.asarray(key_map).reshape(-1)[surface].astype(np.int64)
        conf = np.asarray(conf_map, np.float32).reshape(-1)[surface]
        confident = (keys >= 0) & (conf >= self.params.select_low_conf)
        unsure_px = np.zeros(h * w, bool)
        unsure_px[np.flatnonzero(surface)[~confident]] = True
        ev = ViewEvidence(
            frame_id=int(frame_id), stamp_s=stamp_ns / 1e9, view_px=h * w, robot=str(robot),
            map_s=self.clock.map_s(str(robot), stamp_ns / 1e9), bins=self._bins_of(rays, T),
            cells=self._cells_of(points), keys=keys, confident=confident, unsure_px=unsure_px.reshape(h, w),
            surface_idx=np.flatnonzero(surface), T_world_cam=T)
        ev.support = self._support_of(np.unique(keys[confident]))  # outside the record's lock
        if full_depth_m is not None and full_intrinsics is not None:
            mh, mw = scoring_size(full_intrinsics, mark_width_px(w))
            ev.mark_depth_m = np.asarray(resize_nearest(np.asarray(full_depth_m), (mh, mw)), np.float32)
            ev.mark_intrinsics = full_intrinsics.scaled(mw, mh)
        return ev

    def _marks(self, ev: ViewEvidence) -> tuple[np.ndarray, np.ndarray]:
        """(cubes, bins) a chosen view marks as shown: its unsure surface (the rest is labelled and
        never looked up), sampled denser than it was scored (:func:`mark_width_px`)."""
        unsure = ~ev.confident
        if ev.mark_depth_m is None or ev.mark_intrinsics is None or ev.unsure_px is None or ev.T_world_cam is None:
            return ev.cells[unsure], ev.bins[unsure]
        mh, mw = ev.mark_depth_m.shape
        fine = ev.mark_depth_m.astype(np.float64).reshape(-1)
        pick = (np.isfinite(fine) & (fine > 0) & resize_nearest(ev.unsure_px, (mh, mw)).reshape(-1))
        T = ev.T_world_cam
        rays = self._camera_rays(ev.mark_intrinsics)[pick]
        return self._cells_of((rays * fine[pick, None]) @ T[:3, :3].T + T[:3, 3]), self._bins_of(rays, T)

    def prepare_frame(self, frame: Frame, render: Callable[[np.ndarray, CameraIntrinsics], Any],
                      robot: str = "", *, labels_version: Hashable | None = None) -> ViewEvidence:
        """:meth:`prepare` for a frame of ``robot``, with ``render(T_world_cam, intrinsics[, depth_m])``
        giving the map's ``key_map``, ``conf_map`` and ``depth_m`` at the scored size (a
        ``RenderedView`` or a render reply); unless ``select_view`` is ``render`` it is given the
        frame's depth at that size, to probe the map there when the map is large
        (:mod:`openfusion.mapping.surface_probe`). A render reply's ``T_map_cam`` (the frame's pose
        joined to the map's frame: another robot's frame) is the pose the view is filed under, so every robot's views
        share one record. ``labels_version`` (changes with every update and merge): a still camera
        reuses its last render (:mod:`openfusion.mapping.still_views`); None: always rendered."""
        K, depth_small, look = self._scored_view(frame, render)
        mh, mw = scoring_size(frame.intrinsics, mark_width_px(K.width_px))
        depth_mark = frame.depth_m((mh, mw))
        rendered = self.still.render(look, robot, frame.T_world_cam, K, depth_small, frame.stamp_ns / 1e9,
                                     labels_version)
        T_map_cam = getattr(rendered, "T_map_cam", None)
        T_map_cam = frame.T_world_cam if T_map_cam is None else T_map_cam
        return self.prepare(frame_id=frame.frame_id, stamp_ns=frame.stamp_ns, T_world_cam=T_map_cam,
                            intrinsics=K, depth_m=depth_small,
                            key_map=rendered.key_map, conf_map=rendered.conf_map, full_depth_m=depth_mark,
                            full_intrinsics=frame.intrinsics.scaled(mw, mh), robot=robot)

    # ------------------------------------------------------------------ score
    def score(self, ev: ViewEvidence) -> ViewScore:
        """The view's gain against the record as it is now (cheap: call again after it changed)."""
        p = self.params
        with self._lock:
            # new surface: unlabelled / unsure pixels whose cube was not shown from this bin
            unsure = ~ev.confident
            new_surface = 0
            if unsure.any():
                cells, bins = ev.cells[unsure], ev.bins[unsure]
                uniq, inv = np.unique(cells, return_inverse=True)
                tried, held = self._cell_tries[-1], self._held.bits
                masks = np.fromiter((tried.get(c, 0) | held.get(c, 0) for c in uniq.tolist()), np.int64, len(uniq))
                new_surface = int((((masks[inv] >> bins) & 1) == 0).sum())
            # regions: new directions and staleness, for regions big enough to count
            new_direction = stale = regions = 0
            if ev.confident.any():
                keys, bins = ev.keys[ev.confident], ev.bins[ev.confident]
                uniq, inv, counts = np.unique(keys, return_inverse=True, return_counts=True)
                big = counts >= max(1.0, p.select_min_region_share * ev.view_px)
                regions = int(big.sum())
                masks = np.fromiter((self._region_bins.get(int(k), 0) for k in uniq), np.int64, len(uniq))
                few = np.fromiter((self._region_views.get(int(k), 0) < p.select_min_views for k in uniq), bool,
                                  len(uniq))
                new_px = ((((masks[inv] >> bins) & 1) == 0) | few[inv]) & big[inv]
                new_direction = int(new_px.sum())
                if p.select_stale_s is not None:
                    last = np.fromiter((self._region_last_s.get(int(k), math.inf) for k in uniq), np.float64,
                                       len(uniq))
                    is_stale = big & (ev.map_s - last >= p.select_stale_s)
                    stale = int(counts[is_stale].sum())
        n = max(1, ev.view_px)
        gain = (new_surface + p.select_direction_weight * new_direction + stale) / n
        return ViewScore(frame_id=ev.frame_id, stamp_s=ev.stamp_s, gain=gain, new_surface=new_surface / n,
                         new_direction=new_direction / n, stale=stale / n, surface=ev.surface_px / n,
                         regions=regions, robot=ev.robot)

    def wanted_px(self, ev: ViewEvidence) -> np.ndarray | None:
        """(h, w) bool over the scored view: the pixels whose regions are worth an embedding
        against the record as it is now (:mod:`openfusion.mapping.region_gate`): surface without a
        confident region, and pixels of a region seen from a direction bin it was not encoded
        from, written by fewer than ``select_min_views`` encoded frames, whose embedding averages
        fewer than ``select_embed_min_views`` views or views that disagree (the mean's length under
        ``select_embed_min_agreement``; :attr:`embedding_support`), or gone stale. Unlike the
        score, every region counts whatever its size (a small region's first view from a
        direction is still its first). None for a view prepared without its pixel layout."""
        if ev.unsure_px is None or ev.surface_idx is None:
            return None
        with self._lock:
            ev.wanted_base = self._new_to(ev.keys, ev.bins, ev.confident, stale_at_s=ev.map_s)
            want = ~ev.confident | ev.wanted_base
            if ev.confident.any():
                uniq, inv = np.unique(ev.keys[ev.confident], return_inverse=True)
                want[ev.confident] |= self._unsettled(uniq, ev.support)[inv]
        return self._view_mask(ev, want)

    def wanted_now(self, ev: ViewEvidence, key_map: np.ndarray | None = None,
                   conf_map: np.ndarray | None = None) -> np.ndarray | None:
        """:meth:`wanted_px` of a chosen view as its encoder call is made, over the map's
        ``key_map`` / ``conf_map`` rendered again at its scored view (None: the decision's). The
        services' window encodes a chosen frame after the frames taken before it labelled and settled
        much of what its render showed (with the decision's mask they embedded 3.5-4x the regions
        one process does: docs/EVAL.md, "Embeddings per region"). Pixels confident at the decision
        keep its reasons; pixels labelled since are wanted from a direction new to their region;
        unlabelled ones are wanted; every region if not settled now."""
        if ev.wanted_base is None or ev.surface_idx is None or ev.unsure_px is None:
            return ev.wanted_px
        keys, confident = ev.keys, ev.confident
        if key_map is not None and conf_map is not None:
            keys = self._at_surface(ev, key_map).astype(np.int64)
            confident = (keys >= 0) & (self._at_surface(ev, conf_map) >= self.params.select_low_conf)
        uniq, inv = np.unique(keys[confident], return_inverse=True)
        support = self._support_of(uniq)
        with self._lock:
            since = confident & ~ev.confident  # labelled after the decision
            want = ~confident | (ev.wanted_base & confident)
            want |= self._new_to(keys, ev.bins, since)
            if len(uniq):
                want[confident] |= self._unsettled(uniq, support)[inv]
        return self._view_mask(ev, want)

    def _new_to(self, keys: np.ndarray, bins: np.ndarray, where: np.ndarray,
                stale_at_s: float | None = None) -> np.ndarray:
        """(lock held) Per pixel in ``where``: its region was not encoded from its direction bin
        (or, given ``stale_at_s``, not seen for ``select_stale_s``); False elsewhere."""
        out = np.zeros(len(keys), bool)
        if not where.any():
            return out
        uniq, inv = np.unique(keys[where], return_inverse=True)
        masks = np.fromiter((self._region_bins.get(int(k), 0) for k in uniq), np.int64, len(uniq))
        new = ((masks[inv] >> bins[where]) & 1) == 0
        if stale_at_s is not None and self.params.select_stale_s is not None:
            last = np.fromiter((self._region_last_s.get(int(k), math.inf) for k in uniq), np.float64, len(uniq))
            new |= (stale_at_s - last >= self.params.select_stale_s)[inv]
        out[where] = new
        return out

    def _support_of(self, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """Per key, (embeddings averaged, their agreement); None: no support, or regions not gated."""
        if self.embedding_support is None or self.params.select_embed_share is None:
            return None
        count, agreement = self.embedding_support(keys)
        return np.asarray(count), np.asarray(agreement)

    def _unsettled(self, keys: np.ndarray, support: tuple[np.ndarray, np.ndarray] | None) -> np.ndarray:
        """(lock held) Per key: fewer than ``select_min_views`` encoded frames, or (``support``) fewer
        than ``select_embed_min_views`` embeddings or ones that disagree; embeddings in flight count."""
        p = self.params
        extra = np.zeros(len(keys), np.int64)
        for taken in self._in_flight.values():
            extra += np.isin(keys, taken)
        views = np.fromiter((self._region_views.get(int(k), 0) for k in keys), np.int64, len(keys))
        again = views + extra < p.select_min_views
        if support is not None and len(support[0]) == len(keys):
            count, agreement = support
            again |= (count + extra < p.select_embed_min_views) | (agreement < p.select_embed_min_agreement)
        return again

    def embedding_in_flight(self, ev: ViewEvidence, key_map: np.ndarray | None, wanted_px: np.ndarray | None) -> None:
        """A chosen view was handed to an encoder with ``wanted_px`` (:meth:`wanted_now`, over the
        map's ``key_map`` at its scored view, None: as decided): until :meth:`release`, the regions
        it will likely embed (at least ``select_embed_share`` of their pixels wanted) count one view
        more. So a second worker of the pool, taking a frame while the first encodes, does not
        embed them again. Surface it shows unlabelled stays wanted: crediting it too (the pool
        then embedded what one process does) lost the ceiling's only region in 4 of 9 runs of the
        bench scene, where the frame in flight did not label it after all. One encoder at a time
        releases each frame before the next is taken."""
        share = self.params.select_embed_share
        if wanted_px is None or share is None or ev.surface_idx is None:
            return
        keys = ev.keys if key_map is None else self._at_surface(ev, key_map).astype(np.int64)
        want = self._at_surface(ev, wanted_px)
        labelled = keys >= 0
        uniq, inv = np.unique(keys[labelled], return_inverse=True)
        hit = np.bincount(inv, weights=want[labelled], minlength=len(uniq)) >= share * np.bincount(inv, minlength=len(uniq))
        taken = uniq[hit].tolist()
        with self._lock:
            self._in_flight[(ev.robot, ev.frame_id, ev.stamp_s)] = taken

    @staticmethod
    def _at_surface(ev: ViewEvidence, image: np.ndarray) -> np.ndarray:
        """An (h, w) image of the scored view at the view's surface pixels (as ``ev.keys``)."""
        return np.asarray(image).reshape(-1)[ev.surface_idx]

    @staticmethod
    def _view_mask(ev: ViewEvidence, want: np.ndarray) -> np.ndarray:
        out = np.zeros(ev.unsure_px.shape, bool)  # type: ignore[union-attr]  # callers check it
        out.reshape(-1)[ev.surface_idx[want]] = True  # type: ignore[index]
        return out

    def render_again(self, frame: Frame, render: Callable[..., Any]) -> tuple[np.ndarray, np.ndarray]:
        """The map's ``(key_map, conf_map)`` at ``frame``'s scored view now, rendered as
        :meth:`prepare_frame` renders it (never a reused render): for :meth:`wanted_now`."""
        K, _depth, look = self._scored_view(frame, render)
        rendered = look(frame.T_world_cam, K)
        return rendered.key_map, rendered.conf_map

    def _scored_view(self, frame: Frame, render: Callable[..., Any]) -> tuple[CameraIntrinsics, np.ndarray, Callable]:
        """``(K, depth_m, look)`` of ``frame``'s scored view: its intrinsics, its depth at that size,
        and ``look(T_world_cam, K)`` rendering the map there (with the depth, to probe, unless
        ``select_view`` is ``render``)."""
        h, w = scoring_size(frame.intrinsics, self.params.select_width_px)
        depth_small = frame.depth_m((h, w))
        look = render if self.params.select_view == "render" else lambda T, K: render(T, K, depth_small)
        return frame.intrinsics.scaled(w, h), depth_small, look

    def _wanted_if_gated(self, ev: ViewEvidence) -> np.ndarray | None:
        """:meth:`wanted_px` when ``select_embed_share`` gates regions (None, not computed, otherwise)."""
        return self.wanted_px(ev) if self.params.select_embed_share is not None else None

    def min_gain_at(self, stamp_s: float, robot: str = "") -> float:
        """The gain a view of frame time ``stamp_s`` needs: ``select_min_gain``, falling as
        ``1 / (1 + t / select_patience_s)`` with the frame time ``t`` to the nearest view chosen
        (in one process the last one; in the services' window, where an older candidate can be
        taken after a newer one, the nearest on either side), among ``robot``'s views: another
        robot's stamps are another clock and another stream (two robots whose chosen frames
        interleaved held each other's bar up: 0.013 f-mIoU under one robot walking both routes)."""
        p = self.params
        with self._lock:
            chosen = self._selected_s.get(robot, [])
            if p.select_patience_s is None or not chosen:
                return p.select_min_gain
            i = bisect.bisect_left(chosen, stamp_s)
            t = min(abs(stamp_s - chosen[j]) for j in (i - 1, i) if 0 <= j < len(chosen))
        return p.select_min_gain / (1.0 + t / p.select_patience_s)

    def worth_encoding(self, score: ViewScore) -> bool:
        """A view is encoded only when it adds something and its gain reaches :meth:`min_gain_at`."""
        return score.gain > 0 and score.gain >= self.min_gain_at(score.stamp_s, score.robot)

    def decide(self, ev: ViewEvidence, *, hold: bool = False) -> tuple[ViewScore, bool]:
        """Score a view and choose it or not; a chosen view is recorded at once
        (:meth:`mark_selected`), and with ``hold`` held until it is encoded (:meth:`hold`). The one
        decision of every pipeline: one process asks it for every frame, the services' window for
        every frame as it comes."""
        with self._lock:
            score = self.score(ev)
            chosen = self.worth_encoding(score)
            if chosen:
                ev.wanted_px = self._wanted_if_gated(ev)
                self.mark_selected(ev)
                if hold:
                    self.hold(ev)
            return score, chosen

    def decide_best(self, evs: list[ViewEvidence], *, hold: bool = False) -> tuple[list[ViewScore], int | None]:
        """Score a run of views (``select_lookahead`` consecutive frames) and choose at most one: the
        one of highest gain (ties: the newest), when :meth:`worth_encoding`; it is recorded at once.
        Returns every view's score and the index of the chosen one (None: none)."""
        with self._lock:
            scores = [self.score(ev) for ev in evs]
            if not scores:
                return scores, None
            best = max(range(len(scores)), key=lambda i: (scores[i].gain, scores[i].stamp_s, i))
            if not self.worth_encoding(scores[best]):
                return scores, None
            evs[best].wanted_px = self._wanted_if_gated(evs[best])
            self.mark_selected(evs[best])
            if hold:
                self.hold(evs[best])
            return scores, best

    # ------------------------------------------------------------------ views chosen, not encoded yet
    def hold(self, ev: ViewEvidence) -> None:
        """A chosen view waits for the encoder: until :meth:`release`, the unsure surface it shows
        counts as shown ``select_tries`` times from its bins. One process encodes a chosen frame
        before it scores the next; behind a busy encoder the next frames see the same surface still
        unlabelled, and without the hold chose it again and again (84 of 90 frames on the bench
        scene, against 50 in one process). Released, the surface counts as it then is."""
        cells, bins = self._marks(ev)
        with self._lock:
            self._held.add((ev.robot, ev.frame_id, ev.stamp_s), cells, bins)

    def release(self, frame_id: int, stamp_s: float, robot: str = "") -> None:
        """A held view of ``robot`` was encoded and its update sent, or let go (no-op for a view
        not held)."""
        with self._lock:
            self._held.remove((str(robot), int(frame_id), float(stamp_s)))
            self._in_flight.pop((str(robot), int(frame_id), float(stamp_s)), None)

    @property
    def held(self) -> int:
        with self._lock:
            return len(self._held)


    # ------------------------------------------------------------------ record what was encoded
    def mark_selected(self, ev: ViewEvidence) -> None:
        """Record a view chosen for the encoder (before its result is back, so the next choice
        does not pick the same new surface again): its surface cubes and the map's regions in it
        are now covered from its bins, the regions seen at its stamp."""
        with self._lock:
            chosen = self._selected_s.setdefault(ev.robot, [])
            bisect.insort(chosen, ev.stamp_s)
            if len(chosen) > SELECTED_KEPT:
                del chosen[0]
            cells, bins = self._marks(ev)
            if len(cells):
                self._mark_cells(cells, bins)
            labelled = ev.keys >= 0
            if labelled.any():
                or_into(self._region_bins, ev.keys[labelled], ev.bins[labelled])
                for k in np.unique(ev.keys[labelled]).tolist():
                    self._region_last_s[k] = max(ev.map_s, self._region_last_s.get(k, -math.inf))

    def observe_plan(self, key_map: np.ndarray, T_world_cam: np.ndarray, intrinsics: CameraIntrinsics,
                     stamp_ns: int, robot: str = "") -> None:
        """Record the regions an applied update wrote (the plan's ``key_map`` at the encoder's
        size, ``intrinsics`` of that size) of ``robot``'s frame: new regions get their first
        direction bins, every region written its last-seen stamp (in map time). Scored at
        :attr:`SelectParams.select_width_px`."""
        key_map = np.asarray(key_map)
        if key_map.ndim != 2 or key_map.size == 0:
            return
        h, w = scoring_size(intrinsics, self.params.select_width_px)
        small = resize_nearest(key_map, (h, w)).reshape(-1)
        labelled = small >= 0
        if not labelled.any():
            return
        rays = self._camera_rays(intrinsics.scaled(w, h))[labelled]
        bins = self._bins_of(rays, T_world_cam)
        keys = small[labelled].astype(np.int64)
        seen_s = self.clock.map_s(str(robot), stamp_ns / 1e9)
        with self._lock:
            or_into(self._region_bins, keys, bins)
            for k in np.unique(keys).tolist():
                self._region_last_s[k] = max(seen_s, self._region_last_s.get(k, -math.inf))
                self._region_views[k] = self._region_views.get(k, 0) + 1

    def _mark_cells(self, cells: np.ndarray, bins: np.ndarray) -> None:
        """(lock held) One more encoded frame showed ``cells`` from ``bins``: count it per try level
        (a bin reaches level i + 1 when it was at level i before this frame)."""
        uniq, bits = group_bits_arrays(cells, bins)
        keys = uniq.tolist()
        old = [np.fromiter((t.get(c, 0) for c in keys), np.int64, len(keys)) for t in self._cell_tries]
        for level, table in enumerate(self._cell_tries):
            new = old[level] | (bits if level == 0 else old[level - 1] & bits)
            changed = np.flatnonzero(new != old[level])
            table.update(zip(uniq[changed].tolist(), new[changed].tolist(), strict=True))
