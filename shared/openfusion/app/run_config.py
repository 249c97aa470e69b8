"""The one config of ``openfusion run``: every service's section, validated before anything starts.

``openfusion run`` builds a :class:`RunConfig` from defaults < ``--config FILE`` < ``OPENFUSION_*``
< its flags < ``--set SECTION.FIELD=VALUE``. The flags it shows (``--source``, ``--encoder``,
``--noise``, ``--semantic-every``, ``--rate-hz``, ``--text-encoder``) are derived from the same
section fields the services declare (:data:`RUN_FLAGS`), and every other parameter of every
service can be set with ``--set`` or the file. The launcher writes the validated result to
``OUT/run-config.json`` and starts each service with ``--config`` that file (and no
``OPENFUSION_*`` variables, which are already folded in), so services never receive settings as
re-typed argument strings; the in-process run reads the same sections.
"""

from __future__ import annotations

import json
from pathlib import Path

from pydantic import Field

from openfusion.config import ServiceConfig
from openfusion.services.bridge.service import BridgeSection
from openfusion.services.encoder.options import EncoderOptions
from openfusion.services.encoder.service import EncoderSection
from openfusion.services.geometry.service import GeometrySection
from openfusion.services.query.service import QuerySection
from openfusion.services.semantic.service import SemanticSection

#: The section fields ``openfusion run`` offers as flags (everything else: ``--set`` or ``--config``).
RUN_FLAGS: dict[str, list[str]] = {
    "bridge": ["source", "rate_hz"],
    "semantic": ["encoder", "noise", "every_k", "encoder_delay_ms"],
    "query": ["text_encoder"],
}


class RunConfig(ServiceConfig):
    """Every service's section of one map."""

    bridge: BridgeSection = Field(default_factory=BridgeSection)
    geometry: GeometrySection = Field(default_factory=GeometrySection)
    semantic: SemanticSection = Field(default_factory=SemanticSection)
    query: QuerySection = Field(default_factory=QuerySection)
    #: the encoder workers' section (``--encoder-workers``): the semantic section's encoder options
    encoder: EncoderSection = Field(default_factory=EncoderSection)

    def use_encoder_pool(self) -> None:
        """Send the semantic service's frames to encoder workers built like its own encoder."""
        self.semantic.encoder_pool = True
        self.semantic.local_encoder = False
        self.encoder = EncoderSection(**self.semantic.model_dump(include=set(EncoderOptions.model_fields)))


SECTION_MODELS = {name: RunConfig.model_fields[name].annotation for name in ("bridge", "geometry", "semantic", "query")}


def write_service_config(config: RunConfig, path: Path) -> Path:
    """The config file every service of the run reads (JSON; its Zenoh settings are left out:
    the launcher gives each service its endpoints)."""
    data = config.model_dump(mode="json", exclude={"zenoh"})
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=2) + "\n")
    return path
