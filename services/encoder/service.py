"""Encoder worker: a stateless region encoder of the encoder pool (``openfusion service encoder``,
``python -m openfusion.services.encoder``; ``openfusion run --encoder-workers N`` starts N).

| key | direction | message |
|---|---|---|
| ``{prefix}/@pool/encoder/{worker_id}`` | liveliness token | (presence: the worker serves) |
| ``{prefix}/@pool/encoder/{worker_id}/info`` | queryable | WorkerInfoRequest -> :class:`~openfusion.wire.schemas.WorkerInfo` |
| ``{prefix}/@pool/encoder/{worker_id}/encode`` | queryable | :class:`~openfusion.wire.schemas.EncodeRequest` -> :class:`~openfusion.wire.schemas.EncodeReply` |
| ``…/{map}/health/encoder-{worker_id}`` | liveliness + stats | counters ``frames_encoded``, ``refused_space``, ``encode_busy_s`` |

The pool's keys live outside any map (``@pool`` is a Zenoh verbatim chunk, see
:class:`openfusion.wire.keys.PoolKeys`): one pool serves every map of the prefix. Each request
names its map and embedding space; a worker refuses a space it does not hold (``wrong_space``).
The worker keeps no state between requests: the semantic service of each map keeps matching, the
dictionary and the order in which results are applied (docs/DEPLOY.md, "Encoder pool").
Requests are answered one at a time, in arrival order; the semantic services keep at most two in
flight per worker, so one is encoded while the next travels.
"""

from __future__ import annotations

import logging
import os
import re
import socket
import time
from typing import Any

from pydantic import Field, field_validator

from openfusion.bus import RequestError, ServiceRunner
from openfusion.config import ServiceConfig
from openfusion.mapping.region_gate import encode_where
from openfusion.services.common import ServiceDefinition
from openfusion.services.encoder.options import EncoderOptions, region_encoder_from_section, warm_up_encoder
from openfusion.wire.counters import EncoderCounter
from openfusion.wire.keys import PoolKeys, segment_error
from openfusion.wire.schemas import EncodeReply, EncodeRequest, WorkerInfo, WorkerInfoRequest

logger = logging.getLogger(__name__)

#: Requests a semantic service keeps in flight per worker (announced in WorkerInfo).
MAX_IN_FLIGHT = 2


def default_worker_id() -> str:
    """``<host>-<pid>``, reduced to key-segment characters."""
    return (
        re.sub(r"[^A-Za-z0-9_.-]+", "-", f"{socket.gethostname()}-{os.getpid()}").strip(".")
        or f"w{os.getpid()}"
    )


class EncoderSection(EncoderOptions):
    """An encoder worker's settings: the encoder (:class:`EncoderOptions`, as the semantic
    service's) and the worker's id in the pool."""

    worker_id: str | None = Field(None, description="this worker's id in the pool (default <host>-<pid>)")

    @field_validator("worker_id")
    @classmethod
    def _worker_id(cls, value: str | None) -> str | None:
        if value is not None and (why := segment_error(value)) is not None:
            raise ValueError(f"worker id {value!r} is not a valid key segment: it {why}")
        return value


class EncoderConfig(ServiceConfig):
    encoder: EncoderSection = Field(default_factory=EncoderSection)


class EncoderWorker:
    """Answers encode requests of any map in its embedding space."""

    def __init__(self, config: EncoderConfig, *, encoder: Any = None) -> None:
        self.config = config
        self.section = config.encoder
        self.worker_id = self.section.worker_id or default_worker_id()
        self.encoder = encoder if encoder is not None else region_encoder_from_section(self.section)
        self.pool = PoolKeys(config.keys.prefix)
        self._runner: ServiceRunner | None = None
        self._token: Any = None

    @property
    def info(self) -> WorkerInfo:
        return WorkerInfo(
            worker_id=self.worker_id,
            encoder=self.section.encoder,
            embedding_space=self.encoder.embedding_space,
            dim=int(self.encoder.dim),
            device=str(getattr(self.encoder, "device", self.section.device)),
            needs_instances=bool(getattr(self.encoder, "needs_instances", False)),
            max_in_flight=MAX_IN_FLIGHT,
        )

    def handle_info(self, _req: WorkerInfoRequest) -> WorkerInfo:
        return self.info

    def handle_encode(self, req: EncodeRequest) -> EncodeReply:
        assert self._runner is not None
        stats = self._runner.stats
        if req.embedding_space != self.encoder.embedding_space:
            stats.incr(EncoderCounter.REFUSED_SPACE)
            raise RequestError(
                "wrong_space",
                f"encoder worker {self.worker_id!r} holds embedding space "
                f"{self.encoder.embedding_space!r}; map {req.map_id!r} is in {req.embedding_space!r}",
            )
        started = time.monotonic()
        obs = encode_where(self.encoder, req.to_frame(), req.embed_where, req.embed_share)
        spent = time.monotonic() - started
        stats.incr(EncoderCounter.FRAMES_ENCODED)
        stats.incr(EncoderCounter.ENCODE_BUSY_S, spent)
        return EncodeReply(
            frame_id=req.frame_id,
            worker_id=self.worker_id,
            embedding_space=obs.embedding_space,
            conf_maps=obs.conf_maps,
            embeddings=obs.embeddings,
            encode_ms=1e3 * spent,
            embedded=obs.embedded,
        )

    def setup(self, runner: ServiceRunner) -> None:
        self._runner = runner
        warm_up_encoder(self.encoder, f"encoder worker {self.worker_id}")  # before anyone sends it a frame
        runner.queryable_at(self.pool.info(self.worker_id), WorkerInfoRequest, WorkerInfo, self.handle_info)
        runner.queryable_at(
            self.pool.encode(self.worker_id),
            EncodeRequest,
            EncodeReply,
            self.handle_encode,
            queue_size=4 * MAX_IN_FLIGHT,
        )
        runner.stats.set(EncoderCounter.FRAMES_ENCODED, 0)
        # last: whoever sees the token can ask for the info and send frames
        self._token = runner.liveliness_token(self.pool.worker(self.worker_id))
        logger.info(
            "encoder worker %s: %s in space %s on %s",
            self.worker_id,
            self.section.encoder,
            self.encoder.embedding_space,
            self.info.device,
        )

    def close(self) -> None:
        return None


def _instance_name(config: EncoderConfig) -> str:
    return f"encoder-{config.encoder.worker_id or default_worker_id()}"


DEFINITION = ServiceDefinition(
    name="encoder",
    help="a stateless region-encoder worker of the encoder pool (serves every map of the prefix)",
    config_model=EncoderConfig,
    build=EncoderWorker,
    instance_name=_instance_name,
)
