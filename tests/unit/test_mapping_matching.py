"""Soft-IoU matching, Jonker-Volgenant assignment and the planned update (no volume needed)."""

from __future__ import annotations

import numpy as np
import pytest

from openfusion.mapping import (
    EmbeddingSpaceError,
    RegionDictionary,
    RenderedView,
    match_regions,
    plan_update,
    region_conf_maps,
    soft_iou_matrix,
)
from openfusion.mapping.mask_edges import depth_cut_spill, mask_edge_weights
from openfusion.mapping.params import MatchParams
from openfusion.testing.analytic_scene import SimpleObservation

H, W = 30, 40


def rendered_from(key_map: np.ndarray, conf_map: np.ndarray) -> RenderedView:
    return RenderedView(
        key_map.astype(np.int32), conf_map.astype(np.float32), np.ones(key_map.shape, np.float32)
    )


def unit(v: np.ndarray) -> np.ndarray:
    return (v / np.linalg.norm(v)).astype(np.float32)


def test_fast_soft_iou_equals_dense_definition() -> None:
    """The one-pass soft IoU over disjoint rendered regions equals sum(min)/sum(max) computed densely:
    against the rendered confidences by default, against the rendered key masks on request."""
    rng = np.random.default_rng(1)
    key_map = rng.integers(-1, 5, size=(H, W))
    conf_map = rng.uniform(0.0, 1.0, size=(H, W))
    rendered = rendered_from(key_map, conf_map)
    frame = rng.uniform(0.0, 1.0, size=(6, H, W)).astype(np.float32) * (rng.uniform(size=(6, H, W)) > 0.5)
    keys, maps = region_conf_maps(rendered)
    weighted = match_regions(frame, rendered, min_iou=0.0)
    np.testing.assert_array_equal(weighted.rendered_keys, keys)
    np.testing.assert_allclose(weighted.iou, soft_iou_matrix(frame, maps), atol=1e-5)
    masks = match_regions(frame, rendered, min_iou=0.0, rendered_conf_weighted=False)
    np.testing.assert_array_equal(masks.rendered_keys, keys)
    np.testing.assert_allclose(masks.iou, soft_iou_matrix(frame, (maps > 0).astype(np.float32)), atol=1e-5)


def test_match_against_rendered_masks_on_request() -> None:
    """A key rendered at confidence 0.25 and a frame region covering it exactly: soft IoU 0.25 with
    the rendered confidences (default), 1 against the key's mask (``rendered_conf_weighted=False``).
    Pixels whose key has no confidence left (0) are not part of the key's mask."""
    key_map = np.full((H, W), -1)
    key_map[5:15, 5:15] = 3
    conf = np.where(key_map >= 0, 0.25, 0.0)
    frame = (key_map == 3).astype(np.float32)[None]
    weighted = match_regions(frame, rendered_from(key_map, conf), min_iou=0.3)
    np.testing.assert_allclose(weighted.iou, [[0.25]], atol=1e-6)
    assert weighted.pairs == []
    result = match_regions(frame, rendered_from(key_map, conf), min_iou=0.3, rendered_conf_weighted=False)
    np.testing.assert_allclose(result.iou, [[1.0]], atol=1e-6)
    assert result.pairs == [(0, 3)]
    conf[5:15, 5:10] = 0.0  # half of the key has no confidence left
    half = match_regions(frame, rendered_from(key_map, conf), min_iou=0.0, rendered_conf_weighted=False)
    np.testing.assert_allclose(half.iou, [[0.5]], atol=1e-6)


def test_region_conf_maps_split_the_rendered_view() -> None:
    """One map per key in view, confidence where that key is rendered and 0 elsewhere."""
    key_map = np.full((H, W), -1)
    key_map[:10] = 4
    key_map[20:] = 9
    conf = np.full((H, W), 0.7)
    keys, maps = region_conf_maps(rendered_from(key_map, conf))
    np.testing.assert_array_equal(keys, [4, 9])
    assert maps.shape == (2, H, W)
    np.testing.assert_allclose(maps[0][:10], 0.7)
    assert maps[0][10:].sum() == 0 and maps[1][:20].sum() == 0


