"""Semantic service: region encoder + matcher at its own rate; owns the region dictionary.

| key | direction | message |
|---|---|---|
| ``…/sensor/rgbd`` | subscribes, latest frame only | :class:`~openfusion.wire.schemas.RgbdFrame` |
| ``…/sensor/instance`` | subscribes when the encoder reads instance images (gt) | :class:`~openfusion.wire.schemas.InstanceFrame` |
| ``…/geometry/render`` | queries | RenderRequest → RenderReply |
| ``…/geometry/dictionary`` | queries once on start (recovery) | DictionaryRequest → DictionarySnapshot |
| ``…/semantic/update`` | publishes | :class:`~openfusion.wire.schemas.SemanticUpdate` |
| ``…/semantic/dictionary/delta`` | publishes | :class:`~openfusion.wire.schemas.DictionaryDelta` |
| ``…/semantic/dictionary`` | queryable | DictionaryRequest → DictionarySnapshot |
| ``…/health/semantic`` | liveliness + stats | counters ``semantic_frames``, ``skipped_switch``, ``skipped_no_instance``, ``regions``, ``matched``, ``new_regions`` |

A slow encoder never builds a queue: the frame subscription keeps only the newest frame and
counts the ones it replaced. An encoder that reads ground-truth instance images (gt) gets each
frame joined with its ``InstanceFrame`` (same frame id and stamp; the bridge sends it first); a
frame whose instance image has not come within ``instance_wait_s`` is skipped and counted in
``skipped_no_instance`` (a frame that carries its own instance image uses that). The semantic switch: ``every_k = 0`` turns semantics off,
``every_k = k`` uses every k-th frame (by frame id), ``max_hz`` caps the rate.
On start the service asks geometry for the dictionary it checkpointed, so a restarted semantic
service continues with the same keys and embeddings.
"""

from __future__ import annotations

import argparse
import logging
import time
from typing import Any

import numpy as np
from pydantic import Field

from openfusion.bus import Publisher, QueryError, ServiceRunner, Subscriber, get
from openfusion.bus.instance_join import InstanceBuffer
from openfusion.config import ConfigSection, ServiceConfig
from openfusion.encoders import make_region_encoder
from openfusion.frame import resize_nearest
from openfusion.mapping import RegionDictionary, RenderedView, plan_update
from openfusion.services.common import ServiceDefinition
from openfusion.services.dictionary_sync import delta_message, dictionary_from_snapshot, snapshot_message
from openfusion.wire.schemas import (
    DictionaryRequest,
    DictionarySnapshot,
    InstanceFrame,
    RenderReply,
    RenderRequest,
    RgbdFrame,
    SemanticUpdate,
)

logger = logging.getLogger(__name__)


class SemanticSection(ConfigSection):
    encoder: str = "gt"
    noise: str = "off"
    seed: int = 0
    every_k: int = Field(default=1, ge=0)
    max_hz: float | None = Field(default=None, gt=0)
    min_iou: float = Field(default=0.10, ge=0, le=1)
    render_timeout_s: float = Field(default=5.0, gt=0)
    # How long a frame waits for its instance image (gt encoder) before it is skipped.
    instance_wait_s: float = Field(default=0.5, ge=0, le=10)
    recover_timeout_s: float = Field(default=10.0, ge=0)
    model_path: str | None = None
    device: str = "auto"
    # Fault injection: sleep this long after every encoder call, as a slower encoder would
    # (used by the "10x slower encoder" test; 0 in normal use).
    simulate_latency_s: float = Field(default=0.0, ge=0, le=60)


class SemanticConfig(ServiceConfig):
    semantic: SemanticSection = Field(default_factory=SemanticSection)


class SemanticSwitch:
    """Decides which frames get semantics: off (every_k=0), every k-th frame id, at most max_hz."""

    def __init__(self, every_k: int, max_hz: float | None) -> None:
        self.every_k = every_k
        self.max_hz = max_hz
        self._last_s: float | None = None

    def accept(self, frame_id: int, now_s: float) -> bool:
        if self.every_k == 0 or frame_id % self.every_k != 0:
            return False
        if self.max_hz is not None and self._last_s is not None and now_s - self._last_s < 1.0 / self.max_hz:
            return False
        self._last_s = now_s
        return True


