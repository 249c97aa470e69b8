"""What a run leaves in its output folder besides the map: query answers, their points, the mesh,
and the optional rerun recording. Shared by the multi-process and the in-process run."""

from __future__ import annotations

import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from openfusion.io.ply import write_ply_vertices


def region_record(region: Any) -> dict[str, Any]:
    """A ranked region (bus ``RegionHit`` or library ``RegionResult``) as a JSON-ready dict."""
    return {"key": int(region.key), "score": round(float(region.score), 4), "label": region.label,
            "num_points": int(region.num_points),
            "bbox_min": [round(float(v), 3) for v in region.bbox_min],
            "bbox_max": [round(float(v), 3) for v in region.bbox_max]}


def write_query_outputs(
    out: Path,
    replies: list[tuple[str, str, list[Any]]],
    mesh: tuple[Any, Any, Any, Any] | Any | None,
    *,
    say: Any = None,
) -> list[dict[str, Any]]:
    """Write ``queries.json``, ``query_<i>.ply`` (points of each query's best region) and
    ``mesh.ply`` (vertex colour + region key). ``replies``: (query, embedding space, ranked hits with
    key/score/label/bbox_min/bbox_max/num_points/points); ``mesh``: a SurfaceMesh-like object or
    (vertices, triangles, colors, keys)."""
    records = []
    for i, (text, space, hits) in enumerate(replies):
        regions = [region_record(r) for r in hits]
        record: dict[str, Any] = {"query": text, "embedding_space": space, "regions": regions}
        if hits and hits[0].points is not None and len(hits[0].points):
            p = hits[0].points
            write_ply_vertices(out / f"query_{i}.ply", {"x": p[:, 0], "y": p[:, 1], "z": p[:, 2]})
            record["points_file"] = f"query_{i}.ply"
        records.append(record)
        if say is not None:
            best = hits[0] if hits else None
            say(f"query {text!r}: " + (f"region {best.key} ({best.label or '?'}) score {best.score:.3f}, "
                                        f"{best.num_points} points" if best else "no region"))
    (out / "queries.json").write_text(json.dumps(records, indent=2))
    if mesh is not None:
        vertices, triangles, colors, keys = (mesh if isinstance(mesh, tuple)
                                             else (mesh.vertices, mesh.triangles, mesh.colors, mesh.keys))
        if len(vertices):
            write_ply_vertices(out / "mesh.ply", {
                "x": vertices[:, 0], "y": vertices[:, 1], "z": vertices[:, 2],
                "red": colors[:, 0], "green": colors[:, 1], "blue": colors[:, 2],
                "key": keys.astype("int32")}, faces=triangles)
    return records


def say_progress(quiet: bool) -> Callable[[str], None] | None:
    """Where a run's progress lines go: stderr (stdout carries only the run summary, so it can be
    piped), or nowhere with ``--quiet``."""
    if quiet:
        return None
    return lambda text: print(text, file=sys.stderr, flush=True)


def open_rerun(sink: str | None) -> Any:
    """A :class:`openfusion.viz.rerun_log.RerunLogger` for ``--rerun SINK``, or None."""
    if not sink:
        return None
    from openfusion.viz.rerun_log import RerunLogger

    return RerunLogger(sink)


def surface_mesh(vertices: Any, triangles: Any, colors: Any, keys: Any) -> Any:
    """A :class:`openfusion.mapping.SurfaceMesh` (with vertex normals) from mesh arrays off the bus."""
    import numpy as np
    import open3d as o3d

    from openfusion.mapping import SurfaceMesh

    legacy = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.array(vertices, np.float64)),
                                       o3d.utility.Vector3iVector(np.array(triangles, np.int32)))
    legacy.compute_vertex_normals()
    return SurfaceMesh(vertices=np.asarray(vertices, np.float32), triangles=np.asarray(triangles, np.int32),
                       colors=np.asarray(colors, np.uint8), normals=np.asarray(legacy.vertex_normals, np.float32),
                       keys=np.asarray(keys, np.int32), conf=np.ones(len(vertices), np.float32))