@pytest.mark.parametrize(("overlap", "matched"), [(0.09, False), (0.11, True)])
def test_min_iou_threshold(overlap: float, matched: bool) -> None:
    """A pair with soft IoU 0.09 is dropped (the region becomes new), 0.11 is kept.

    The frame map equals ``overlap`` on exactly the rendered region (rendered conf 1), so its soft
    IoU is sum(min)/sum(max) = overlap exactly."""
    key_map = np.full((H, W), -1)
    key_map[5:15, 5:15] = 3
    rendered = rendered_from(key_map, np.where(key_map >= 0, 1.0, 0.0))
    frame = np.zeros((1, H, W), np.float32)
    frame[0][key_map == 3] = overlap
    result = match_regions(frame, rendered, min_iou=0.10)
    np.testing.assert_allclose(result.iou[0, 0], overlap, atol=1e-6)
    assert (result.pairs == [(0, 3)]) is matched


def test_assignment_is_global_not_greedy() -> None:
    """Jonker-Volgenant maximises the total IoU: region 0 overlaps A best, but giving A to region 1
    and B to region 0 is better overall (a greedy matcher would leave region 1 unmatched)."""
    key_map = np.full((H, W), -1)
    key_map[:, :20] = 1  # A
    key_map[:, 20:30] = 2  # B
    rendered = rendered_from(key_map, (key_map >= 0).astype(np.float32))
    frame = np.zeros((2, H, W), np.float32)
    frame[0][:, 5:30] = 1.0  # covers half of A and all of B
    frame[1][:, :20] = 1.0  # exactly A
    result = match_regions(frame, rendered, min_iou=0.1)
    assert sorted(result.pairs) == [(0, 2), (1, 1)]


def test_match_rejects_bad_frame_maps() -> None:
    """Wrong map size or values outside [0, 1] are refused with a clear error."""
    rendered = rendered_from(np.zeros((H, W)), np.ones((H, W)))
    with pytest.raises(ValueError, match="must be"):
        match_regions(np.zeros((2, H + 1, W)), rendered)
    with pytest.raises(ValueError, match="within"):
        match_regions(np.full((1, H, W), 1.5), rendered)


def test_plan_update_matches_existing_and_adds_new_regions() -> None:
    """Matched region: same key, running-mean embedding, count + 1. Unmatched: new key with its
    embedding. Per pixel the most confident region wins; a region winning no pixel is skipped."""
    d = RegionDictionary("test-space", 4)
    e_old = unit(np.array([1.0, 0, 0, 0]))
    k_old = d.add(e_old, label="chair")
    key_map = np.full((H, W), -1)
    key_map[:, :20] = k_old
    rendered = rendered_from(key_map, (key_map >= 0) * 0.8)
    conf = np.zeros((3, H, W), np.float32)
    conf[0][:, :20] = 0.9  # the chair again
    conf[1][:, 25:] = 0.7  # something new
    conf[2][:, 25:] = 0.3  # weaker than region 1 everywhere: wins no pixel
    e_new_view = unit(np.array([0.0, 1.0, 0, 0]))
    emb = np.stack([e_new_view, unit(np.array([0, 0, 1.0, 0])), unit(np.array([0, 0, 0, 1.0]))])
    obs = SimpleObservation(conf, emb, "test-space", ["chair", "table", "ghost"])
    version_before = d.version
    plan = plan_update(obs, rendered, d)
    assert plan.matched == [(0, k_old)]
    assert len(plan.new_keys) == 1 and plan.new_keys[0][0] == 1
    new_key = plan.new_keys[0][1]
    assert plan.skipped == [2]
    assert d.version == version_before + 1 == plan.dictionary_version  # one batch
    assert d.count(k_old) == 2
    np.testing.assert_allclose(d.mean_embedding(k_old), (e_old + e_new_view) / 2, atol=1e-6)
    np.testing.assert_allclose(d.embedding(k_old), unit(e_old + e_new_view), atol=1e-6)
    assert d.label(new_key) == "table" and d.count(new_key) == 1
    assert (plan.key_map[:, :20] == k_old).all() and (plan.key_map[:, 25:] == new_key).all()
    assert (plan.key_map[:, 20:25] == -1).all()
    # The region's margin over the runner-up (region 2 claims the same pixels at 0.3: 0.7 - 0.3),
    # times the mask-edge weight 1/3, 2/3, 1 at 0, 1, >= 2 pixels from its border with the
    # uncovered columns 20:25 (the image border is no edge).
    np.testing.assert_allclose(plan.conf_map[:, 25], 0.4 / 3, atol=1e-6)
    np.testing.assert_allclose(plan.conf_map[:, 26], 0.4 * 2 / 3, atol=1e-6)
    np.testing.assert_allclose(plan.conf_map[:, 27:], 0.4, atol=1e-6)
    np.testing.assert_allclose(plan.conf_map[:, 18:20], [[0.9 * 2 / 3, 0.9 / 3]] * H, atol=1e-6)


