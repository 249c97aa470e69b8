"""End-to-end evaluation on tiny synthetic scenes: the CLI writes the documented outputs, and a
small noise-free run labels most of the scene correctly."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from openfusion.app.cli import main as cli_main


def main(argv: list[str]) -> int:
    return cli_main(["eval", *argv])

pytest.importorskip("open3d")

#: Fields docs/EVAL.md promises in results.json.
SCENE_FIELDS = {"scene", "ground_truth", "surface_points", "quality", "geometry", "speed", "memory", "query", "wrong_regions"}
METRIC_FIELDS = {
    "mAcc", "f_mIoU", "mIoU", "overall_accuracy", "num_points", "unlabelled_fraction",
    "classes_evaluated", "classes_excluded", "per_class",
}  # fmt: skip
GEOMETRY_FIELDS = {
    "accuracy_m", "accuracy_vox", "accuracy_median_m", "accuracy_p90_m", "completeness",
    "completeness_threshold_m", "num_reconstructed", "num_gt", "num_gt_observed", "voxel_size_m",
}  # fmt: skip
SPEED_FIELDS = {
    "frames", "semantic_frames", "integrate_s", "encode_s", "semantic_step_s", "rec3d_fps",
    "raw_open3d_integrate_s", "raw_open3d_fps", "sem_rec3d_fps", "encode_ms", "semantic_step_ms",
}  # fmt: skip
MAPS = {"region_map", "region_map_nn_fill", "point_features", "block_samples_16"}
STORED_MAPS = {"region_map", "point_features", "block_samples_16"}


def test_cli_writes_documented_json_and_markdown(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Heavily reduced run (3 frames of 64x48, hashed text embeddings, coarse GT). A missing field,
    NaN in the JSON, a missing baseline or a missing markdown section fails here."""
    out = tmp_path / "eval"
    rc = main(
        [
            "--scenes", "synthetic:seed=1,frames=3,width=64,height=48", "synthetic:seed=2,frames=2,width=64,height=48",
            "--text-encoder", "hash", "--gt-spacing", "0.15", "--out", str(out), "--exclude-background",
        ]
    )  # fmt: skip
    assert rc == 0
    results = json.loads((out / "results.json").read_text())  # strict JSON: NaN would not parse back as NaN
    assert set(results) == {"config", "scenes", "summary"}
    assert results["config"]["exclude_background"] is True
    assert [s["scene"] for s in results["scenes"]] == ["synthetic:seed=1", "synthetic:seed=2"]
    for scene in results["scenes"]:
        assert SCENE_FIELDS <= set(scene)
        assert set(scene["quality"]) == MAPS
        for q in scene["quality"].values():
            assert METRIC_FIELDS <= set(q["metrics"])
            assert "wall" not in q["metrics"]["classes_evaluated"]
            k = len(q["confusion"]["class_names"])
            assert len(q["confusion"]["counts"]) == k and all(
                len(r) == k + 1 for r in q["confusion"]["counts"]
            )
        assert GEOMETRY_FIELDS <= set(scene["geometry"])
        assert SPEED_FIELDS <= set(scene["speed"])
        assert scene["speed"]["frames"] == scene["speed"]["semantic_frames"] > 0
        speed = scene["speed"]  # every frame ends in one outcome: encoded, no gain, left out by --semantic-every
        assert speed["frames"] == speed["encoder_calls"] + speed["skipped_no_gain"] + speed["skipped_switch"]
        assert set(scene["memory"]) == STORED_MAPS and set(scene["query"]) == {"region_map", "point_features"}
        assert scene["ground_truth"]["accuracy_reference"] == "mesh"
        for r in scene["wrong_regions"]:  # the regions holding mislabelled surface, most first
            assert 0 < r["wrong"] <= r["points"] and sum(r["gt_classes"].values()) <= r["points"]
        wrong = [r["wrong"] for r in scene["wrong_regions"]]
        assert wrong == sorted(wrong, reverse=True)
    summary = results["summary"]
    assert set(summary["quality"]) == MAPS
    assert summary["speed"]["frames"] == 5 and summary["speed"]["raw_open3d_fps"] > 0
    assert {t["name"] for t in summary["targets"]} >= {"f_mIoU >= 0.9 (noise off)", "completeness >= 0.9"}
    md = (out / "results.md").read_text()
    for section in ("## Quality", "## Per class", "## Geometry", "## Speed", "## Baselines", "## Targets"):
        assert section in md
    if any(s["wrong_regions"] for s in results["scenes"]):
        assert "## Regions holding the most mislabelled surface" in md
    assert "**all (summed)**" in md and "per-point features" in md and "skipped (--semantic-every)" in md
    assert "f-mIoU" in capsys.readouterr().out


