"""Bridge service: plays a frame source onto ``{prefix}/{map}/sensor/rgbd``.

| key | direction | message |
|---|---|---|
| ``…/sensor/rgbd`` | publishes | :class:`~openfusion.wire.schemas.RgbdFrame` (without the instance image) |
| ``…/sensor/instance`` | publishes, for frames that have one, just before the frame | :class:`~openfusion.wire.schemas.InstanceFrame` |
| ``…/geometry/progress`` | subscribes (flow control and resume announcements, playback only) | :class:`~openfusion.wire.schemas.GeometryProgress` |
| ``…/health/semantic`` | liveliness subscriber (replayable playback only) | the semantic service went away / came back |
| ``…/health/bridge`` | liveliness + stats | counters ``frames_read``, ``frames_published``, ``instances_published``, ``skipped_<reason>``, ``frames_throttled``, ``playback_done``, ``flow_wait_s``, ``flow_timeouts``, ``frames_replayed``, ``rewinds`` |

Ground-truth instance images (synthetic scene, ScanNet, Replica) go on their own key: only the
semantic service's gt encoder reads them, and on ``sensor/rgbd`` they were 45 % of every
640x480 frame that geometry had to receive and decode at camera rate.

Rates: ``rate_hz = 0`` publishes as fast as the source produces; ``rate_hz > 0`` paces at that
rate; unset (None) follows the frames' own timestamps (recorded rate). A live source is never
waited for: it publishes every frame as it comes, and ``rate_hz > 0`` caps its rate by dropping
the frames that come sooner than their turn (counted in ``frames_throttled``; ``max_frames`` then
counts published frames). ``loop`` replays the source forever (``max_frames`` is per pass). Before the first frame the bridge waits up to ``wait_for_subscribers_s`` for a
subscriber (so a geometry service started at the same time does not miss the start).

Playback versus live: for a dataset, recording or the synthetic scene the bridge must get every
frame into the map, so it blocks when Zenoh is congested and has flow control: at most
``max_in_flight`` frames are published and not yet taken by geometry (acknowledged on
``geometry/progress``), so a replay at ``rate_hz = 0`` goes exactly as fast as geometry integrates
and never overflows its bounded queue (it dropped half of a 150-frame replay before). No
acknowledgement within ``flow_wait_s`` (no geometry, or one that died): counted in
``flow_timeouts``, and publishing continues open loop until geometry acknowledges again. For a live
source (``FrameSource.live``: Kinect + T265, ROS 2 topics) the bridge never blocks or waits: Zenoh
drops a frame under congestion and geometry's queue drops its oldest, since a stale frame is worth
less than a fresh one. ``block_when_congested`` (default: by source) overrides the choice. See
:mod:`openfusion.bus.flow_control`.

Replay for a restarted geometry (an indexed playback source: datasets, the synthetic scene; not
with ``loop``): each frame carries the playback's name (new for each bridge process) and the id
of the frame published before it (``prev_frame_id``). Geometry announces on ``geometry/progress``
the last frame of this playback it holds (from its checkpoint, after a restart) whenever it
needs the frames after it (:class:`~openfusion.wire.schemas.GeometryProgress`, ``resume > 0``);
the bridge then goes back to the frame after that one (``rewinds``), re-reads the frames from the
source and publishes them again (``frames_replayed``; ``frames_read`` and ``frames_published`` count
each frame once), also after its playback was done. It goes back once per announcement (the
announcement's ``incarnation`` and ``resume``), and again for the same one only when geometry still
repeats it ``flow_wait_s`` later (the replayed frames were lost). The start announcement of the
first geometry it hears of is not a restart (the frames already published are on their way to it).
A bridge restarted with the same ``playback`` name (``openfusion run`` gives its bridge one)
continues that playback: it publishes from the first frame again and geometry drops the frames
it already holds, so none is integrated twice.

The semantic service takes the latest frame only, so frames published while it is down are never
fused. The bridge therefore watches its liveliness token (``health/semantic``): when it goes away,
the bridge notes the last frame published, and when a semantic service is back it goes back to that
frame too (geometry drops the replayed frames it holds, as duplicates, and the semantic service
sees them again). Replayed frames are paced like the first ones (``rate_hz``, or their own
timestamps), so the semantic service takes as many of them as it would have the first time.
"""

