"""Semantic TSDF volume: geometry accuracy, key encoding, capacity, depth-tested render/update.

Scenes are analytic (exact ray/box depth), so reconstructions are compared with the true surface.
"""

from __future__ import annotations

import numpy as np
import pytest

from openfusion.frame import CameraIntrinsics
from openfusion.mapping import (
    CapacityError,
    SemanticVolume,
    VolumeParams,
)
from openfusion.mapping.update_rule import fuse_semantics
from openfusion.mapping.volume import fill_nearest_labels
from openfusion.poses import look_at
from openfusion.testing.analytic_scene import AnalyticScene, Box, Room

K_FULL = CameraIntrinsics(320, 240, 262.5, 262.5, 159.5, 119.5)
K_SMALL = K_FULL.scaled(160, 120)
VOXEL_M = 0.02


def two_box_scene() -> AnalyticScene:
    return AnalyticScene(
        room=Room(size_m=(3.0, 3.0, 2.5)),
        boxes=[
            Box((1.0, 1.8, 0.0), (1.6, 2.3, 0.8), 10, "chair"),
            Box((1.9, 1.5, 0.0), (2.6, 2.1, 0.5), 11, "table"),
        ],
    )


POSES = [
    look_at((1.5, 0.3, 1.4), (1.5, 2.0, 0.4)),
    look_at((0.4, 0.5, 1.4), (1.6, 2.0, 0.4)),
    look_at((2.6, 0.5, 1.4), (1.6, 2.0, 0.4)),
]


def integrated_volume(
    params: VolumeParams | None = None, scene: AnalyticScene | None = None
) -> SemanticVolume:
    scene = scene or two_box_scene()
    volume = SemanticVolume(params or VolumeParams())
    for i, T in enumerate(POSES):
        volume.integrate(scene.make_frame(T, K_FULL, frame_id=i))
    return volume


@pytest.fixture(scope="module")
def scene() -> AnalyticScene:
    return two_box_scene()


@pytest.fixture(scope="module")
def volume() -> SemanticVolume:
    return integrated_volume()


# ---------------------------------------------------------------- parameters


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("voxel_size_m", 0.0),
        ("voxel_size_m", float("nan")),
        ("block_resolution", 1),
        ("trunc_voxels", -1.0),
        ("depth_max_m", 0.05),
        ("initial_block_count", 0),
        ("max_blocks", 0),
        ("when_full", "explode"),
        ("device", "GPU:0"),
        ("update_min_width_px", -1),
    ],
)
def test_params_reject_bad_values(field: str, value: object) -> None:
    """Bad parameter values: each raises ValueError naming the field."""
    with pytest.raises(ValueError, match=field.split("_")[0]):
        VolumeParams(**{field: value})


def test_params_device_normalised_and_cuda_refused_without_cuda() -> None:
    """'cpu' is accepted as CPU:0; asking for CUDA on a CPU-only Open3D is a clear error, not a crash."""
    import open3d.core as o3c

    assert VolumeParams(device="cpu").device == "CPU:0"
    if not o3c.cuda.is_available():
        with pytest.raises(ValueError, match="CUDA"):
            SemanticVolume(VolumeParams(device="cuda"))


# ---------------------------------------------------------------- geometry


def test_reconstructed_surface_matches_analytic_surface(volume: SemanticVolume, scene: AnalyticScene) -> None:
    """Surface points lie on the true surface: median distance 0 to 1/4 voxel (zero crossings are
    interpolated exactly on planes), 95 % within one voxel (2 cm; convex box edges bulge by up to
    about a voxel because truncated SDFs of two faces blend there)."""
    points = volume.extract_points()
    assert len(points) > 20_000
    dist = scene.surface_distance(points.points.astype(np.float64))
    assert np.median(dist) <= 0.25 * VOXEL_M
    assert np.percentile(dist, 95) <= VOXEL_M


