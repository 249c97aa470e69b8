"""Ground-truth region encoder and its noise model (openfusion.encoders.gt / .noise)."""

from __future__ import annotations

import numpy as np
import pytest

from openfusion.encoders import (
    NOISE_PROFILES,
    EncoderError,
    NoiseProfile,
    RegionObservation,
    make_region_encoder,
    make_text_encoder,
    onnx_providers,
    select_device,
)
from openfusion.encoders.captions import CAPTIONS, region_text_embeddings
from openfusion.encoders.gt import GroundTruthRegionEncoder
from openfusion.encoders.masks import area_downsample_labels, label_ids
from openfusion.encoders.noise import apply_region_noise, perturb_embeddings
from openfusion.encoders.text_hash import HashTextEncoder
from openfusion.testing.images import PixelRect, grid_boxes, make_box_frame

CATEGORIES = ["office chair", "table", "sofa", "bed", "bookshelf", "cabinet", "lamp", "monitor"]


@pytest.fixture(scope="module")
def text() -> HashTextEncoder:
    return HashTextEncoder(dim=64)


def _grid_frame(frame_id: int = 0, *, h: int = 128, w: int = 160, rows: int = 3, cols: int = 4, gap: int = 0):
    return make_box_frame(
        grid_boxes(height_px=h, width_px=w, rows=rows, cols=cols, categories=CATEGORIES, gap_px=gap),
        height_px=h,
        width_px=w,
        frame_id=frame_id,
    )


def test_noise_off_regions_equal_ground_truth(text):
    """Clean gt regions are exactly the instance masks at 1/4 size: a wrong downsampling, a shifted
    pixel grid, a lost region or the wrong category text would all change the result."""
    boxes = [
        PixelRect(1, "office chair", 40, 80, 200, 240),  # 4-px aligned: binary at 1/4
        PixelRect(2, "table", 240, 320, 400, 600),
        PixelRect(7, "lamp", 10, 401, 50, 443),  # not aligned: soft boundary cells
    ]
    frame = make_box_frame(boxes, height_px=480, width_px=640)
    enc = GroundTruthRegionEncoder(text, noise="off")
    assert enc.output_size(480, 640) == (120, 160)
    obs = enc.encode(frame)
    obs.validate(dim=text.dim)
    assert isinstance(obs, RegionObservation)
    assert obs.conf_maps.shape == (3, 120, 160)
    assert obs.labels == ["office chair", "table", "lamp"]
    assert obs.embedding_space == text.embedding_space
    # each region embeds its name and captions (openfusion.encoders.captions)
    np.testing.assert_allclose(obs.embeddings, region_text_embeddings(text.encode, ["office chair", "table", "lamp"]),
                               atol=1e-6)

    expected_chair = np.zeros((120, 160), np.float32)
    expected_chair[10:50, 20:60] = 1.0
    np.testing.assert_array_equal(obs.conf_maps[0], expected_chair)
    lamp = obs.conf_maps[2]
    # columns 401..442 cover cells 100 (3 of 4 px), 101..109 (full), 110 (3 of 4 px)
    assert lamp[5, 100] == pytest.approx(0.75)
    assert lamp[5, 105] == pytest.approx(1.0)
    assert lamp[5, 110] == pytest.approx(0.75)
    assert lamp[5, 99] == 0.0 and lamp[5, 111] == 0.0
    # area average preserves each region's area (in output pixels)
    assert obs.conf_maps[2].sum() * 16 == pytest.approx(40 * 42, rel=1e-5)


def test_area_downsample_handles_non_integer_ratio():
    """A 100x90 -> 33x30 grid: every cell's fractions over all labels (incl. background) sum to 1."""
    rng = np.random.default_rng(3)
    labels = rng.integers(0, 4, (100, 90)).astype(np.int32)
    conf = area_downsample_labels(labels, np.array([0, 1, 2, 3]), (33, 30))
    assert conf.shape == (4, 33, 30)
    np.testing.assert_allclose(conf.sum(axis=0), 1.0, atol=1e-6)
    with pytest.raises(EncoderError, match="output size"):
        area_downsample_labels(labels, np.array([1]), (200, 30))


