"""The semantic step's view of a large map by a probe at the encoded frame's own depth
(``MatchParams.step_probe_blocks``; :mod:`openfusion.mapping.surface_probe`), instead of a ray cast
whose cost grows with the blocks the map holds.

On an analytic room with two objects, mapped from four poses: a mapper that always probes never
ray-casts, writes its updates through the probe's own hits, and maps the scene as well as one that
ray-casts (the same labels on the surface); below the threshold the step still ray-casts. Bad input
tried: an encoded frame whose depth is all missing or not finite (nothing found, nothing written,
the map's labels unchanged)."""

from __future__ import annotations

import numpy as np
import pytest

from openfusion.mapping import (
    RegionDictionary,
    SemanticMapper,
    SemanticVolume,
    VolumeParams,
    raycast,
    segment_points,
)
from openfusion.mapping.params import MatchParams
from openfusion.testing.analytic_scene import (
    ANALYTIC_SPACE,
    TWO_OBJECTS_CAMERA,
    TWO_OBJECTS_OBS_HW,
    TWO_OBJECTS_POSES,
    category_embedding,
    observation_from_instances,
    two_objects_room,
)

K_FULL, OBS_HW, POSES, SPACE = TWO_OBJECTS_CAMERA, TWO_OBJECTS_OBS_HW, TWO_OBJECTS_POSES, ANALYTIC_SPACE
DIM = 32
CLASSES = ["wall", "floor", "chair", "table"]
SCENE = two_objects_room()


def _map(step_probe_blocks: int | None, monkeypatch: pytest.MonkeyPatch | None = None) -> tuple[SemanticMapper, list]:
    volume = SemanticVolume(VolumeParams())
    mapper = SemanticMapper(volume, RegionDictionary(SPACE, DIM), params=MatchParams(step_probe_blocks=step_probe_blocks))
    updates = []
    for i, T in enumerate(POSES):
        frame = SCENE.make_frame(T, K_FULL, frame_id=i)
        volume.integrate(frame)
        if monkeypatch is not None:  # integration may ray-cast nothing either way; the step must not
            monkeypatch.setattr(raycast, "_cast", _no_cast)
        obs = observation_from_instances(frame.instance, frame.instance_categories, out_size=OBS_HW, dim=DIM)
        mapper.step(obs, T, K_FULL, depth_m=frame.depth_m())
        updates.append(mapper.last_update)
        if monkeypatch is not None:
            monkeypatch.undo()
    return mapper, updates


def _no_cast(*_a, **_k):  # noqa: ANN002, ANN003, ANN202
    raise AssertionError("the step ray-cast the map")


def _labels(mapper: SemanticMapper) -> tuple[np.ndarray, np.ndarray]:
    class_emb = np.stack([category_embedding(c, DIM) for c in CLASSES])
    return segment_points(mapper.volume, mapper.dictionary, class_emb)


def _truth(points: np.ndarray) -> np.ndarray:
    names = SCENE.categories
    ids = SCENE.instance_at(points.astype(np.float64))
    return np.array([CLASSES.index(names[int(i)]) if names[int(i)] in CLASSES else -1 for i in ids])


@pytest.fixture(scope="module")
def rendered() -> SemanticMapper:
    return _map(None)[0]


def test_a_probing_step_never_ray_casts_and_writes_through_its_own_hits(monkeypatch: pytest.MonkeyPatch) -> None:
    mapper, updates = _map(0, monkeypatch)
    assert mapper.volume.stats.probes == len(POSES) and mapper.volume.stats.renders == 0
    # every update wrote through the probe's hits: none cast again
    assert all(u.reused_render for u in updates)
    assert all(u.voxels_updated > 1000 for u in updates), [u.voxels_updated for u in updates]


def test_a_probing_step_maps_the_scene_as_a_ray_casting_one(rendered: SemanticMapper) -> None:
    probed, _ = _map(0)
    points, labels = _labels(probed)
    truth = _truth(points)
    labelled = labels >= 0
    # the bar the ray-casting mapper meets (test_mapping_mapper.test_segmentation_of_two_object_scene)
    assert labelled.mean() >= 0.90
    assert (labels[labelled] == truth[labelled]).mean() >= 0.95
    for c in (2, 3):
        assert ((labels == c) & (truth == c)).sum() > 200
    # and, point for point, the labels the ray-casting mapper gives the same surface
    ref_points, ref_labels = _labels(rendered)
    ref = dict(zip(map(tuple, np.round(ref_points, 4)), ref_labels, strict=True))
    common = [(ref[p], lab) for p, lab in zip(map(tuple, np.round(points, 4)), labels, strict=True) if p in ref]
    assert len(common) >= 0.95 * len(points)
    same = np.mean([a == b for a, b in common])
    assert same >= 0.97, same


def test_below_the_threshold_and_by_default_the_step_ray_casts(rendered: SemanticMapper) -> None:
    mapper, _ = _map(20_000)
    assert mapper.volume.num_blocks <= 20_000  # a small room
    assert mapper.volume.stats.renders == len(POSES) and mapper.volume.stats.probes == 0
    assert MatchParams().step_probe_blocks is None  # the default: always ray-cast
    assert rendered.volume.stats.renders == len(POSES) and rendered.volume.stats.probes == 0


def test_a_frame_without_usable_depth_writes_nothing_through_a_probe() -> None:
    mapper, _ = _map(0)
    before = _labels(mapper)
    T = POSES[1]
    frame = SCENE.make_frame(T, K_FULL, frame_id=9)
    obs = observation_from_instances(frame.instance, frame.instance_categories, out_size=OBS_HW, dim=DIM)
    for depth in (np.zeros_like(frame.depth_m()), np.full_like(frame.depth_m(), np.nan),
                  np.full_like(frame.depth_m(), np.inf)):
        stats = mapper.step(obs, T, K_FULL, depth_m=depth)
        assert stats.voxels_updated == 0 and mapper.last_update.pixels_used == 0
    after = _labels(mapper)
    np.testing.assert_array_equal(before[0], after[0])
    np.testing.assert_array_equal(before[1], after[1])
