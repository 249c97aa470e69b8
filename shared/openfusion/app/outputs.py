"""What a run leaves in its output folder besides the map: query answers, their points, the mesh,
and the optional rerun recording. Shared by the multi-process and the in-process run."""

from __future__ import annotations

import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from openfusion.io.ply import write_ply_vertices


def _nearby_record(nearby: Any) -> dict[str, Any]:
    return {"key": int(nearby.key), "label": nearby.label, "relation": nearby.relation,
            "distance_m": round(float(nearby.distance_m), 3)}


def region_record(region: Any) -> dict[str, Any]:
    """A ranked region (bus ``RegionHit`` or library ``RegionResult``) as a JSON-ready dict:
    key, score (cosine), label, num_points, bbox_min/bbox_max, relevancy ([0, 1] or null), match
    (bool or null), centroid ([x, y, z] or null), nearby (up to 3 ``{key, label, relation,
    distance_m}``) and, for a hit of an "X next to Y" query that stands in the relation,
    ``relation`` (the anchor, same form)."""
    centroid = getattr(region, "centroid", None)
    relevancy = getattr(region, "relevancy", None)
    record = {"key": int(region.key), "score": round(float(region.score), 4), "label": region.label,
              "num_points": int(region.num_points),
              "bbox_min": [round(float(v), 3) for v in region.bbox_min],
              "bbox_max": [round(float(v), 3) for v in region.bbox_max],
              "relevancy": None if relevancy is None else round(float(relevancy), 4),
              "match": getattr(region, "match", None),
              "centroid": None if centroid is None else [round(float(v), 3) for v in centroid],
              "nearby": [_nearby_record(n) for n in getattr(region, "nearby", None) or []]}
    relation = getattr(region, "relation", None)
    if relation is not None:
        record["relation"] = _nearby_record(relation)
    return record


def region_name(region: Any) -> str:
    """How a region is named in a sentence: its label, else ``region KEY``."""
    return region.label or f"region {int(region.key)}"


def no_match_line(text: str, regions: list[Any]) -> str | None:
    """``no match for "X" (closest: Y, relevancy R)`` when no region of the answer is a match
    (None when one is, or when relevancy was not computed); Y is the region of highest relevancy
    ("nothing" when the map has no region to answer)."""
    if any(getattr(r, "match", None) for r in regions):
        return None
    scored = [r for r in regions if getattr(r, "relevancy", None) is not None]
    if regions and not scored:
        return None
    if not scored:
        return f'no match for "{text}" (closest: nothing)'
    best = max(scored, key=lambda r: (float(r.relevancy), float(r.score)))
    return f'no match for "{text}" (closest: {region_name(best)}, relevancy {float(best.relevancy):.2f})'


def where_line(region: Any) -> str:
    """The relation of a relation query's hit and its nearby regions, e.g. ``next to table (key 4);
    near: on floor (key 1), next to chair (key 7, 0.21 m)``; empty when there is none."""
    def name(n: Any) -> str:
        far = f", {float(n.distance_m):.2f} m" if float(n.distance_m) > 0 else ""
        return f"{n.relation} {n.label or 'region'} (key {int(n.key)}{far})"

    parts = []
    relation = getattr(region, "relation", None)
    if relation is not None:
        parts.append(name(relation))
    nearby = getattr(region, "nearby", None) or []
    if nearby:
        parts.append("near: " + ", ".join(name(n) for n in nearby))
    return "; ".join(parts)


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
            best = next((h for h in hits if getattr(h, "match", None)), None)
            none = no_match_line(text, hits)
            if none is not None:
                say(f"query {text!r}: {none}")
            else:
                best = best or (hits[0] if hits else None)
                where = where_line(best) if best is not None else ""
                say(f"query {text!r}: " + (f"region {best.key} ({best.label or '?'}) score {best.score:.3f}"
                                            + (f", relevancy {best.relevancy:.2f}" if best.relevancy is not None
                                               else "")
                                            + f", {best.num_points} points" + (f"; {where}" if where else "")
                                            if best else "no region"))
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


