"""Semantic TSDF map core: volume, render, matching, update rule, dictionary, queries, map files.

See docs/ARCHITECTURE.md ("Map core") for the contract; the update rule is written down in
``openfusion.mapping.volume`` and the soft IoU in ``openfusion.mapping.matching``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from openfusion.lazy import lazy_exports

if TYPE_CHECKING:
    from openfusion.mapping.dictionary import RegionDictionary
    from openfusion.mapping.errors import (
        CapacityError,
        EmbeddingSpaceError,
        MapFormatError,
        MappingError,
        StaleVersionError,
    )
    from openfusion.mapping.mapfile import (
        FORMAT_VERSION,
        LoadedMap,
        MapSummary,
        load_latest_map,
        load_map,
        load_map_summary,
        previous_map_path,
        save_map,
    )
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
    from openfusion.mapping.params import MatchParams, QueryParams, VolumeParams
    from openfusion.mapping.queries import (
        RegionResult,
        RegionTable,
        classify_regions,
        query_region_table,
        query_regions,
        segment_points,
    )
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

# Names are imported on first use (PEP 562): ``from openfusion.mapping import load_map`` must not
# load Open3D and SciPy (the volume, matching) for a caller that only reads a map's summaries.
_EXPORTS: dict[str, str] = {
    "RegionDictionary": "openfusion.mapping.dictionary",
    "CapacityError": "openfusion.mapping.errors",
    "EmbeddingSpaceError": "openfusion.mapping.errors",
    "MapFormatError": "openfusion.mapping.errors",
    "MappingError": "openfusion.mapping.errors",
    "StaleVersionError": "openfusion.mapping.errors",
    "FORMAT_VERSION": "openfusion.mapping.mapfile",
    "LoadedMap": "openfusion.mapping.mapfile",
    "load_map": "openfusion.mapping.mapfile",
    "load_latest_map": "openfusion.mapping.mapfile",
    "previous_map_path": "openfusion.mapping.mapfile",
    "save_map": "openfusion.mapping.mapfile",
    "MapSummary": "openfusion.mapping.mapfile",
    "load_map_summary": "openfusion.mapping.mapfile",
    "SemanticMapper": "openfusion.mapping.mapper",
    "StepStats": "openfusion.mapping.mapper",
    "DEFAULT_MIN_IOU": "openfusion.mapping.matching",
    "MatchResult": "openfusion.mapping.matching",
    "PlannedUpdate": "openfusion.mapping.matching",
    "match_regions": "openfusion.mapping.matching",
    "plan_update": "openfusion.mapping.matching",
    "region_conf_maps": "openfusion.mapping.matching",
    "soft_iou_matrix": "openfusion.mapping.matching",
    "MatchParams": "openfusion.mapping.params",
    "VolumeParams": "openfusion.mapping.params",
    "QueryParams": "openfusion.mapping.params",
    "RegionResult": "openfusion.mapping.queries",
    "classify_regions": "openfusion.mapping.queries",
    "query_regions": "openfusion.mapping.queries",
    "segment_points": "openfusion.mapping.queries",
    "RegionTable": "openfusion.mapping.queries",
    "query_region_table": "openfusion.mapping.queries",
    "fuse_semantics": "openfusion.mapping.update_rule",
    "SEMANTIC_BYTES_PER_VOXEL": "openfusion.mapping.volume",
    "IntegrateStats": "openfusion.mapping.volume",
    "RayHits": "openfusion.mapping.volume",
    "RenderedView": "openfusion.mapping.volume",
    "SemanticVolume": "openfusion.mapping.volume",
    "SurfaceMesh": "openfusion.mapping.volume",
    "SurfacePoints": "openfusion.mapping.volume",
    "UpdateStats": "openfusion.mapping.volume",
    "VolumeStats": "openfusion.mapping.volume",
}

__all__ = [
    "CapacityError",
    "DEFAULT_MIN_IOU",
    "EmbeddingSpaceError",
    "FORMAT_VERSION",
    "IntegrateStats",
    "LoadedMap",
    "MapFormatError",
    "MapSummary",
    "MappingError",
    "MatchParams",
    "MatchResult",
    "PlannedUpdate",
    "QueryParams",
    "RayHits",
    "RegionDictionary",
    "RegionResult",
    "RegionTable",
    "RenderedView",
    "SEMANTIC_BYTES_PER_VOXEL",
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
    "load_latest_map",
    "load_map",
    "load_map_summary",
    "match_regions",
    "plan_update",
    "previous_map_path",
    "query_region_table",
    "query_regions",
    "region_conf_maps",
    "save_map",
    "segment_points",
    "soft_iou_matrix",
]


__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
