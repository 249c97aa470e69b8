"""Geometry metrics on analytic point sets with known distances."""

from __future__ import annotations

import numpy as np
import pytest

from openfusion.eval.geometry import ObservedSurface, geometry_metrics
from openfusion.frame import CameraIntrinsics

VOXEL_M = 0.01


def _plane(n: int = 101, spacing: float = 0.01) -> np.ndarray:
    """Grid on z = 0 over [0, 1]^2 (n x n points)."""
    g = np.arange(n) * spacing
    x, y = np.meshgrid(g, g, indexing="ij")
    return np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)


def test_accuracy_is_the_offset_of_a_shifted_copy() -> None:
    """A copy lifted 5 mm off the GT plane is 5 mm (half a voxel) off everywhere."""
    gt = _plane()
    recon = gt + [0.0, 0.0, 0.005]
    g = geometry_metrics(recon, gt, voxel_size_m=VOXEL_M)
    assert g.accuracy_m == pytest.approx(0.005, abs=1e-9)
    assert g.accuracy_vox == pytest.approx(0.5, abs=1e-6)
    assert g.accuracy_median_m == pytest.approx(0.005, abs=1e-9)
    assert g.completeness == 1.0


def test_completeness_counts_gt_points_within_two_voxels() -> None:
    """Reconstruction covers columns x <= 0.49 (lifted 5 mm): GT columns up to x = 0.50 are within
    2 voxels (sqrt(0.01^2 + 0.005^2) = 11 mm), x = 0.51 is 21 mm away -> 51 of 101 columns."""
    gt = _plane()
    recon = gt[gt[:, 0] < 0.495] + [0.0, 0.0, 0.005]
    g = geometry_metrics(recon, gt, voxel_size_m=VOXEL_M, completeness_voxels=2.0)
    assert g.completeness == pytest.approx(51 / 101)
    assert g.completeness_threshold_m == pytest.approx(0.02)
    # Restricting to observed GT points (only the covered half) makes it complete.
    observed = gt[:, 0] < 0.495
    g2 = geometry_metrics(recon, gt, voxel_size_m=VOXEL_M, observed_mask=observed)
    assert g2.completeness == 1.0 and g2.num_gt_observed == int(observed.sum())


def test_outliers_raise_accuracy_distance() -> None:
    """One reconstructed point 1 m above the plane among 99 exact ones: mean 1 cm, median 0."""
    gt = _plane(11, 0.1)
    recon = np.vstack([gt[:99], [[0.5, 0.5, 1.0]]])
    g = geometry_metrics(recon, gt, voxel_size_m=VOXEL_M)
    assert g.accuracy_m == pytest.approx(0.01)
    assert g.accuracy_median_m == 0.0


def _looking_down(height_m: float) -> np.ndarray:
    """Camera above (0.5, 0.5) looking down -z: OpenCV x = world x, y = world -y, z = world -z."""
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])
    T[:3, 3] = [0.5, 0.5, height_m]
    return T


def test_observed_surface_uses_fov_and_depth_test() -> None:
    """Camera 1 m above the plane sees all of it; missing depth (left image half) and an
    occluder (depth 0.5 m in the top-right quarter) hide exactly those points."""
    gt = _plane()
    K = CameraIntrinsics(100, 100, 100.0, 100.0, 49.5, 49.5)  # 1 px = 1 cm at 1 m
    depth = np.ones((100, 100), np.float32)
    obs = ObservedSurface(gt, depth_tolerance_m=0.02, depth_min_m=0.1, depth_max_m=3.0)
    seen = obs.add_view(depth, K, _looking_down(1.0))
    # u = 100 x - 0.5 and v = 99.5 - 100 y: the column x = 1 and the row y = 0 round to pixel 100,
    # outside the image; every other point is seen.
    x, y = gt[:, 0], gt[:, 1]
    in_image = (x < 0.995) & (y > 0.005)
    assert np.array_equal(obs.mask, in_image) and seen == int(in_image.sum())

    depth2 = np.ones((100, 100), np.float32)
    depth2[:, :50] = 0.0  # no measurement for u < 50, i.e. x < 0.495
    depth2[:50, 50:] = 0.5  # something in front for v < 50, i.e. y > 0.495
    obs2 = ObservedSurface(gt, depth_tolerance_m=0.02, depth_min_m=0.1, depth_max_m=3.0)
    obs2.add_view(depth2, K, _looking_down(1.0))
    expected = (x > 0.5) & (y < 0.5) & in_image
    interior = (np.abs(x - 0.5) > 0.015) & (np.abs(y - 0.5) > 0.015)  # stay off the pixel seams
    assert np.array_equal(obs2.mask[interior], expected[interior])

    # A camera beyond depth_max sees nothing.
    far = ObservedSurface(gt, depth_tolerance_m=0.02, depth_max_m=3.0)
    assert far.add_view(np.full((100, 100), 5.0, np.float32), K, _looking_down(5.0)) == 0


def test_bad_inputs_are_refused() -> None:
    """Wrong shapes, NaN points, empty GT and mismatched masks name the problem."""
    gt = _plane(5, 0.1)
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        geometry_metrics(np.zeros((4, 2)), gt, voxel_size_m=VOXEL_M)
    with pytest.raises(ValueError, match="NaN"):
        geometry_metrics(np.full((1, 3), np.nan), gt, voxel_size_m=VOXEL_M)
    with pytest.raises(ValueError, match="empty"):
        geometry_metrics(gt, np.zeros((0, 3)), voxel_size_m=VOXEL_M)
    with pytest.raises(ValueError, match="observed_mask"):
        geometry_metrics(gt, gt, voxel_size_m=VOXEL_M, observed_mask=np.ones(3, bool))
    obs = ObservedSurface(gt, depth_tolerance_m=0.02)
    with pytest.raises(ValueError, match="intrinsics are for"):
        obs.add_view(np.ones((10, 10), np.float32), CameraIntrinsics(20, 10, 10, 10, 10, 5), np.eye(4))
    empty = geometry_metrics(np.zeros((0, 3)), gt, voxel_size_m=VOXEL_M)
    assert empty.completeness == 0.0 and np.isnan(empty.accuracy_m)


def test_mesh_distances_are_exact_point_to_triangle_distances() -> None:
    """Unit square at z = 0 as two triangles: a point above the interior is its height away, a
    point beside an edge is its Euclidean distance to that edge; accuracy can use them."""
    from openfusion.eval.geometry import mesh_distances

    verts = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    tris = np.array([[0, 1, 2], [0, 2, 3]])
    pts = np.array([[0.5, 0.5, 0.03], [0.2, 0.7, -0.01], [1.3, 0.5, 0.4]])
    d = mesh_distances(pts, verts, tris)
    np.testing.assert_allclose(d, [0.03, 0.01, 0.5], atol=1e-6)
    g = geometry_metrics(pts, verts, voxel_size_m=VOXEL_M, accuracy_distances_m=d)
    assert g.accuracy_m == pytest.approx(0.18, abs=1e-6)
    with pytest.raises(ValueError, match="one entry per reconstructed point"):
        geometry_metrics(pts, verts, voxel_size_m=VOXEL_M, accuracy_distances_m=d[:2])
    with pytest.raises(ValueError, match="out of range"):
        mesh_distances(pts, verts, np.array([[0, 1, 7]]))