from __future__ import annotations

import logging
import threading
import time
import uuid
from typing import Any

from pydantic import Field, field_validator

from openfusion.bus import Publisher, ServiceRunner
from openfusion.bus.flow_control import InFlightWindow, ShardWindows
from openfusion.config import ConfigSection, ServiceConfig
from openfusion.frame import Frame
from openfusion.progress import progress_bar
from openfusion.services.common import ServiceDefinition
from openfusion.sources import FrameSource, open_source
from openfusion.sources.base import IndexedFrameSource
from openfusion.wire.codec import EncodeError
from openfusion.wire.counters import BridgeCounter
from openfusion.wire.endpoints import GEOMETRY_PROGRESS, SENSOR_INSTANCE, SENSOR_RGBD
from openfusion.wire.keys import MAX_SHARDS, ShardId
from openfusion.wire.schemas import GeometryProgress, InstanceFrame, RgbdFrame
from openfusion.wire.schemas.base import DEFAULT_ROBOT, check_robot_name

logger = logging.getLogger(__name__)


class BridgeSection(ConfigSection):
    """The bridge's settings."""

    source: str = Field(
        "synthetic", description="frame source spec: synthetic[:seed=N,...], scannet:PATH, replica:PATH, tum:PATH, "
        "redwood:PATH, folder:PATH, replay:FILE, live:kinect-t265, rosbag:PATH[,color=/topic,...] (rosbag2 folder, .mcap, .db3), "
        "ros2[:layout=bridge|rmw_zenoh,connect=EP,domain_id=N,...] (live ROS 2 topics over Zenoh)"
    )
    rate_hz: float | None = Field(
        None, ge=0, description="publish rate; 0 = as fast as geometry takes frames; none = the frames' timestamps; "
        "a live source is never waited for: every frame as it comes, and a rate drops the frames above it"
    )
    loop: bool = Field(False, description="replay the source forever")
    max_frames: int | None = Field(
        None, ge=0, description="stop after this many frames (with --loop: each pass; a live source: published frames)"
    )
    progress: bool = Field(False, description="show a progress bar")
    wait_for_subscribers_s: float = Field(
        10.0, ge=0, description="before the first frame, wait this long for a subscriber (geometry starting)"
    )
    # Playback must not lose frames: block (back-pressure) instead of letting Zenoh drop a frame
    # when the link is congested, and wait for geometry (flow control). Live sensors must not
    # wait: a stale frame is worth less than a fresh one.
    block_when_congested: bool | None = Field(
        None, description="block instead of dropping when the link is congested (none = by source: playback blocks)"
    )
    max_in_flight: int = Field(
        16, ge=0, description="playback: frames published and not yet taken by geometry (0 = do not wait for geometry); "
        "well under geometry's frame queue"
    )
    flow_wait_s: float = Field(5.0, gt=0, description="playback: without an acknowledgement this long, go open loop")
    geometry_shards: int = Field(
        1, ge=1, le=MAX_SHARDS, description="geometry shards the map is split into (docs/SHARDS.md): playback waits "
        "for every shard's acknowledgement"
    )
    playback: str = Field(
        "", max_length=64, description="name of this playback (none = a new one); a bridge restarted with the same "
        "name continues it: geometry drops the frames it already holds"
    )
    robot: str = Field(
        DEFAULT_ROBOT, description="the robot whose frames these are (one bridge per robot; frame ids, chains, flow "
        "control and the odometry frame are per robot)"
    )

    @field_validator("robot")
    @classmethod
    def _robot_name(cls, value: str) -> str:
        return check_robot_name(value)


class BridgeConfig(ServiceConfig):
    bridge: BridgeSection = Field(default_factory=BridgeSection)