@pytest.mark.parametrize("dtype", [np.int32, np.uint16, np.int64])
def test_area_downsample_equals_counting_pixels_per_cell(dtype):
    """Against the definition (the share of each cell's pixels carrying the id), for compact ids
    (lookup table), ids spread over a wide range (binary search), negative labels, an id absent
    from the image and ids in any order; ``label_ids`` agrees with ``np.unique``."""
    rng = np.random.default_rng(5)
    for spread in (1, 3_000_000):
        labels = rng.integers(0 if dtype == np.uint16 else -2, 6, (37, 51)).astype(np.int64)
        labels = (labels * (spread if dtype == np.int64 else 1)).astype(dtype)
        present = np.unique(labels)
        np.testing.assert_array_equal(label_ids(labels), present)
        ids = np.array([present[3], present[0], int(present[-1]) + spread + 1, present[-1]], np.int64)
        conf = area_downsample_labels(labels, ids, (10, 17))
        rows = np.minimum(((np.arange(37) + 0.5) * 10 / 37).astype(int), 9)
        cols = np.minimum(((np.arange(51) + 0.5) * 17 / 51).astype(int), 16)
        want = np.zeros((4, 10, 17))
        per_cell = np.zeros((10, 17))
        np.add.at(per_cell, (rows[:, None], cols[None, :]), 1.0)
        for k, i in enumerate(ids):
            np.add.at(want[k], (rows[:, None], cols[None, :]), (labels == i).astype(float))
        np.testing.assert_allclose(conf, want / per_cell, rtol=1e-6)
        assert not conf[2].any()


def test_frame_without_ground_truth_is_a_clear_error(text):
    """A live camera frame has no instance image: the gt encoder must say so, not crash."""
    frame = make_box_frame([PixelRect(1, "table", 0, 0, 8, 8)], height_px=32, width_px=32, with_instances=False)
    enc = GroundTruthRegionEncoder(text)
    with pytest.raises(EncoderError, match="no ground-truth instance image"):
        enc.encode(frame)
    frame.instance = np.zeros((32, 32), np.int64)
    with pytest.raises(EncoderError, match="int32"):
        enc.encode(frame)


def test_instances_without_category_are_skipped_and_counted(text):
    """An instance id missing from instance_categories is skipped (counted), the others still encode."""
    frame = make_box_frame([PixelRect(1, "table", 0, 0, 16, 16), PixelRect(2, "sofa", 16, 16, 32, 32)], height_px=32, width_px=32)
    del frame.instance_categories[2]
    enc = GroundTruthRegionEncoder(text)
    obs = enc.encode(frame)
    assert obs.labels == ["table"]
    assert enc.stats["regions_without_category"] == 1


def test_tiny_regions_below_min_area_are_skipped(text):
    """A 2x2-pixel instance is a quarter of one output pixel: below min_area_px=1 it is not a region."""
    frame = make_box_frame([PixelRect(1, "table", 0, 0, 16, 16), PixelRect(2, "lamp", 20, 20, 22, 22)], height_px=32, width_px=32)
    obs = GroundTruthRegionEncoder(text, min_area_px=1.0).encode(frame)
    assert obs.labels == ["table"]
    obs = GroundTruthRegionEncoder(text, min_area_px=0.1).encode(frame)
    assert obs.labels == ["table", "lamp"]


def test_standard_noise_changes_regions_by_the_stated_amounts(text):
    """'standard' = 20 % dropped, 10 % split, 10 % merged, embeddings at cosine 0.9, 2-px boundaries.
    Over 150 frames of 12 regions the observed rates must match within sampling tolerance."""
    enc = GroundTruthRegionEncoder(text, noise="standard", seed=11)
    clean = GroundTruthRegionEncoder(text, noise="off")
    totals = {"in": 0, "dropped": 0, "split": 0, "merged": 0, "candidates": 0}
    cosines = []
    for fid in range(150):
        frame = _grid_frame(fid)
        obs = enc.encode(frame)
        obs.validate(dim=text.dim)
        rep = enc.last_noise_report
        totals["in"] += rep.input_regions
        totals["dropped"] += rep.dropped
        totals["split"] += rep.split
        totals["merged"] += rep.merged
        totals["candidates"] += rep.input_regions - rep.dropped
        ref = dict(zip(clean.encode(frame).labels, clean.encode(frame).embeddings, strict=True))
        for lab, e in zip(obs.labels, obs.embeddings, strict=True):
            cosines.append(float(e @ ref[lab]))
        assert rep.output_regions == obs.num_regions
    n = totals["in"]
    assert totals["dropped"] / n == pytest.approx(0.2, abs=0.03)
    # merges are drawn per surviving region; each event consumes the drawn region and a partner
    assert totals["merged"] / totals["candidates"] == pytest.approx(0.1, abs=0.03)
    assert totals["split"] / totals["candidates"] == pytest.approx(0.1 * 0.85, abs=0.04)
    assert np.mean(cosines) == pytest.approx(0.9, abs=0.02)
    assert np.min(cosines) > 0.88 and np.max(cosines) < 0.92


