"""Ground-truth labelled surfaces for evaluation: ScanNet meshes and the synthetic world.

A :class:`GroundTruth` is a labelled point set: ``points`` (N, 3) in the world frame of the
frames' ``T_world_cam``, ``labels`` (N,) indices into ``class_names`` (``-1`` = unannotated /
not evaluated), and the class list that the protocol uses as text queries.

- ScanNet: ``<scene>_vh_clean_2.labels.ply`` vertices, property ``label`` = NYU40 id (0 =
  unannotated). Class names come from ``scannetv2-labels.combined.tsv`` (columns ``nyu40id``,
  ``nyu40class``) when found next to the scene or given, else from the fixed NYU40 list below.
  The scene's class list is the NYU40 classes that occur in its mesh.
- Synthetic: :meth:`SyntheticWorld.ground_truth_surface` points with instance ids; each
  instance's raw category maps to an evaluation class through
  :data:`openfusion.eval.classes.SYNTHETIC_CATEGORY_TO_CLASS` (the one place that table lives).
"""

from __future__ import annotations

import csv
import logging
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np

from openfusion.eval.classes import NYU40_CLASSES, class_for_category
from openfusion.io.ply import PlyError, read_ply

logger = logging.getLogger(__name__)

SCANNET_LABEL_TSV = "scannetv2-labels.combined.tsv"


@dataclass(frozen=True)
class GroundTruth:
    """A labelled ground-truth surface (points in metres, world frame)."""

    points: np.ndarray  # (N, 3) float32
    labels: np.ndarray  # (N,) int32, index into class_names, -1 = not evaluated
    class_names: tuple[str, ...]
    source: str
    #: The ground-truth mesh when known (accuracy is then the exact point-to-mesh distance).
    mesh_vertices: np.ndarray | None = None  # (V, 3) float
    mesh_triangles: np.ndarray | None = None  # (T, 3) int
    #: Per-point object instance id (0 = none) when the source knows objects (synthetic scenes).
    instance_ids: np.ndarray | None = None  # (N,) int64

    def __post_init__(self) -> None:
        p, lab = np.asarray(self.points), np.asarray(self.labels)
        if p.ndim != 2 or p.shape[1] != 3:
            raise ValueError(f"ground-truth points must be (N, 3), got {p.shape}")
        if lab.shape != (len(p),):
            raise ValueError(f"ground-truth labels must be ({len(p)},), got {lab.shape}")
        if lab.size and (lab.min() < -1 or lab.max() >= len(self.class_names)):
            raise ValueError(f"ground-truth labels out of range for {len(self.class_names)} classes")
        if (self.mesh_vertices is None) != (self.mesh_triangles is None):
            raise ValueError("give both mesh_vertices and mesh_triangles, or neither")
        object.__setattr__(self, "points", p.astype(np.float32, copy=False))
        object.__setattr__(self, "labels", lab.astype(np.int32, copy=False))

    @property
    def has_mesh(self) -> bool:
        return (
            self.mesh_vertices is not None
            and self.mesh_triangles is not None
            and len(self.mesh_triangles) > 0
        )

    def class_counts(self) -> dict[str, int]:
        counts = np.bincount(self.labels[self.labels >= 0], minlength=len(self.class_names))
        return {n: int(c) for n, c in zip(self.class_names, counts, strict=True)}


# ----------------------------------------------------------------------------- ScanNet


def read_scannet_label_table(tsv_path: str | Path) -> dict[int, str]:
    """``nyu40id -> nyu40class`` from ``scannetv2-labels.combined.tsv``."""
    tsv_path = Path(tsv_path)
    table: dict[int, str] = {}
    try:
        with tsv_path.open(newline="", encoding="utf-8") as fh:
            reader = csv.DictReader(fh, delimiter="\t")
            missing = {"nyu40id", "nyu40class"} - set(reader.fieldnames or [])
            if missing:
                raise ValueError(f"{tsv_path}: missing column(s) {sorted(missing)}")
            for line, row in enumerate(reader, start=2):
                raw_id = (row.get("nyu40id") or "").strip()
                name = (row.get("nyu40class") or "").strip()
                if not raw_id or not name:
                    continue
                try:
                    nyu_id = int(raw_id)
                except ValueError as exc:
                    raise ValueError(f"{tsv_path}:{line}: nyu40id {raw_id!r} is not an integer") from exc
                prev = table.setdefault(nyu_id, name)
                if prev != name:
                    raise ValueError(f"{tsv_path}:{line}: nyu40id {nyu_id} named both {prev!r} and {name!r}")
    except OSError as exc:
        raise ValueError(f"cannot read ScanNet label table {tsv_path}: {exc}") from exc
    return table


def find_scannet_label_tsv(scene_dir: Path) -> Path | None:
    """The label table next to the scene, or one or two folders up (ScanNet's release layout)."""
    for d in (scene_dir, scene_dir.parent, scene_dir.parent.parent):
        p = d / SCANNET_LABEL_TSV
        if p.is_file():
            return p
    return None


