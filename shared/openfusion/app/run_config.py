"""The one config of ``openfusion run``: every service's section, validated before anything starts.

``openfusion run`` builds a :class:`RunConfig` from defaults < ``--config FILE`` < ``OPENFUSION_*``
< its flags < ``--set SECTION.FIELD=VALUE``. The flags it shows (``--source``, ``--encoder``,
``--noise``, ``--semantic-every``, ``--rate-hz``, ``--text-encoder``) are derived from the same
section fields the services declare (:data:`RUN_FLAGS`), and every other parameter of every
service can be set with ``--set`` or the file. The launcher writes the validated result to
``OUT/run-config.json`` and starts each service with ``--config`` that file (and no
``OPENFUSION_*`` variables, which are already folded in), so services never receive settings as
re-typed argument strings; the in-process run reads the same sections.

The ``supervision`` section is the launcher's own (:class:`SupervisionSection`: how dead services
are restarted, how often geometry checkpoints during the run); no service reads it.
"""

from __future__ import annotations

import json
from pathlib import Path

from pydantic import Field

from openfusion.app.launcher import RestartPolicy
from openfusion.config import ConfigSection, ServiceConfig
from openfusion.services.bridge.service import BridgeSection
from openfusion.services.encoder.options import EncoderOptions
from openfusion.services.encoder.service import EncoderSection
from openfusion.services.geometry.service import GeometrySection
from openfusion.services.query.service import QuerySection
from openfusion.services.semantic.service import SemanticSection

#: The section fields ``openfusion run`` offers as flags (everything else: ``--set`` or ``--config``).
RUN_FLAGS: dict[str, list[str]] = {
    "bridge": ["rate_hz"],  # --source is the run's own (repeatable: one bridge per robot)
    "geometry": ["memory_budget_mb"],
    "semantic": ["encoder", "noise", "every_k", "encoder_delay_ms", "select"],
    "query": ["text_encoder"],
    "supervision": ["max_restarts", "restart_backoff_s"],
}


class SupervisionSection(ConfigSection):
    """How ``openfusion run`` keeps its services alive (:class:`~openfusion.app.launcher.RestartPolicy`)."""

    max_restarts: int = Field(3, ge=0, description="restarts of each service before a death ends the run "
                              "(0 = a service that dies ends the run)")
    restart_backoff_s: float = Field(1.0, ge=0, description="wait before a service's first restart; doubled for "
                                     "each further restart of it")
    restart_backoff_max_s: float = Field(30.0, ge=0, description="longest wait before a restart")
    checkpoint_period_s: float = Field(
        10.0, ge=0, description="seconds between geometry's checkpoints during the run: a restarted geometry "
        "resumes from the last one and the bridge replays the frames after it (0 = no checkpoints: a restarted "
        "geometry starts an empty map and the whole playback is replayed)")

    def policy(self) -> RestartPolicy:
        return RestartPolicy(max_restarts=self.max_restarts, backoff_s=self.restart_backoff_s,
                             backoff_max_s=self.restart_backoff_max_s)


class RunConfig(ServiceConfig):
    """Every service's section of one map."""

    bridge: BridgeSection = Field(default_factory=BridgeSection)
    geometry: GeometrySection = Field(default_factory=GeometrySection)
    semantic: SemanticSection = Field(default_factory=SemanticSection)
    query: QuerySection = Field(default_factory=QuerySection)
    supervision: SupervisionSection = Field(default_factory=SupervisionSection)
    #: the encoder workers' section (``--encoder-workers``): the semantic section's encoder options
    encoder: EncoderSection = Field(default_factory=EncoderSection)
    #: several robots (``--source`` given more than once): robot name -> its source, one bridge each
    #: (empty: one bridge, ``bridge.source`` as ``bridge.robot``)
    robots: dict[str, str] = Field(default_factory=dict)
    #: ... and the frames each robot's bridge plays
    robot_frames: dict[str, int] = Field(default_factory=dict)

    def robot_sources(self) -> dict[str, str]:
        """Robot name -> source spec of every bridge of the run (one at least)."""
        return dict(self.robots) or {self.bridge.robot: self.bridge.source}

    def use_encoder_pool(self) -> None:
        """Send the semantic service's frames to encoder workers built like its own encoder."""
        self.semantic.encoder_pool = True
        self.semantic.local_encoder = False
        self.encoder = EncoderSection(**self.semantic.model_dump(include=set(EncoderOptions.model_fields)))


SECTION_MODELS = {name: RunConfig.model_fields[name].annotation
                  for name in ("bridge", "geometry", "semantic", "query", "supervision")}


def write_service_config(config: RunConfig, path: Path) -> Path:
    """The config file every service of the run reads (JSON; its Zenoh settings are left out:
    the launcher gives each service its endpoints)."""
    data = config.model_dump(mode="json", exclude={"zenoh", "supervision", "robots", "robot_frames"})
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=2) + "\n")
    return path
