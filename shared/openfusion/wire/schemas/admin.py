"""Admin actions, health stats and the payload of every refusal."""

from __future__ import annotations

from typing import ClassVar, Literal

from pydantic import Field

from openfusion.wire.message import Message, Record
from openfusion.wire.schemas.base import RobotName


class ControlRequest(Message):
    """Admin action on a map: save to / load from ``path`` (service default when None), or reset."""

    schema_name: ClassVar[str] = "control.request"
    schema_version: ClassVar[int] = 1

    action: Literal["save", "load", "reset"]
    path: str | None = None


class ControlReply(Message):
    """Outcome of a :class:`ControlRequest`."""

    schema_name: ClassVar[str] = "control.reply"
    schema_version: ClassVar[int] = 1

    ok: bool
    message: str = ""


class RobotStatus(Record):
    """One robot's stream as geometry sees it (:attr:`HealthStats.robots`; run.json ``robots``).

    ``state``: ``joined`` (its frames go into the map through ``T_map_odom``) or ``held`` (not
    joined yet: its frames wait in its own submap, never fused misaligned). Counts are of frames
    taken from geometry's queue: ``frames_integrated`` into the map, the rest skipped by
    ``skipped`` reason (``duplicate``, ``out_of_order``, ``failed``, ``capacity``, ``held_dropped``),
    ``frames_gap`` ids never seen between two live frames; ``queued``: its frames waiting in
    geometry's queue now; ``lag_s``: how long the oldest of them has waited."""

    state: Literal["joined", "held"]
    frames_taken: int = Field(0, ge=0)
    frames_integrated: int = Field(0, ge=0)
    frames_held: int = Field(0, ge=0)
    frames_gap: int = Field(0, ge=0)
    skipped: dict[str, int] = Field(default_factory=dict)
    last_frame_id: int = Field(-1, ge=-1)
    queued: int = Field(0, ge=0)
    lag_s: float = Field(0.0, ge=0)
    T_map_odom: list[float] = Field(default_factory=lambda: [1.0, 0, 0, 0, 0, 1.0, 0, 0, 0, 0, 1.0, 0, 0, 0, 0, 1.0],
                                    min_length=16, max_length=16)
    join_method: str = ""
    join_fitness: float = Field(0.0, ge=0)
    join_attempts: int = Field(0, ge=0)
    join_reason: str = ""
    corrections: int = Field(0, ge=0)
    join_pending: bool = False  # held, and a registration runs or is due


class HealthStats(Message):
    """Periodic stats of one service instance (published on ``…/health/{service}``).

    v2: ``robots`` (geometry): each robot's stream, by robot name (:class:`RobotStatus`)."""

    schema_name: ClassVar[str] = "health.stats"
    schema_version: ClassVar[int] = 2

    service: str
    map_id: str
    pid: int
    stamp_ns: int = Field(default=0, ge=0)
    uptime_s: float = Field(ge=0)
    fps: float = Field(ge=0)
    latency_ms_p50: float = Field(ge=0)
    latency_ms_p99: float = Field(ge=0)
    drops: int = Field(ge=0)
    errors: int = Field(ge=0)
    counters: dict[str, float] = Field(default_factory=dict)
    robots: dict[RobotName, RobotStatus] = Field(default_factory=dict)

    def counter(self, name: str, default: float = 0.0) -> float:
        """One named counter (names: :mod:`openfusion.wire.counters`), ``default`` when absent."""
        return float(self.counters.get(str(name), default))


class ErrorReply(Message):
    """The payload of every ``reply_err``: a machine-readable ``code`` and a human ``reason``.

    Codes used by :mod:`openfusion.bus`: ``bad_request:<decode reason>`` (the request did not
    decode), ``handler_error`` (the service failed on a valid request), or a code the handler
    chose by raising :class:`openfusion.bus.RequestError`.
    """

    schema_name: ClassVar[str] = "error"
    schema_version: ClassVar[int] = 1

    reason: str
    code: str
