"""Several robots, one map: each robot's stream of frames, its chain, and its frame joined to the map's.

A frame names its robot (``RgbdFrame.robot``, ``robot0`` by default). Everything that was per map
when a map had one bridge is per robot here (:class:`RobotStream`):

Chain (exactly once, resume)
    A playback frame carries its playback's name and the id of the frame published before it
    (``prev_frame_id``). A robot's frame is taken only right after the one it holds: one it holds
    already (same playback, id at most the last taken) is a ``duplicate``, one whose predecessor it
    does not hold is ``out_of_order`` and the robot's bridge is asked (an announcement naming the
    robot) to replay from the frame after the last one held. A live frame (no ``prev_frame_id``)
    is taken as it comes and the ids missing before it are counted as ``frames_gap``. Two robots'
    frames never disturb each other's chains.

Join (:mod:`openfusion.mapping.robot_join`)
    A robot's poses are in its own odometry frame. How its frame joins the map's is given per robot
    (:func:`parse_robot_frames`; ``geometry.robot_frames``):

    ``fixed[:x,y,z,yaw_deg]``  joined at once with this transform (identity when none is given):
                               poses already in the map frame, or a calibrated offset;
    ``guess[:x,y,z,yaw_deg]``  held, then registered by ICP from the guess;
    ``search``                 held, then registered by the global search (the identity is tried
                               as one more candidate): no guess at all. The default.

    Robots given as ``fixed`` define the map's frame. Without one, the first robot on an empty map
    (no joined robot, no surface) has nothing to register to: it anchors the map at its transform
    (its guess, or identity), whatever its mode. A held robot's
    frames go into its *submap* (points in its own frame, for registration) and, up to
    ``join_max_held_frames``, into a hold; none of them reaches the shared map until the robot is
    joined, so nothing is fused misaligned. When a registration is accepted the held frames are
    integrated, in order, through the transform found. Frames past the hold's bound are not kept:
    for a playback the chain is set back to the last frame integrated and the robot's bridge
    replays the rest (exactly once still holds); a live robot loses them (``skipped.held_dropped``).

    A joined robot (not ``fixed``, not the anchor) is re-checked every ``join_recheck_every`` of
    its frames: the frame, before it is integrated, is registered by ICP against the map's surface
    rendered at its pose; a correction between the ``min`` and ``max`` bounds replaces the
    transform (logged, counted), a larger one is refused and logged (a re-check is one frame; a
    jump that large is more likely a bad frame than drift).

Checkpoints
    :meth:`RobotStreams.to_meta` gives what a map file records per robot: the chain position of the
    last frame in the map (a held robot's frames are not in it: after a restart they are replayed),
    the transform and whether it was joined. :meth:`RobotStreams.restore` reads it back, and reads a
    map saved before robots existed (``playback``/``last_frame_id`` at the top level) as ``robot0``'s.

Fairness is the geometry service's frame queue's (:class:`openfusion.bus.Subscriber` with
``fair=True``): one queue per robot's bridge, served in turn, so one robot's backlog never starves
another.

This module holds state and decisions only (no bus, no threads); the geometry service calls it under
its map lock and runs registrations on a thread of its own.
"""

from __future__ import annotations

import collections
import dataclasses
import enum
import logging
import re
import time
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from openfusion.errors import UserError
from openfusion.frame import Frame
from openfusion.mapping.params import JoinParams
from openfusion.mapping.robot_join import Registration, Submap, pose_difference
from openfusion.poses import check_pose

logger = logging.getLogger(__name__)

JoinMode = Literal["fixed", "guess", "search"]
JOIN_MODES: tuple[str, ...] = ("fixed", "guess", "search")
NO_FRAME_ID = -1


class RobotFramesError(UserError, ValueError):
    """A ``robot_frames`` setting that does not parse (names the entry and why)."""


@dataclass(frozen=True)
class RobotFrameSpec:
    """How one robot's odometry frame joins the map's (module docstring, "Join")."""

    mode: JoinMode = "search"
    T_map_odom: np.ndarray = field(default_factory=lambda: np.eye(4))


