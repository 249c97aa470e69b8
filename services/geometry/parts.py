"""What the parts of the geometry service share: the state of
:class:`~openfusion.services.geometry.service.GeometryService` that its parts
(:mod:`.frame_intake`, :mod:`.persistence`, :mod:`.dictionary_follower`) read and change.

The service is one object made of parts (mixins), each in its own module, so each concern stays a
module of its own while the handlers stay plain methods tests call without a bus. This base
declares the state they share (set by the service's ``__init__``); each part declares what else it
uses. The service's own helpers the parts call: ``_map_changed()``, ``_count()``, ``_robot()``,
``_first_robot()`` and ``_set_memory_stats()``. They log under the service's logger name.
"""

from __future__ import annotations

import logging
import threading
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from openfusion.bus import ServiceRunner
    from openfusion.mapping import SemanticVolume
    from openfusion.mapping.robot_streams import RobotStreams
    from openfusion.services.dictionary_replica import DictionaryReplica
    from openfusion.services.geometry.section import GeometryConfig, GeometrySection

#: The logger of the geometry service and its parts (one name in the logs for the whole service).
logger = logging.getLogger("openfusion.services.geometry.service")


class ServiceParts:
    """The state the geometry service's parts share (module docstring)."""

    config: GeometryConfig
    section: GeometrySection
    _lock: threading.RLock
    volume: SemanticVolume
    replica: DictionaryReplica
    robots: RobotStreams
    frames_integrated: int
    integrate_busy_s: float
    _dirty: bool
    _runner: ServiceRunner | None
