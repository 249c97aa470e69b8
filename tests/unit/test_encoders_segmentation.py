"""Graph-segmentation proposals and crop preprocessing used by clip-regions and onnx crop embedders."""

from __future__ import annotations

import numpy as np
import pytest

from openfusion.encoders import EncoderError
from openfusion.encoders.crops import CLIP_MEAN, CropSpec, preprocess_image, region_crops
from openfusion.encoders.graph_segmentation import GraphSegmentationProposer, felzenszwalb_segment
from openfusion.encoders.masks import area_downsample_labels
from openfusion.testing.images import PixelRect, grid_boxes, make_box_frame


def _noisy(frame, *, sigma: float, shade: float, seed: int = 0):
    """Add a vertical shading ramp and Gaussian sensor noise to the frame's color."""
    rng = np.random.default_rng(seed)
    h = frame.color.shape[0]
    ramp = (np.arange(h) / h * shade)[:, None, None]
    frame.color = np.clip(frame.color + ramp + rng.normal(0, sigma, frame.color.shape), 0, 255).astype(np.uint8)
    return frame


def test_proposals_follow_objects_despite_shading_and_noise():
    """12 boxes on a shaded, noisy background: one proposal per box (IoU > 0.85) plus background,
    no over-segmentation into hundreds of fragments, disjoint binary masks."""
    frame = _noisy(make_box_frame(grid_boxes(height_px=480, width_px=640, rows=3, cols=4, categories=["x"], gap_px=10)),
                   sigma=4.0, shade=30.0)
    masks = GraphSegmentationProposer().propose(frame, (120, 160))
    assert masks.shape == (13, 120, 160)
    assert set(np.unique(masks)) <= {0.0, 1.0}
    np.testing.assert_array_equal(masks.sum(axis=0), 1.0)  # a partition of the image
    gt = area_downsample_labels(frame.instance, np.arange(1, 13), (120, 160)) >= 0.5
    for g in gt:
        iou = (g & (masks > 0)).sum(axis=(1, 2)) / (g | (masks > 0)).sum(axis=(1, 2))
        assert iou.max() > 0.85


def test_depth_edges_separate_same_colored_objects():
    """A grey box in front of a grey wall is invisible to color; the depth jump must separate it."""
    box = PixelRect(1, "box", 40, 60, 120, 160, rgb=(90, 90, 90), depth_m=1.0)
    frame = make_box_frame([box], height_px=160, width_px=240, background_rgb=(90, 90, 90), background_depth_m=3.0)
    masks = GraphSegmentationProposer(min_region_px=4).propose(frame, (40, 60))
    assert masks.shape[0] == 2
    inside = area_downsample_labels(frame.instance, np.array([1]), (40, 60))[0] >= 0.5
    best = max(((m > 0) & inside).sum() / ((m > 0) | inside).sum() for m in masks)
    assert best > 0.9
    no_depth = GraphSegmentationProposer(depth_weight=0.0, min_region_px=4).propose(frame, (40, 60))
    assert no_depth.shape[0] == 1


def test_max_regions_and_textured_input_stay_bounded():
    """Pure noise (worst case for graph segmentation) still returns at most max_regions masks."""
    frame = make_box_frame([], height_px=120, width_px=160)
    frame.color = np.random.default_rng(0).integers(0, 256, (120, 160, 3), dtype=np.uint8)
    masks = GraphSegmentationProposer(max_regions=10).propose(frame, (120, 160))
    assert 1 <= masks.shape[0] <= 10
    with pytest.raises(ValueError, match="max_regions"):
        GraphSegmentationProposer(max_regions=0)
    with pytest.raises(EncoderError, match="depth"):
        felzenszwalb_segment(np.zeros((4, 4, 3)), np.zeros((3, 3)))


def test_region_crops_mask_out_the_background():
    """A crop keeps the region's pixels and paints everything else with the mean color (-> 0 after
    normalisation), so the embedder sees the object, not its neighbours."""
    color = np.zeros((64, 64, 3), np.uint8)
    color[:, :] = (255, 0, 0)
    mask = np.zeros((1, 16, 16), np.float32)
    mask[0, 4:12, 4:12] = 1.0  # pixels 16..48
    spec = CropSpec(size=32, padding=0.5)
    crops, kept = region_crops(color, mask, spec)
    assert crops.shape == (1, 3, 32, 32) and kept.tolist() == [0]
    centre = crops[0, :, 16, 16]
    corner = crops[0, :, 0, 0]
    np.testing.assert_allclose(corner, 0.0, atol=0.02)  # background -> mean color -> 0
    assert centre[0] > 1.5 and centre[1] < -1.5  # red stays red
    empty = np.zeros((2, 16, 16), np.float32)
    empty[1] = mask[0]
    crops, kept = region_crops(color, empty, spec)
    assert kept.tolist() == [1] and crops.shape[0] == 1


def test_preprocess_image_center_crops_and_normalises():
    """Whole-image preprocessing: shorter side to S, centre crop, CLIP mean/std (mean color -> 0)."""
    rgb = np.empty((60, 100, 3), np.uint8)
    rgb[:] = [int(round(255 * m)) for m in CLIP_MEAN]
    x = preprocess_image(rgb, CropSpec(size=24))
    assert x.shape == (1, 3, 24, 24) and x.dtype == np.float32
    np.testing.assert_allclose(x, 0.0, atol=0.01)
    with pytest.raises(EncoderError, match="uint8"):
        preprocess_image(rgb.astype(np.float32), CropSpec())
