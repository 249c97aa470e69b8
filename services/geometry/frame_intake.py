"""Frames into the geometry service's map: admission per robot, integration, acknowledgements
and resume announcements (a part of :class:`~openfusion.services.geometry.service.GeometryService`,
apart from its saves and requests; the state it works on, ``_lock``, ``volume``, ``robots``,
``joiner``, ``_runner``..., is the service's).

A frame is admitted by its robot's chain (:mod:`openfusion.mapping.robot_streams`): a duplicate or
out-of-order playback frame is acknowledged and counted but changes nothing, and a resume
announcement tells the bridge where to replay from; a robot not joined yet holds its frames in its
submap; a joined robot's frame is integrated through its transform. A frame that fails to integrate
is logged, counted (``capacity_refused``, ``frames_failed``) and taken as done. Every frame taken
from the queue is acknowledged on ``geometry/progress`` (the bridge's flow control, per shard). The
service's module docstring has the resume story in full.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

import zenoh

from openfusion.bus import Publisher, Subscriber
from openfusion.frame import Frame
from openfusion.mapping import CapacityError
from openfusion.mapping.robot_streams import Admission, RobotStream
from openfusion.services.geometry.parts import ServiceParts, logger
from openfusion.services.geometry.persistence import NO_FRAME_ID
from openfusion.wire.counters import GeometryCounter
from openfusion.wire.keys import ShardId
from openfusion.wire.schemas import GeometryProgress, RgbdFrame

if TYPE_CHECKING:
    from openfusion.services.geometry.robots import RobotJoiner


class FrameIntake(ServiceParts):
    """The frame half of the geometry service (mixed into it)."""

    joiner: RobotJoiner
    shard: ShardId
    incarnation: str
    last_integrated_frame_id: int | None
    _robot_sources: dict[bytes, str]
    _frames_sub: Subscriber[RgbdFrame] | None
    _progress_pub: Publisher | None
    # and the service's helpers (parts.py)

    def announce(self, robot: RobotStream | None = None) -> None:
        """Publish where a robot's playback should continue (``resume`` announcement on
        ``geometry/progress``), for ``robot`` or for every robot that waits for frames."""
        if self._progress_pub is None:
            return
        for r in [robot] if robot is not None else self.robots.announcements_due():
            r.announce_due = False
            playback, held = r.announcement()
            try:
                self._progress_pub.put(GeometryProgress(
                    frame_id=-1, stamp_ns=0, integrated=False, frames_integrated=self.frames_integrated, queued=0,
                    incarnation=self.incarnation, holds_playback=playback, holds_frame_id=held, resume=r.resume,
                    robot=r.name))
            except zenoh.ZError as exc:  # repeated every second while waiting
                logger.warning("geometry: resume announcement for robot %s not published: %s", r.name, exc)

    def announce_robots(self) -> None:
        """Announce for the robots that need one now (a join that asks for a replay)."""
        with self._lock:
            due = [r for r in self.robots if r.announce_due]
        for robot in due:
            self.announce(robot)

    def on_frame(self, msg: RgbdFrame) -> None:
        robot = self._robot(msg.robot)
        self._note_queue(robot)
        gaps = robot.frames_gap
        admission = robot.admit(playback=msg.playback, frame_id=msg.frame_id, prev_frame_id=msg.prev_frame_id)
        if robot.frames_gap > gaps:
            self._count(GeometryCounter.FRAMES_GAP, robot.frames_gap - gaps)
        if admission is not Admission.TAKE:
            self._count(GeometryCounter.FRAMES_DUPLICATE if admission is Admission.DUPLICATE
                        else GeometryCounter.FRAMES_OUT_OF_ORDER)
            if robot.announce_due:
                self.announce(robot)
            self._acknowledge(msg, integrated=False)
            return
        frame = msg.to_frame()
        with self._lock:  # the join (another thread) changes the state under this lock
            robot.took(playback=msg.playback, frame_id=msg.frame_id, stamp_ns=msg.stamp_ns)
            held = robot.state == "held"
            if held:  # into its submap and hold, never into the map (robot_streams)
                robot.hold(frame, playback=msg.playback, frame_id=msg.frame_id, prev_frame_id=msg.prev_frame_id)
            else:
                if robot.recheck_due():
                    self.joiner.queue_recheck(robot, frame)
                robot.recent.append(frame)
        if held:
            self._count(GeometryCounter.FRAMES_HELD)
            self._acknowledge(msg, integrated=False)
            self.joiner.wake()
            return
        integrated = self._integrate(robot, frame, playback=msg.playback)
        self._acknowledge(msg, integrated=integrated)

    def _note_queue(self, robot: RobotStream) -> None:
        """Which publisher is this robot's, and how long its frame waited (health: queued, lag)."""
        sub = self._frames_sub
        if sub is None:
            return
        self._robot_sources[sub.current_source] = robot.name
        robot.lag_s = max(0.0, time.monotonic() - sub.current_arrival_s)

    def _integrate(self, robot: RobotStream, frame: Frame, *, playback: str) -> bool:
        """Integrate one of a joined robot's frames through its transform; a frame that fails is
        logged, counted and taken as done (a replay never retries it). True when integrated."""
        started = time.monotonic()
        try:
            with self._lock:
                self.volume.integrate(robot.to_map(frame))
                self.frames_integrated += 1
                robot.frames_integrated += 1
                robot.in_map(playback=playback, frame_id=frame.frame_id, stamp_ns=frame.stamp_ns)
                self.last_integrated_frame_id = frame.frame_id
                self._map_changed()
                self._dirty = True
        except CapacityError as exc:
            logger.warning("geometry: frame %d of robot %s refused: %s", frame.frame_id, robot.name, exc)
            # taken: the playback goes on after it
            robot.in_map(playback=playback, frame_id=frame.frame_id, stamp_ns=frame.stamp_ns)
            robot.skipped["capacity"] += 1
            self._count(GeometryCounter.CAPACITY_REFUSED)
            return False
        except Exception:  # anything else on this one frame: logged, counted, taken (a replay never retries it)
            logger.exception("geometry: frame %d of robot %s (%s) failed to integrate and was skipped",
                             frame.frame_id, robot.name, frame.source)
            robot.in_map(playback=playback, frame_id=frame.frame_id, stamp_ns=frame.stamp_ns)
            robot.skipped["failed"] += 1
            self._count(GeometryCounter.FRAMES_FAILED)
            if self._runner is not None:
                self._runner.stats.add_error()
            return False
        ended = time.monotonic()
        elapsed = ended - started
        self.integrate_busy_s += elapsed
        if self._runner is not None:
            self._runner.stats.record(elapsed)
            self._runner.stats.set(GeometryCounter.INTEGRATE_BUSY_S, self.integrate_busy_s)
            self._runner.stats.set(GeometryCounter.LAST_INTEGRATED_AT_S, ended)
            self._runner.stats.set(GeometryCounter.FRAMES_INTEGRATED, self.frames_integrated)
            self._set_memory_stats()
            self._runner.stats.set(GeometryCounter.LAST_FRAME_ID, frame.frame_id)
        return True

    def _integrate_held(self, robot: RobotStream, frames: list) -> None:
        """A robot just joined: its held frames, in order, through the transform found (the
        joiner calls this with the lock held)."""
        for held in frames:
            self._integrate(robot, held.frame, playback=held.playback)

    def robot_status(self) -> dict[str, dict]:
        """Each robot's stream for health (:class:`~openfusion.wire.schemas.admin.RobotStatus`)."""
        queued: dict[str, int] = {}
        if self._frames_sub is not None:
            for source, (n, _oldest) in self._frames_sub.queued_by_source().items():
                name = self._robot_sources.get(source)
                if name is not None:
                    queued[name] = queued.get(name, 0) + n
        with self._lock:
            robots = list(self.robots)
            status = {}
            for robot in robots:
                robot.queued = queued.get(robot.name, 0)
                status[robot.name] = robot.status(map_blocks=self.volume.num_blocks)
        if self._runner is not None:
            self._runner.stats.set(GeometryCounter.ROBOTS, len(robots))
            self._runner.stats.set(GeometryCounter.ROBOTS_HELD, sum(r.state == "held" for r in robots))
        return status

    def _acknowledge(self, msg: RgbdFrame, *, integrated: bool) -> None:
        """Tell the robot's bridge this frame left the queue (its flow control waits for this)."""
        if self._progress_pub is None:
            return
        queued = self._frames_sub.queued if self._frames_sub is not None else 0
        robot = self.robots.robots.get(msg.robot)
        playback, held = robot.holds() if robot is not None else ("", NO_FRAME_ID)
        try:
            self._progress_pub.put(GeometryProgress(frame_id=msg.frame_id, stamp_ns=msg.stamp_ns, integrated=integrated,
                                                    frames_integrated=self.frames_integrated, queued=queued,
                                                    incarnation=self.incarnation, holds_playback=playback,
                                                    holds_frame_id=held, robot=msg.robot, shard=self.shard.service))
        except zenoh.ZError as exc:  # the map is fine; the bridge falls back to open loop
            logger.warning("geometry: progress for frame %d not published: %s", msg.frame_id, exc)