class Pacer:
    """Playback: sleeps so frames go out at ``rate_hz`` (0 = no pacing) or at their own timestamps
    (None), :meth:`due_s`. Live: never sleeps; :meth:`take_live` drops the frames above ``rate_hz``."""

    def __init__(self, rate_hz: float | None) -> None:
        self.rate_hz = rate_hz
        self._t0_wall: float | None = None
        self._t0_stamp_ns: int | None = None
        self._count = 0
        self._next_live_s: float | None = None

    def take_live(self, now_s: float | None = None) -> bool:
        """A live frame that came at ``now_s`` (default: now): True when it goes out, False when it
        comes before its turn at ``rate_hz`` (dropped). Turns are ``1/rate_hz`` apart, so a sensor
        faster than the rate gives exactly the rate on average; after a pause the turns restart."""
        if not self.rate_hz:
            return True
        now = time.monotonic() if now_s is None else now_s
        period = 1.0 / self.rate_hz
        if self._next_live_s is None or now >= self._next_live_s + period:  # first frame, or after a pause
            self._next_live_s = now
        if now < self._next_live_s:
            return False
        self._next_live_s += period
        return True

    def due_s(self, stamp_ns: int) -> float:
        """Seconds to wait before publishing a frame with ``stamp_ns`` (0 when late)."""
        now = time.monotonic()
        if self._t0_wall is None:
            self._t0_wall, self._t0_stamp_ns = now, stamp_ns
        if self.rate_hz == 0:
            target = now
        elif self.rate_hz is None:
            target = self._t0_wall + max(0, stamp_ns - (self._t0_stamp_ns or 0)) / 1e9
        else:
            target = self._t0_wall + self._count / self.rate_hz
        self._count += 1
        return max(0.0, target - now)