def test_render_depth_matches_analytic_depth(volume: SemanticVolume, scene: AnalyticScene, capfd) -> None:
    """Render at encoder size: depth within one voxel (median; Open3D's ray march samples the TSDF at
    the voxel grid), the view complete (no range-map holes), and no Open3D range-map warnings."""
    rendered = volume.render(POSES[0], K_SMALL)
    truth, _, _ = scene.render(POSES[0], K_SMALL)
    assert rendered.key_map.shape == (120, 160) and rendered.key_map.dtype == np.int32
    assert rendered.conf_map.dtype == np.float32
    hit = (rendered.depth_m > 0) & (truth > 0)
    assert hit.mean() > 0.97
    assert np.median(np.abs(rendered.depth_m[hit] - truth[hit])) <= VOXEL_M
    out, err = capfd.readouterr()
    assert "range map" not in out + err


def test_truncation_is_passed_to_open3d(scene: AnalyticScene) -> None:
    """trunc_voxels reaches Open3D (whose default is 8): a voxel 6 voxels behind a wall is observed
    with 8-voxel truncation and left empty with 4."""
    T = look_at((1.5, 1.5, 1.25), (1.5, 3.0, 1.25))  # facing the y = 3 m wall
    frame = scene.make_frame(T, K_FULL)
    weights = {}
    for trunc in (4.0, 8.0):
        vol = SemanticVolume(VolumeParams(trunc_voxels=trunc, depth_max_m=6.0))
        vol.integrate(frame)
        arrays = vol.to_arrays()
        centres = (arrays["block_coords"][:, None, None, None, :] * 8 + _voxel_offsets()) * VOXEL_M
        behind = np.linalg.norm(centres - np.array([1.5, 3.0 + 6 * VOXEL_M, 1.24]), axis=-1)
        weights[(trunc, "behind")] = arrays["weight"][behind < 0.5 * VOXEL_M + 1e-6]
    assert weights[(8.0, "behind")].size and weights[(8.0, "behind")].max() > 0
    assert weights[(4.0, "behind")].size == 0 or weights[(4.0, "behind")].max() == 0


def _voxel_offsets() -> np.ndarray:
    z, y, x = np.meshgrid(np.arange(8), np.arange(8), np.arange(8), indexing="ij")
    return np.stack([x, y, z], axis=-1)


def test_empty_frame_is_counted_not_fatal(scene: AnalyticScene) -> None:
    """A frame with no depth (sensor dropout) changes nothing and is counted."""
    vol = SemanticVolume()
    frame = scene.make_frame(POSES[0], K_FULL)
    frame.depth[:] = 0
    stats = vol.integrate(frame)
    assert stats.empty and vol.stats.frames_empty == 1 and vol.num_blocks == 0


def test_integrate_rejects_inconsistent_frame(scene: AnalyticScene) -> None:
    """A frame whose pose is not a rigid transform is refused with a clear error."""
    frame = scene.make_frame(POSES[0], K_FULL)
    frame.T_world_cam = frame.T_world_cam * 2.0
    with pytest.raises(ValueError, match="T_world_cam"):
        SemanticVolume().integrate(frame)


# ---------------------------------------------------------------- key encoding and capacity


def test_unlabelled_voxels_read_minus_one_also_after_growth(scene: AnalyticScene) -> None:
    """Open3D zero-fills new blocks; keys are stored +1 so never-labelled voxels read -1 — also for
    blocks allocated after the grid grew (re-hash), while labels written before survive it."""
    vol = SemanticVolume(VolumeParams(initial_block_count=64))
    vol.integrate(scene.make_frame(POSES[0], K_FULL))
    assert (vol.to_arrays()["key"] == -1).all()
    assert (vol.render(POSES[0], K_SMALL).key_map == -1).all()
    keys = np.full((120, 160), 7, np.int32)
    vol.apply_update(POSES[0], K_SMALL, keys, np.full((120, 160), 0.5, np.float32))
    labelled_before = int((vol.to_arrays()["key"] == 7).sum())
    assert labelled_before > 1000
    capacity_before = vol.capacity_blocks
    for i, T in enumerate(POSES[1:]):
        vol.integrate(scene.make_frame(T, K_FULL, frame_id=i + 1))
    assert vol.capacity_blocks > capacity_before and vol.stats.grow_events >= 1
    keys_after = vol.to_arrays()["key"]
    assert set(np.unique(keys_after)) == {-1, 7}
    assert int((keys_after == 7).sum()) == labelled_before
    again = vol.render(POSES[0], K_SMALL)
    assert (again.key_map[again.depth_m > 0] == 7).mean() > 0.95


