"""openfusion.viz export: PLY/GLB files re-read with the right counts, colours, keys and legends."""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest

from openfusion.io.ply import read_ply
from openfusion.mapping import load_map
from openfusion.testing.maps import cached_synthetic_map
from openfusion.viz.colouring import (
    QueryHit,
    assign_classes,
    colour_by_label,
    colour_by_query,
    colour_by_region,
    legend_markdown,
)
from openfusion.viz.errors import MissingDependencyError, VizError
from openfusion.viz.export import export_mesh, export_mesh_glb, export_points, write_legend
from openfusion.viz.palette import HIGHLIGHT_RGB, UNLABELLED_RGB, index_colors, key_colors


@pytest.fixture(scope="module")
def loaded(tmp_path_factory):
    return load_map(cached_synthetic_map(tmp_path_factory.getbasetemp()))


@pytest.fixture(scope="module")
def mesh(loaded):
    return loaded.volume.extract_mesh()


def _labels(dictionary) -> dict[int, str | None]:
    return {int(k): dictionary.label(int(k)) for k in dictionary.keys}


# ------------------------------------------------------------------ palette


def test_palette_is_deterministic_distinct_and_keeps_grey_for_no_region():
    """Same key -> same colour on every call; the first 18 keys are pairwise distinct; key -1 is grey."""
    keys = np.array([-1, 0, 1, 2, 17, 18, 500, 0])
    a, b = key_colors(keys), key_colors(keys)
    assert np.array_equal(a, b)
    assert tuple(a[0]) == UNLABELLED_RGB
    assert np.array_equal(a[1], a[-1])
    first = index_colors(np.arange(18))
    assert len({tuple(c) for c in first}) == 18
    assert not any(tuple(c) == UNLABELLED_RGB for c in index_colors(np.arange(200)))
    with pytest.raises(ValueError, match=">= 0"):
        index_colors([-2])


# ------------------------------------------------------------------ PLY


def test_mesh_ply_round_trip_keeps_counts_colours_keys_and_faces(mesh, loaded, tmp_path):
    """Region-coloured mesh PLY re-read: same vertices, triangles, per-vertex colour and key."""
    colouring = colour_by_region(mesh.keys, labels=_labels(loaded.dictionary))
    written = export_mesh(mesh, tmp_path / "regions.ply", colouring=colouring)
    assert [p.name for p in written] == ["regions.ply", "regions.legend.json", "regions.legend.md"]
    ply = read_ply(tmp_path / "regions.ply")
    v = ply.vertices
    assert len(v["x"]) == len(mesh.vertices) > 1000
    assert ply.triangles is not None and np.array_equal(ply.triangles, mesh.triangles)
    np.testing.assert_allclose(np.stack([v["x"], v["y"], v["z"]], 1), mesh.vertices, atol=1e-6)
    rgb = np.stack([v["red"], v["green"], v["blue"]], 1)
    assert np.array_equal(rgb, key_colors(mesh.keys))
    assert np.array_equal(v["key"], mesh.keys)
    # every labelled key's vertices share one colour, different keys differ (first 18 keys)
    for key in np.unique(mesh.keys[mesh.keys >= 0])[:18]:
        assert len(np.unique(rgb[mesh.keys == key], axis=0)) == 1


def test_legend_lists_every_colour_with_counts_that_add_up(mesh, loaded, tmp_path):
    """The legend JSON names each region's colour, key, label and vertex count; counts sum to V."""
    colouring = colour_by_region(mesh.keys, labels=_labels(loaded.dictionary))
    json_path, md_path = write_legend(colouring, tmp_path / "m")
    legend = json.loads(json_path.read_text())
    assert legend["mode"] == "region"
    entries = legend["entries"]
    assert sum(e["count"] for e in entries) == len(mesh.vertices)
    for e in entries:
        if "key" in e:
            sel = mesh.keys == e["key"]
            assert e["count"] == int(sel.sum())
            assert tuple(e["color_rgb"]) == tuple(key_colors([e["key"]])[0])
            assert e["color_hex"].startswith("#") and len(e["color_hex"]) == 7
            assert e.get("label") == loaded.dictionary.label(e["key"])
    md = md_path.read_text()
    assert md.startswith("# Legend") and md.count("\n| `#") == len(entries)