def _encoder_options(section: SemanticSection) -> dict[str, Any]:
    if section.encoder == "gt":
        return {"noise": section.noise, "seed": section.seed}
    opts: dict[str, Any] = {"device": section.device}
    if section.model_path:
        opts["model_path" if section.encoder == "onnx" else "model"] = section.model_path
    return opts


class SemanticService:
    """Encoder → render request → match → update; the dictionary lives here."""

    def __init__(self, config: SemanticConfig, *, encoder: Any = None) -> None:
        self.config = config
        self.section = config.semantic
        self.encoder = encoder if encoder is not None else make_region_encoder(
            self.section.encoder, **_encoder_options(self.section))
        self.dictionary = RegionDictionary(self.encoder.embedding_space, self.encoder.dim)
        self.switch = SemanticSwitch(self.section.every_k, self.section.max_hz)
        self._frames: Subscriber[RgbdFrame] | None = None
        self._instances: InstanceBuffer | None = InstanceBuffer() if self.encoder.needs_instances else None
        self._update_pub: Publisher | None = None
        self._delta_pub: Publisher | None = None
        self._published_version = self.dictionary.version
        self._frames_without_instance = 0

    def recover(self, runner: ServiceRunner) -> bool:
        """Take the dictionary geometry checkpointed (same space only). True when recovered."""
        if self.section.recover_timeout_s <= 0:
            return False
        # Right after joining, routes to geometry's queryable may not be known yet: a get then
        # finds nobody at once. Retry until the deadline; a refusal (no dictionary) is final.
        deadline = time.monotonic() + self.section.recover_timeout_s
        while True:
            try:
                snap = get(runner.session, runner.keys.geometry_dictionary, DictionaryRequest(), DictionarySnapshot,
                           timeout_s=max(0.5, min(3.0, deadline - time.monotonic())), service="geometry")
                break
            except QueryError as exc:
                if exc.code != "timeout" or time.monotonic() >= deadline:
                    logger.info("semantic: no dictionary to recover (%s); starting empty", exc.reason)
                    return False
                time.sleep(0.3)
        if snap.embedding_space != self.dictionary.embedding_space:
            logger.error("semantic: the map's dictionary is in space %r but the encoder is %r; starting empty "
                         "(a new map id is safer)", snap.embedding_space, self.dictionary.embedding_space)
            runner.stats.add_error()
            return False
        self.dictionary = dictionary_from_snapshot(snap)
        self._published_version = self.dictionary.version
        logger.info("semantic: recovered %d regions (version %d) from geometry", len(self.dictionary),
                    self.dictionary.version)
        return True

    def handle_snapshot(self, _req: DictionaryRequest) -> DictionarySnapshot:
        return snapshot_message(self.dictionary)

    def process(self, runner: ServiceRunner, msg: RgbdFrame, instance: InstanceFrame | None = None) -> None:
        """One semantic step for one frame (called from the loop), with its instance image when
        the encoder reads them."""
        started = time.monotonic()
        frame = msg.to_frame(instance)
        obs = self.encoder.encode(frame)
        if self.section.simulate_latency_s > 0:
            time.sleep(self.section.simulate_latency_s)
        h, w = obs.conf_maps.shape[1:] if obs.conf_maps.ndim == 3 else self.encoder.output_size(
            frame.intrinsics.height_px, frame.intrinsics.width_px)
        K_small = frame.intrinsics.scaled(w, h)
        reply = get(runner.session, runner.keys.geometry_render,
                    RenderRequest(frame_id=frame.frame_id, T_world_cam=frame.T_world_cam,
                                  **RenderRequest.intrinsics_fields(K_small)),
                    RenderReply, timeout_s=self.section.render_timeout_s, service="geometry")
        rendered = RenderedView(key_map=reply.key_map, conf_map=reply.conf_map, depth_m=reply.depth_m)
        prev_version = self.dictionary.version
        planned = plan_update(obs, rendered, self.dictionary, min_iou=self.section.min_iou)
        assert self._update_pub is not None and self._delta_pub is not None
        # The delta goes first, so a key never reaches geometry before its dictionary row.
        delta = delta_message(self.dictionary, since_version=self._published_version)
        if delta is not None:
            self._delta_pub.put(delta)
            self._published_version = self.dictionary.version
        self._update_pub.put(SemanticUpdate(
            frame_id=frame.frame_id, T_world_cam=frame.T_world_cam, **SemanticUpdate.intrinsics_fields(K_small),
            key_map=planned.key_map, conf_map=planned.conf_map,
            new_keys=np.array([key for _, key in planned.new_keys], np.int32),
            depth_m=resize_nearest(frame.depth_m(), (h, w)).astype(np.float32)))
        stats = runner.stats
        stats.record(time.monotonic() - started)
        stats.incr("semantic_frames")
        stats.incr("matched", len(planned.matched))
        stats.incr("new_regions", len(planned.new_keys))
        stats.set("regions", len(self.dictionary))
        stats.set("dictionary_version", self.dictionary.version)
        stats.set("last_frame_id", frame.frame_id)
        stats.incr("busy_s", time.monotonic() - started)
        logger.debug("semantic: frame %d: %d regions, %d matched, %d new (dictionary v%d -> v%d)",
                     frame.frame_id, obs.conf_maps.shape[0], len(planned.matched), len(planned.new_keys),
                     prev_version, self.dictionary.version)

    def setup(self, runner: ServiceRunner) -> None:
        keys = runner.keys
        self.recover(runner)
        self._update_pub = runner.publisher(keys.semantic_update)
        self._delta_pub = runner.publisher(keys.semantic_dictionary_delta)
        runner.queryable(keys.semantic_dictionary, DictionaryRequest, self.handle_snapshot)
        if self._instances is not None:
            runner.subscriber(keys.sensor_instance, InstanceFrame, self._instances.add, queue_size=8)
        self._frames = runner.subscriber(keys.sensor_rgbd, RgbdFrame, latest_only=True)
        runner.stats.set("semantic_frames", 0)
        runner.stats.set("regions", len(self.dictionary))

    def loop(self, runner: ServiceRunner) -> None:
        assert self._frames is not None
        while not runner.stopping:
            msg = self._frames.recv(timeout_s=0.2)
            if msg is None:
                continue
            if not self.switch.accept(msg.frame_id, time.monotonic()):
                runner.stats.incr("skipped_switch")
                continue
            instance = None
            if self._instances is not None and msg.instance is None:
                instance = self._instances.take(msg, timeout_s=self.section.instance_wait_s)
                runner.stats.set("instances_evicted", self._instances.evicted)
                if instance is None:
                    self._skip_without_instance(runner, msg)
                    continue
            try:
                self.process(runner, msg, instance)
            except QueryError as exc:
                logger.warning("semantic: frame %d skipped: %s", msg.frame_id, exc)
                runner.stats.incr("skipped_no_render")
            except ValueError as exc:
                logger.warning("semantic: frame %d refused: %s", msg.frame_id, exc)
                runner.stats.add_error()

    def _skip_without_instance(self, runner: ServiceRunner, msg: RgbdFrame) -> None:
        runner.stats.incr("skipped_no_instance")
        self._frames_without_instance += 1
        if self._frames_without_instance % 100 == 1:  # the first, then every 100th
            logger.warning(
                "semantic: frame %d skipped: its instance image did not arrive on %s within %.2f s (%d such "
                "frames so far; the %r encoder needs a source with instance labels)", msg.frame_id,
                runner.keys.sensor_instance, self.section.instance_wait_s, self._frames_without_instance,
                self.section.encoder)

    def close(self) -> None:
        return None


def _add_options(parser: argparse.ArgumentParser) -> None:
    g = parser.add_argument_group("semantic")
    g.add_argument("--encoder", help="region encoder: gt, onnx, clip-regions (default gt)")
    g.add_argument("--noise", help="gt encoder noise profile: off, standard, heavy")
    g.add_argument("--semantic-every", dest="every_k", type=int, help="semantics on every k-th frame (0 = off)")
    g.add_argument("--max-hz", type=float, help="at most this many semantic frames per second")
    g.add_argument("--model-path", help="model file/folder for onnx or clip-regions")


def _options(args: argparse.Namespace) -> dict[str, Any]:
    return {"semantic": {"encoder": args.encoder, "noise": args.noise, "every_k": args.every_k,
                         "max_hz": args.max_hz, "model_path": args.model_path}}


DEFINITION = ServiceDefinition(
    name="semantic",
    help="encode regions of the latest frame, match them to the map, send updates, own the dictionary",
    config_model=SemanticConfig,
    add_options=_add_options,
    options_to_config=_options,
    build=SemanticService,
)
