"""Ground-truth loaders: ScanNet labelled PLY + label table, synthetic instance -> class mapping."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from openfusion.eval.classes import NYU40_CLASSES, SYNTHETIC_CLASSES, class_for_category
from openfusion.eval.ground_truth import (
    ground_truth_from_instances,
    load_scannet_ground_truth,
    read_scannet_label_table,
)
from openfusion.io.ply import PlyError, read_ply, read_ply_vertices, write_ply_vertices


def _write_scannet_like_ply(path: Path, xyz: np.ndarray, label: np.ndarray, *, truncate: int = 0) -> None:
    """Byte layout of ScanNet's *_vh_clean_2.labels.ply, written by hand (not by our writer)."""
    n = len(xyz)
    faces = np.array([[0, 1, 2]] if n >= 3 else [], dtype=np.int32).reshape(-1, 3)
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment VCGLIB generated\n"
        f"element vertex {n}\nproperty float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nproperty uchar alpha\n"
        "property ushort label\n"
        f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    vdt = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("r", "u1"), ("g", "u1"), ("b", "u1"),
                    ("a", "u1"), ("label", "<u2")])  # fmt: skip
    v = np.zeros(n, dtype=vdt)
    v["x"], v["y"], v["z"] = xyz.T
    v["r"] = 200
    v["label"] = label
    fdt = np.dtype([("n", "u1"), ("i", "<i4", (3,))])
    f = np.zeros(len(faces), dtype=fdt)
    f["n"], f["i"] = 3, faces
    data = header.encode() + v.tobytes() + f.tobytes()
    path.write_bytes(data[: len(data) - truncate] if truncate else data)


def _write_tsv(path: Path) -> None:
    rows = [
        "id\traw_category\tcategory\tcount\tnyu40id\teigen13id\tnyu40class\teigen13class",
        "1\twall\twall\t8277\t1\t12\twall\tWall",
        "2\tchair\tchair\t4646\t5\t4\tchair\tChair",
        "3\toffice chair\tchair\t595\t5\t4\tchair\tChair",
        "4\ttable\ttable\t1170\t7\t10\ttable\tTable",
        "5\tlamp\tlamp\t419\t35\t13\tlamp\tObjects",
    ]
    path.write_text("\n".join(rows) + "\n")


def test_scannet_labels_ply_and_tsv(tmp_path: Path) -> None:
    """Vertex positions and NYU40 labels survive; label 0 becomes -1; the class list is exactly
    the classes present in the mesh (lamp is in the table but not in the mesh)."""
    scene = tmp_path / "scans" / "scene0000_00"
    scene.mkdir(parents=True)
    xyz = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]], dtype=np.float32)
    label = np.array([1, 5, 5, 0, 7], dtype=np.uint16)
    _write_scannet_like_ply(scene / "scene0000_00_vh_clean_2.labels.ply", xyz, label)
    _write_tsv(tmp_path / "scannetv2-labels.combined.tsv")  # two folders up, as in the release

    gt = load_scannet_ground_truth(scene)
    assert gt.has_mesh and gt.mesh_triangles.tolist() == [[0, 1, 2]]
    assert gt.class_names == ("wall", "chair", "table")
    assert gt.labels.tolist() == [0, 1, 1, -1, 2]
    np.testing.assert_array_equal(gt.points, xyz)
    assert gt.class_counts() == {"wall": 1, "chair": 2, "table": 1}


def test_scannet_without_tsv_uses_builtin_nyu40_names(tmp_path: Path) -> None:
    """Without the label table the fixed NYU40 list names the ids (id 22 = ceiling)."""
    ply = tmp_path / "x_vh_clean_2.labels.ply"
    _write_scannet_like_ply(ply, np.zeros((2, 3), np.float32), np.array([22, 40], np.uint16))
    gt = load_scannet_ground_truth(ply)
    assert gt.class_names == ("ceiling", "otherprop")
    assert NYU40_CLASSES[21] == "ceiling"