def test_capacity_refusal_is_typed_counted_and_leaves_map_unchanged(scene: AnalyticScene) -> None:
    """max_blocks reached: CapacityError, counter +1, volume untouched; mapping continues afterwards."""
    first = scene.make_frame(POSES[0], K_FULL)
    probe = SemanticVolume()
    probe.integrate(first)
    budget = probe.num_blocks + 10
    vol = SemanticVolume(VolumeParams(max_blocks=budget, initial_block_count=budget))
    vol.integrate(first)
    before = vol.to_arrays()
    with pytest.raises(CapacityError, match="max_blocks") as info:
        vol.integrate(scene.make_frame(POSES[1], K_FULL, frame_id=1))
    assert info.value.blocks_needed > info.value.blocks_free == 10
    assert vol.stats.capacity_refusals == 1 and vol.stats.blocks_refused > 0
    after = vol.to_arrays()
    for name in before:
        np.testing.assert_array_equal(before[name], after[name])
    vol.integrate(first)  # the same view needs no new blocks: still works
    assert vol.stats.frames_integrated == 2


def test_capacity_drop_new_integrates_existing_blocks_only(scene: AnalyticScene) -> None:
    """when_full='drop_new': no exception, block count stays within the budget, refusals counted."""
    first = scene.make_frame(POSES[0], K_FULL)
    probe = SemanticVolume()
    probe.integrate(first)
    budget = probe.num_blocks + 10
    vol = SemanticVolume(VolumeParams(max_blocks=budget, when_full="drop_new"))
    vol.integrate(first)
    weight_before = vol.to_arrays()["weight"].sum()
    stats = vol.integrate(scene.make_frame(POSES[1], K_FULL, frame_id=1))
    assert stats.blocks_refused > 0 and vol.num_blocks <= budget
    assert vol.stats.capacity_refusals == 1
    assert vol.to_arrays()["weight"].sum() > weight_before  # existing blocks were updated


# ---------------------------------------------------------------- update rule


def test_fuse_semantics_rule() -> None:
    """The written rule (w = 3, a new observation weighs 1/(w+1) = 0.25): new label -> c; same key ->
    weighted average (3 conf + c) / 4; other key -> conf - c/4, and the key switches (keeping the
    remaining evidence) only once the stored confidence is used up."""
    old_key1 = np.array([0, 3, 3, 3, 3], np.int32)  # stored key+1: none, then key 2 four times
    old_conf = np.array([0.0, 0.6, 0.6, 0.1, 0.9], np.float32)
    new_key1 = np.array([5, 3, 9, 9, 3], np.int32)
    new_conf = np.array([0.7, 0.2, 0.4, 0.9, 0.8], np.float32)
    key1, conf, counts = fuse_semantics(old_key1, old_conf, new_key1, new_conf, history_weight=3.0)
    np.testing.assert_array_equal(key1, [5, 3, 3, 9, 3])
    # 0.7; (3*0.6 + 0.2)/4; 0.6 - 0.4/4; 0.9/4 - 0.1 (switched); (3*0.9 + 0.8)/4
    np.testing.assert_allclose(conf, [0.7, 0.5, 0.5, 0.125, 0.875], atol=1e-6)
    assert counts == (1, 2, 1, 1)
    # w = 0: the latest confidence replaces the stored one; a stronger contrary one takes the key.
    key1, conf, _ = fuse_semantics(old_key1, old_conf, new_key1, new_conf, history_weight=0.0)
    np.testing.assert_array_equal(key1, [5, 3, 3, 9, 3])
    np.testing.assert_allclose(conf, [0.7, 0.2, 0.2, 0.8, 0.8], atol=1e-6)
    with pytest.raises(ValueError, match="history_weight"):
        fuse_semantics(old_key1, old_conf, new_key1, new_conf, history_weight=-1.0)

    def observe(state: tuple[np.ndarray, np.ndarray], key1: int) -> tuple[np.ndarray, np.ndarray]:
        """One full-confidence observation of stored key ``key1`` on a single voxel."""
        k, c, _ = fuse_semantics(
            *state, np.array([key1], np.int32), np.ones(1, np.float32), history_weight=3.0
        )
        return k, c

    # An established voxel (seen 6 times at confidence 1): one or two contrary observations do not
    # flip it; w + 1 = 4 use its confidence up (exactly 0, key kept) and the 5th switches it; the
    # new key then starts with only the evidence left over.
    state = (np.array([0], np.int32), np.array([0.0], np.float32))
    for _ in range(6):
        state = observe(state, 3)
    assert state[0][0] == 3 and state[1][0] == pytest.approx(1.0)
    for want_key, want_conf in [(3, 0.75), (3, 0.5), (3, 0.25), (3, 0.0), (8, 0.25)]:
        state = observe(state, 8)
        assert (state[0][0], state[1][0]) == (want_key, pytest.approx(want_conf))
    # Interleaved evidence: key 2, 7, 2, 7, 2 -> 1, 0.75, (3*0.75+1)/4, -0.25, (3*0.5625+1)/4.
    state = (np.array([0], np.int32), np.array([0.0], np.float32))
    for key1 in (3, 8, 3, 8, 3):
        state = observe(state, key1)
    assert state[0][0] == 3 and state[1][0] == pytest.approx(0.671875)


