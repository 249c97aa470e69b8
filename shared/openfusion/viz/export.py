"""Write a map's mesh or points to files other tools open: PLY (always) and GLB (with trimesh).

PLY files are binary little-endian, written atomically by :func:`openfusion.io.ply.write_ply_vertices`.
Vertex properties: ``x y z`` (float, world metres), ``nx ny nz`` (mesh only), ``red green blue``
(uchar, the chosen :class:`~openfusion.viz.colouring.Colouring`), ``key`` (int, region key, -1 = none)
and ``conf`` (float, the key's confidence); meshes add a ``face`` element of triangles. MeshLab,
CloudCompare, Blender and Open3D read them (the extra properties are ignored where unknown).

GLB (binary glTF 2.0) carries positions, normals, triangles and RGBA vertex colours; it needs the
optional package trimesh (``pip install 'openfusion-z[viz]'``), and without it raises
:class:`~openfusion.viz.errors.MissingDependencyError`.

The legend of a colouring goes next to the geometry as ``<name>.legend.json`` and
``<name>.legend.md`` (:func:`write_legend`).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import tempfile
from pathlib import Path

import numpy as np

from openfusion.io.ply import write_ply_vertices
from openfusion.mapping.volume import SurfaceMesh, SurfacePoints
from openfusion.viz.colouring import Colouring, legend_markdown
from openfusion.viz.errors import MissingDependencyError, VizError

logger = logging.getLogger(__name__)


def _colors_for(colouring: Colouring | None, default: np.ndarray, n: int, what: str) -> np.ndarray:
    colors = default if colouring is None else colouring.colors
    colors = np.ascontiguousarray(colors, dtype=np.uint8)
    if colors.shape != (n, 3):
        raise VizError(f"the colouring has {colors.shape[0]} colours but the {what} has {n} elements")
    return colors


def _check_parent(path: Path) -> None:
    if not path.parent.is_dir():
        raise VizError(f"cannot write {path}: folder {path.parent} does not exist")


def export_mesh_ply(mesh: SurfaceMesh, path: str | os.PathLike[str], *, colouring: Colouring | None = None) -> Path:
    """Write ``mesh`` as a binary PLY with normals, colours (``colouring`` or the camera colours), keys, conf."""
    path = Path(path)
    _check_parent(path)
    n = len(mesh.vertices)
    colors = _colors_for(colouring, mesh.colors, n, "mesh")
    vertices = np.asarray(mesh.vertices, np.float32)
    normals = np.asarray(mesh.normals, np.float32)
    props = {
        "x": vertices[:, 0], "y": vertices[:, 1], "z": vertices[:, 2],
        "nx": normals[:, 0], "ny": normals[:, 1], "nz": normals[:, 2],
        "red": colors[:, 0], "green": colors[:, 1], "blue": colors[:, 2],
        "key": np.asarray(mesh.keys, np.int32), "conf": np.asarray(mesh.conf, np.float32),
    }  # fmt: skip
    write_ply_vertices(path, props, faces=np.asarray(mesh.triangles, np.int32).reshape(-1, 3))
    logger.info("wrote mesh %s: %d vertices, %d triangles", path, n, len(mesh.triangles))
    return path


def export_points_ply(
    points: SurfacePoints, path: str | os.PathLike[str], *, colouring: Colouring | None = None
) -> Path:
    """Write surface ``points`` as a binary PLY point cloud with colours, keys and conf."""
    path = Path(path)
    _check_parent(path)
    n = len(points.points)
    colors = _colors_for(colouring, points.colors, n, "point cloud")
    xyz = np.asarray(points.points, np.float32)
    props = {
        "x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2],
        "red": colors[:, 0], "green": colors[:, 1], "blue": colors[:, 2],
        "key": np.asarray(points.keys, np.int32), "conf": np.asarray(points.conf, np.float32),
    }  # fmt: skip
    write_ply_vertices(path, props)
    logger.info("wrote point cloud %s: %d points", path, n)
    return path


def _import_trimesh(purpose: str):  # noqa: ANN202 - returns the module
    try:
        import trimesh
    except ImportError as exc:
        raise MissingDependencyError("trimesh", purpose) from exc
    return trimesh


def export_mesh_glb(mesh: SurfaceMesh, path: str | os.PathLike[str], *, colouring: Colouring | None = None) -> Path:
    """Write ``mesh`` as binary glTF (GLB) with RGBA vertex colours; needs trimesh."""
    trimesh = _import_trimesh("GLB export")
    path = Path(path)
    _check_parent(path)
    n = len(mesh.vertices)
    if n == 0 or len(mesh.triangles) == 0:
        raise VizError("the mesh is empty: a GLB needs at least one triangle")
    colors = _colors_for(colouring, mesh.colors, n, "mesh")
    rgba = np.concatenate([colors, np.full((n, 1), 255, np.uint8)], axis=1)
    tm = trimesh.Trimesh(
        vertices=np.asarray(mesh.vertices, np.float64),
        faces=np.asarray(mesh.triangles, np.int64),
        vertex_normals=np.asarray(mesh.normals, np.float64),
        vertex_colors=rgba,
        process=False,
    )
    data = tm.export(file_type="glb")
    _write_atomic(path, data)
    logger.info("wrote GLB %s: %d vertices, %d triangles", path, n, len(mesh.triangles))
    return path


def _write_atomic(path: Path, data: bytes) -> None:
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def write_legend(colouring: Colouring, stem: str | os.PathLike[str]) -> tuple[Path, Path]:
    """Write ``<stem>.legend.json`` and ``<stem>.legend.md``; returns both paths."""
    stem = Path(stem)
    _check_parent(stem)
    json_path = stem.with_name(stem.name + ".legend.json")
    md_path = stem.with_name(stem.name + ".legend.md")
    _write_atomic(json_path, (json.dumps(colouring.to_dict(), indent=2) + "\n").encode("utf-8"))
    _write_atomic(md_path, legend_markdown(colouring).encode("utf-8"))
    return json_path, md_path


def export_mesh(
    mesh: SurfaceMesh,
    path: str | os.PathLike[str],
    *,
    colouring: Colouring | None = None,
    legend: bool = True,
) -> list[Path]:
    """Write ``mesh`` in the format of ``path``'s suffix (``.ply`` or ``.glb``), plus the legend
    files when the colouring has one. Returns every file written."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".ply":
        written = [export_mesh_ply(mesh, path, colouring=colouring)]
    elif suffix == ".glb":
        written = [export_mesh_glb(mesh, path, colouring=colouring)]
    else:
        raise VizError(f"{path}: unknown mesh format {suffix or '(none)'!r}; use .ply or .glb")
    if legend and colouring is not None and colouring.legend:
        written += list(write_legend(colouring, path.with_suffix("")))
    return written


def export_points(
    points: SurfacePoints,
    path: str | os.PathLike[str],
    *,
    colouring: Colouring | None = None,
    legend: bool = True,
) -> list[Path]:
    """Write ``points`` as ``.ply`` plus the legend files when the colouring has one."""
    path = Path(path)
    if path.suffix.lower() != ".ply":
        raise VizError(f"{path}: point clouds are written as .ply, got {path.suffix or '(none)'!r}")
    written = [export_points_ply(points, path, colouring=colouring)]
    if legend and colouring is not None and colouring.legend:
        written += list(write_legend(colouring, path.with_suffix("")))
    return written


__all__ = [
    "export_mesh",
    "export_mesh_glb",
    "export_mesh_ply",
    "export_points",
    "export_points_ply",
    "write_legend",
]