def load_scannet_ground_truth(
    scene: str | Path,
    *,
    label_tsv: str | Path | None = None,
) -> GroundTruth:
    """Ground truth of a ScanNet scene folder (or a ``*_vh_clean_2.labels.ply`` path).

    Raises ValueError naming the missing file or the malformed content.
    """
    scene = Path(scene)
    if scene.is_file():
        ply_path, scene_dir = scene, scene.parent
    else:
        scene_dir = scene
        ply_path = scene_dir / f"{scene_dir.name}_vh_clean_2.labels.ply"
        if not ply_path.is_file():
            candidates = sorted(scene_dir.glob("*_vh_clean_2.labels.ply"))
            if len(candidates) != 1:
                raise ValueError(
                    f"{scene_dir}: expected one *_vh_clean_2.labels.ply ground-truth mesh, found {len(candidates)}"
                )
            ply_path = candidates[0]
    try:
        ply = read_ply(ply_path)
    except PlyError as exc:
        raise ValueError(str(exc)) from exc
    verts = ply.vertices
    missing = {"x", "y", "z", "label"} - set(verts)
    if missing:
        raise ValueError(f"{ply_path}: vertex element lacks propert(ies) {sorted(missing)}")
    points = np.stack([verts["x"], verts["y"], verts["z"]], axis=1).astype(np.float32)
    if not np.isfinite(points).all():
        raise ValueError(f"{ply_path}: vertex coordinates contain NaN or inf")
    nyu = verts["label"].astype(np.int64)

    tsv = Path(label_tsv) if label_tsv is not None else find_scannet_label_tsv(scene_dir)
    if tsv is not None:
        names_by_id = read_scannet_label_table(tsv)
        logger.info("ScanNet class names from %s", tsv)
    else:
        names_by_id = {i + 1: n for i, n in enumerate(NYU40_CLASSES)}
        logger.info("no %s found near %s; using the built-in NYU40 class names", SCANNET_LABEL_TSV, scene_dir)
    unknown = sorted(set(np.unique(nyu[nyu > 0]).tolist()) - set(names_by_id))
    if unknown:
        logger.warning(
            "%s: label id(s) %s have no class name; they are not evaluated", ply_path, unknown[:10]
        )
    present = sorted(set(np.unique(nyu[nyu > 0]).tolist()) & set(names_by_id))
    class_names = tuple(names_by_id[i] for i in present)
    lut = np.full(int(max(nyu.max(initial=0), max(names_by_id, default=0))) + 1, -1, dtype=np.int32)
    for j, i in enumerate(present):
        lut[i] = j
    labels = np.where(nyu > 0, lut[np.clip(nyu, 0, len(lut) - 1)], -1).astype(np.int32)
    logger.info("ScanNet GT %s: %d vertices, %d classes", ply_path.name, len(points), len(class_names))
    return GroundTruth(
        points=points,
        labels=labels,
        class_names=class_names,
        source=str(ply_path),
        mesh_vertices=points if ply.triangles is not None else None,
        mesh_triangles=ply.triangles,
    )


# ----------------------------------------------------------------------------- synthetic


class _SurfaceLike(Protocol):
    points: np.ndarray
    instance_ids: np.ndarray
    categories: Mapping[int, str]


def ground_truth_from_instances(
    points: np.ndarray,
    instance_ids: np.ndarray,
    categories: Mapping[int, str],
    *,
    source: str,
    category_to_class: Mapping[str, str] | None = None,
    mesh_vertices: np.ndarray | None = None,
    mesh_triangles: np.ndarray | None = None,
) -> GroundTruth:
    """Labelled points from per-point instance ids and instance -> raw category names.

    Instance id 0 (or an id without a category) is unlabelled. Raw categories map to classes
    with ``category_to_class`` (default: :func:`openfusion.eval.classes.class_for_category`).
    The class list is the classes present, sorted by name.
    """
    inst = np.asarray(instance_ids).astype(np.int64)
    if inst.shape != (len(points),):
        raise ValueError(f"instance_ids must be ({len(points)},), got {inst.shape}")
    cls_of_instance: dict[int, str] = {}
    for iid, cat in categories.items():
        if int(iid) == 0:
            continue
        cls_of_instance[int(iid)] = (
            category_to_class[cat]
            if category_to_class is not None and cat in category_to_class
            else class_for_category(cat)
        )
    present_ids = set(np.unique(inst).tolist()) - {0}
    class_names = tuple(sorted({cls_of_instance[i] for i in present_ids if i in cls_of_instance}))
    index = {n: j for j, n in enumerate(class_names)}
    lut = {i: index[c] for i, c in cls_of_instance.items() if c in index}
    ids, inverse = np.unique(inst, return_inverse=True)
    mapped = np.array([lut.get(int(i), -1) for i in ids], dtype=np.int32)
    labels = mapped[inverse.reshape(-1)]
    return GroundTruth(
        points=np.asarray(points),
        labels=labels,
        class_names=class_names,
        source=source,
        mesh_vertices=mesh_vertices,
        mesh_triangles=mesh_triangles,
        instance_ids=inst,
    )


def synthetic_ground_truth(world: object, *, spacing_m: float, source: str = "synthetic") -> GroundTruth:
    """Ground truth of a :class:`openfusion.sources.synthetic.SyntheticWorld`: its visible surface
    sampled at ``spacing_m`` (labels) and its full mesh (accuracy)."""
    if not spacing_m > 0:
        raise ValueError(f"spacing_m must be positive, got {spacing_m}")
    surface: _SurfaceLike = world.ground_truth_surface(spacing_m)  # type: ignore[attr-defined]
    mesh = world.to_mesh()  # type: ignore[attr-defined]
    return ground_truth_from_instances(
        surface.points,
        surface.instance_ids,
        surface.categories,
        source=source,
        mesh_vertices=np.asarray(mesh.vertices),
        mesh_triangles=np.asarray(mesh.triangles),
    )