def test_apply_update_rule_through_the_volume(volume: SemanticVolume) -> None:
    """The update rule through the volume (w = 3): the same key twice averages (3 * 0.8 + 0.4) / 4;
    contrary observations at 0.95 each remove 0.95 / 4, so two only weaken the voxels and the third
    takes them over with the evidence left over; pixels with key -1 change nothing."""
    vol = integrated_volume()
    ones = np.ones((120, 160), np.float32)
    vol.apply_update(POSES[0], K_SMALL, np.full((120, 160), 4, np.int32), 0.8 * ones)
    vol.apply_update(POSES[0], K_SMALL, np.full((120, 160), 4, np.int32), 0.4 * ones)
    r = vol.render(POSES[0], K_SMALL)
    seen = r.depth_m > 0
    np.testing.assert_allclose(np.median(r.conf_map[seen]), (3 * 0.8 + 0.4) / 4, atol=1e-5)
    left = np.full((120, 160), -1, np.int32)
    left[:, :80] = 9
    for weakened_to in (0.7 - 0.95 / 4, 0.7 - 2 * 0.95 / 4):
        stats = vol.apply_update(POSES[0], K_SMALL, left, 0.95 * ones)
        assert stats.voxels_switched == 0 and stats.voxels_weakened > 0
        r = vol.render(POSES[0], K_SMALL)
        assert (r.key_map[seen] == 4).mean() > 0.95
        np.testing.assert_allclose(np.median(r.conf_map[:, :70][seen[:, :70]]), weakened_to, atol=3e-5)  # conf stored as uint16: 1.5e-5 per write
    stats = vol.apply_update(POSES[0], K_SMALL, left, 0.95 * ones)
    assert stats.voxels_switched > 0
    r = vol.render(POSES[0], K_SMALL)
    assert (r.key_map[:, :70][seen[:, :70]] == 9).mean() > 0.95
    assert (r.key_map[:, 90:][seen[:, 90:]] == 4).mean() > 0.95
    np.testing.assert_allclose(np.median(r.conf_map[:, :70][seen[:, :70]]), 3 * 0.95 / 4 - 0.7, atol=3e-5)


def test_occluded_region_is_not_updated(scene: AnalyticScene) -> None:
    """The box hides part of the back wall from pose A. Labelling *every* pixel from A must not
    reach the wall voxels in the box's shadow (ray casting stops at the first surface)."""
    T_a = look_at((1.3, 0.4, 0.4), (1.3, 3.0, 0.4))  # low, straight at the chair box and the wall
    vol = SemanticVolume()
    for i, T in enumerate([*POSES, T_a]):
        vol.integrate(scene.make_frame(T, K_FULL, frame_id=i))
    vol.apply_update(T_a, K_SMALL, np.full((120, 160), 3, np.int32), np.full((120, 160), 0.9, np.float32))
    arrays = vol.to_arrays()
    centres = (arrays["block_coords"][:, None, None, None, :] * 8 + _voxel_offsets()) * VOXEL_M
    keys = arrays["key"]
    wall_band = np.abs(centres[..., 1] - 3.0) <= 2 * VOXEL_M
    # Shadow of the box on the wall from T_a: |x - 1.3| < 0.41, z < 0.95; seen from POSES[0] above 0.55.
    shadow = (
        wall_band
        & (np.abs(centres[..., 0] - 1.3) < 0.15)
        & (centres[..., 2] > 0.6)
        & (centres[..., 2] < 0.85)
    )
    box_front = (np.abs(centres[..., 1] - 1.8) <= VOXEL_M) & (np.abs(centres[..., 0] - 1.3) < 0.2)
    box_front &= (centres[..., 2] > 0.1) & (centres[..., 2] < 0.7)
    assert (keys[box_front] == 3).sum() > 50
    assert shadow.sum() > 50 and (keys[shadow] == -1).all()


