"""The geometry service's robots: each robot's stream (:mod:`openfusion.mapping.robot_streams`) and
a thread that joins held robots to the map and re-checks joined ones.

Registrations take seconds (a global search over a building), so they never run on the frame
thread: :class:`RobotJoiner` takes the map's surface under the lock, registers outside it, and
applies an accepted join under the lock again (the held frames are integrated then, in order,
through the transform found). A re-check's map side is rendered on the frame thread before that
frame is integrated (the map must not already hold the frame it is checked against); only its ICP
runs here. While the thread registers, other robots' frames go on being integrated.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from openfusion.frame import Frame
from openfusion.mapping import SemanticVolume
from openfusion.mapping.robot_join import (
    Submap,
    backproject_depth,
    depth_points,
    recheck,
    register_submap,
    thin,
    view_conflict,
)
from openfusion.mapping.robot_streams import RobotStream, RobotStreams
from openfusion.wire.counters import GeometryCounter


class MapOwner(Protocol):
    """What the joiner needs of the geometry service (its map lock, volume and robots)."""

    _lock: threading.RLock
    volume: SemanticVolume
    robots: RobotStreams

    def _count(self, name: str, by: float = 1.0) -> None: ...

    def announce_robots(self) -> None: ...

logger = logging.getLogger("openfusion.services.geometry.service")

RECHECK_DOWNSCALE = 4  # a re-check renders the map at a quarter of the frame's size


@dataclass
class _Recheck:
    robot: RobotStream
    frame_points: np.ndarray  # the frame's points in the robot's odometry frame
    map_points: np.ndarray  # the map's surface rendered at the frame's pose, map frame
    T_map_odom: np.ndarray  # the transform in use when it was rendered


def rendered_map_points(service: MapOwner, robot: RobotStream, frame: Frame) -> np.ndarray:
    """The map's surface seen from the frame's pose (map frame), at a quarter of its size. Call
    with the service's lock held."""
    K = frame.intrinsics.scaled(max(1, frame.intrinsics.width_px // RECHECK_DOWNSCALE),
                                max(1, frame.intrinsics.height_px // RECHECK_DOWNSCALE))
    T_map_cam = robot.T_map_odom @ np.asarray(frame.T_world_cam, np.float64)
    view = service.volume.render(T_map_cam, K)
    return depth_points(view.depth_m, K, T_map_cam)


class RobotJoiner:
    """Joins held robots and re-checks joined ones on a thread of its own (module docstring)."""

    def __init__(self, service: MapOwner, *, integrate_held: Callable[[RobotStream, list], None]) -> None:
        self.service = service
        self._integrate_held = integrate_held
        self._cond = threading.Condition()
        self._rechecks: list[_Recheck] = []
        self._stopping = False
        self._thread: threading.Thread | None = None

    @property
    def robots(self) -> RobotStreams:
        return self.service.robots

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="geometry-robots", daemon=True)
        self._thread.start()

    def wake(self) -> None:
        with self._cond:
            self._cond.notify_all()

    def queue_recheck(self, robot: RobotStream, frame: Frame) -> None:
        """Call with the service's lock held, before ``frame`` is integrated: the robot's recent
        frames (this one last) and the map seen from their poses."""
        frames = [*robot.recent, frame]
        frame_points = thin(np.concatenate([backproject_depth(f) for f in frames]), self.robots.params.join_voxel_m / 2)
        map_points = thin(np.concatenate([rendered_map_points(self.service, robot, f) for f in frames]),
                          self.robots.params.join_voxel_m / 2)
        job = _Recheck(robot, frame_points, map_points, robot.T_map_odom.copy())
        with self._cond:
            self._rechecks = [r for r in self._rechecks if r.robot is not robot] + [job]
            self._cond.notify_all()

    def stop(self, timeout_s: float = 60.0) -> None:
        """Stop the thread after the step in hand (a registration may take seconds)."""
        with self._cond:
            self._stopping = True
            self._cond.notify_all()
        if self._thread is not None:
            self._thread.join(timeout_s)

    # ------------------------------------------------------------------ the thread
    def _run(self) -> None:
        # Lock order: the service's map lock is never taken while holding _cond (the frame thread
        # queues re-checks with the map lock held).
        while True:
            due = self._due()
            with self._cond:
                if self._stopping:
                    return
                if not due and not self._rechecks:
                    self._cond.wait(1.0)
                    continue
                rechecks, self._rechecks = self._rechecks, []
            for job in rechecks:
                self._guarded(self._recheck, job)
            for robot in due:
                if self._stopping:
                    return
                self._guarded(self._attempt, robot)

    def _due(self) -> list[RobotStream]:
        with self.service._lock:
            if self.service.volume.num_blocks == 0:
                return []  # nothing mapped yet to register to
            blocks = self.service.volume.num_blocks
            return [robot for robot in self.robots.held if robot.attempt_due(map_blocks=blocks)]

    def _guarded(self, step: Callable, arg: object) -> None:
        try:
            step(arg)
        except Exception:  # one robot's registration failing never stops the others or the service
            logger.exception("geometry: a robot registration step failed; going on")
            self.service._count(GeometryCounter.JOIN_FAILURES)

    def step(self) -> None:
        """Run what is due now on the calling thread (tests)."""
        with self._cond:
            rechecks, self._rechecks = self._rechecks, []
        for job in rechecks:
            self._recheck(job)
        for robot in self._due():
            self._attempt(robot)

    def _attempt(self, robot: RobotStream) -> None:
        """Register the held robot's recent frames, and (each attempt another) a stretch of its
        hold's older frames: a robot that walked through mapped space earlier and is now somewhere
        the map has not seen (a playback that ran ahead of the others) still joins on those."""
        service = self.service
        params = self.robots.params
        with service._lock:
            if robot.state != "held":
                return
            robot.attempted(map_blocks=service.volume.num_blocks)
            windows = [(robot.submap.points.copy(), robot.submap.frames)]
            recent = {id(frame) for frame in robot.submap.frames}
            older = [held.frame for held in robot.held if id(held.frame) not in recent]
            size = params.join_submap_frames
            if older:
                chunks = [older[i:i + size] for i in range(0, len(older), size)]
                chunk = chunks[(robot.stretches_tried - 1) % len(chunks)]
                window = Submap(params.join_voxel_m, window_frames=size)
                for frame in chunk:
                    window.add(frame)
                windows.append((window.points, window.frames))
            volume = service.volume
        # A whole-map read-out: a job of the read-out worker, asked for holding no lock (its rule 1).
        map_points = volume.extract_points().points.astype(np.float64)
        guess = robot.spec.T_map_odom if robot.spec.mode == "guess" else None

        def render_depth(T_map_cam: np.ndarray, K) -> np.ndarray:  # noqa: ANN001
            with service._lock:
                return service.volume.render(T_map_cam, K).depth_m

        # A surface of the map is only as sharp as its truncation band: beyond it is a contradiction.
        tolerance_m = params.join_conflict_tolerance_m + service.volume.params.trunc_m
        found = None
        try:
            for points, frames in windows:
                views = _spread(frames, params.join_conflict_views)

                def conflict(T_map_odom: np.ndarray, views: list = views) -> float:
                    return view_conflict(views, T_map_odom, render_depth, tolerance_m=tolerance_m)

                # A search tries the identity too: poses are often in the map's frame already (a site map).
                tried = register_submap(points, map_points, params, guess=guess,
                                        extra_starts=[np.eye(4)] if guess is None else (), conflict=conflict)
                found = found or tried  # the recent window's reason is the one reported when none joins
                if tried.accepted:
                    found = tried
                    break
        finally:
            robot.attempt_pending = False
        assert found is not None
        robot.last_registration = found
        service._count(GeometryCounter.JOIN_ATTEMPTS)
        if not found.accepted:
            logger.info("geometry: robot %s still held after attempt %d (%s, %d submap frames): %s", robot.name,
                        robot.join_attempts, found.method, robot.submap.num_frames, found.reason)
            return
        with service._lock:
            if robot.state != "held":
                return
            frames = robot.join(found.T_map_odom, method=found.method, registration=found)
            self._integrate_held(robot, frames)
        service._count(GeometryCounter.ROBOTS_JOINED)
        t = found.T_map_odom
        logger.info("geometry: robot %s joined (%s, fitness %.2f, rmse %.1f cm, runner-up %.2f): T_map_odom "
                    "translation [%.3f, %.3f, %.3f] m, yaw %.2f deg; %d held frames integrated", robot.name,
                    found.method, found.fitness, found.rmse_m * 100, found.runner_up_fitness, t[0, 3], t[1, 3],
                    t[2, 3], float(np.degrees(np.arctan2(t[1, 0], t[0, 0]))), len(frames))
        service.announce_robots()

    def _recheck(self, job: _Recheck) -> None:
        robot = job.robot
        if len(job.map_points) < self.robots.params.join_min_submap_points // 4:
            return  # the map shows too little of what this frame sees
        params = self.robots.params.model_copy(update={
            "join_min_submap_points": self.robots.params.join_min_submap_points // 4})
        found = recheck(job.frame_points, job.map_points, job.T_map_odom, params)
        with self.service._lock:
            if not np.array_equal(robot.T_map_odom, job.T_map_odom):
                return  # changed meanwhile
            outcome = robot.apply_recheck(found)
        self.service._count(GeometryCounter.JOIN_RECHECKS)
        if outcome.startswith("corrected"):
            self.service._count(GeometryCounter.JOIN_CORRECTIONS)
            logger.info("geometry: robot %s re-checked: %s", robot.name, outcome)
        elif outcome.startswith("refused"):
            logger.info("geometry: robot %s re-check not applied: %s", robot.name, outcome)


def _spread(frames: list[Frame], count: int) -> list[Frame]:
    """At most ``count`` of ``frames``, evenly spread (first and last included)."""
    if len(frames) <= count:
        return list(frames)
    picks = np.linspace(0, len(frames) - 1, count).round().astype(int)
    return [frames[i] for i in picks]