def test_drop_rate_matches_profile_in_the_output(text):
    """Drop-only noise: the share of regions that reach the output is 1 - drop_prob (0.8 +- 0.03)."""
    enc = GroundTruthRegionEncoder(text, noise=NoiseProfile("drop", drop_prob=0.2), seed=5)
    seen = kept = 0
    for fid in range(200):
        obs = enc.encode(_grid_frame(fid, h=64, w=64, rows=3, cols=4))
        seen += 12
        kept += obs.num_regions
    assert kept / seen == pytest.approx(0.8, abs=0.03)


def test_boundary_noise_moves_boundaries_by_two_pixels(text):
    """Boundary-only noise (2 px): a region's >=0.5 support grows or shrinks by 2 output px per side."""
    box = PixelRect(1, "table", 64, 64, 192, 256)  # output cells rows 16..47, cols 16..63
    enc = GroundTruthRegionEncoder(text, noise=NoiseProfile("edge", boundary_px=2), seed=0)
    outcomes = set()
    for fid in range(12):
        obs = enc.encode(make_box_frame([box], height_px=256, width_px=320, frame_id=fid))
        support = obs.conf_maps[0] >= 0.5
        rows = np.flatnonzero(support.any(axis=1))
        cols = np.flatnonzero(support.any(axis=0))
        grow = 16 - rows[0]
        assert grow in (2, -2)
        assert (rows[-1] - 47, 16 - cols[0], cols[-1] - 63) == (grow, grow, grow)
        outcomes.add(int(grow))
    assert outcomes == {2, -2}, "both erosion and dilation should occur"


def test_split_keeps_embedding_and_covers_the_original(text):
    """A split region becomes two disjoint halves with the same embedding and label whose union is
    the original map; the number of regions grows by the number of splits."""
    rng = np.random.default_rng(0)
    frame = _grid_frame(0, gap=2)
    clean = GroundTruthRegionEncoder(text).encode(frame)
    prof = NoiseProfile("split", split_prob=1.0)
    conf, emb, labels, rep = apply_region_noise(clean.conf_maps, clean.embeddings, clean.labels, prof, rng)
    assert rep.split == clean.num_regions
    assert conf.shape[0] == 2 * clean.num_regions
    for i in range(clean.num_regions):
        a, b = conf[2 * i], conf[2 * i + 1]
        assert labels[2 * i] == labels[2 * i + 1] == clean.labels[i]
        np.testing.assert_array_equal(emb[2 * i], emb[2 * i + 1])
        assert not np.any((a > 0) & (b > 0))
        np.testing.assert_array_equal(a + b, clean.conf_maps[i])
        assert abs(a.sum() - b.sum()) <= 0.25 * clean.conf_maps[i].sum()


def test_merge_joins_adjacent_regions_only(text):
    """Merging pairs only touching regions; the merged map is their union and carries one of their
    embeddings. Regions separated by a gap never merge."""
    rng = np.random.default_rng(1)
    touching = GroundTruthRegionEncoder(text).encode(_grid_frame(0, rows=2, cols=2))
    prof = NoiseProfile("merge", merge_prob=1.0)
    conf, emb, labels, rep = apply_region_noise(
        touching.conf_maps, touching.embeddings, touching.labels, prof, rng
    )
    assert rep.merged == 2 and conf.shape[0] == 2
    for m, e, lab in zip(conf, emb, labels, strict=True):
        sources = [i for i in range(4) if np.any((touching.conf_maps[i] > 0) & (m > 0))]
        assert len(sources) == 2
        np.testing.assert_array_equal(m, np.maximum(touching.conf_maps[sources[0]], touching.conf_maps[sources[1]]))
        assert lab in [touching.labels[i] for i in sources]
        assert any(np.array_equal(e, touching.embeddings[i]) for i in sources)

    apart = GroundTruthRegionEncoder(text).encode(_grid_frame(0, rows=2, cols=2, gap=8))
    conf, _, _, rep = apply_region_noise(apart.conf_maps, apart.embeddings, apart.labels, prof, rng)
    assert rep.merged == 0 and conf.shape[0] == 4


def test_embedding_noise_hits_target_cosine_exactly():
    """Perturbed embeddings are unit-norm and at the requested cosine (not just on average)."""
    rng = np.random.default_rng(2)
    e = rng.standard_normal((50, 384)).astype(np.float32)
    e /= np.linalg.norm(e, axis=1, keepdims=True)
    for target in (0.9, 0.5):
        p = perturb_embeddings(e, target, rng)
        np.testing.assert_allclose(np.linalg.norm(p, axis=1), 1.0, atol=1e-5)
        np.testing.assert_allclose(np.sum(p * e, axis=1), target, atol=1e-4)


