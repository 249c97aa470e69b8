"""Baselines of the evaluation (per-point features, 16 samples per block) and scene-spec parsing."""

from __future__ import annotations

import numpy as np
import pytest

from openfusion.eval.baselines import SAMPLE_BYTES, block_sampled_keys, fuse_point_features, record_frame
from openfusion.eval.protocol import classify_embeddings, labels_from_region_keys
from openfusion.eval.scenes import parse_scene_specs
from openfusion.frame import CameraIntrinsics


def _plane(n: int = 50, spacing: float = 0.02) -> np.ndarray:
    g = (np.arange(n) + 0.5) * spacing
    x, y = np.meshgrid(g, g, indexing="ij")
    return np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)


def _down(height_m: float = 1.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])
    T[:3, 3] = [0.5, 0.5, height_m]
    return T


def _unit(d: int, i: int) -> np.ndarray:
    e = np.zeros(d, np.float32)
    e[i] = 1.0
    return e


def test_point_features_take_the_region_that_covered_each_point() -> None:
    """Camera 1 m above a 1 m plane; region 0 covers the left image half, region 1 the right.
    Points must carry the embedding of the region over them; points hidden by an occluder (depth
    test) or never covered stay unlabelled. A wrong projection or axis flip would swap halves."""
    pts = _plane()
    K = CameraIntrinsics(100, 100, 100.0, 100.0, 49.5, 49.5)
    conf = np.zeros((2, 25, 25), np.float32)  # encoder output at 1/4 resolution
    conf[0, :, :12] = 1.0
    conf[1, :, 13:] = 0.8  # column 12 (the seam) is covered by no region
    emb = np.stack([_unit(8, 0), _unit(8, 1)])
    depth = np.ones((100, 100), np.float32)
    depth[:20, :] = 0.4  # an occluder over the top rows (y > 0.8) hides the plane there
    rec = record_frame(conf, emb, depth_m=depth, intrinsics=K, T_world_cam=_down())
    assert rec.region_index.shape == (25, 25) and rec.intrinsics.width_px == 25

    pf = fuse_point_features(pts, [rec, rec], depth_tolerance_m=0.04)
    labels = pf.classify(np.stack([_unit(8, 0), _unit(8, 1)]))
    x, y = pts[:, 0], pts[:, 1]
    visible = y < 0.79
    assert np.all(labels[visible & (x < 0.47)] == 0)
    assert np.all(labels[visible & (x > 0.53)] == 1)
    assert np.all(labels[y > 0.81] == -1)
    assert pf.weights[visible & (x > 0.53)].min() == pytest.approx(1.6, rel=1e-3)  # 2 frames x conf 0.8
    assert pf.nbytes == len(pts) * (8 * 4 + 4)


def test_point_features_refuse_empty_or_inconsistent_records() -> None:
    """No frames or a changing embedding dimension are caller bugs, reported as such."""
    pts = _plane(4)
    with pytest.raises(ValueError, match="no frames"):
        fuse_point_features(pts, [], depth_tolerance_m=0.04)
    K = CameraIntrinsics(8, 8, 8.0, 8.0, 3.5, 3.5)
    a = record_frame(np.ones((1, 2, 2), np.float32), _unit(4, 0)[None], depth_m=np.ones((8, 8), np.float32),
                     intrinsics=K, T_world_cam=_down())  # fmt: skip
    b = record_frame(np.ones((1, 2, 2), np.float32), _unit(5, 0)[None], depth_m=np.ones((8, 8), np.float32),
                     intrinsics=K, T_world_cam=_down())  # fmt: skip
    with pytest.raises(ValueError, match="dimension changed"):
        fuse_point_features(pts, [a, b], depth_tolerance_m=0.04)
    with pytest.raises(ValueError, match="conf_maps"):
        record_frame(np.ones((2, 2, 2), np.float32), _unit(4, 0)[None], depth_m=np.ones((8, 8), np.float32),
                     intrinsics=K, T_world_cam=_down())  # fmt: skip


def test_block_sampling_keeps_at_most_16_per_block_and_labels_by_nearest() -> None:
    """A 16x16 grid at 1 cm = 4 blocks of 8^3 voxels with 64 points each; keys differ per half.
    16 samples per block keep 64 points (memory 64 x 20 bytes) and most points keep their key;
    with 64 samples per block every point is kept and the keys are exact."""
    g = (np.arange(16) + 0.5) * 0.01
    x, y = np.meshgrid(g, g, indexing="ij")
    pts = np.stack([x.ravel(), y.ravel(), np.full(x.size, 0.005)], axis=1)
    keys = np.where(pts[:, 0] < 0.08, 1, 2)
    keys[:5] = -1  # unkeyed points are never sampled but still get a key from their neighbours
    bs = block_sampled_keys(pts, keys, voxel_size_m=0.01, samples_per_block=16, seed=3)
    assert bs.num_blocks == 4 and bs.num_samples == 64 and bs.nbytes == 64 * SAMPLE_BYTES
    assert np.all(bs.keys >= 1)
    keyed = keys >= 0
    assert np.mean(bs.keys[keyed] == keys[keyed]) > 0.8
    exact = block_sampled_keys(pts, keys, voxel_size_m=0.01, samples_per_block=64)
    assert np.array_equal(exact.keys[keyed], keys[keyed])
    with pytest.raises(ValueError, match="one entry per point"):
        block_sampled_keys(pts, keys[:3], voxel_size_m=0.01)


def test_region_labels_follow_keys_through_the_dictionary() -> None:
    """Point keys -> region class via the dictionary; unknown keys and -1 stay unlabelled;
    excluded classes are never predicted (ConceptGraphs sets their scores to -inf)."""
    region_keys = np.array([10, 3, 7])
    region_emb = np.stack([_unit(4, 0), _unit(4, 1), _unit(4, 2)])
    classes = np.stack([_unit(4, 0), _unit(4, 1), _unit(4, 2)])
    allowed = np.array([True, True, False])
    region_cls = classify_embeddings(region_emb, classes, allowed=allowed)
    assert region_cls[:2].tolist() == [0, 1] and region_cls[2] != 2
    labels = labels_from_region_keys(np.array([3, 10, -1, 99, 7]), region_keys, region_cls)
    assert labels[:4].tolist() == [1, 0, -1, -1] and labels[4] in (0, 1)
    with pytest.raises(ValueError, match="every class is excluded"):
        classify_embeddings(region_emb, classes, allowed=np.zeros(3, bool))


def test_scene_specs_parse_and_refuse_bad_items() -> None:
    """The documented forms parse; typos fail with the offending item named."""
    specs = parse_scene_specs(["synthetic:seed=1,synthetic:seed=2", "scannet:/data/scene0000_00"])
    assert [s.name for s in specs] == ["synthetic:seed=1", "synthetic:seed=2", "scannet:scene0000_00"]
    one = parse_scene_specs(["synthetic:seed=4,frames=12,width=64"])
    assert one[0].seed == 4 and one[0].options == {"frames": "12", "width": "64"}
    assert parse_scene_specs(["synthetic"])[0].seed == 0
    for bad, match in (
        (["replica:/x"], "bad scene"),
        (["synthetic:seed=x"], "bad synthetic scene options"),
        (["synthetic:sede=1"], "unknown synthetic scene option"),
        (["synthetic:seed=1,synthetic:seed=1"], "given twice"),
        (["scannet:"], "needs a path"),
        ([""], "no scenes"),
    ):
        with pytest.raises(ValueError, match=match):
            parse_scene_specs(bad)