def yaw_transform(x_m: float, y_m: float, z_m: float, yaw_deg: float) -> np.ndarray:
    """``T_map_odom`` of a gravity-aligned odometry frame: a turn about z and a shift."""
    a = np.deg2rad(yaw_deg)
    T = np.eye(4)
    T[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    T[:3, 3] = (x_m, y_m, z_m)
    return T


_ENTRY = re.compile(r"^\s*([A-Za-z0-9_.\-]+)\s*=\s*(fixed|guess|search)\s*(?::\s*(.*))?$")


def parse_robot_frames(text: str) -> dict[str, RobotFrameSpec]:
    """``"robot0=fixed; robot1=guess:0.3,0,0,5; robot2=search"`` -> specs by robot name.

    Entries are separated by ``;``; a transform is ``x,y,z,yaw_deg`` (metres, degrees). Raises
    :class:`RobotFramesError` naming the bad entry."""
    specs: dict[str, RobotFrameSpec] = {}
    for entry in filter(None, (part.strip() for part in text.split(";"))):
        match = _ENTRY.match(entry)
        if match is None:
            raise RobotFramesError(
                f"robot_frames entry {entry!r} is not ROBOT=fixed|guess|search[:x,y,z,yaw_deg]")
        name, mode, values = match.group(1), match.group(2), match.group(3)
        if name in specs:
            raise RobotFramesError(f"robot_frames names robot {name!r} twice")
        T = np.eye(4)
        if values:
            if mode == "search":
                raise RobotFramesError(f"robot_frames entry {entry!r}: 'search' takes no transform (use guess:...)")
            try:
                numbers = [float(v) for v in values.split(",")]
            except ValueError:
                raise RobotFramesError(f"robot_frames entry {entry!r}: the transform must be numbers "
                                       "x,y,z,yaw_deg") from None
            if len(numbers) != 4 or not np.isfinite(numbers).all():
                raise RobotFramesError(f"robot_frames entry {entry!r}: the transform is x,y,z,yaw_deg "
                                       f"(4 finite numbers), got {len(numbers)}")
            T = yaw_transform(*numbers)
        specs[name] = RobotFrameSpec(mode=mode, T_map_odom=T)  # type: ignore[arg-type]
    return specs


class Admission(enum.Enum):
    """What becomes of a frame on arrival (module docstring, "Chain")."""

    TAKE = "take"
    DUPLICATE = "duplicate"
    OUT_OF_ORDER = "out_of_order"


@dataclass
class HeldFrame:
    frame: Frame
    playback: str
    frame_id: int
    prev_frame_id: int | None  # the frame its playback published before it (None: live)


class RobotStream:
    """One robot's chain, join state and counts (module docstring)."""

    def __init__(self, name: str, spec: RobotFrameSpec, params: JoinParams) -> None:
        self.name = name
        self.spec = spec
        self.params = params
        # Chain: the last frame taken (integrated, held, or taken and failed) and the last one in
        # the map with every frame before it (what a checkpoint records).
        self.playback = ""
        self.last_taken: int | None = None
        self.last_stamp_ns: int | None = None  # the last taken frame's stamp (None: not known)
        self.map_playback = ""
        self.map_last_frame_id: int | None = None
        self.map_last_stamp_ns: int | None = None
        self.waiting = True  # an announcement is due until the next frame comes in order
        self.announce_due = False  # one is due now (out of order, or a join that asks for a replay)
        self.replay_after: tuple[str, int] | None = None  # a join's replay for the semantic service
        self.resume = 1
        # Join.
        self.state: Literal["joined", "held"] = "held"
        self.anchor = False
        self.T_map_odom = np.array(spec.T_map_odom, np.float64)
        self.submap = Submap(params.join_voxel_m, window_frames=params.join_submap_frames)
        self.held: collections.deque[HeldFrame] = collections.deque()
        self.hold_overflowed = False  # frames were taken but not kept in the hold
        self.frames_since_attempt = 0
        self.last_held_at_s = 0.0  # time.monotonic() of the last frame held
        self.last_attempt_at_s = 0.0
        self.map_blocks_at_attempt = 0  # the map's size at the last attempt
        self.stretches_tried = 0  # stretches of the hold tried since the map or the robot last changed
        self.attempt_pending = False
        self.last_registration: Registration | None = None
        self.join_method = ""
        self.join_attempts = 0
        self.corrections = 0
        self.frames_since_recheck = 0
        self.proposed_correction: np.ndarray | None = None  # a re-check's transform, waiting for the next one
        self.recent: collections.deque[Frame] = collections.deque(maxlen=params.join_recheck_frames)
        # Counts.
        self.frames_taken = 0
        self.frames_integrated = 0
        self.frames_gap = 0
        self.skipped: collections.Counter[str] = collections.Counter()
        self.lag_s = 0.0
        self.queued = 0

    # ------------------------------------------------------------------ chain
    def admit(self, *, playback: str, frame_id: int, prev_frame_id: int | None) -> Admission:
        """Whether to take this frame; counts duplicates, out-of-order frames and live gaps. After
        ``OUT_OF_ORDER`` an announcement is due when :attr:`announce_due` says so."""
        held = NO_FRAME_ID if self.last_taken is None else self.last_taken
        if prev_frame_id is None:  # live: as it comes; count the ids that never arrived
            if self.last_taken is not None and frame_id > held + 1:
                self.frames_gap += frame_id - held - 1
            self.waiting = False
            return Admission.TAKE
        if playback != self.playback:  # another playback: it starts at its first frame
            if prev_frame_id == NO_FRAME_ID:
                self.playback = playback
                self.waiting = False
                return Admission.TAKE
            held = NO_FRAME_ID
        elif frame_id <= held:
            self.skipped["duplicate"] += 1
            return Admission.DUPLICATE
        if prev_frame_id != held:
            self.skipped["out_of_order"] += 1
            if not self.waiting:
                self.waiting = True
                self.resume += 1
                self.announce_due = True
                logger.warning("geometry: robot %s: frame %d follows frame %d, but the last frame held is %d; "
                               "asking for the frames after it", self.name, frame_id, prev_frame_id, held)
            return Admission.OUT_OF_ORDER
        self.waiting = False
        return Admission.TAKE

    def took(self, *, playback: str, frame_id: int, stamp_ns: int) -> None:
        """A taken frame is done with (integrated, held or failed): the chain moves on."""
        self.frames_taken += 1
        self.last_taken = frame_id
        self.last_stamp_ns = stamp_ns
        if playback:
            self.playback = playback

    def in_map(self, *, playback: str, frame_id: int, stamp_ns: int) -> None:
        """The frame is in the map (or was taken and failed for good), with every frame before it."""
        self.map_playback = playback
        self.map_last_frame_id = frame_id
        self.map_last_stamp_ns = stamp_ns

    def copy_holds(self, *, frame_id: int, stamp_ns: int) -> bool:
        """Whether a live frame is one this robot's chain holds already (a peer copy's): its id is
        at or below the last taken and, where that frame's stamp is known, so is its stamp. A later
        stamp under a lower id is a restarted bridge's new frame."""
        if self.last_taken is None or frame_id > self.last_taken:
            return False
        return self.last_stamp_ns is None or stamp_ns <= self.last_stamp_ns

    def holds(self) -> tuple[str, int]:
        """(playback, frame id) of the last frame held, for acknowledgements."""
        return self.playback, NO_FRAME_ID if self.last_taken is None else self.last_taken

    def announcement(self) -> tuple[str, int]:
        """(playback, frame id) to announce: after a join, the frame before the first held one, so
        the bridge replays the held frames (geometry drops them as duplicates; the semantic service
        sees them again, now that their robot is in the map's frame); else :meth:`holds`."""
        if self.replay_after is not None:
            replay, self.replay_after = self.replay_after, None
            return replay
        return self.holds()

    # ------------------------------------------------------------------ join
    def to_map(self, frame: Frame) -> Frame:
        """The frame with its pose in the map's frame."""
        return dataclasses.replace(frame, T_world_cam=self.T_map_odom @ np.asarray(frame.T_world_cam, np.float64))

    def hold(self, frame: Frame, *, playback: str, frame_id: int, prev_frame_id: int | None = None) -> None:
        """A frame of a held robot: into its submap, and into the hold while there is room."""
        self.submap.add(frame)
        self.frames_since_attempt += 1
        self.last_held_at_s = time.monotonic()
        if len(self.held) < self.params.join_max_held_frames and not self.hold_overflowed:
            self.held.append(HeldFrame(frame, playback, frame_id, prev_frame_id))
        else:
            self.hold_overflowed = True
            if not playback:  # a live frame: lost (a playback's are replayed after the join)
                self.skipped["held_dropped"] += 1

    def attempt_due(self, *, map_blocks: int, now_s: float | None = None) -> bool:
        """A held robot's submap is ready for a (new) registration attempt: enough frames, and new
        ones since the last attempt (``join_attempt_every`` of them); or the robot has sent nothing
        for ``join_idle_attempt_s`` (a playback that ended, a robot that stopped) and since its last
        attempt it sent a frame, or the map (``map_blocks``) grew by a tenth, or a stretch of its
        hold was not tried yet against the map as it is now (each attempt tries the next one)."""
        if (self.state != "held" or self.attempt_pending
                or self.submap.num_frames < self.params.join_min_submap_frames
                or len(self.submap) < self.params.join_min_submap_points):
            return False
        if self.join_attempts == 0 or self.frames_since_attempt >= self.params.join_attempt_every:
            return True
        now = time.monotonic() if now_s is None else now_s
        if now - max(self.last_held_at_s, self.last_attempt_at_s) < self.params.join_idle_attempt_s:
            return False
        grew = map_blocks > self.map_blocks_at_attempt * 1.1
        return self.frames_since_attempt > 0 or grew or self.stretches_tried < self.hold_stretches

    @property
    def hold_stretches(self) -> int:
        """Stretches of ``join_submap_frames`` frames of the hold outside the submap's window."""
        window = self.params.join_submap_frames
        return max(0, -(-(len(self.held) - window) // window))

    def attempted(self, *, map_blocks: int) -> None:
        """An attempt starts (on the map as it is now)."""
        self.attempt_pending = True
        grew = map_blocks > self.map_blocks_at_attempt * 1.1
        self.stretches_tried = 1 if grew or self.frames_since_attempt > 0 else self.stretches_tried + 1
        self.frames_since_attempt = 0
        self.join_attempts += 1
        self.map_blocks_at_attempt = map_blocks
        self.last_attempt_at_s = time.monotonic()

    def join_pending(self, *, map_blocks: int) -> bool:
        """A registration of this held robot runs or is due (a run is not finished while one is)."""
        return self.state == "held" and (self.attempt_pending or self.attempt_due(map_blocks=map_blocks))

    def join(self, T_map_odom: np.ndarray, *, method: str, registration: Registration | None = None) -> list[HeldFrame]:
        """Joined with ``T_map_odom``: returns the held frames to integrate (in order). After it,
        a robot whose hold overflowed waits for its playback's replay (:attr:`waiting`)."""
        self.T_map_odom = check_pose(T_map_odom, what="T_map_odom")
        self.state = "joined"
        self.join_method = method
        self.last_registration = registration
        frames = list(self.held)
        self.held.clear()
        self.submap.clear()
        first = frames[0] if frames else None
        if first is not None and first.playback and first.prev_frame_id is not None:
            # The semantic service skipped these frames while the robot was held: its bridge replays
            # them (announced from the frame before the first one; geometry drops them as duplicates).
            self.replay_after = (first.playback, first.prev_frame_id)
            self.resume += 1
            self.announce_due = True
        if self.hold_overflowed:
            # The chain goes back to the last frame kept: its bridge replays the ones after it.
            last = frames[-1] if frames else None
            self.last_taken = last.frame_id if last is not None else self.map_last_frame_id
            self.last_stamp_ns = last.frame.stamp_ns if last is not None else self.map_last_stamp_ns
            self.playback = last.playback if last is not None else self.map_playback
            if self.playback:
                self.waiting = True
                if not self.announce_due:  # the replay above goes back further already
                    self.resume += 1
                    self.announce_due = True
            self.hold_overflowed = False
        return frames

    def recheck_due(self) -> bool:
        """A joined robot (not fixed, not the anchor) is due for a re-check of its transform."""
        every = self.params.join_recheck_every
        if self.state != "joined" or self.anchor or self.spec.mode == "fixed" or every <= 0:
            return False
        self.frames_since_recheck += 1
        if self.frames_since_recheck < every:
            return False
        self.frames_since_recheck = 0
        return True

    def apply_recheck(self, found: Registration) -> str:
        """Take a re-check's transform when it is accepted, its correction within bounds, and the
        re-check before it proposed the same (within the smallest correction): one re-check is a
        few frames, and a jump one of them alone proposes is more likely noise than drift. Returns
        what was done (for the log): ``corrected``, ``kept``, ``pending`` or ``refused: ...``."""
        p = self.params
        proposed, self.proposed_correction = self.proposed_correction, None
        if not found.accepted:
            return f"refused: {found.reason}"
        metres, degrees = pose_difference(self.T_map_odom, found.T_map_odom)
        if metres > p.join_recheck_max_correction_m or degrees > p.join_recheck_max_correction_deg:
            return (f"refused: a correction of {metres * 100:.1f} cm / {degrees:.2f} deg is over the bound "
                    f"({p.join_recheck_max_correction_m * 100:.0f} cm / {p.join_recheck_max_correction_deg:.1f} deg)")
        if metres < p.join_recheck_min_correction_m and degrees < p.join_recheck_min_correction_deg:
            return "kept"
        if proposed is None or _apart(proposed, found.T_map_odom, p):
            self.proposed_correction = found.T_map_odom
            return f"pending: {metres * 100:.1f} cm / {degrees:.2f} deg, applied if the next re-check agrees"
        self.T_map_odom = found.T_map_odom
        self.corrections += 1
        return f"corrected by {metres * 100:.1f} cm / {degrees:.2f} deg"

    # ------------------------------------------------------------------ report
    def status(self, *, map_blocks: int = 0) -> dict[str, Any]:
        """What health and run.json report (:class:`openfusion.wire.schemas.admin.RobotStatus` fields)."""
        reg = self.last_registration
        return {
            "state": self.state,
            "frames_taken": self.frames_taken,
            "frames_integrated": self.frames_integrated,
            "frames_held": len(self.held),
            "frames_gap": self.frames_gap,
            "skipped": {reason: int(n) for reason, n in sorted(self.skipped.items()) if n},
            "last_frame_id": NO_FRAME_ID if self.last_taken is None else self.last_taken,
            "queued": self.queued,
            "lag_s": round(self.lag_s, 4),
            "T_map_odom": [float(v) for v in self.T_map_odom.ravel()],
            "join_method": self.join_method,
            "join_fitness": round(reg.fitness, 4) if reg is not None else 0.0,
            "join_attempts": self.join_attempts,
            "join_reason": reg.reason if reg is not None else "",
            "corrections": self.corrections,
            "join_pending": self.join_pending(map_blocks=map_blocks),
        }


class RobotStreams:
    """Every robot's stream of one map (module docstring)."""

    def __init__(self, params: JoinParams | None = None, specs: dict[str, RobotFrameSpec] | None = None) -> None:
        self.params = params or JoinParams()
        self.specs = dict(specs or {})
        self.robots: dict[str, RobotStream] = {}

    def __iter__(self):
        return iter(list(self.robots.values()))

    def __len__(self) -> int:
        return len(self.robots)

    def get(self, name: str, *, map_empty: bool) -> RobotStream:
        """The robot's stream; a robot seen for the first time starts joined (``fixed``, or the
        anchor of an empty map) or held (module docstring, "Join")."""
        stream = self.robots.get(name)
        if stream is not None:
            return stream
        spec = self.specs.get(name, RobotFrameSpec())
        stream = self.robots[name] = RobotStream(name, spec, self.params)
        # Robots given as fixed define the map's frame; without one, the first robot on an empty map does.
        anchor = (map_empty and not any(r.state == "joined" for r in self.robots.values())
                  and not any(s.mode == "fixed" for s in self.specs.values()))
        if spec.mode == "fixed" or anchor:
            stream.anchor = anchor
            stream.join(spec.T_map_odom, method="anchor" if anchor else "fixed")
            logger.info("geometry: robot %s joined at once (%s)", name, stream.join_method)
        else:
            logger.info("geometry: robot %s held until its submap registers to the map (%s)", name, spec.mode)
        return stream

    def announcements_due(self) -> list[RobotStream]:
        """Robots whose bridge must be told where to resume (then repeated while they wait)."""
        return [r for r in self.robots.values() if r.announce_due or r.waiting]

    @property
    def held(self) -> list[RobotStream]:
        return [r for r in self.robots.values() if r.state == "held"]

    # ------------------------------------------------------------------ checkpoints
    def to_meta(self) -> dict[str, Any]:
        """Per robot: what the map holds of its chain, its transform and whether it was joined."""
        robots = {
            r.name: {
                "playback": r.map_playback,
                "last_frame_id": r.map_last_frame_id,
                "last_stamp_ns": r.map_last_stamp_ns,
                "joined": r.state == "joined",
                "anchor": r.anchor,
                "join_method": r.join_method,
                "T_map_odom": [float(v) for v in r.T_map_odom.ravel()] if r.state == "joined" else None,
                "frames_integrated": r.frames_integrated,
            }
            for r in self.robots.values()
        }
        return {"robots": robots}

    def restore(self, meta: dict[str, Any], *, default_robot: str) -> None:
        """Take back what :meth:`to_meta` recorded (a restart); a map from before robots existed
        holds ``default_robot``'s chain at its top level. Robots it does not name start afresh."""
        self.robots.clear()
        recorded = meta.get("robots")
        if not isinstance(recorded, dict):
            last = meta.get("last_frame_id")
            if last is None and not meta.get("playback"):
                return
            recorded = {default_robot: {"playback": meta.get("playback") or "", "last_frame_id": last,
                                        "joined": True, "anchor": True, "join_method": "anchor", "T_map_odom": None,
                                        "frames_integrated": int(meta.get("frames_integrated") or 0)}}
        for name, entry in recorded.items():
            spec = self.specs.get(name, RobotFrameSpec())
            stream = RobotStream(str(name), spec, self.params)
            last = entry.get("last_frame_id")
            stream.playback = stream.map_playback = str(entry.get("playback") or "")
            stream.last_taken = stream.map_last_frame_id = None if last is None else int(last)
            stamp = entry.get("last_stamp_ns")  # absent in checkpoints from before it was recorded
            stream.last_stamp_ns = stream.map_last_stamp_ns = None if stamp is None else int(stamp)
            stream.frames_integrated = int(entry.get("frames_integrated") or 0)
            stream.anchor = bool(entry.get("anchor"))
            if entry.get("joined"):
                values = entry.get("T_map_odom")
                T = np.asarray(values, np.float64).reshape(4, 4) if values is not None else spec.T_map_odom
                stream.join(T, method=str(entry.get("join_method") or "restored"))
            self.robots[stream.name] = stream


def _apart(T_a: np.ndarray, T_b: np.ndarray, params: JoinParams) -> bool:
    """Two transforms differ by at least the smallest correction a re-check applies."""
    metres, degrees = pose_difference(T_a, T_b)
    return metres >= params.join_recheck_min_correction_m or degrees >= params.join_recheck_min_correction_deg
