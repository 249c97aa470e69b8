"""Evaluation: the ConceptFusion / ConceptGraphs protocol, geometry metrics and baselines.

See docs/EVAL.md. Entry points: ``openfusion eval`` (:mod:`openfusion.app.eval_cmd`),
:func:`~openfusion.eval.runner.run_eval`, and ``bench/bench_eval.py``. Heavy dependencies
(Open3D, the map core, encoders) are imported only by the functions that need them.
"""

from openfusion.eval.classes import (
    DEFAULT_BACKGROUND_CLASSES,
    NYU40_CLASSES,
    SYNTHETIC_CATEGORY_TO_CLASS,
    SYNTHETIC_CLASSES,
    class_for_category,
)
from openfusion.eval.geometry import GeometryMetrics, ObservedSurface, geometry_metrics, mesh_distances
from openfusion.eval.ground_truth import (
    GroundTruth,
    ground_truth_from_instances,
    load_scannet_ground_truth,
    synthetic_ground_truth,
)
from openfusion.eval.metrics import (
    ClassMetrics,
    ConfusionMatrix,
    SemanticMetrics,
    compute_metrics,
    sum_confusions,
)
from openfusion.io.ply import PlyError, read_ply, read_ply_vertices, write_ply_vertices

__all__ = [
    "DEFAULT_BACKGROUND_CLASSES",
    "NYU40_CLASSES",
    "SYNTHETIC_CATEGORY_TO_CLASS",
    "SYNTHETIC_CLASSES",
    "ClassMetrics",
    "ConfusionMatrix",
    "GeometryMetrics",
    "GroundTruth",
    "ObservedSurface",
    "PlyError",
    "SemanticMetrics",
    "class_for_category",
    "compute_metrics",
    "geometry_metrics",
    "ground_truth_from_instances",
    "load_scannet_ground_truth",
    "mesh_distances",
    "read_ply",
    "read_ply_vertices",
    "sum_confusions",
    "synthetic_ground_truth",
    "write_ply_vertices",
]
