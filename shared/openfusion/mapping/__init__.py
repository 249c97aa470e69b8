"""Semantic TSDF map core: volume, render, matching, update rule, dictionary, queries, map files.

See docs/ARCHITECTURE.md ("Map core") for the contract; the update rule is written down in
``openfusion.mapping.volume`` and the soft IoU in ``openfusion.mapping.matching``.
"""

from openfusion.mapping.dictionary import RegionDictionary
from openfusion.mapping.errors import (
    CapacityError,
    EmbeddingSpaceError,
    MapFormatError,
    MappingError,
    StaleVersionError,
)
from openfusion.mapping.mapfile import FORMAT_VERSION, LoadedMap, load_map, save_map
from openfusion.mapping.mapper import SemanticMapper, StepStats
from openfusion.mapping.matching import (
    DEFAULT_MIN_IOU,
    MatchResult,
    PlannedUpdate,
    match_regions,
    plan_update,
    region_conf_maps,
    soft_iou_matrix,
)
from openfusion.mapping.params import MatchParams, VolumeParams
from openfusion.mapping.queries import RegionResult, classify_regions, query_regions, segment_points
from openfusion.mapping.update_rule import fuse_semantics
from openfusion.mapping.volume import (
    SEMANTIC_BYTES_PER_VOXEL,
    IntegrateStats,
    RayHits,
    RenderedView,
    SemanticVolume,
    SurfaceMesh,
    SurfacePoints,
    UpdateStats,
    VolumeStats,
)

__all__ = [
    "DEFAULT_MIN_IOU",
    "MatchParams",
    "FORMAT_VERSION",
    "SEMANTIC_BYTES_PER_VOXEL",
    "CapacityError",
    "EmbeddingSpaceError",
    "IntegrateStats",
    "LoadedMap",
    "MapFormatError",
    "MappingError",
    "MatchResult",
    "PlannedUpdate",
    "RayHits",
    "RegionDictionary",
    "RegionResult",
    "RenderedView",
    "SemanticMapper",
    "SemanticVolume",
    "StaleVersionError",
    "StepStats",
    "SurfaceMesh",
    "SurfacePoints",
    "UpdateStats",
    "VolumeParams",
    "VolumeStats",
    "classify_regions",
    "fuse_semantics",
    "load_map",
    "match_regions",
    "plan_update",
    "query_regions",
    "region_conf_maps",
    "save_map",
    "segment_points",
    "soft_iou_matrix",
]