def test_cli_bad_scene_is_one_line_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A typo in --scenes or a ScanNet folder without its GT mesh ends with exit 2 and one line,
    and writes no results."""
    assert main(["--scenes", "synthetc:seed=1", "--out", str(tmp_path / "a")]) == 2
    assert "bad scene 'synthetc:seed=1'" in capsys.readouterr().err
    (tmp_path / "scene0000_00").mkdir()
    assert main(["--scenes", f"scannet:{tmp_path / 'scene0000_00'}", "--out", str(tmp_path / "b")]) == 2
    assert "vh_clean_2.labels.ply" in capsys.readouterr().err
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


@pytest.mark.slow
def test_small_noise_free_run_labels_the_scene(tmp_path: Path) -> None:
    """16 frames at 320x240, gt encoder with MiniLM, no noise. The thresholds are below the
    full-size targets (at 320x240 the encoder's 80x60 regions make boundaries coarse) but far above
    what a broken label mapping, axis flip or key mix-up gives (f-mIoU < 0.3). Geometry must be
    within a voxel and complete; the region map must be far smaller than per-point features."""
    out = tmp_path / "eval"
    rc = main(
        [
            "--scenes",
            "synthetic:seed=1",
            "--frames",
            "16",
            "--width",
            "320",
            "--height",
            "240",
            "--out",
            str(out),
        ]
    )
    assert rc == 0
    s = json.loads((out / "results.json").read_text())["summary"]
    m = s["quality"]["region_map"]["metrics"]
    assert m["f_mIoU"] > 0.7 and m["mAcc"] > 0.55
    assert s["geometry"]["accuracy_vox"] < 1.0 and s["geometry"]["completeness"] > 0.9
    assert s["memory_bytes"]["region_map"] * 5 < s["memory_bytes"]["point_features"]


def test_scannet_layout_scene_is_evaluated_with_nyu40_classes(tmp_path: Path) -> None:
    """A ScanNet export (written from a synthetic scene by the sources' writer) evaluates through
    the ScanNet reader and the labelled-PLY ground truth: classes are NYU40 names ("office chair"
    counted as chair), background exclusion removes wall/floor rows, and accuracy falls back to
    nearest GT points because that PLY has no faces."""
    from openfusion.sources.scannet_writer import write_scannet_layout
    from openfusion.sources.synthetic import SyntheticSource, SyntheticWorld

    scene = tmp_path / "scans" / "scene0001_00"
    src = SyntheticSource(SyntheticWorld(1), 4, 160, 120, frames_per_lap=4)
    write_scannet_layout(src, scene, ground_truth_spacing_m=0.1)
    out = tmp_path / "eval"
    rc = main(["--scenes", f"scannet:{scene}", "--frames", "4", "--text-encoder", "hash",
               "--exclude-background", "--out", str(out)])  # fmt: skip
    assert rc == 0
    s = json.loads((out / "results.json").read_text())["scenes"][0]
    assert s["scene"] == "scannet:scene0001_00" and s["speed"]["frames"] == 4
    assert "chair" in s["ground_truth"]["classes"] and "office chair" not in s["ground_truth"]["classes"]
    assert s["ground_truth"]["accuracy_reference"] == "points"
    evaluated = s["quality"]["region_map"]["metrics"]["classes_evaluated"]
    assert evaluated and not {"wall", "floor"} & set(evaluated)