def test_plan_update_embedding_gate() -> None:
    """With min_embedding_cos, a region overlapping a key whose embedding differs gets a new key."""
    d = RegionDictionary("s", 2)
    k = d.add(np.array([1.0, 0.0], np.float32))
    key_map = np.full((H, W), k)
    rendered = rendered_from(key_map, np.ones((H, W)))
    obs = SimpleObservation(np.ones((1, H, W), np.float32), np.array([[0.0, 1.0]], np.float32), "s")
    assert plan_update(obs, rendered, d).matched == [(0, k)]
    d2 = RegionDictionary("s", 2)
    k2 = d2.add(np.array([1.0, 0.0], np.float32))
    plan = plan_update(obs, rendered_from(np.full((H, W), k2), np.ones((H, W))), d2,
                       MatchParams(min_embedding_cos=0.5, min_embedding_cos_views=0))
    assert plan.matched == [] and len(plan.new_keys) == 1


def test_embedding_gate_judges_only_keys_settled_by_enough_views() -> None:
    """``min_embedding_cos_views`` 3: a key seen once is matched by geometry alone, even by a region
    whose embedding is orthogonal to it (one view is not yet the key's word: the encoder's own
    noise); once its embedding averages 3 views that region gets a new key (the floor key that
    took a wall, docs/EVAL.md "A settled key refuses"), while a region that agrees (cosine 0.9)
    still matches it."""
    params = MatchParams(min_embedding_cos=0.6, min_embedding_cos_views=3)
    d = RegionDictionary("s", 2)
    k = d.add(np.array([1.0, 0.0], np.float32))
    rendered = rendered_from(np.full((H, W), k), np.ones((H, W)))
    other = SimpleObservation(np.ones((1, H, W), np.float32), np.array([[0.0, 1.0]], np.float32), "s")
    agreeing = SimpleObservation(np.ones((1, H, W), np.float32), np.array([[0.9, 0.436]], np.float32), "s")
    young = d.snapshot()
    assert plan_update(other, rendered, RegionDictionary.from_snapshot(young), params).matched == [(0, k)]
    for _ in range(2):
        d.observe(k, np.array([1.0, 0.0], np.float32))
    assert d.count(k) == 3
    settled = RegionDictionary.from_snapshot(d.snapshot())
    plan = plan_update(other, rendered, settled, params)
    assert plan.matched == [] and len(plan.new_keys) == 1
    assert plan_update(agreeing, rendered, RegionDictionary.from_snapshot(d.snapshot()), params).matched == [(0, k)]
    # With the views rule off (0) the gate judges the young key too.
    every_key = MatchParams(min_embedding_cos=0.6, min_embedding_cos_views=0)
    plan = plan_update(other, rendered, RegionDictionary.from_snapshot(young), every_key)
    assert plan.matched == [] and len(plan.new_keys) == 1


def test_plan_update_refuses_other_embedding_space_and_bad_shapes() -> None:
    """Embeddings of another space, or of the wrong dimension/count, never reach the dictionary."""
    d = RegionDictionary("clip-vit-b-32", 4)
    rendered = rendered_from(np.full((H, W), -1), np.zeros((H, W)))
    conf = np.ones((1, H, W), np.float32)
    with pytest.raises(EmbeddingSpaceError, match="minilm"):
        plan_update(SimpleObservation(conf, np.ones((1, 4), np.float32), "minilm-l6-v2"), rendered, d)
    with pytest.raises(ValueError, match="embeddings"):
        plan_update(SimpleObservation(conf, np.ones((1, 3), np.float32), "clip-vit-b-32"), rendered, d)
    assert len(d) == 0 and d.version == 0


