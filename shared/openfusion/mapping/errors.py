"""Typed errors of the map core, so callers (services, CLI) can tell failures apart."""

from __future__ import annotations

from openfusion.errors import OpenFusionError, UserError


class MappingError(OpenFusionError):
    """Base class of every error raised by ``openfusion.mapping``."""


class CapacityError(MappingError):
    """The volume's block budget (``VolumeParams.max_blocks``) would be exceeded.

    Raised before anything is written: the volume is unchanged. ``blocks_needed`` is the number of
    new blocks the refused frame asked for, ``blocks_free`` how many the budget still allows.
    """

    def __init__(self, message: str, *, blocks_needed: int, blocks_free: int) -> None:
        super().__init__(message)
        self.blocks_needed = blocks_needed
        self.blocks_free = blocks_free


class MapFormatError(MappingError, UserError):
    """A map file is truncated, corrupt, of an unknown format version or internally inconsistent."""


class EmbeddingSpaceError(MappingError, UserError):
    """Embeddings or a query come from another embedding space (or dimension) than the map's."""


class StaleVersionError(MappingError):
    """A dictionary delta cannot be produced or applied from the given version: fetch a snapshot."""


class StoreWriteError(MappingError, OSError):
    """The tile store could not be written (disk full, read-only folder, ...): an ``OSError``, so
    callers that keep the map in memory on a failed save treat it like any other write failure."""