def test_noise_is_deterministic_given_seed_and_frame(text):
    """Same seed + frame id -> identical observation (reproducible experiments); another seed differs."""
    frame = _grid_frame(4)
    a = GroundTruthRegionEncoder(text, noise="heavy", seed=3).encode(frame)
    b = GroundTruthRegionEncoder(text, noise="heavy", seed=3).encode(frame)
    c = GroundTruthRegionEncoder(text, noise="heavy", seed=4).encode(frame)
    np.testing.assert_array_equal(a.conf_maps, b.conf_maps)
    np.testing.assert_array_equal(a.embeddings, b.embeddings)
    assert a.labels == b.labels
    assert a.conf_maps.shape != c.conf_maps.shape or not np.array_equal(a.embeddings, c.embeddings)


def test_heavy_is_noisier_than_standard(text):
    """Profiles are ordered: heavy drops more regions and moves embeddings further than standard."""
    assert set(NOISE_PROFILES) >= {"off", "standard", "heavy"}
    s, h = NOISE_PROFILES["standard"], NOISE_PROFILES["heavy"]
    assert h.drop_prob > s.drop_prob and h.embedding_cosine < s.embedding_cosine and h.boundary_px > s.boundary_px


def test_registry_builds_gt_and_rejects_unknown_names():
    """Names and profiles come from config files: a typo must produce an error listing the valid names."""
    enc = make_region_encoder("gt", text_encoder="hash", text_options={"dim": 32}, noise="standard", seed=1)
    assert enc.name == "gt" and enc.dim == 32 and enc.embedding_space == "hash-trigram-32"
    with pytest.raises(ValueError, match="gt, onnx, clip-regions"):
        make_region_encoder("sam2")
    with pytest.raises(ValueError, match="minilm"):
        make_text_encoder("bert")
    with pytest.raises(ValueError, match="off, light, standard, heavy"):
        make_region_encoder("gt", text_encoder="hash", noise="extreme")
    with pytest.raises(ValueError, match="drop_prob"):
        NoiseProfile("bad", drop_prob=1.5)


def test_device_selection_is_cpu_without_a_gpu():
    """On a CPU-only machine "auto" picks cpu, "cuda" is refused, and onnxruntime gets the CPU provider."""
    import torch

    expected = "cuda" if torch.cuda.is_available() else "cpu"
    assert select_device() == expected
    assert select_device("CPU") == "cpu"
    assert onnx_providers("cpu") == ["CPUExecutionProvider"]
    if expected == "cpu":
        with pytest.raises(RuntimeError, match="cuda"):
            select_device("cuda")
    with pytest.raises(ValueError, match="auto, cpu, cuda"):
        select_device("tpu")
    with pytest.raises(ValueError, match="select_device"):
        onnx_providers("gpu")


class _CountingHash(HashTextEncoder):
    """The hash text encoder, recording the texts of each ``encode`` call."""

    def __init__(self) -> None:
        super().__init__(dim=64)
        self.calls: list[list[str]] = []

    def encode(self, texts: list[str]) -> np.ndarray:
        self.calls.append(list(texts))
        return super().encode(texts)


def test_warm_up_embeds_the_vocabulary_so_the_first_frames_cost_no_text_encoding() -> None:
    """Each category a frame showed first used to cost a text-model call inside that frame's
    encode (1 to 3 s per encoder worker at the start of a run); after ``warm_up`` a frame of
    those categories calls the text model no more, through the delay wrapper too."""
    from openfusion.encoders.delayed import DelayedRegionEncoder

    text = _CountingHash()
    encoder = DelayedRegionEncoder(GroundTruthRegionEncoder(text), delay_ms=0)
    encoder.warm_up(CATEGORIES + ["table"])
    names = sorted(set(CATEGORIES))  # one call, each name once, then the captions of those that have them
    assert len(text.calls) == 1 and text.calls[0][: len(names)] == names
    assert len(text.calls[0]) == len(set(text.calls[0])) == len(names) + sum(len(CAPTIONS.get(c, ())) for c in names)
    obs = encoder.encode(_grid_frame())
    assert len(obs.labels) == 12 and set(obs.labels) <= set(CATEGORIES)
    assert len(text.calls) == 1  # nothing left to embed

    fresh = _CountingHash()
    GroundTruthRegionEncoder(fresh).warm_up()  # no vocabulary: the text model's first call still happens
    assert len(fresh.calls) == 1
