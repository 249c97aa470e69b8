"""``openfusion render`` / ``openfusion export`` through the real console-script entry point:
outputs a user opens, and one clear line (no traceback) for everything a user can get wrong."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

from openfusion.app import cli
from openfusion.io.ply import read_ply
from openfusion.mapping import RegionDictionary, SemanticVolume, VolumeParams, save_map
from openfusion.sources import open_source
from openfusion.testing.maps import cached_synthetic_map

COMMANDS = {
    "render": "openfusion.app.render_cmd:RenderCommand",
    "export": "openfusion.app.export_cmd:ExportCommand",
}


@pytest.fixture(autouse=True)
def _registered(monkeypatch):
    """Use the registry entries the integrator added; add ours where one is missing."""
    have = {s.name for s in cli.SUBCOMMANDS}
    extra = [cli.Subcommand(name, target, name) for name, target in COMMANDS.items() if name not in have]
    monkeypatch.setattr(cli, "SUBCOMMANDS", [*cli.SUBCOMMANDS, *extra])


@pytest.fixture(scope="module")
def map_dir(tmp_path_factory):
    return cached_synthetic_map(tmp_path_factory.getbasetemp())


def _geometry_only_map(folder, space: str, dim: int):
    volume = SemanticVolume(VolumeParams(voxel_size_m=0.05))
    for frame in open_source("synthetic:seed=2,frames=2,width=80,height=60"):
        volume.integrate(frame)
    dictionary = RegionDictionary(space, dim)
    dictionary.add(np.ones(dim, np.float32), label="thing")
    save_map(folder, volume, dictionary)
    return folder


def _run(capsys, *argv: str) -> tuple[int, str, str]:
    code = cli.main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test_render_writes_png_of_the_requested_size_with_query_summary(map_dir, tmp_path, capsys):
    """render --query: a PNG of --width x --height, JSON summary names the best region and the
    highlighted share of the image."""
    out = tmp_path / "chair.png"
    code, stdout, err = _run(
        capsys, "render", "--map-dir", str(map_dir), "--query", "chair", "--out", str(out),
        "--width", "200", "--height", "150", "--supersample", "1", "--json",
    )  # fmt: skip
    assert code == 0, err
    summary = json.loads(stdout)
    assert summary["hits"][0]["label"] == "chair"
    assert 0 < summary["highlighted_fraction"] < 0.2
    with Image.open(out) as img:
        assert img.size == (200, 150) and img.mode == "RGB"


def test_render_label_colours_and_exports_the_same_colours(map_dir, tmp_path, capsys):
    """render --colour label --export-mesh: the exported PLY's colours are the picture's colouring,
    and a legend is written beside it; the plain-text summary names the files."""
    png, ply = tmp_path / "labels.png", tmp_path / "labels.ply"
    code, stdout, err = _run(
        capsys, "render", "--map-dir", str(map_dir), "--colour", "label", "--out", str(png),
        "--width", "160", "--height", "120", "--export-mesh", str(ply),
    )  # fmt: skip
    assert code == 0, err
    assert f"wrote {png}" in stdout and str(ply) in stdout
    legend = json.loads((tmp_path / "labels.legend.json").read_text())
    labels = {e.get("label") for e in legend["entries"]}
    assert {"floor", "wall", "chair"} <= labels
    v = read_ply(ply).vertices
    rgb = np.stack([v["red"], v["green"], v["blue"]], 1)
    floor = next(e for e in legend["entries"] if e.get("label") == "floor")
    sel = np.isin(v["key"], floor["keys"])
    assert sel.sum() == floor["count"] and (rgb[sel] == floor["color_rgb"]).all()


def test_export_glb_and_points(map_dir, tmp_path, capsys):
    """export: a region-coloured GLB (when trimesh is installed) and a query-coloured point cloud."""
    pytest.importorskip("trimesh", reason="GLB export needs the optional trimesh package")
    code, stdout, err = _run(capsys, "export", "--map-dir", str(map_dir), "--out", str(tmp_path / "m.glb"), "--colour", "region")
    assert code == 0, err
    assert (tmp_path / "m.glb").stat().st_size > 10_000 and (tmp_path / "m.legend.md").exists()
    code, stdout, err = _run(
        capsys, "export", "--map-dir", str(map_dir), "--out", str(tmp_path / "p.ply"), "--points",
        "--max-points", "3000", "--query", "chair", "--json",
    )  # fmt: skip
    assert code == 0, err
    summary = json.loads(stdout)
    assert summary["elements"] == 3000 and summary["colour"] == "query"
    v = read_ply(tmp_path / "p.ply").vertices
    red = (v["red"] == 235) & (v["green"] == 30)
    assert red.any() and (v["key"][red] == summary["hits"][0]["key"]).all()


def test_export_colours_by_best_matching_class(map_dir, tmp_path, capsys):
    """--colour label --classes: every region takes one of the given classes; colours follow the
    order the classes were given in (first class -> first palette colour)."""
    code, _, err = _run(
        capsys, "export", "--map-dir", str(map_dir), "--out", str(tmp_path / "c.ply"),
        "--colour", "label", "--classes", "chair, floor ,wall",
    )  # fmt: skip
    assert code == 0, err
    legend = json.loads((tmp_path / "c.legend.json").read_text())
    assert legend["title"] == "best-matching class"
    labels = [e.get("label") for e in legend["entries"]]
    assert labels[:3] == ["chair", "floor", "wall"] and set(labels) <= {"chair", "floor", "wall", "(no label)"}
    from openfusion.viz.palette import index_colors

    assert legend["entries"][0]["color_rgb"] == list(index_colors([0])[0])
    floor = legend["entries"][1]
    v = read_ply(tmp_path / "c.ply").vertices
    rgb = np.stack([v["red"], v["green"], v["blue"]], 1)
    painted = (rgb == floor["color_rgb"]).all(axis=1)
    assert floor["count"] == int(painted.sum()) > 1000
    assert set(np.unique(v["key"][painted]).tolist()) == set(floor["keys"])


@pytest.mark.parametrize(
    ("case", "message"),
    [
        ("missing", "does not exist"),
        ("empty-folder", "not a map folder"),
        ("corrupt", "cannot read the map"),
        ("bad-size", "width must be an integer between 16 and 8192"),
        ("bad-out", "--out must name a .png"),
        ("unknown-space", "no built-in text encoder embeds queries"),
        ("other-space", "embeds in space 'hash-trigram-256'"),
        ("bad-top-k", "--top-k must be >= 1"),
        ("classes-without-label", "--classes only applies"),
        ("bad-export-suffix", "--export-mesh must end in .ply or .glb"),
    ],
)
def test_render_user_errors_are_one_line_without_traceback(case, message, map_dir, tmp_path, capsys):
    """Each mistake ends with exit code 2 and one stderr line naming the problem (no traceback)."""
    out = str(tmp_path / "v.png")
    args = ["render", "--map-dir", str(map_dir), "--out", out, "--width", "64", "--height", "48"]
    if case == "missing":
        args[2] = str(tmp_path / "nowhere")
    elif case == "empty-folder":
        args[2] = str(tmp_path)
    elif case == "corrupt":
        (tmp_path / "bad").mkdir()
        (tmp_path / "bad" / "map.ofz.npz").write_bytes(b"PK\x03\x04 not really a zip")
        args[2] = str(tmp_path / "bad")
    elif case == "bad-size":
        args[args.index("--width") + 1] = "3"
    elif case == "bad-out":
        args[args.index("--out") + 1] = str(tmp_path / "v.jpg")
    elif case == "unknown-space":
        args[2] = str(_geometry_only_map(tmp_path / "foreign", "mystery-space-v1", 8))
        args += ["--query", "chair"]
    elif case == "other-space":
        args[2] = str(_geometry_only_map(tmp_path / "h64", "hash-trigram-64", 64))
        args += ["--query", "chair", "--text-encoder", "hash"]
    elif case == "bad-top-k":
        args += ["--query", "chair", "--top-k", "0"]
    elif case == "classes-without-label":
        args += ["--classes", "chair,table"]
    elif case == "bad-export-suffix":
        args += ["--export-mesh", str(tmp_path / "m.obj")]
    code, stdout, err = _run(capsys, *args)
    assert code == 2
    assert message in err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert not (tmp_path / "v.png").exists()


def test_export_without_trimesh_exits_1_naming_the_package(map_dir, tmp_path, capsys, monkeypatch):
    """export to .glb with trimesh missing: exit 1, one line saying how to install it."""
    monkeypatch.setitem(__import__("sys").modules, "trimesh", None)
    code, _, err = _run(capsys, "export", "--map-dir", str(map_dir), "--out", str(tmp_path / "m.glb"))
    assert code == 1
    assert "trimesh" in err and "pip install" in err and len(err.strip().splitlines()) == 1
    # render --export-mesh x.glb refuses before rendering: no picture is left behind
    png = tmp_path / "v.png"
    code, _, err = _run(
        capsys, "render", "--map-dir", str(map_dir), "--out", str(png), "--export-mesh", str(tmp_path / "m.glb"),
    )  # fmt: skip
    assert code == 1 and "trimesh" in err and not png.exists()