def test_apply_update_rejects_bad_maps(volume: SemanticVolume) -> None:
    """Wrong size, NaN confidences, out-of-range keys and a non-rigid pose: clear ValueErrors."""
    good_keys = np.zeros((120, 160), np.int32)
    good_conf = np.ones((120, 160), np.float32)
    with pytest.raises(ValueError, match="must both be"):
        volume.apply_update(POSES[0], K_SMALL, good_keys[:60], good_conf)
    bad_conf = good_conf.copy()
    bad_conf[0, 0] = np.nan
    with pytest.raises(ValueError, match="conf_map"):
        volume.apply_update(POSES[0], K_SMALL, good_keys, bad_conf)
    with pytest.raises(ValueError, match="key_map"):
        volume.apply_update(POSES[0], K_SMALL, good_keys - 5, good_conf)
    with pytest.raises(ValueError, match="T_world_cam"):
        volume.apply_update(np.eye(3), K_SMALL, good_keys, good_conf)


def test_tensor_path_matches_numpy_path(scene: AnalyticScene) -> None:
    """The Open3D-tensor attribute path (used on CUDA) writes and reads exactly what the CPU
    numpy-view path does (run here on CPU by switching paths)."""
    results = []
    for use_views in (True, False):
        vol = integrated_volume()
        vol._storage.use_numpy_views = use_views
        keys = np.where(np.arange(160)[None, :] < 80, 2, 5).repeat(120, axis=0).astype(np.int32)
        vol.apply_update(POSES[0], K_SMALL, keys, np.full((120, 160), 0.6, np.float32))
        vol.relabel_keys({5: 6})
        r = vol.render(POSES[1], K_SMALL)
        results.append((r.key_map, r.conf_map, vol.to_arrays()["key"]))
    for a, b in zip(results[0], results[1], strict=True):
        np.testing.assert_array_equal(a, b)


# ---------------------------------------------------------------- extraction


def test_extract_points_and_mesh_restricted_to_keys(scene: AnalyticScene) -> None:
    """Labelled chair pixels -> extracted chair points and mesh; filtering by key keeps only those.

    Also the depth gate: chair-mask pixels on the chair's silhouette whose ray hits the wall behind
    must not label that wall when the frame's depth is given."""
    _, inst, _ = scene.render(POSES[0], K_SMALL)
    keys = np.where(inst == 10, 1, np.where(inst == 11, 2, -1)).astype(np.int32)
    conf = np.full((120, 160), 0.9, np.float32)
    # Only the two objects are labelled here, so the read-out fill (tested below) is off: this
    # test is about the voxels the update labels.
    no_fill = VolumeParams(label_fill_radius_m=0.0)
    ungated = integrated_volume(no_fill)
    ungated.apply_update(POSES[0], K_SMALL, keys, conf)
    leaked = ungated.extract_points(keys=[1])
    vol = integrated_volume(no_fill)
    frame = scene.make_frame(POSES[0], K_FULL)
    stats = vol.apply_update(POSES[0], K_SMALL, keys, conf, observed_depth_m=frame.depth_m())
    assert stats.pixels_depth_rejected > 0
    all_points = vol.extract_points()
    chair = vol.extract_points(keys=[1])
    assert 0 < len(chair) < len(all_points) and (chair.keys == 1).all()
    on_chair = (scene.instance_at(chair.points.astype(np.float64)) == 10).mean()
    assert on_chair > 0.97
    assert on_chair > (scene.instance_at(leaked.points.astype(np.float64)) == 10).mean()
    sub = vol.extract_points(max_points=500, seed=3)
    assert len(sub) == 500
    np.testing.assert_array_equal(sub.points, vol.extract_points(max_points=500, seed=3).points)
    mesh = vol.extract_mesh(keys=[1])
    assert len(mesh.triangles) > 100 and (mesh.keys == 1).all()
    assert mesh.triangles.max() < len(mesh.vertices)
    full = vol.extract_mesh()
    assert len(full.triangles) > len(mesh.triangles)


