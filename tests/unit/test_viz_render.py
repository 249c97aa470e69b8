"""openfusion.viz render: geometry of the virtual camera, visibility rules, and query highlights
that land on the queried object of the synthetic scene."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from openfusion.encoders import make_text_encoder
from openfusion.poses import look_at
from openfusion.sources.synthetic import SyntheticWorld
from openfusion.testing.maps import (
    SyntheticMapSpec,
    cached_synthetic_map,
    project_points,
    sample_instance_points,
)
from openfusion.viz.camera import VirtualCamera, overview_camera, pinhole
from openfusion.viz.errors import VizError
from openfusion.viz.picture import ViewOptions, open_map, picture_of_map
from openfusion.viz.render import CaptionLine, draw_caption, render_mesh, save_png


def _quad(z: float, half: float = 0.5, *, normal_up: bool = True):
    """A square at height z; vertex normals +z (or -z)."""
    v = np.array([[-half, -half, z], [half, -half, z], [half, half, z], [-half, half, z]], np.float64)
    t = np.array([[0, 1, 2], [0, 2, 3]], np.int64)
    n = np.tile([0.0, 0.0, 1.0 if normal_up else -1.0], (4, 1))
    return v, t, n


def _cam_parts(cam: VirtualCamera):
    return cam.T_world_cam, cam.intrinsics


def _top_camera(height_m: float = 3.0, size_px: int = 101) -> VirtualCamera:
    T = look_at(np.array([0.0, 0.0, height_m]), np.zeros(3), up=(0.0, 1.0, 0.0))
    return VirtualCamera(T, pinhole(size_px, size_px, fov_deg=60.0))


# ------------------------------------------------------------------ render geometry


def test_quad_covers_exactly_the_pixels_its_corners_project_to():
    """A 1 m square seen from 3 m above: its pixel footprint, depth and colour match the projection."""
    v, t, n = _quad(0.0)
    cam = _top_camera()
    colors = np.tile(np.array([[200, 40, 40]], np.uint8), (4, 1))
    out = render_mesh(v, t, colors, cam, vertex_normals=n)
    uv, z, ok = project_points(v, cam.T_world_cam, cam.intrinsics)
    assert ok.all()
    u0, u1 = uv[:, 0].min(), uv[:, 0].max()
    v0, v1 = uv[:, 1].min(), uv[:, 1].max()
    hit = out.triangle_index >= 0
    ys, xs = np.nonzero(hit)
    assert abs(xs.min() - u0) <= 1 and abs(xs.max() - u1) <= 1
    assert abs(ys.min() - v0) <= 1 and abs(ys.max() - v1) <= 1
    np.testing.assert_allclose(out.depth_m[hit], 3.0, atol=1e-4)
    assert (out.depth_m[~hit] == 0).all()
    px = out.rgb[hit].astype(int)
    assert (px[:, 0] > 2 * px[:, 1]).all() and (px[:, 1] == px[:, 2]).all()  # shaded red, hue kept
    assert (out.rgb[~hit] == 250).all()


def test_back_faces_are_culled_and_noise_pockets_are_peeled():
    """Seen from above: a square whose normal points down is invisible (culled); a front-facing
    square 3 cm under a back face (a pocket inside a wall) is skipped with peel_gap_m, but one
    0.5 m under it (a real gap of free space) is kept."""
    cam = _top_camera()
    v_hi, t_hi, n_hi = _quad(0.5, normal_up=False)
    white = np.full((4, 3), 255, np.uint8)
    only_back = render_mesh(v_hi, t_hi, white, cam, vertex_normals=n_hi)
    assert only_back.coverage == 0.0
    two_sided = render_mesh(v_hi, t_hi, white, cam, vertex_normals=None)
    assert two_sided.coverage > 0.1

    for gap_below_m, expect_visible in ((0.03, False), (0.5, True)):
        v_lo, t_lo, n_lo = _quad(0.5 - gap_below_m, half=0.3, normal_up=True)
        v = np.concatenate([v_hi, v_lo])
        t = np.concatenate([t_hi, t_lo + 4])
        n = np.concatenate([n_hi, n_lo])
        out = render_mesh(v, t, np.full((8, 3), 200, np.uint8), cam, vertex_normals=n, peel_gap_m=0.1)
        assert (out.coverage > 0.01) is expect_visible, gap_below_m
        plain = render_mesh(v, t, np.full((8, 3), 200, np.uint8), cam, vertex_normals=n)
        assert plain.coverage > 0.01  # without peeling the pocket's far side shows


def test_supersampling_keeps_size_and_coverage():
    """supersample=2 gives the same image size and about the same covered area."""
    v, t, n = _quad(0.0)
    cam = _top_camera()
    c = np.full((4, 3), 180, np.uint8)
    a = render_mesh(v, t, c, cam, vertex_normals=n)
    b = render_mesh(v, t, c, cam, vertex_normals=n, supersample=2)
    assert b.rgb.shape == a.rgb.shape
    assert abs(a.coverage - b.coverage) < 0.02


def test_render_refuses_bad_inputs():
    """Wrong colour dtype, out-of-range triangle indices, bad supersample and tiny images are VizErrors."""
    v, t, n = _quad(0.0)
    cam = _top_camera()
    with pytest.raises(VizError, match="uint8"):
        render_mesh(v, t, np.zeros((4, 3)), cam)
    with pytest.raises(VizError, match="do not exist"):
        render_mesh(v, t + 10, np.zeros((4, 3), np.uint8), cam)
    with pytest.raises(VizError, match="supersample"):
        render_mesh(v, t, np.zeros((4, 3), np.uint8), cam, supersample=9)
    with pytest.raises(VizError, match="width"):
        pinhole(8, 100, fov_deg=45)


def test_overview_camera_frames_all_points_tightly():
    """With no outlier allowance every point projects inside the image, and the fit is tight (the
    points span >= 80% of one side); the default allowance drops at most 0.2% per side."""
    rng = np.random.default_rng(3)
    pts = rng.uniform([0, 0, 0], [6, 4, 2.5], size=(4000, 3))
    _, _, ok_default = project_points(pts, *_cam_parts(overview_camera(pts, width_px=400, height_px=300)))
    assert ok_default.mean() >= 1 - 4 * 0.002
    cam = overview_camera(pts, width_px=400, height_px=300, outlier_quantile=0.0)
    uv, z, ok = project_points(pts, cam.T_world_cam, cam.intrinsics)
    assert ok.all() and (z > 0).all()
    span_u = (uv[:, 0].max() - uv[:, 0].min()) / 400
    span_v = (uv[:, 1].max() - uv[:, 1].min()) / 300
    assert max(span_u, span_v) > 0.8
    # above the box: the camera is higher than the top of the points
    assert cam.position_m[2] > 2.5
    with pytest.raises(VizError, match="up axis"):
        overview_camera(pts, up="z")
    with pytest.raises(VizError, match="empty"):
        overview_camera(np.zeros((0, 3)))


def test_caption_draws_text_and_swatch(tmp_path):
    """The caption box holds dark text pixels and the exact swatch colour; PNG is written atomically."""
    img = Image.new("RGB", (320, 240), (250, 250, 250))
    out = draw_caption(img, [CaptionLine("query: chair"), CaptionLine("#1 chair 0.91", (235, 30, 30))])
    a = np.asarray(out)
    box = a[:60, :200]
    assert (box.sum(axis=2) < 200).any()  # text
    assert ((box == (235, 30, 30)).all(axis=2)).sum() > 20  # swatch
    assert (a[200:, 250:] == 250).all()  # rest untouched
    path = save_png(out, tmp_path / "c.png")
    with Image.open(path) as back:
        assert back.size == (320, 240)
    with pytest.raises(VizError, match=".png"):
        save_png(out, tmp_path / "c.jpg")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.png"]


# ------------------------------------------------------------------ the synthetic scene


@pytest.fixture(scope="module")
def scene_map(tmp_path_factory):
    spec = SyntheticMapSpec()
    return open_map(cached_synthetic_map(tmp_path_factory.getbasetemp(), spec)), spec


def _dilate(mask: np.ndarray, steps: int) -> np.ndarray:
    for _ in range(steps):
        g = mask.copy()
        g[1:] |= mask[:-1]
        g[:-1] |= mask[1:]
        g[:, 1:] |= mask[:, :-1]
        g[:, :-1] |= mask[:, 1:]
        mask = g
    return mask


def test_map_picture_shows_the_room_from_outside(scene_map, tmp_path):
    """RGB picture of the map: the map fills a fair part of the image and looks like the scene
    (floor wood tones and wall greys present, not a blank or single-colour image)."""
    loaded, _ = scene_map
    pic = picture_of_map(loaded, view=ViewOptions(width_px=320, height_px=240), caption=True)
    assert pic.image.size == (320, 240)
    assert 0.15 < pic.rendered.coverage < 0.95
    rgb = np.asarray(pic.image)[pic.rendered.triangle_index >= 0]
    assert len(np.unique(rgb // 32, axis=0)) > 20
    save_png(pic.image, tmp_path / "view.png")
    assert (tmp_path / "view.png").stat().st_size > 10_000


def test_query_highlight_falls_on_the_queried_object(scene_map):
    """Query "chair": the red pixels of the picture lie on the ground-truth chair.

    Ground truth: points sampled on every "chair" instance of the synthetic world, projected with
    the picture's own camera and kept where they agree with the rendered depth (8 cm, two 4 cm
    voxels), then grown by 3 px (a 4 cm voxel spans about 2 px here). At least 75% of the red
    pixels must fall on it (the rest is the region's label bleeding onto neighbouring voxels at the
    encoder's 40x30 resolution), and at least half of the visible chair must be red.
    """
    loaded, spec = scene_map
    text = make_text_encoder(spec.text_encoder)
    pic = picture_of_map(
        loaded, view=ViewOptions(width_px=320, height_px=240), query="chair", text_encoder=text, caption=False
    )
    assert pic.hits and pic.hits[0].label == "chair"
    rgb = np.asarray(pic.image).astype(int)
    red = (rgb[..., 0] > 60) & (rgb[..., 0] > 2 * rgb[..., 1]) & (rgb[..., 0] > 2 * rgb[..., 2])
    assert red.sum() >= 30
    assert (red & pic.highlight_mask).sum() == pic.highlight_mask.sum()
    # colour only where the matched region is: pixels off every triangle touching one of its
    # vertices are grey (r == g == b up to rounding)
    touching = np.isin(pic.mesh.keys, [h.key for h in pic.hits])[pic.mesh.triangles].any(axis=1)
    near_region = _dilate(pic.rendered.mask_of_triangles(touching), 1)
    others = rgb[~near_region & (pic.rendered.triangle_index >= 0)]
    assert len(others) > 1000
    assert (np.abs(others[:, 0] - others[:, 1]) <= 2).all() and (np.abs(others[:, 1] - others[:, 2]) <= 2).all()

    world = SyntheticWorld(spec.seed)
    pts = sample_instance_points(world, "chair")
    cam = pic.rendered.camera
    uv, z, ok = project_points(pts, cam.T_world_cam, cam.intrinsics)
    d = pic.rendered.depth_m[uv[:, 1], uv[:, 0]]
    visible = ok & (d > 0) & (np.abs(d - z) < 0.08)
    gt = np.zeros(red.shape, bool)
    gt[uv[visible, 1], uv[visible, 0]] = True
    assert gt.sum() >= 30
    precision = (red & _dilate(gt, 3)).sum() / red.sum()
    recall = (gt & red).sum() / gt.sum()
    assert precision >= 0.75, precision
    assert recall >= 0.5, recall


def test_picture_refuses_a_map_without_regions_for_a_query(tmp_path):
    """A map mapped without semantics cannot answer a query: one clear VizError."""
    from openfusion.mapping import RegionDictionary, SemanticVolume, VolumeParams, load_map, save_map
    from openfusion.sources import open_source

    volume = SemanticVolume(VolumeParams(voxel_size_m=0.05))
    for frame in open_source("synthetic:seed=2,frames=2,width=80,height=60"):
        volume.integrate(frame)
    save_map(tmp_path / "geo", volume, RegionDictionary("hash-trigram-256", 256))
    loaded = load_map(tmp_path / "geo")
    with pytest.raises(VizError, match="no regions"):
        picture_of_map(loaded, view=ViewOptions(width_px=64, height_px=48), query="chair", text_encoder=make_text_encoder("hash"))
    pic = picture_of_map(loaded, view=ViewOptions(width_px=64, height_px=48))  # geometry alone renders
    assert pic.rendered.coverage > 0


def test_overview_camera_does_not_depend_on_point_order():
    """The same points in another order (Open3D's mesh order varies run to run) give the same camera."""
    rng = np.random.default_rng(5)
    pts = rng.uniform([0, 0, 0], [6, 4, 2.5], size=(30_000, 3))
    a = overview_camera(pts, width_px=320, height_px=240, max_fit_points=5000)
    b = overview_camera(pts[rng.permutation(len(pts))], width_px=320, height_px=240, max_fit_points=5000)
    np.testing.assert_allclose(a.T_world_cam, b.T_world_cam, atol=1e-9)
