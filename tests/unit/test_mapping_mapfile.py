"""Map files: save -> load gives the same map and the same answers; bad files are refused whole."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from openfusion.frame import CameraIntrinsics
from openfusion.mapping import (
    MapFormatError,
    QueryParams,
    RegionDictionary,
    RegionTable,
    SemanticMapper,
    SemanticVolume,
    VolumeParams,
    load_map,
    load_map_summary,
    query_region_table,
    query_regions,
    save_map,
    segment_points,
)
from openfusion.mapping.mapfile import MAP_FILE_NAME
from openfusion.poses import look_at
from openfusion.testing.analytic_scene import (
    AnalyticScene,
    Box,
    Room,
    category_embedding,
    observation_from_instances,
)
from openfusion.testing.maps import plant_small_region, strip_region_summaries

K_FULL = CameraIntrinsics(160, 120, 131.25, 131.25, 79.5, 59.5)
DIM = 16


@pytest.fixture(scope="module")
def mapper() -> SemanticMapper:
    scene = AnalyticScene(
        room=Room(size_m=(3.0, 3.0, 2.5)),
        boxes=[
            Box((0.8, 1.8, 0.0), (1.4, 2.3, 0.8), 10, "chair"),
            Box((1.8, 1.6, 0.0), (2.5, 2.2, 0.5), 11, "table"),
        ],
    )
    params = VolumeParams(voxel_size_m=0.04, initial_block_count=256)
    m = SemanticMapper(SemanticVolume(params), RegionDictionary("analytic-test", DIM))
    for i, T in enumerate(
        [look_at((1.5, 0.3, 1.4), (1.5, 2.0, 0.4)), look_at((0.5, 0.5, 1.3), (1.5, 2.0, 0.4))]
    ):
        frame = scene.make_frame(T, K_FULL, frame_id=i)
        m.volume.integrate(frame)
        obs = observation_from_instances(
            frame.instance, frame.instance_categories, out_size=(60, 80), dim=DIM
        )
        m.step(obs, T, K_FULL, depth_m=frame.depth_m())
    return m


def answers(volume: SemanticVolume, dictionary: RegionDictionary) -> list[tuple]:
    out = []
    for name in ("chair", "table", "wall"):
        for r in query_regions(dictionary, volume, category_embedding(name, DIM), top_k=3):
            out.append(
                (r.key, round(r.score, 6), r.label, r.num_points, tuple(r.bbox_min), tuple(r.bbox_max))
            )
    return out


@pytest.mark.parametrize("version", [1, 2])
def test_save_load_round_trip_gives_identical_answers(mapper: SemanticMapper, tmp_path: Path, version: int) -> None:
    """Everything survives: arrays, parameters, dictionary (keys, means, counts, labels, version),
    meta; queries, segmentation and renders from the loaded map equal the original's. Version 2
    (a tile store folder, the default) and version 1 (an ``.npz`` path) alike."""
    target = tmp_path / "site" if version == 2 else tmp_path / "site" / MAP_FILE_NAME
    written = save_map(target, mapper.volume, mapper.dictionary, {"map_id": "lab-1", "frames": 2})
    assert written == (tmp_path / "site" / "map.ofz" if version == 2 else target)
    loaded = load_map(tmp_path / "site")
    assert loaded.meta["map_id"] == "lab-1" and loaded.meta["frames"] == 2
    assert loaded.volume.params == mapper.volume.params
    original, restored = mapper.volume.to_arrays(), loaded.volume.to_arrays()
    order_o = np.lexsort(original["block_coords"].T)
    order_r = np.lexsort(restored["block_coords"].T)
    for name in original:
        np.testing.assert_array_equal(original[name][order_o], restored[name][order_r])
    d0, d1 = mapper.dictionary, loaded.dictionary
    assert (d1.embedding_space, d1.dim, d1.version, d1.next_key) == (
        d0.embedding_space,
        d0.dim,
        d0.version,
        d0.next_key,
    )
    assert answers(loaded.volume, d1) == answers(mapper.volume, d0)
    classes = np.stack([category_embedding(c, DIM) for c in ("wall", "floor", "chair", "table")])
    p0, l0 = segment_points(mapper.volume, d0, classes)
    p1, l1 = segment_points(loaded.volume, d1, classes)
    np.testing.assert_array_equal(p0, p1)
    np.testing.assert_array_equal(l0, l1)
    T = look_at((1.5, 0.3, 1.4), (1.5, 2.0, 0.4))
    r0, r1 = mapper.volume.render(T, K_FULL), loaded.volume.render(T, K_FULL)
    np.testing.assert_array_equal(r0.key_map, r1.key_map)
    np.testing.assert_array_equal(r0.conf_map, r1.conf_map)


def test_save_is_atomic_and_leaves_no_temp_files(mapper: SemanticMapper, tmp_path: Path) -> None:
    """A second save replaces the file in one step (the replaced one kept as ``.prev``); a save
    that fails (meta not JSON) leaves the previous map intact and no temporary file behind."""
    path = tmp_path / "m.npz"
    save_map(path, mapper.volume, mapper.dictionary, {"v": 1})
    with pytest.raises(ValueError, match="JSON"):
        save_map(path, mapper.volume, mapper.dictionary, {"bad": object()})
    assert load_map(path).meta["v"] == 1
    save_map(path, mapper.volume, mapper.dictionary, {"v": 2})
    assert load_map(path).meta["v"] == 2
    assert sorted(os.listdir(tmp_path)) == ["m.npz", "m.prev.npz"]
    assert load_map(tmp_path / "m.prev.npz").meta["v"] == 1


def test_truncated_file_is_refused(mapper: SemanticMapper, tmp_path: Path) -> None:
    """A file cut short (crash while copying) raises MapFormatError, not a zip/numpy error."""
    path = save_map(tmp_path / "m.npz", mapper.volume, mapper.dictionary)
    data = path.read_bytes()
    for cut in (len(data) // 2, len(data) - 100, 10):
        path.write_bytes(data[:cut])
        with pytest.raises(MapFormatError, match="m.npz"):
            load_map(path)


def test_corrupt_bytes_are_refused(mapper: SemanticMapper, tmp_path: Path) -> None:
    """Flipped bytes inside the TSDF data (same size, valid zip layout) fail the CRC check."""
    path = save_map(tmp_path / "m.npz", mapper.volume, mapper.dictionary)
    data = bytearray(path.read_bytes())
    start = data.find(b"volume_tsdf.npy")
    assert start > 0
    offset = start + 4096  # well inside that member's array data
    data[offset : offset + 8] = bytes(b ^ 0xFF for b in data[offset : offset + 8])
    path.write_bytes(bytes(data))
    with pytest.raises(MapFormatError, match="CRC|corrupt|unreadable"):
        load_map(path)


def test_incompatible_or_foreign_files_are_refused(mapper: SemanticMapper, tmp_path: Path) -> None:
    """Another format version, a plain npz without our header, a missing file: one clear error each."""
    path = save_map(tmp_path / "m.npz", mapper.volume, mapper.dictionary)
    with np.load(path, allow_pickle=False) as npz:
        members = {name: npz[name] for name in npz.files}
    members["format_version"] = np.array(99, np.int64)
    future = tmp_path / "future.npz"
    np.savez(future, **members)
    with pytest.raises(MapFormatError, match="version 99"):
        load_map(future)
    header = json.loads(str(members["meta_json"][()]))
    header["arrays"]["dict_counts"]["shape"] = [12345]
    members["format_version"] = np.array(1, np.int64)
    members["meta_json"] = np.array(json.dumps(header))
    inconsistent = tmp_path / "inconsistent.npz"
    np.savez(inconsistent, **members)
    with pytest.raises(MapFormatError, match="dict_counts"):
        load_map(inconsistent)
    foreign = tmp_path / "foreign.npz"
    np.savez(foreign, x=np.zeros(3))
    with pytest.raises(MapFormatError, match="not an OpenFusion-Z map"):
        load_map(foreign)
    with pytest.raises(MapFormatError, match="no map file"):
        load_map(tmp_path / "nowhere")


def test_single_array_file_is_refused(tmp_path: Path) -> None:
    """A plain .npy renamed to .npz is not mistaken for a map (and leaves no open file behind)."""
    path = tmp_path / "array.npz"
    with open(path, "wb") as fh:
        np.save(fh, np.arange(5))
    with pytest.raises(MapFormatError, match="not an OpenFusion-Z map"):
        load_map(path)


# ----------------------------------------------------------------------- region summaries


def _rows(results: list) -> list[tuple]:
    return [(r.key, round(r.score, 6), r.label, r.num_points) for r in results]


def test_summary_answers_equal_the_full_map_answers(mapper: SemanticMapper, tmp_path: Path) -> None:
    """A saved map carries per-region summaries (count, centroid, 1st-99th percentile box) of its
    surface; ``load_map_summary`` reads them and the dictionary without the volume, and a query
    from them returns the same regions, scores, counts and boxes as one from the loaded volume."""
    path = save_map(tmp_path / "site", mapper.volume, mapper.dictionary)
    summary = load_map_summary(path)
    assert summary is not None and summary.volume_params == mapper.volume.params
    surface = mapper.volume.extract_points()
    want = RegionTable.of_points(surface.keys, surface.points)
    np.testing.assert_array_equal(summary.regions.keys, want.keys)
    np.testing.assert_array_equal(summary.regions.num_points, want.num_points)
    for name in ("centroid", "bbox_min", "bbox_max"):
        np.testing.assert_allclose(getattr(summary.regions, name), getattr(want, name), atol=1e-6)
    chair = next(int(k) for k in want.keys if mapper.dictionary.label(int(k)) == "chair")
    np.testing.assert_allclose(summary.regions.centroid[summary.regions.row(chair)],
                               surface.points[surface.keys == chair].mean(axis=0), atol=1e-5)
    loaded = load_map(path)
    for name in ("chair", "table", "wall", "floor"):
        vector = category_embedding(name, DIM)
        for top_k in (1, 3, 5):
            full = query_regions(loaded.dictionary, loaded.volume, vector, top_k)
            lean = query_region_table(summary.dictionary, summary.regions, vector, top_k)
            assert _rows(lean) == _rows(full) and lean
            for a, b in zip(lean, full, strict=True):
                np.testing.assert_allclose(a.bbox_min, b.bbox_min, atol=1e-6)
                np.testing.assert_allclose(a.bbox_max, b.bbox_max, atol=1e-6)


def test_a_region_of_a_few_points_is_not_an_answer(mapper: SemanticMapper, tmp_path: Path) -> None:
    """A stray fragment (a region of a few surface points with the chair's embedding, so it ties
    with the chair at score 1) is left out by both query paths under the declared default
    ``min_region_points``, and comes back only when the caller asks for regions that small."""
    chair = next(int(k) for k in mapper.dictionary.snapshot().keys if mapper.dictionary.label(int(k)) == "chair")
    volume, dictionary, fragment = plant_small_region(mapper.volume, mapper.dictionary, like_key=chair,
                                                      label="chair fragment")
    path = save_map(tmp_path / "m.npz", volume, dictionary)
    summary = load_map_summary(path)
    assert summary is not None
    n = int(summary.regions.num_points[summary.regions.row(fragment)])
    assert 0 < n < QueryParams().min_region_points == 50
    vector = category_embedding("chair", DIM)
    for results in (query_regions(dictionary, volume, vector, 3),
                    query_region_table(summary.dictionary, summary.regions, vector, 3)):
        assert results[0].key == chair and fragment not in [r.key for r in results] and len(results) == 3
        assert all(r.num_points >= 50 for r in results)
    for results in (query_regions(dictionary, volume, vector, 3, min_points=1),
                    query_region_table(summary.dictionary, summary.regions, vector, 3, min_points=1)):
        assert fragment in [r.key for r in results[:2]]


def test_map_saved_without_summaries_still_loads(mapper: SemanticMapper, tmp_path: Path) -> None:
    """A map saved before summaries were stored: ``load_map`` reads it as before and
    ``load_map_summary`` says there are none (None), so a query falls back to the volume."""
    path = save_map(tmp_path / "m.npz", mapper.volume, mapper.dictionary)
    old = strip_region_summaries(path, tmp_path / "old.npz")
    with np.load(old) as npz:
        assert not [n for n in npz.files if n.startswith("summary_")]
    assert load_map_summary(old) is None
    assert answers(load_map(old).volume, load_map(old).dictionary) == answers(mapper.volume, mapper.dictionary)


def test_a_checkpoint_saved_without_summaries_reads_like_an_old_map(mapper: SemanticMapper, tmp_path: Path) -> None:
    """``save_map(summary=False)`` (geometry's periodic checkpoints) stores no summary member,
    ``load_map_summary`` answers None and the volume gives the same answers."""
    path = save_map(tmp_path / "ckpt.npz", mapper.volume, mapper.dictionary, summary=False)
    with np.load(path) as npz:
        assert not [n for n in npz.files if n.startswith("summary_")]
    assert load_map_summary(path) is None
    loaded = load_map(path)
    assert answers(loaded.volume, loaded.dictionary) == answers(mapper.volume, mapper.dictionary)


def test_corrupt_summaries_are_refused_by_both_readers(mapper: SemanticMapper, tmp_path: Path) -> None:
    """The summary members are checked like every array (the zip's and the header's CRC-32):
    flipped bytes in them fail both ``load_map_summary`` and ``load_map`` (refused whole)."""
    path = save_map(tmp_path / "m.npz", mapper.volume, mapper.dictionary)
    data = bytearray(path.read_bytes())
    start = data.find(b"summary_num_points.npy")
    assert start > 0
    offset = data.find(b"\n", data.find(b"{'descr'", start)) + 1  # first byte after the .npy header
    data[offset : offset + 4] = bytes(b ^ 0xFF for b in data[offset : offset + 4])
    path.write_bytes(bytes(data))
    for read in (load_map_summary, load_map):
        with pytest.raises(MapFormatError, match=r"CRC.*summary_num_points|summary_num_points.*CRC"):
            read(path)


class _CategoryEncoder:
    """Text -> the analytic scene's category embedding of its last word (a stand-in text encoder)."""

    embedding_space = "analytic-test"

    def encode(self, texts: list[str]) -> np.ndarray:
        return np.stack([category_embedding(t.split()[-1], DIM) for t in texts]).astype(np.float32)


def test_a_map_records_its_relevancy_calibration_and_answers_where_things_are(
    mapper: SemanticMapper, tmp_path: Path
) -> None:
    """The header records the calibration of the map's space (here an uncalibrated one: the 0.5
    fallback), both readers return it; answered from the saved summaries, the chair is on the
    floor and next to the table, and "the chair next to the table" names the table."""
    from openfusion.mapping.queries import answer_texts
    from openfusion.mapping.relevancy import calibration_for

    path = save_map(tmp_path / "m.npz", mapper.volume, mapper.dictionary)
    want = calibration_for("analytic-test").to_dict()
    assert want["calibrated"] is False and want["threshold"] == 0.5
    summary = load_map_summary(path)
    assert summary.relevancy == want and load_map(path).relevancy == want
    (chair, _), (related, answer) = answer_texts(
        summary.dictionary, summary.regions, ["chair", "the chair next to the table"], _CategoryEncoder(), top_k=1,
        calibration=calibration_for("analytic-test", summary.relevancy))
    assert chair[0].label == "chair" and chair[0].match and chair[0].relevancy > 0.5
    labels = {(n.label, n.relation) for n in chair[0].nearby}
    assert ("floor", "on") in labels and ("table", "next to") in labels
    assert related[0].label == "chair" and related[0].relation.label == "table" and answer.relation.anchor == "table"
    np.testing.assert_allclose(chair[0].centroid, summary.regions.centroid[summary.regions.row(chair[0].key)])