def test_mask_edge_weights_by_distance_to_the_border() -> None:
    """weight = min(1, (d + 1) / (mask_edge_px + 1)), d = Euclidean distance in pixels to the nearest
    pixel whose label differs from a 4-neighbour; both sides of a border are edge pixels; the image
    border is not an edge; 0 turns the weighting off."""
    labels = np.zeros((9, 12), np.int64)
    labels[:, 6:] = 1  # a vertical border between columns 5 and 6
    w = mask_edge_weights(labels, 2.0)
    np.testing.assert_allclose(w[:, 5], 1 / 3)
    np.testing.assert_allclose(w[:, 6], 1 / 3)
    np.testing.assert_allclose(w[:, 4], 2 / 3)
    np.testing.assert_allclose(w[:, 7], 2 / 3)
    np.testing.assert_allclose(w[:, :4], 1.0)
    np.testing.assert_allclose(w[:, 8:], 1.0)
    labels[4, 2] = 7  # a one-pixel region: it and its 4 neighbours are edge pixels
    w = mask_edge_weights(labels, 2.0)
    assert w[4, 2] == pytest.approx(1 / 3) and w[3, 2] == pytest.approx(1 / 3)
    assert w[3, 1] == pytest.approx(2 / 3)  # diagonal neighbour: d = 1 (to (3, 2) and (4, 1))
    assert w[2, 1] == pytest.approx((np.sqrt(2) + 1) / 3)  # d = sqrt(2) (to (3, 2))
    assert w[0, 0] == 1.0
    np.testing.assert_array_equal(mask_edge_weights(labels, 0.0), 1.0)
    np.testing.assert_array_equal(mask_edge_weights(np.full((5, 5), 3), 2.0), 1.0)
    with pytest.raises(ValueError, match="mask_edge_px"):
        mask_edge_weights(labels, -1.0)


def test_plan_update_mask_edge_option() -> None:
    """mask_edge_px=0 plans the regions' own confidences; a larger value widens the down-weighted
    band; the option is validated."""
    d = RegionDictionary("s", 2)
    conf = np.zeros((2, H, W), np.float32)
    conf[0][:, :20] = 0.8
    conf[1][:, 20:] = 0.6
    obs = SimpleObservation(conf, np.eye(2, dtype=np.float32), "s")
    empty = rendered_from(np.full((H, W), -1), np.zeros((H, W)))
    plan = plan_update(obs, empty, d, MatchParams(mask_edge_px=0))
    np.testing.assert_allclose(plan.conf_map[:, :20], 0.8)
    np.testing.assert_allclose(plan.conf_map[:, 20:], 0.6)
    plan = plan_update(obs, empty, RegionDictionary("s", 2), MatchParams(mask_edge_px=4))
    np.testing.assert_allclose(plan.conf_map[:, 19], 0.8 / 5, atol=1e-6)
    np.testing.assert_allclose(plan.conf_map[:, 16], 0.8 * 4 / 5, atol=1e-6)
    np.testing.assert_allclose(plan.conf_map[:, :16], 0.8, atol=1e-6)
    with pytest.raises(ValueError, match="mask_edge_px"):
        MatchParams(mask_edge_px=float("nan"))


def test_plan_update_contested_pixels_fuse_nothing() -> None:
    """Where two frame regions claim a pixel, the planned confidence is the winner's margin over the
    runner-up: a mask dilated over its neighbour (both at 1.0 there) writes nothing on the
    neighbour, a soft border writes its margin, and uncontested pixels keep their confidence.
    ``contested_margin=False`` plans the winner's own confidence everywhere (the earlier rule)."""
    conf = np.zeros((2, H, W), np.float32)
    conf[0][:, :24] = 1.0  # region 0, dilated 4 columns over region 1
    conf[1][:, 20:] = 1.0
    conf[0][:, 30] = 0.7  # a soft pixel column inside region 1: region 0 at 0.7, region 1 at 1.0
    obs = SimpleObservation(conf, np.eye(2, dtype=np.float32), "s")
    empty = rendered_from(np.full((H, W), -1), np.zeros((H, W)))
    plan = plan_update(obs, empty, RegionDictionary("s", 2), MatchParams(mask_edge_px=0))
    assert MatchParams().contested_margin
    np.testing.assert_allclose(plan.conf_map[:, :20], 1.0)
    np.testing.assert_allclose(plan.conf_map[:, 20:24], 0.0)  # both at 1.0: nothing to fuse
    np.testing.assert_allclose(plan.conf_map[:, 30], 0.3, atol=1e-6)
    np.testing.assert_allclose(plan.conf_map[:, 24:30], 1.0)
    plan = plan_update(
        obs, empty, RegionDictionary("s", 2), MatchParams(mask_edge_px=0, contested_margin=False)
    )
    np.testing.assert_allclose(plan.conf_map[:, :30], 1.0)
    np.testing.assert_allclose(plan.conf_map[:, 30], 1.0)


