"""ScanNet export reader on a tiny scene written in the real layout (color at a larger size than
depth, inf poses, a missing depth file, 8-bit and wrong-size depth, a corrupt JPEG)."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from openfusion.sources import SkipFrame, open_source
from openfusion.sources.base import SourceError
from openfusion.sources.files import read_depth_u16
from openfusion.sources.scannet import LABEL_TSV_COLUMNS, ScanNetSource, majority_labels, read_label_tsv

DEPTH_W, DEPTH_H = 64, 48
COLOR_W, COLOR_H = 96, 72  # ScanNet color is larger than depth (1296x968 vs 640x480)
K_DEPTH = np.array([[57.7, 0, 31.5, 0], [0, 57.9, 23.6, 0], [0, 0, 1, 0], [0, 0, 0, 1]])


def _pose(i: int) -> np.ndarray:
    a = 0.1 * i
    T = np.eye(4)
    T[:3, :3] = [[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]
    T[:3, 3] = [0.5 * i, -0.25 * i, 1.5]
    return T


def _write_matrix(path: Path, M: np.ndarray) -> None:
    path.write_text("\n".join(" ".join(f"{v:.9f}" for v in row) for row in M) + "\n")


def _depth(i: int) -> np.ndarray:
    rng = np.random.default_rng(i)
    d = rng.integers(300, 65535, size=(DEPTH_H, DEPTH_W), dtype=np.uint16)
    d[0, 0] = 65535  # full 16-bit range must survive decoding
    d[0, 1] = 0
    return d


def _tsv(path: Path, rows: list[tuple[int, str, str, int]]) -> None:
    lines = ["\t".join(LABEL_TSV_COLUMNS)]
    for label_id, raw, cat, nyu in rows:
        values = {"id": str(label_id), "raw_category": raw, "category": cat, "count": "10", "nyu40id": str(nyu)}
        lines.append("\t".join(values.get(c, "") for c in LABEL_TSV_COLUMNS))
    path.write_text("\n".join(lines) + "\n")


def _instance_and_label() -> tuple[np.ndarray, np.ndarray]:
    """At color resolution: instance 3 in the left half (mostly label 40 'office chair', a strip
    of label 2), instance 7 in the right half (label 1 'wall'), a band of instance 0."""
    inst = np.zeros((COLOR_H, COLOR_W), dtype=np.uint8)
    label = np.zeros((COLOR_H, COLOR_W), dtype=np.uint16)
    inst[8:, : COLOR_W // 2] = 3
    inst[8:, COLOR_W // 2 :] = 7
    label[8:, : COLOR_W // 2] = 40
    label[8:12, : COLOR_W // 2] = 2
    label[8:, COLOR_W // 2 :] = 1
    return inst, label


@pytest.fixture
def scene(tmp_path: Path) -> Path:
    root = tmp_path / "scans" / "scene0000_00"
    for sub in ("color", "depth", "pose", "intrinsic", "instance-filt", "label-filt"):
        (root / sub).mkdir(parents=True)
    _write_matrix(root / "intrinsic" / "intrinsic_depth.txt", K_DEPTH)
    _write_matrix(root / "intrinsic" / "intrinsic_color.txt", K_DEPTH * 1.5)
    rng = np.random.default_rng(0)
    inst, label = _instance_and_label()
    for i in range(8):
        color = rng.integers(0, 255, size=(COLOR_H, COLOR_W, 3), dtype=np.uint8)
        Image.fromarray(color).save(root / "color" / f"{i}.jpg", quality=95)
        Image.fromarray(_depth(i)).save(root / "depth" / f"{i}.png")
        _write_matrix(root / "pose" / f"{i}.txt", _pose(i))
        Image.fromarray(inst).save(root / "instance-filt" / f"{i}.png")
        Image.fromarray(label).save(root / "label-filt" / f"{i}.png")
    # ScanNet marks tracking failures with -inf poses
    (root / "pose" / "1.txt").write_text("-inf -inf -inf -inf\n" * 4)
    (root / "pose" / "5.txt").write_text("nan nan nan nan\n" * 4)
    (root / "depth" / "2.png").unlink()
    Image.fromarray((_depth(3) >> 8).astype(np.uint8)).save(root / "depth" / "3.png")  # 8-bit depth
    Image.fromarray(np.zeros((DEPTH_H // 2, DEPTH_W // 2), np.uint16)).save(root / "depth" / "4.png")
    (root / "color" / "6.jpg").write_bytes(b"\xff\xd8\xff\xe0 this is not a jpeg")
    _tsv(tmp_path / "scannetv2-labels.combined.tsv", [(1, "wall", "wall", 1), (2, "chair", "chair", 5), (40, "office chair", "chair", 5)])
    return root


def test_reads_good_frames_and_counts_each_bad_one(scene: Path, caplog: pytest.LogCaptureFixture) -> None:
    """Bad input: inf and NaN poses, a missing depth file, 8-bit depth, wrong-size depth and a
    corrupt JPEG in one scene. Only the two good frames come out, each skip is counted under its
    reason, and each reason is logged once (two invalid poses, one warning)."""
    src = ScanNetSource(scene)
    with caplog.at_level(logging.WARNING, logger="openfusion.sources.base"):
        frames = list(src)
    assert [f.frame_id for f in frames] == [0, 7]
    assert src.stats.read == 8 and src.stats.yielded == 2
    assert src.stats.skipped == {
        "invalid_pose": 2,
        "missing_depth": 1,
        "depth_dtype": 1,
        "depth_size": 1,
        "unreadable_color": 1,
    }
    pose_warnings = [r for r in caplog.records if "invalid_pose" in r.getMessage()]
    assert len(pose_warnings) == 1 and "scene0000_00 frame 1" in pose_warnings[0].getMessage()
    for f in frames:
        f.validate()
        np.testing.assert_allclose(f.T_world_cam, _pose(f.frame_id), atol=1e-9)
        np.testing.assert_array_equal(f.depth, _depth(f.frame_id))
        assert f.depth_scale == 1000.0
        assert f.color.shape == (DEPTH_H, DEPTH_W, 3)
        assert f.stamp_ns == round(f.frame_id * 1e9 / 30)
        assert f.source == "scannet:scene0000_00"


def test_intrinsics_are_depth_intrinsics_at_depth_size(scene: Path) -> None:
    """Bad input avoided: using the color intrinsics (1.5x here) or the color size would misplace
    every depth pixel."""
    src = ScanNetSource(scene)
    K = src.intrinsics
    assert (K.width_px, K.height_px) == (DEPTH_W, DEPTH_H)
    np.testing.assert_allclose(K.K, K_DEPTH[:3, :3])


def test_instances_resized_nearest_and_named_by_majority_label(scene: Path) -> None:
    """Instance/label images at color resolution: resized to depth size without blending ids,
    each instance named by its majority label's tsv raw_category (the tsv two folders up)."""
    frame = next(iter(ScanNetSource(scene)))
    assert frame.instance is not None and frame.instance.dtype == np.int32
    assert frame.instance.shape == (DEPTH_H, DEPTH_W)
    assert set(np.unique(frame.instance)) == {0, 3, 7}
    assert frame.instance[-1, 0] == 3 and frame.instance[-1, -1] == 7 and frame.instance[0, 0] == 0
    assert frame.instance_categories == {3: "office chair", 7: "wall"}


