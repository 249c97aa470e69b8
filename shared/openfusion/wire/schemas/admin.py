"""Admin actions, health stats and the payload of every refusal."""

from __future__ import annotations

from typing import ClassVar, Literal

from pydantic import Field

from openfusion.wire.message import Message


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


class HealthStats(Message):
    """Periodic stats of one service instance (published on ``…/health/{service}``)."""

    schema_name: ClassVar[str] = "health.stats"
    schema_version: ClassVar[int] = 1

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