def _dilated_over_an_edge(depth_m: np.ndarray) -> tuple[SimpleObservation, RenderedView, RegionDictionary]:
    """Region 0 (map key 0, columns < 20) dilated 2 columns over region 1 (map key 1), which is eroded."""
    conf = np.zeros((2, H, W), np.float32)
    conf[0][:, :22] = 1.0
    conf[1][:, 22:] = 1.0
    d = RegionDictionary("s", 2)
    d.add(np.array([1, 0], np.float32))
    d.add(np.array([0, 1], np.float32))
    key_map = np.where(np.arange(W)[None, :] < 20, 0, 1).repeat(H, axis=0)
    rendered = RenderedView(key_map.astype(np.int32), np.ones((H, W), np.float32), depth_m.astype(np.float32))
    return SimpleObservation(conf, np.eye(2, dtype=np.float32), "s"), rendered, d


def test_plan_update_depth_cut_spill_fuses_nothing() -> None:
    """A mask dilated over an occlusion edge (depth jump) or around a crease (the inverse depth's slope
    changes) fuses nothing on the far side where the map holds another region; with the cut off
    (``depth_cut_rel=0`` / ``crease_rel=0``) the spill is fused with the mask's key."""
    jump = np.where(np.arange(W)[None, :] < 20, 1.0, 3.0).repeat(H, axis=0)
    obs, rendered, d = _dilated_over_an_edge(jump)
    assert MatchParams().depth_cut_rel > 0 and MatchParams().crease_rel > 0
    plan = plan_update(obs, rendered, d)
    assert plan.matched == [(0, 0), (1, 1)]
    np.testing.assert_array_equal(plan.conf_map[:, 20:22], 0.0)
    assert (plan.conf_map[:, 18:20] > 0).all() and (plan.key_map[:, :20] == 0).all()
    obs, rendered, d = _dilated_over_an_edge(jump)
    plan = plan_update(obs, rendered, d, MatchParams(depth_cut_rel=0))
    assert (plan.conf_map[:, 20:22] > 0).all() and (plan.key_map[:, 20:22] == 0).all()

    # A corner (a wall meeting another wall): depth continuous, inverse depth linear on each side.
    col = np.arange(W, dtype=np.float64)
    inv = np.where(col < 20, 0.5 + 0.01 * col, 0.7 - 0.01 * (col - 20))
    crease = (1.0 / inv)[None, :].repeat(H, axis=0)
    obs, rendered, d = _dilated_over_an_edge(crease)
    plan = plan_update(obs, rendered, d)
    np.testing.assert_array_equal(plan.conf_map[:, 20:22], 0.0)
    obs, rendered, d = _dilated_over_an_edge(crease)
    plan = plan_update(obs, rendered, d, MatchParams(crease_rel=0))
    assert (plan.conf_map[:, 20:22] > 0).all()


def test_plan_update_depth_cut_keeps_new_and_own_surface() -> None:
    """Cut-off border pixels still fuse where the map already shows this region's key, and on surface
    the map has not labelled yet that is not behind the mask's body (a background mask dilated over a
    nearer object nobody labelled yet): noise-free masks on a first view lose nothing there."""
    jump = np.where(np.arange(W)[None, :] < 20, 1.0, 3.0).repeat(H, axis=0)
    obs, rendered, d = _dilated_over_an_edge(jump)
    rendered.key_map[:, 20:22] = 0
    plan = plan_update(obs, rendered, d)
    assert (plan.conf_map[:, 20:22] > 0).all() and (plan.key_map[:, 20:22] == 0).all()
    nearer = np.where(np.arange(W)[None, :] < 20, 3.0, 1.0).repeat(H, axis=0)
    obs, rendered, d = _dilated_over_an_edge(nearer)
    rendered.key_map[:, 20:22] = -1
    plan = plan_update(obs, rendered, d)
    assert (plan.conf_map[:, 20:22] > 0).all() and (plan.key_map[:, 20:22] == 0).all()