def test_relabel_keys_moves_and_clears(volume: SemanticVolume) -> None:
    """relabel {a: b} rewrites every voxel of a; {b: -1} clears them back to unlabelled."""
    vol = integrated_volume()
    vol.apply_update(
        POSES[0], K_SMALL, np.full((120, 160), 3, np.int32), np.full((120, 160), 0.9, np.float32)
    )
    n3 = int((vol.to_arrays()["key"] == 3).sum())
    assert vol.relabel_keys({3: 8}) == n3
    keys = vol.to_arrays()["key"]
    assert (keys == 3).sum() == 0 and (keys == 8).sum() == n3
    assert vol.relabel_keys({8: -1}) == n3
    arrays = vol.to_arrays()
    assert (arrays["key"] == -1).all() and (arrays["conf"] == 0).all()
    with pytest.raises(ValueError, match="relabel"):
        vol.relabel_keys({-1: 2})


def test_float_depth_frames_integrate_like_uint16(scene: AnalyticScene) -> None:
    """A frame with float32 metres (depth_scale 1) gives the same surface as its uint16 twin."""
    frame = scene.make_frame(POSES[0], K_FULL)
    vol_u16 = SemanticVolume()
    vol_u16.integrate(frame)
    frame.depth = frame.depth_m()
    frame.depth_scale = 1.0
    vol_f32 = SemanticVolume()
    vol_f32.integrate(frame)
    a, b = vol_u16.extract_points(), vol_f32.extract_points()
    assert abs(len(a) - len(b)) <= 0.01 * len(a)
    np.testing.assert_allclose(np.median(a.points, axis=0), np.median(b.points, axis=0), atol=1e-3)
    np.testing.assert_allclose(a.colors.mean(axis=0), b.colors.mean(axis=0), atol=1.0)


def test_concurrent_render_and_integrate_are_serialised(scene: AnalyticScene) -> None:
    """A render thread and an integrate thread on one volume (as in the geometry service) finish
    without errors and the map ends up with every frame."""
    import threading

    vol = SemanticVolume(VolumeParams(initial_block_count=64))  # forces growth while rendering
    vol.integrate(scene.make_frame(POSES[0], K_FULL))
    errors: list[BaseException] = []

    def render_loop() -> None:
        try:
            for _ in range(15):
                vol.render(POSES[1], K_SMALL)
        except BaseException as exc:  # collected and asserted below
            errors.append(exc)

    t = threading.Thread(target=render_loop)
    t.start()
    for i, T in enumerate(POSES * 2):
        vol.integrate(scene.make_frame(T, K_FULL, frame_id=i))
    t.join()
    assert not errors and vol.stats.frames_integrated == 7 and vol.stats.renders == 15


def test_update_reuses_render_only_while_buffers_are_valid(scene: AnalyticScene) -> None:
    """apply_update reuses the render's ray cast for the same pose and size; after the grid grew
    (voxel buffer indices moved) or for another pose it casts again instead of writing stale indices."""
    vol = SemanticVolume(VolumeParams(initial_block_count=64))
    vol.integrate(scene.make_frame(POSES[0], K_FULL))
    keys = np.full((120, 160), 1, np.int32)
    conf = np.full((120, 160), 0.5, np.float32)
    rendered = vol.render(POSES[0], K_SMALL)
    assert vol.apply_update(POSES[0], K_SMALL, keys, conf, rendered=rendered).reused_render
    assert not vol.apply_update(POSES[1], K_SMALL, keys, conf, rendered=rendered).reused_render
    generation = vol.generation
    for i, T in enumerate(POSES[1:]):
        vol.integrate(scene.make_frame(T, K_FULL, frame_id=i + 1))
    assert vol.generation != generation
    stats = vol.apply_update(
        POSES[0],
        K_SMALL,
        np.full((120, 160), 2, np.int32),
        np.full((120, 160), 0.9, np.float32),
        rendered=rendered,
    )
    assert not stats.reused_render and stats.voxels_weakened > 0
    # Key-1 voxels hold 0.5; each key-2 observation at 0.9 removes 0.9 / 4 (update rule, w = 3):
    # 0.275, 0.05, then the third takes them over. Written through fresh ray casts every time.
    for _ in range(2):
        vol.apply_update(
            POSES[0], K_SMALL, np.full((120, 160), 2, np.int32), np.full((120, 160), 0.9, np.float32)
        )
    after = vol.render(POSES[0], K_SMALL)
    assert (after.key_map[after.depth_m > 0] == 2).mean() > 0.95