def test_instances_without_tsv_are_named_by_label_id(scene: Path) -> None:
    """Missing label table: categories fall back to 'label_<id>' instead of failing."""
    (scene.parent.parent / "scannetv2-labels.combined.tsv").unlink()
    frame = next(iter(ScanNetSource(scene)))
    assert frame.instance_categories == {3: "label_40", 7: "label_1"}


def test_missing_instance_file_is_counted(scene: Path) -> None:
    """Bad input: the instance image of one good frame is missing -> that frame is skipped."""
    (scene / "instance-filt" / "7.png").unlink()
    src = ScanNetSource(scene)
    assert [f.frame_id for f in src] == [0]
    assert src.stats.skipped["missing_instance"] == 1


def test_not_a_scannet_folder(tmp_path: Path) -> None:
    """Bad input: a folder without color/depth/pose and one without intrinsics."""
    with pytest.raises(FileNotFoundError, match="color/, depth/, pose/"):
        ScanNetSource(tmp_path)
    for sub in ("color", "depth", "pose"):
        (tmp_path / sub).mkdir()
    with pytest.raises(FileNotFoundError, match="intrinsic_depth.txt"):
        ScanNetSource(tmp_path)
    with pytest.raises(SourceError, match="does not exist"):
        open_source(f"scannet:{tmp_path / 'nope'}")