def test_points_ply_coloured_by_label_round_trip(loaded, tmp_path):
    """Label-coloured point cloud: all points of one label share its colour; legend keys match."""
    points = loaded.volume.extract_points(max_points=5000)
    labels = _labels(loaded.dictionary)
    colouring = colour_by_label(points.keys, labels)
    export_points(points, tmp_path / "pts.ply", colouring=colouring)
    v = read_ply(tmp_path / "pts.ply").vertices
    assert len(v["x"]) == len(points) == 5000
    rgb = np.stack([v["red"], v["green"], v["blue"]], 1)
    assert np.array_equal(rgb, colouring.colors)
    for entry in colouring.legend:
        if not entry.keys:
            continue
        sel = np.isin(points.keys, entry.keys)
        assert sel.sum() == entry.count
        assert (rgb[sel] == entry.color_rgb).all()
    # two regions with the same label share the label's colour
    walls = [e for e in colouring.legend if e.label == "wall"]
    assert walls and len(walls[0].keys) >= 2


def test_query_highlight_colours_only_the_matched_region(mesh):
    """Query colouring: matched key in the highlight red, every other vertex grey (r == g == b)."""
    key = int(np.bincount(mesh.keys[mesh.keys >= 0]).argmax())
    colouring = colour_by_query(mesh.keys, mesh.colors, [QueryHit(key, 0.9, "floor")], query_text="floor")
    sel = mesh.keys == key
    assert (colouring.colors[sel] == HIGHLIGHT_RGB).all()
    other = colouring.colors[~sel]
    assert (other[:, 0] == other[:, 1]).all() and (other[:, 1] == other[:, 2]).all()
    assert colouring.legend[0].key == key and colouring.legend[0].count == int(sel.sum())
    assert "floor" in legend_markdown(colouring)


def test_assign_classes_picks_best_cosine_and_checks_shapes():
    """Each region takes the class whose embedding is closest; mismatched dimensions are refused."""
    regions = np.eye(3, dtype=np.float32)
    classes = np.array([[0, 1, 0], [1, 0, 0]], np.float32)
    got = assign_classes(np.array([5, 6, 7]), regions, classes, ["b", "a"])
    assert got[5] == "a" and got[6] == "b"
    with pytest.raises(ValueError, match="dimension"):
        assign_classes(np.array([1]), np.ones((1, 4), np.float32), classes, ["b", "a"])


# ------------------------------------------------------------------ GLB


def test_glb_round_trip_with_trimesh(mesh, tmp_path):
    """GLB re-read with trimesh: same vertex/face counts and the vertex colours written."""
    trimesh = pytest.importorskip("trimesh", reason="GLB export needs the optional trimesh package")
    colouring = colour_by_region(mesh.keys)
    export_mesh_glb(mesh, tmp_path / "m.glb", colouring=colouring)
    back = trimesh.load(tmp_path / "m.glb", force="mesh", process=False)
    assert len(back.vertices) == len(mesh.vertices)
    assert len(back.faces) == len(mesh.triangles)
    np.testing.assert_allclose(back.vertices, mesh.vertices, atol=1e-5)
    assert np.array_equal(np.asarray(back.visual.vertex_colors)[:, :3], colouring.colors)


def test_glb_without_trimesh_names_the_missing_package(mesh, tmp_path, monkeypatch):
    """With trimesh not importable, GLB export fails with one clear line naming it (no file left)."""
    monkeypatch.setitem(sys.modules, "trimesh", None)
    with pytest.raises(MissingDependencyError, match="trimesh"):
        export_mesh(mesh, tmp_path / "m.glb")
    assert not list(tmp_path.iterdir())


def test_export_refuses_bad_targets_and_mismatched_colours(mesh, tmp_path):
    """Unknown suffix, missing folder and a colouring of the wrong length are VizErrors."""
    with pytest.raises(VizError, match="unknown mesh format"):
        export_mesh(mesh, tmp_path / "m.obj")
    with pytest.raises(VizError, match="does not exist"):
        export_mesh(mesh, tmp_path / "nope" / "m.ply")
    short = colour_by_region(mesh.keys[:10])
    with pytest.raises(VizError, match="10 colours"):
        export_mesh(mesh, tmp_path / "m.ply", colouring=short)
    assert not (tmp_path / "m.ply").exists()