# ---------------------------------------------------------------- read-out fill


def test_fill_labels_only_within_radius_and_only_from_original_labels() -> None:
    """A line of points 4 cm apart, only the first labelled: with a 6 cm radius only the next point
    takes its key (one pass, no creeping); points farther stay -1; radius 0 changes nothing."""
    points = np.stack([np.arange(6) * 0.04, np.zeros(6), np.zeros(6)], axis=1).astype(np.float32)
    keys = np.array([7, -1, -1, -1, -1, -1], np.int32)
    conf = np.array([0.8, 0, 0, 0, 0, 0], np.float32)
    assert fill_nearest_labels(points, keys.copy(), conf.copy(), 0.0) == 0
    assert fill_nearest_labels(points, keys, conf, 0.06) == 1
    assert list(keys) == [7, 7, -1, -1, -1, -1] and conf[1] == pytest.approx(0.8)


def test_fill_needs_a_source_facing_the_same_way() -> None:
    """Floor points (normal +z) next to a labelled wall (normal -y) stay unlabelled; a floor point
    next to a labelled floor point takes the floor's key even when a wall point is nearer."""
    wall = np.array([[0.0, 0.0, 0.02], [0.5, 0.0, 0.02]], np.float32)
    floor_lab = np.array([[0.5, -0.05, 0.0]], np.float32)
    floor_unl = np.array([[0.0, -0.02, 0.0], [0.5, -0.02, 0.0]], np.float32)
    points = np.concatenate([wall, floor_lab, floor_unl])
    normals = np.array([[0, -1, 0], [0, -1, 0], [0, 0, 1], [0, 0, 1], [0, 0, 1]], np.float32)
    keys = np.array([3, 3, 4, -1, -1], np.int32)
    conf = np.array([0.9, 0.9, 0.7, 0, 0], np.float32)
    assert fill_nearest_labels(points, keys, conf, 0.06, normals) == 1
    assert list(keys) == [3, 3, 4, -1, 4]


def test_read_out_fill_labels_surface_the_encoder_view_missed(scene: AnalyticScene) -> None:
    """Every instance labelled from one encoder-sized view: with the default fill radius fewer
    surface points stay unlabelled than without, and the share of labelled points that carry the
    key of the object they lie on drops by at most 3 points (filled points sit at the edges of
    what the view labelled, where points lie within a voxel of two objects)."""
    _, inst, _ = scene.render(POSES[0], K_SMALL)
    keys = np.where(inst >= 0, inst, -1).astype(np.int32)
    conf = np.full((120, 160), 0.9, np.float32)
    result = {}
    for radius in (0.0, VolumeParams().label_fill_radius_m):
        vol = integrated_volume(VolumeParams(label_fill_radius_m=radius))
        vol.apply_update(POSES[0], K_SMALL, keys, conf)
        result[radius] = vol.extract_points()
    (r0, off), (r1, on) = result.items()
    assert r1 > 0 and np.array_equal(off.points, on.points)
    filled = (off.keys < 0) & (on.keys >= 0)
    assert (on.keys < 0).sum() < (off.keys < 0).sum() and filled.sum() > 100
    truth = scene.instance_at(on.points.astype(np.float64))

    def right(sel: np.ndarray) -> float:
        return float((on.keys[sel] == truth[sel]).mean())

    assert right(on.keys >= 0) >= right(off.keys >= 0) - 0.03
    assert right(filled) >= 0.75
    mesh = integrated_volume(VolumeParams(label_fill_radius_m=r1))
    mesh.apply_update(POSES[0], K_SMALL, keys, conf)
    assert (mesh.extract_mesh().keys >= 0).mean() > 0.5