class BridgeService:
    """Publishes every frame of ``source``; counts read, skipped (by reason) and published."""

    def __init__(self, config: BridgeConfig, *, source: FrameSource | None = None) -> None:
        self.config = config
        self.section = config.bridge
        self.robot = self.section.robot
        self.source = source if source is not None else open_source(self.section.source)
        #: A live source's frame budget (per pass) counts published frames, as a rate drops some; a
        #: playback's is the source's own.
        self.max_published: int | None = None
        if self.section.max_frames is not None:
            if self.source.live:
                self.max_published = self.section.max_frames
            else:
                self.source.max_frames = self.section.max_frames
        self._pub: Publisher | None = None
        self._instance_pub: Publisher | None = None
        blocking = self.section.block_when_congested
        self.blocking = (not self.source.live) if blocking is None else blocking
        self.window: InFlightWindow | ShardWindows | None = None
        if self.blocking and self.section.max_in_flight > 0:
            n = self.section.geometry_shards
            self.window = (InFlightWindow(self.section.max_in_flight) if n == 1 else
                           ShardWindows(self.section.max_in_flight, [s.service for s in ShardId.all(n)]))
        # Replay for a restarted geometry (module docstring): an indexed playback source only.
        self.replayable = isinstance(self.source, IndexedFrameSource) and not self.source.live and not self.section.loop
        self.playback = (self.section.playback or uuid.uuid4().hex[:16]) if self.replayable else ""
        self._replay_lock = threading.Lock()
        self._positions: dict[int, int] = {}  # frame id -> source position, for frames published
        self._next_position = 0
        self._rewind_to: tuple[int, int] | None = None  # (position, id of the frame before it)
        self._handled: tuple[str, int] | None = None  # the last announcement gone back for, and when
        self._handled_at = 0.0
        self._incarnations: set[tuple[str, str]] = set()  # the geometry processes heard from: (shard, incarnation)
        self._semantic_lost_at: int | None = None  # position of the last frame published when it went away
        self._semantic_watch: Any = None

    def setup(self, runner: ServiceRunner) -> None:
        import zenoh

        congestion = zenoh.CongestionControl.BLOCK if self.blocking else zenoh.CongestionControl.DROP
        logger.info("bridge: robot %s, %s source %s: %s", self.robot, "live" if self.source.live else "playback",
                    self.source.name,
                    f"blocks when congested, at most {self.window.limit} frames ahead of geometry"
                    if self.window is not None else "blocks when congested" if self.blocking
                    else "never blocks (frames may be dropped under congestion)")
        self._pub = runner.publisher(SENSOR_RGBD, congestion_control=congestion)
        self._instance_pub = runner.publisher(SENSOR_INSTANCE, congestion_control=congestion)
        if self.window is not None or self.replayable:
            runner.subscriber(GEOMETRY_PROGRESS, self.on_progress, queue_size=256)
        if self.replayable and getattr(runner, "session", None) is not None:
            self._semantic_watch = runner.session.liveliness().declare_subscriber(
                runner.keys.liveliness("semantic"), zenoh.handlers.Callback(self._on_semantic_liveliness))

    def _on_semantic_liveliness(self, sample: Any) -> None:
        # On a Zenoh thread: bookkeeping only.
        import zenoh

        self.on_semantic(alive=sample.kind == zenoh.SampleKind.PUT)

    def on_semantic(self, *, alive: bool) -> None:
        """The semantic service's liveliness token came (``alive``) or went: when one comes back
        after one went away, go back to the last frame published when it went (module docstring)."""
        with self._replay_lock:
            if not alive:
                self._semantic_lost_at = max(0, self._next_position - 1) if self._positions else None
                return
            position, self._semantic_lost_at = self._semantic_lost_at, None
            if position is None or position >= self._next_position:
                return
            before = [p for p in self._positions.values() if p < position]
            previous = max(before, default=-1)
            prev_id = next((fid for fid, p in self._positions.items() if p == previous), -1)
            self._request_rewind((position, prev_id))
        logger.warning("bridge: the semantic service is back; replaying from position %d for it", position)

    def _request_rewind(self, target: tuple[int, int]) -> None:
        """Call with ``_replay_lock`` held: go back to ``target`` (the earliest of those pending)."""
        if self._rewind_to is None or target[0] < self._rewind_to[0]:
            self._rewind_to = target

    def on_progress(self, msg: GeometryProgress) -> None:
        """An acknowledgement (flow control) and/or a resume announcement of geometry, about this
        bridge's robot (another robot's are another bridge's business)."""
        if msg.robot != self.robot:
            return
        if self.window is not None and msg.frame_id >= 0:
            self.window.acknowledge(msg.frame_id, msg.stamp_ns, shard=msg.shard)
        if msg.resume > 0 and self.replayable:
            self.on_resume(msg)
        if msg.incarnation:
            with self._replay_lock:
                self._incarnations.add((msg.shard, msg.incarnation))

    def on_resume(self, msg: GeometryProgress, now_s: float | None = None) -> None:
        """Geometry wants the frames of this playback after ``holds_frame_id``: go back there when
        frames after it were published (module docstring)."""
        now = time.monotonic() if now_s is None else now_s
        key = (msg.incarnation, msg.resume)
        with self._replay_lock:
            if key == self._handled and now - self._handled_at < self.section.flow_wait_s:
                return
            if msg.resume == 1 and not {i for s, i in self._incarnations if s == msg.shard} - {msg.incarnation}:
                # The start announcement of the first geometry this bridge hears of: the frames
                # published so far are on their way to it, not lost (it may have sent this before
                # they reached it). Frames lost anyway come out of order and it announces again.
                return
            if msg.holds_playback == self.playback and msg.holds_frame_id in self._positions:
                target = (self._positions[msg.holds_frame_id] + 1, msg.holds_frame_id)
            elif msg.holds_playback == self.playback and msg.holds_frame_id >= 0:
                return  # a frame this bridge never published: nothing it could replay
            else:  # geometry holds nothing of this playback
                target = (0, -1)
            self._handled, self._handled_at = key, now
            if target[0] >= self._next_position:
                return  # nothing published after it yet
            self._request_rewind(target)
        logger.warning("bridge: geometry %s holds frames up to %d of this playback; replaying from the frame after it",
                       msg.incarnation, target[1])

    def _take_rewind(self) -> tuple[int, int] | None:
        with self._replay_lock:
            target, self._rewind_to = self._rewind_to, None
            if target is not None:
                self._next_position = target[0]
            return target

    def _publish(self, runner: ServiceRunner, frame: Frame, *, prev_frame_id: int | None = None,
                 replay: bool = False) -> bool:
        """Publish one frame (and its instance image); False when it could not be encoded (counted)."""
        assert self._pub is not None and self._instance_pub is not None
        started = time.monotonic()
        try:
            rgbd = RgbdFrame.from_frame(frame, with_instance=False, playback=self.playback, prev_frame_id=prev_frame_id,
                                        robot=self.robot)
            instance = InstanceFrame.from_frame(frame, robot=self.robot)
            # The instance image goes first, so a subscriber that has the frame has it too.
            if instance is not None:
                self._instance_pub.put(instance)
                runner.stats.incr(BridgeCounter.INSTANCES_PUBLISHED)
            self._pub.put(rgbd)
            if self.window is not None:
                self.window.sent(frame.frame_id, frame.stamp_ns)
        except (EncodeError, ValueError) as exc:
            logger.warning("bridge: frame %d not published: %s", frame.frame_id, exc)
            runner.stats.add_error()
            if not replay:
                runner.stats.incr(BridgeCounter.SKIPPED_UNENCODABLE)
            return False
        except Exception:  # anything else on this one frame: logged with its traceback, counted, skipped
            if runner.stopping:
                raise
            logger.exception("bridge: frame %d from %s not published", frame.frame_id, self.source.name)
            runner.stats.add_error()
            if not replay:
                runner.stats.incr(BridgeCounter.SKIPPED_PUBLISH_FAILED)
            return False
        runner.stats.record(time.monotonic() - started)
        runner.stats.incr(BridgeCounter.FRAMES_REPLAYED if replay else BridgeCounter.FRAMES_PUBLISHED)
        return True

    def _wait_for_geometry(self, runner: ServiceRunner) -> bool:
        """Flow control: wait until geometry has room for another frame. False when stopping."""
        if self.window is None:
            return True
        started = time.monotonic()
        deadline = started + self.section.flow_wait_s
        while not self.window.wait_for_room(min(0.2, max(0.0, deadline - time.monotonic()))):
            if runner.stopping:
                return False
            if self._rewind_to is not None:  # geometry came back and asked for earlier frames
                break
            if time.monotonic() >= deadline:
                self.window.give_up()
                runner.stats.set(BridgeCounter.FLOW_TIMEOUTS, self.window.timeouts)
                logger.warning(
                    "bridge: geometry took none of the last %d frames within %.1f s (acknowledged on %s); "
                    "publishing without waiting until it does", self.window.limit, self.section.flow_wait_s,
                    GEOMETRY_PROGRESS.key(runner.keys))
                break
        runner.stats.incr(BridgeCounter.FLOW_WAIT_S, time.monotonic() - started)
        return True

    def _sync_source_stats(self, runner: ServiceRunner) -> None:
        st = self.source.stats
        runner.stats.set(BridgeCounter.FRAMES_READ_PASS, st.read)
        for reason, n in st.skipped.items():
            runner.stats.set(BridgeCounter.skipped(reason), n)

    def loop(self, runner: ServiceRunner) -> None:
        assert self._pub is not None
        if self.section.wait_for_subscribers_s > 0 and not self._pub.wait_for_subscribers(
            self.section.wait_for_subscribers_s
        ):
            logger.warning("bridge: no subscriber on %s after %.1f s; publishing anyway", self._pub.key,
                           self.section.wait_for_subscribers_s)
        progress = _progress(self.source, enabled=self.section.progress)
        runner.stats.set(BridgeCounter.PLAYBACK_DONE, 0)
        if self.replayable:
            self._replayable_loop(runner, progress)
            return
        passes = 0
        while not runner.stopping:
            pacer = Pacer(self.section.rate_hz)
            published = 0
            for frame in self.source:
                if runner.stopping:
                    break
                runner.stats.incr(BridgeCounter.FRAMES_READ)
                if self.source.live:  # never wait for a live source: drop the frames above the rate
                    if not pacer.take_live():
                        runner.stats.incr(BridgeCounter.FRAMES_THROTTLED)
                        continue
                else:
                    wait_s = pacer.due_s(frame.stamp_ns)
                    if wait_s > 0 and runner.wait(wait_s):
                        break
                if not self._wait_for_geometry(runner):
                    break
                self._publish(runner, frame)
                published += 1
                self._sync_source_stats(runner)
                if progress is not None:
                    progress.update(1)
                if self.max_published is not None and published >= self.max_published:
                    break
            self._sync_source_stats(runner)
            passes += 1
            if not self.section.loop:
                break
        if progress is not None:
            progress.close()
        runner.stats.set(BridgeCounter.PLAYBACK_DONE, 1)
        runner.stats.set(BridgeCounter.PASSES, passes)
        logger.info("bridge: playback done (%d pass(es), %s)", passes, self.source.stats)
        runner.wait()

    def _replayable_loop(self, runner: ServiceRunner, progress: Any) -> None:
        """One pass over an indexed playback source that goes back when geometry asks
        (:meth:`on_resume`); after the pass, it waits and goes back again if asked."""
        source = self.source
        assert isinstance(source, IndexedFrameSource)
        source.start_replayable_pass()
        pacer = Pacer(self.section.rate_hz)
        prev_id = -1
        newest_id = -1  # the newest frame published: frames up to it are replays
        while not runner.stopping:
            rewound = False
            for position, frame in source.replay_from(self._next_position):
                if runner.stopping:
                    break
                target = self._take_rewind()
                if target is not None:
                    prev_id, rewound = target[1], True
                    break
                replay = frame.frame_id <= newest_id
                wait_s = pacer.due_s(frame.stamp_ns)  # replays too: the semantic service sees them as before
                if wait_s > 0 and runner.wait(wait_s):
                    break
                if not self._wait_for_geometry(runner):
                    break
                target = self._take_rewind()
                if target is not None:
                    prev_id, rewound = target[1], True
                    break
                published = self._publish(runner, frame, prev_frame_id=prev_id, replay=replay)
                with self._replay_lock:
                    self._next_position = position + 1
                    if published:
                        self._positions[frame.frame_id] = position
                if not replay:  # counted once it went out (or failed to): a frame read before a rewind is not
                    runner.stats.incr(BridgeCounter.FRAMES_READ)
                newest_id = max(newest_id, frame.frame_id)
                if published:
                    prev_id = frame.frame_id
                self._sync_source_stats(runner)
                if progress is not None and not replay:
                    progress.update(1)
            if rewound:
                self._went_back(runner)
                pacer = Pacer(self.section.rate_hz)
                continue
            if runner.stopping:
                break
            self._sync_source_stats(runner)
            runner.stats.set(BridgeCounter.PLAYBACK_DONE, 1)
            runner.stats.set(BridgeCounter.PASSES, 1)
            logger.info("bridge: playback done (%s)", source.stats)
            while not runner.wait(0.2):  # done: until stopped, or until geometry asks for frames again
                target = self._take_rewind()
                if target is not None:
                    prev_id = target[1]
                    runner.stats.set(BridgeCounter.PLAYBACK_DONE, 0)
                    self._went_back(runner)
                    pacer = Pacer(self.section.rate_hz)
                    break
        if progress is not None:
            progress.close()

    def _went_back(self, runner: ServiceRunner) -> None:
        runner.stats.incr(BridgeCounter.REWINDS)
        if self.window is not None:
            self.window.reset()

    def close(self) -> None:
        if self._semantic_watch is not None:
            import zenoh

            try:
                self._semantic_watch.undeclare()
            except zenoh.ZError as exc:
                logger.debug("semantic liveliness subscriber already undeclared: %s", exc)
            self._semantic_watch = None
        close = getattr(self.source, "close", None)
        if callable(close):
            close()


def _progress(source: FrameSource, *, enabled: bool) -> Any:
    if not enabled:
        return None
    try:
        total: int | None = len(source)
    except TypeError:
        total = None
    return progress_bar(total, f"bridge {source.name}")


def bridge_name(robot: str) -> str:
    """The bridge's service name (health key, process, log): ``bridge`` for the default robot,
    ``bridge-ROBOT`` for the others (one bridge per robot on a map)."""
    return "bridge" if robot == DEFAULT_ROBOT else f"bridge-{robot}"


def _instance_name(config: BridgeConfig) -> str:
    return bridge_name(config.bridge.robot)


DEFINITION = ServiceDefinition(
    name="bridge",
    help="publish RGB-D frames from a dataset, the synthetic scene, a recording or live sensors",
    config_model=BridgeConfig,
    build=BridgeService,
    instance_name=_instance_name,
)
