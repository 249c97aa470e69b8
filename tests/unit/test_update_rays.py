"""The semantic update's rays: maps narrower than ``VolumeParams.update_min_width_px`` enlarged
(``view_update.enlarge_update_maps``), each enlarged pixel's ray finding the surface its map pixel
saw (``SemanticVolume.apply_update``; docs/EVAL.md, "Rays for every voxel")."""

from __future__ import annotations

import numpy as np
import pytest

from openfusion.mapping import VolumeParams
from openfusion.testing.analytic_scene import AnalyticScene
from tests.unit.test_mapping_volume import K_FULL, K_SMALL, POSES, integrated_volume, two_box_scene


@pytest.fixture(scope="module")
def scene() -> AnalyticScene:
    return two_box_scene()


def test_narrow_update_maps_get_a_ray_per_voxel(scene: AnalyticScene) -> None:
    """An encoder's quarter-size maps of a 320x240 frame (80x60) are enlarged to 160x120 before the
    update's rays are cast (``update_min_width_px``, default 160): more of the surface in view is
    labelled, the region border stays where the maps put it; with the step's render at hand the
    enlarged rays look for the surface at the depth it found (no ray cast), nearly as a ray cast
    labels it; maps already that wide are written as before (one ray per pixel, the step's render
    reused)."""
    K_OBS = K_FULL.scaled(80, 60)
    keys = np.where(np.arange(80)[None, :] < 40, 2, 5).repeat(60, axis=0).astype(np.int32)
    conf = np.full((60, 80), 0.8, np.float32)
    results = {}
    depth_obs = scene.make_frame(POSES[0], K_OBS).depth_m()
    for name, min_width, step in (("one ray", 0, "render"), ("probed", 160, "probe"), ("cast", 160, None),
                                  ("rendered", 160, "render")):
        vol = integrated_volume(VolumeParams(update_min_width_px=min_width))
        step_view = {"render": lambda v: v.render(POSES[0], K_OBS), "probe": lambda v: v.probe(POSES[0], K_OBS, depth_obs),
                     None: lambda v: None}[step](vol)
        stats = vol.apply_update(POSES[0], K_OBS, keys, conf, rendered=step_view)
        seen = vol.render(POSES[0], K_FULL)
        hit = seen.depth_m > 0
        results[name] = (stats, ((seen.key_map >= 0) & hit).sum() / hit.sum(), np.where(hit, seen.key_map, -1))
    (one_ray, share_one, keys_one), (probed, share_probed, _), (cast, share_cast, keys_cast), (rendered, share_rendered, _) = (
        results.values())
    assert one_ray.reused_render and probed.reused_render and rendered.reused_render and not cast.reused_render
    assert share_rendered > 0.99 and rendered.voxels_updated > 1.3 * one_ray.voxels_updated
    assert cast.pixels_used >= 3.5 * one_ray.pixels_used and probed.pixels_used >= 3.5 * one_ray.pixels_used
    assert probed.voxels_updated > 1.3 * one_ray.voxels_updated and cast.voxels_updated > 1.3 * one_ray.voxels_updated
    assert share_one < 0.98 and share_probed > 0.99 and share_cast > 0.995
    both = (keys_one >= 0) & (keys_cast >= 0)
    differ = np.argwhere(both & (keys_one != keys_cast))
    assert len(differ) < 0.005 * both.sum()
    assert (np.abs(differ[:, 1] - 160) <= 2).all()  # only at the border (column 160), within half a map pixel
    # Maps at least that wide: exactly what one ray per pixel writes.
    wide_keys = np.repeat(np.repeat(keys, 2, axis=0), 2, axis=1)
    wide_conf = np.full((120, 160), 0.8, np.float32)
    arrays = []
    for min_width in (0, 160):
        vol = integrated_volume(VolumeParams(update_min_width_px=min_width))
        stats = vol.apply_update(POSES[0], K_SMALL, wide_keys, wide_conf, rendered=vol.render(POSES[0], K_SMALL))
        assert stats.reused_render
        arrays.append(vol.to_arrays())
    for name in ("key", "conf"):
        np.testing.assert_array_equal(arrays[0][name], arrays[1][name])


def test_enlarged_update_keeps_a_silhouette_off_the_background(scene: AnalyticScene) -> None:
    """An object's key at 80x60, enlarged for the update with the frame's depth given: each
    enlarged pixel is gated by its map pixel's observed depth, so the rays between a map pixel's
    centre and the object's edge, which reach the wall behind, do not label it. The chair's key
    stays on the chair as with one ray per map pixel (96.4 % of its points against 96.7 %); gated
    by the frame's own depth under each enlarged pixel, 94.8 % (the wall passes that gate)."""
    K_OBS = K_FULL.scaled(80, 60)
    _, inst, _ = scene.render(POSES[0], K_OBS)
    keys = np.where(inst == 10, 1, np.where(inst == 11, 2, -1)).astype(np.int32)
    conf = np.full((60, 80), 0.9, np.float32)
    depth = scene.make_frame(POSES[0], K_FULL).depth_m()
    on_chair = {}
    for name, min_width, step in (("one ray", 0, "render"), ("cast", 160, None), ("rendered", 160, "render")):
        # the fill and the vote off: this is about the voxels the update labels
        vol = integrated_volume(VolumeParams(label_fill_radius_m=0.0, label_vote_radius_m=0.0,
                                             update_min_width_px=min_width))
        step_view = vol.render(POSES[0], K_OBS) if step else None
        stats = vol.apply_update(POSES[0], K_OBS, keys, conf, rendered=step_view, observed_depth_m=depth)
        assert stats.pixels_depth_rejected > 0
        chair = vol.extract_points(keys=[1])
        on_chair[name] = ((scene.instance_at(chair.points.astype(np.float64)) == 10).mean(), len(chair))
    for name in ("cast", "rendered"):
        assert on_chair[name][1] > 1.1 * on_chair["one ray"][1]  # more of the chair labelled
        assert on_chair[name][0] > on_chair["one ray"][0] - 0.01 and on_chair[name][0] > 0.955