def test_plan_update_depth_cut_spill_behind_the_object_on_new_surface() -> None:
    """A foreground mask dilated over background the map has not labelled yet (the first view of the
    wall behind a chair) fuses nothing on that background: its key would otherwise hold those voxels
    until the wall's own views wear it down. Not cut: a step of less than ``depth_cut_new_rel`` (10 %)
    behind the body, a grazing plane (depth jumps, but no occlusion), a strip of the object's own
    surface behind its front that meets the next surface across another jump; and
    ``depth_cut_new_rel=0`` fuses the spill with the mask's key (the previous rule: cut only where the
    map holds another region)."""
    assert MatchParams().depth_cut_new_rel == pytest.approx(0.10)
    behind = np.where(np.arange(W)[None, :] < 20, 1.0, 3.0).repeat(H, axis=0)
    obs, rendered, d = _dilated_over_an_edge(behind)
    rendered.key_map[:, 20:] = -1
    plan = plan_update(obs, rendered, d)
    np.testing.assert_array_equal(plan.conf_map[:, 20:22], 0.0)
    assert (plan.conf_map[:, 18:20] > 0).all() and (plan.key_map[:, :20] == 0).all()
    assert (plan.conf_map[:, 24:] > 0).all()  # the background's own region still fuses
    obs, rendered, d = _dilated_over_an_edge(behind)
    rendered.key_map[:, 20:] = -1
    plan = plan_update(obs, rendered, d, MatchParams(depth_cut_new_rel=0))
    assert (plan.conf_map[:, 20:22] > 0).all() and (plan.key_map[:, 20:22] == 0).all()
    step = np.where(np.arange(W)[None, :] < 20, 1.0, 1.07).repeat(H, axis=0)  # a jump, but under 10 %
    # A plane seen at a grazing angle: depth steps of 6 % per pixel (jumps to depth_jumps), yet the
    # inverse depth is linear, so the border band is on the mask's own surface, not behind it.
    inv = np.maximum(0.5 - 0.03 * (np.arange(W) - 20.0), 0.1)
    grazing = (1.0 / inv)[None, :].repeat(H, axis=0)
    # A strip of the mask's own object behind its front (a shelf's back panel, 1.5 m behind 1.0 m)
    # that meets the next surface (3.0 m) across another jump: not background the mask spilled over.
    own_strip = np.select([np.arange(W) < 20, np.arange(W) < 22], [1.0, 1.5], 3.0)[None, :].repeat(H, axis=0)
    for depth in (step, grazing, own_strip):
        obs, rendered, d = _dilated_over_an_edge(depth)
        rendered.key_map[:, 20:] = -1
        plan = plan_update(obs, rendered, d)
        assert (plan.conf_map[:, 20:22] > 0).all() and (plan.key_map[:, 20:22] == 0).all()
    assert depth_cut_spill(
        np.where(np.arange(W) < 22, 0, 1)[None, :].repeat(H, axis=0),
        (np.abs(np.arange(W) - 21.5) < 2)[None, :].repeat(H, axis=0),
        grazing,
        MatchParams().depth_cut_rel,
        0.0,
        2.0,
    )[:, 20:22].all()  # the band is cut off by the jumps: only the behind-the-body test keeps it


def test_plan_update_splits_a_mask_of_two_map_objects() -> None:
    """One frame region over two map regions of different objects (a mask that merged them) matches
    the larger; the part over the other, which no frame region matched, fuses that region's own key
    instead of weakening it. Off (``split_min_share=None``), or when the two map regions' embeddings
    agree (one object in two fragments, left to the merge pass), the whole mask fuses the matched key."""
    conf = np.ones((1, H, W), np.float32)
    key_map = np.where(np.arange(W)[None, :] < 24, 0, 1).repeat(H, axis=0).astype(np.int32)
    rendered = RenderedView(key_map, np.ones((H, W), np.float32), np.ones((H, W), np.float32))

    def plan_with(second: np.ndarray, params: MatchParams | None = None):  # noqa: ANN202
        d = RegionDictionary("s", 2)
        d.add(np.array([1, 0], np.float32))
        d.add(second)
        obs = SimpleObservation(conf, np.array([[1, 0]], np.float32), "s")
        return plan_update(obs, rendered, d, params)

    assert MatchParams().split_min_share is not None
    plan = plan_with(np.array([0, 1], np.float32))
    assert plan.matched == [(0, 0)] and not plan.new_keys
    np.testing.assert_array_equal(plan.key_map, key_map)
    plan = plan_with(np.array([0, 1], np.float32), MatchParams(split_min_share=None))
    np.testing.assert_array_equal(plan.key_map, 0)
    plan = plan_with(unit(np.array([1, 0.1], np.float32)))
    np.testing.assert_array_equal(plan.key_map, 0)