def test_open_source_stride_and_max_frames(scene: Path) -> None:
    """open_source passes reader options; stride keeps every 2nd item, max_frames caps the output."""
    src = open_source(f"scannet:{scene}", stride=7)
    assert len(src) == 2 and [f.frame_id for f in src] == [0, 7]
    src = open_source(f"scannet:{scene}", max_frames=1)
    assert [f.frame_id for f in src] == [0]


def test_majority_labels_ignores_unannotated() -> None:
    inst = np.array([[1, 1, 1, 2], [1, 0, 2, 2]])
    label = np.array([[0, 0, 5, 0], [0, 9, 0, 0]])
    # instance 1: label 0 x3 and 5 x1 -> 5 (0 only when nothing else); instance 2: only 0
    assert majority_labels(inst, label) == {1: 5, 2: 0}


def test_label_tsv_errors(tmp_path: Path) -> None:
    """Bad input: a tsv without the id/raw_category columns, and a non-integer id."""
    p = tmp_path / "x.tsv"
    p.write_text("foo\tbar\n1\t2\n")
    with pytest.raises(ValueError, match="raw_category"):
        read_label_tsv(p)
    p.write_text("id\traw_category\nabc\tchair\n")
    with pytest.raises(ValueError, match="not an integer"):
        read_label_tsv(p)


def test_16bit_png_decodes_full_range(tmp_path: Path) -> None:
    """Pillow mode I;16 must give the exact uint16 values, including >= 32768."""
    d = np.array([[0, 1, 32767, 32768], [40000, 65534, 65535, 12345]], dtype=np.uint16)
    Image.fromarray(d).save(tmp_path / "d.png")
    out = read_depth_u16(tmp_path / "d.png")
    assert out.dtype == np.uint16
    np.testing.assert_array_equal(out, d)
    with pytest.raises(SkipFrame, match="depth_size"):
        read_depth_u16(tmp_path / "d.png", size=(2, 4))


def test_fast_color_decode_matches_full_resize(tmp_path: Path) -> None:
    """The reduced-scale JPEG decode (+ nearest for the last 1.2 %) of a real-size ScanNet color
    image stays within a few levels of decoding at full size and resizing bilinearly."""
    from openfusion.sources.files import read_color

    yy, xx = np.mgrid[0:968, 0:1296]
    img = np.stack([(xx // 3) % 256, (yy // 2) % 256, ((xx + yy) // 8) % 256], axis=-1).astype(np.uint8)
    Image.fromarray(img).save(tmp_path / "0.jpg", quality=95)
    fast = read_color(tmp_path / "0.jpg", size=(640, 480))
    with Image.open(tmp_path / "0.jpg") as im:
        ref = np.asarray(im.convert("RGB").resize((640, 480), Image.Resampling.BILINEAR))
    assert fast.shape == (480, 640, 3)
    assert np.abs(fast.astype(int) - ref.astype(int)).mean() < 3.0