def test_truncated_or_unlabelled_ply_is_refused(tmp_path: Path) -> None:
    """A download cut short or a mesh without the label property must say so, naming the file."""
    ply = tmp_path / "s_vh_clean_2.labels.ply"
    _write_scannet_like_ply(ply, np.zeros((100, 3), np.float32), np.ones(100, np.uint16), truncate=900)
    with pytest.raises(ValueError, match="truncated"):
        load_scannet_ground_truth(ply)
    plain = tmp_path / "p_vh_clean_2.labels.ply"
    write_ply_vertices(
        plain, {"x": np.zeros(3, np.float32), "y": np.zeros(3, np.float32), "z": np.zeros(3, np.float32)}
    )
    with pytest.raises(ValueError, match="label"):
        load_scannet_ground_truth(plain)
    not_ply = tmp_path / "n.ply"
    not_ply.write_bytes(b"solid cube\n")
    with pytest.raises(PlyError, match="not a PLY"):
        read_ply_vertices(not_ply)
    with pytest.raises(ValueError, match="expected one"):
        load_scannet_ground_truth(tmp_path / "missing_scene_dir_is_empty")


def test_ply_writer_reader_roundtrip_and_ascii(tmp_path: Path) -> None:
    """Our writer's output is read back bit-exact; ASCII PLY is read too."""
    props = {"x": np.arange(4, dtype=np.float32), "y": np.ones(4, np.float32), "z": np.zeros(4, np.float32),
             "label": np.array([3, 2, 1, 0], np.uint16)}  # fmt: skip
    write_ply_vertices(tmp_path / "a.ply", props, faces=np.array([[0, 1, 2]]))
    back = read_ply_vertices(tmp_path / "a.ply")
    assert read_ply(tmp_path / "a.ply").triangles.tolist() == [[0, 1, 2]]
    for k, v in props.items():
        assert back[k].dtype == v.dtype and np.array_equal(back[k], v)
    (tmp_path / "b.ply").write_text(
        "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\n"
        "property ushort label\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
        "0 0 0 3\n1.5 2 3 7\n3 0 1 1\n"
    )
    b = read_ply_vertices(tmp_path / "b.ply")
    assert b["x"].tolist() == [0.0, 1.5] and b["label"].tolist() == [3, 7]
    assert read_ply(tmp_path / "b.ply").triangles.tolist() == [[0, 1, 1]]
    # A face index beyond the vertex count is corrupt, not silently accepted.
    (tmp_path / "c.ply").write_text(
        "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\n"
        "element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n3 0 0 5\n"
    )
    with pytest.raises(PlyError, match="out of range"):
        read_ply(tmp_path / "c.ply")


def test_label_table_with_conflicting_names_is_refused(tmp_path: Path) -> None:
    """One nyu40id with two names means a corrupt table; silently picking one would mislabel."""
    tsv = tmp_path / "t.tsv"
    tsv.write_text("id\tnyu40id\tnyu40class\n1\t5\tchair\n2\t5\tsofa\n")
    with pytest.raises(ValueError, match="named both"):
        read_scannet_label_table(tsv)
    (tmp_path / "u.tsv").write_text("id\tcategory\n1\tchair\n")
    with pytest.raises(ValueError, match="missing column"):
        read_scannet_label_table(tmp_path / "u.tsv")


def test_synthetic_instances_map_raw_categories_to_classes() -> None:
    """Two chair kinds become one class; instance 0 and instances without a category are -1."""
    points = np.zeros((6, 3), np.float32)
    inst = np.array([1, 2, 3, 0, 9, 1])
    cats = {1: "office chair", 2: "chair", 3: "sofa"}
    gt = ground_truth_from_instances(points, inst, cats, source="test")
    assert gt.class_names == ("chair", "sofa")
    assert gt.labels.tolist() == [0, 0, 1, -1, -1, 0]
    assert class_for_category("Office Chair") == "chair"
    assert class_for_category("toaster") == "toaster"


def test_every_synthetic_category_has_an_evaluation_class() -> None:
    """A category added to the synthetic world without a class would silently become its own
    class and change the query list; this catches it."""
    from openfusion.sources.synthetic import CATEGORIES

    assert {class_for_category(c) for c in CATEGORIES} == set(SYNTHETIC_CLASSES)
