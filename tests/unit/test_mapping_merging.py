"""Region merging (openfusion.mapping.merging): contacts from labelled voxels, the merge rule, the
pass on a real volume, and the matcher's join of a part of an already known region.

Bad inputs tried: voxels and keys of different lengths, negative keys, radius 0 (refused with a
clear error); contacts naming keys the dictionary does not hold (ignored)."""

from __future__ import annotations

import numpy as np
import pytest

from openfusion.frame import CameraIntrinsics
from openfusion.mapping import RegionDictionary, SemanticMapper, SemanticVolume, VolumeParams
from openfusion.mapping.matching import plan_update
from openfusion.mapping.merging import MergeSchedule, merge_regions, plan_merges, region_contacts
from openfusion.mapping.params import MatchParams, MergeParams
from openfusion.mapping.volume import RenderedView
from openfusion.poses import look_at
from openfusion.testing.analytic_scene import (
    AnalyticScene,
    Box,
    Room,
    SimpleObservation,
    category_embedding,
    observation_from_instances,
)

DIM = 32
SPACE = "analytic-test"


def slab(x0: int, x1: int, y0: int = 0, y1: int = 20, z0: int = 0, z1: int = 2) -> np.ndarray:
    """Integer voxel coordinates of the box [x0, x1) x [y0, y1) x [z0, z1)."""
    g = np.mgrid[x0:x1, y0:y1, z0:z1].reshape(3, -1).T
    return g.astype(np.int64)


def voxels_of(*parts: tuple[np.ndarray, int]) -> tuple[np.ndarray, np.ndarray]:
    vox = np.concatenate([p for p, _ in parts])
    keys = np.concatenate([np.full(len(p), k, np.int64) for p, k in parts])
    return vox, keys


def dictionary_with(*regions: tuple[str, int]) -> RegionDictionary:
    """A dictionary with regions of these (category, observation count), keys 0, 1, ..."""
    d = RegionDictionary(SPACE, DIM)
    for label, count in regions:
        d.add(category_embedding(label, DIM), label=label, count=count)
    return d


def test_contacts_count_each_voxel_next_to_the_other_region_once() -> None:
    """Two 2-voxel-thick slabs side by side along x: the voxels in the last column of one and the
    first of the other touch (26-neighbourhood), each counted once however many neighbours it has."""
    vox, keys = voxels_of((slab(0, 10), 0), (slab(10, 14), 1))
    c = region_contacts(vox, keys)
    assert c.keys.tolist() == [0, 1] and c.surface_voxels.tolist() == [400, 160]
    assert (c.pair_a.tolist(), c.pair_b.tolist()) == ([0], [1])
    assert (c.contact_a.tolist(), c.contact_b.tolist()) == ([40], [40])  # one 20 x 2 column each
    wider = region_contacts(vox, keys, radius_vox=2)
    assert (wider.contact_a.tolist(), wider.contact_b.tolist()) == ([80], [80])


def _brute_force_contacts(vox: np.ndarray, keys: np.ndarray, radius: int) -> dict[tuple[int, int], int]:
    """{(a, b): voxels of a with a voxel of b within ``radius`` per axis}, the obvious way."""
    where = {tuple(v): int(k) for v, k in zip(vox.tolist(), keys.tolist(), strict=True)}
    out: dict[tuple[int, int], int] = {}
    rng = range(-radius, radius + 1)
    for v, k in where.items():
        near = {where.get((v[0] + dx, v[1] + dy, v[2] + dz)) for dx in rng for dy in rng for dz in rng}
        for other in near - {None, k}:
            out[(k, other)] = out.get((k, other), 0) + 1
    return out


@pytest.mark.parametrize("radius", [1, 2])
def test_contacts_equal_a_brute_force_count_across_block_borders(radius: int) -> None:
    """Random voxels of 5 interleaved regions around block borders (negative coordinates too): the
    block-padded computation counts exactly what a voxel-by-voxel search counts."""
    rng = np.random.default_rng(radius)
    vox = np.unique(rng.integers(-10, 14, size=(1500, 3)), axis=0)
    keys = rng.integers(0, 5, size=len(vox))
    c = region_contacts(vox, keys, radius_vox=radius)
    expected = _brute_force_contacts(vox, keys, radius)
    got = {}
    for a, b, ca, cb in zip(c.pair_a, c.pair_b, c.contact_a, c.contact_b, strict=True):
        got[(int(a), int(b))], got[(int(b), int(a))] = int(ca), int(cb)
    assert got == expected and len(c.pair_a) == 10
    np.testing.assert_array_equal(c.surface_voxels, np.bincount(keys))


def test_contacts_refuse_bad_input() -> None:
    with pytest.raises(ValueError, match="differ in length"):
        region_contacts(np.zeros((3, 3)), np.zeros(2))
    with pytest.raises(ValueError, match=">= 0"):
        region_contacts(np.zeros((1, 3)), np.array([-1]))
    with pytest.raises(ValueError, match="radius_vox"):
        region_contacts(np.zeros((1, 3)), np.array([0]), radius_vox=0)
    assert len(region_contacts(np.zeros((0, 3)), np.zeros(0)).keys) == 0


def test_two_touching_fragments_of_one_object_merge_into_the_more_observed() -> None:
    """A wall in two fragments (same embedding, side by side): one group, kept under the key with
    more observations."""
    d = dictionary_with(("wall", 3), ("wall", 9))
    vox, keys = voxels_of((slab(0, 10), 0), (slab(10, 30), 1))
    plan = plan_merges(d, region_contacts(vox, keys), MergeParams())
    assert plan.merged_into == {0: 1}


def test_touching_regions_of_different_objects_do_not_merge() -> None:
    """A chair against a table: as much contact as the fragments above, but the embeddings differ."""
    d = dictionary_with(("chair", 3), ("table", 9))
    vox, keys = voxels_of((slab(0, 10), 0), (slab(10, 30), 1))
    contacts = region_contacts(vox, keys)
    assert float(d.embedding(0) @ d.embedding(1)) < MergeParams().merge_min_cos
    assert plan_merges(d, contacts, MergeParams()).merged_into == {}
    # The same pair merges once the threshold lets any embedding agree: contact alone was enough.
    assert plan_merges(d, contacts, MergeParams(merge_min_cos=-1)).merged_into == {0: 1}


def test_separated_objects_of_one_class_do_not_merge() -> None:
    """Two chairs 3 voxels apart (same embedding) do not touch; a brief touch of a few voxels (under
    merge_min_contact_voxels) and a long region touching along a short edge (under the fraction) do
    not count as contact either."""
    d = dictionary_with(("chair", 3), ("chair", 5))
    apart = voxels_of((slab(0, 10), 0), (slab(13, 23), 1))
    assert len(region_contacts(*apart).pair_a) == 0
    assert plan_merges(d, region_contacts(*apart)).merged_into == {}
    corner = voxels_of((slab(0, 10), 0), (slab(10, 20, y0=19, y1=40), 1))  # share one 1 x 2 column
    c = region_contacts(*corner)
    assert c.contact_a.tolist() == [4]
    assert plan_merges(d, c).merged_into == {}
    edge = voxels_of((slab(0, 100, y1=100), 0), (slab(100, 200, y1=100), 1))  # 200 of 20,000 voxels
    assert plan_merges(d, region_contacts(*edge)).merged_into == {}


def test_a_small_fragment_joins_its_best_neighbour_and_does_not_bridge_two_regions() -> None:
    """A 2-voxel wall fragment between two walls that barely touch each other (one column of a
    corner): it joins the wall it touches most, and the two walls stay apart."""
    d = dictionary_with(("wall", 9), ("wall", 8), ("wall", 1))
    left, right = slab(0, 20, y0=0, y1=20), slab(20, 40, y0=19, y1=40)  # corner: 4 voxels in contact
    bit = np.array([[20, 17, 0], [19, 18, 1]])  # touches left a lot, right a little
    plan = plan_merges(d, region_contacts(*voxels_of((left, 0), (right, 1), (bit, 2))))
    assert plan.merged_into == {2: 0}


def test_merges_are_transitive_and_ignore_unknown_keys() -> None:
    """Fragments a-b-c in a row merge into one (a and c never touch); a region geometry reports but
    the dictionary does not hold (key 7) is left alone."""
    d = dictionary_with(("floor", 2), ("floor", 10), ("floor", 4))
    vox, keys = voxels_of((slab(0, 10), 0), (slab(10, 20), 1), (slab(20, 30), 2), (slab(30, 40), 7))
    plan = plan_merges(d, region_contacts(vox, keys))
    assert plan.merged_into == {0: 1, 2: 1} and plan.groups == {1: [0, 2]}


@pytest.mark.parametrize("embedding", ["weighted", "mean", "first"])
def test_merged_embedding_and_counts(embedding: str) -> None:
    """Counts add up; the embedding is the count-weighted mean (default), the plain mean, or the
    survivor's."""
    d = RegionDictionary(SPACE, 2)
    a = d.add(np.array([1.0, 0.0]), count=3)
    b = d.add(np.array([0.0, 1.0]), count=1)
    d.merge(a, b, embedding=embedding)
    expected = {"weighted": [0.75, 0.25], "mean": [0.5, 0.5], "first": [1.0, 0.0]}[embedding]
    np.testing.assert_allclose(d.mean_embedding(a), expected, atol=1e-6)
    assert d.count(a) == 4 and b not in d
    with pytest.raises(ValueError, match="embedding must be"):
        d.merge(a, d.add(np.array([1.0, 1.0])), embedding="max")


def test_replica_resolves_merged_keys_from_a_delta() -> None:
    """A replica that applied the merge delta maps a merged-away key (and a chain of them) to the
    survivor: what geometry does with an update that still carries the old key."""
    owner = dictionary_with(("wall", 1), ("wall", 5), ("wall", 2))
    replica = RegionDictionary.from_snapshot(owner.snapshot())
    v = owner.version
    owner.merge(1, 0)
    owner.merge(2, 1)
    replica.apply_delta(owner.delta_since(v))
    assert replica.survivor_of(0) == 2 and replica.survivor_of(1) == 2 and replica.survivor_of(9) is None
    np.testing.assert_array_equal(replica.resolve_keys(np.array([[0, 1], [-1, 2]])), [[2, 2], [-1, 2]])


def test_a_region_without_voxels_in_two_passes_is_removed_and_replicas_follow() -> None:
    """Region 1 holds no voxel (taken over by others): kept after the first pass (its first update
    may still be on its way), removed after the second, in the same delta as a merge; a replica
    drops it too (a removal, not a merge)."""
    from openfusion.mapping.merging import EmptyRegions, apply_merges

    d = dictionary_with(("wall", 5), ("chair", 1), ("wall", 2))
    replica = RegionDictionary.from_snapshot(d.snapshot())
    contacts = region_contacts(*voxels_of((slab(0, 10), 0), (slab(10, 20), 2)))
    empty = EmptyRegions()
    assert empty.to_remove(d, contacts) == []
    removed = empty.to_remove(d, contacts)
    assert removed == [1]
    v = d.version
    apply_merges(d, plan_merges(d, contacts).merged_into, removed=removed)
    assert d.version == v + 1 and list(d.keys) == [0]
    delta = d.delta_since(v)
    replica.apply_delta(delta)
    assert list(replica.keys) == [0] and RegionDictionary.merges_of(delta) == {2: 0}


def test_schedule_runs_every_n_semantic_frames() -> None:
    schedule = MergeSchedule(MergeParams(merge_every=3))
    assert [schedule.due() for _ in range(7)] == [False, False, True, False, False, True, False]
    assert not any(MergeSchedule(MergeParams(merge_every=0)).due() for _ in range(5))


def test_schedule_keeps_passes_apart_in_time_when_asked() -> None:
    """The services' schedule (min_interval_s): frames due every 2, passes at least 1 s apart on
    the given clock; a pass held back comes with the first frame after the interval."""
    now = [0.0]
    schedule = MergeSchedule(MergeParams(merge_every=2), min_interval_s=1.0, clock=lambda: now[0])
    due = []
    for _ in range(8):  # 0.25 s per semantic frame
        due.append(schedule.due())
        now[0] += 0.25
    assert due == [False, True, False, False, False, True, False, False]


# ---------------------------------------------------------------------------- on a real volume

K_FULL = CameraIntrinsics(320, 240, 262.5, 262.5, 159.5, 119.5)
OBS_HW = (60, 80)
CHAIR, TABLE, FAR_CHAIR, CHAIR_HALF = 10, 11, 12, 99


def _scene() -> AnalyticScene:
    """A chair against a table (touching at x = 1.3 m) and a second chair 1.1 m further on."""
    return AnalyticScene(
        room=Room(size_m=(4.0, 3.0, 2.5), face_ids=(1, 1, 1, 1, 2, 3)),
        boxes=[
            Box((0.7, 1.8, 0.0), (1.3, 2.3, 0.8), CHAIR, "chair", (200, 40, 40)),
            Box((1.3, 1.8, 0.0), (2.0, 2.3, 0.5), TABLE, "table", (40, 200, 40)),
            Box((3.1, 1.8, 0.0), (3.6, 2.3, 0.8), FAR_CHAIR, "chair", (200, 40, 40)),
        ],
    )


def test_merge_pass_on_a_volume_joins_the_fragments_of_one_chair_only() -> None:
    """The encoder splits the first chair into a left and a right half every frame, so the map holds
    it as two regions. One merge pass: the halves become one region (voxels relabelled, counts
    summed); the table it stands against and the other chair (same class, apart) keep their keys."""
    scene = _scene()
    volume = SemanticVolume(VolumeParams(initial_block_count=2048))
    dictionary = RegionDictionary(SPACE, DIM)
    # Matching without the join rule: the halves must stay two regions until the merge pass.
    mapper = SemanticMapper(volume, dictionary, params=MatchParams(join_min_coverage=None))
    for i, T in enumerate([look_at((2.0, 0.2, 1.5), (1.9, 2.0, 0.4)), look_at((1.6, 0.3, 1.4), (1.6, 2.0, 0.3))]):
        frame = scene.make_frame(T, K_FULL, frame_id=i)
        volume.integrate(frame)
        inst = frame.instance.copy()
        cols = np.nonzero(inst == CHAIR)[1]
        inst[(inst == CHAIR) & (np.arange(inst.shape[1])[None, :] < np.median(cols))] = CHAIR_HALF
        cats = {**frame.instance_categories, CHAIR_HALF: "chair"}
        obs = observation_from_instances(inst, cats, out_size=OBS_HW, dim=DIM, embedding_space=SPACE)
        mapper.step(obs, T, K_FULL, depth_m=frame.depth_m())
    chairs = sorted(int(k) for k in dictionary.keys if dictionary.label(int(k)) == "chair")
    table = [int(k) for k in dictionary.keys if dictionary.label(int(k)) == "table"]
    assert len(chairs) == 3 and len(table) == 1  # two halves + the far chair
    centre_x = {k: volume.extract_points(keys=[k]).points[:, 0].mean() for k in chairs}
    far = max(chairs, key=lambda k: centre_x[k])
    halves = [k for k in chairs if k != far]
    total = sum(dictionary.count(k) for k in halves)

    result = merge_regions(volume, dictionary, MergeParams())

    survivor = result.plan.merged_into.get(halves[0], halves[0])
    assert result.plan.merged_into in ({halves[0]: halves[1]}, {halves[1]: halves[0]})
    assert result.voxels_relabelled > 0 and dictionary.count(survivor) == total
    stored = volume.to_arrays()["key"]
    merged_away = next(iter(result.plan.merged_into))
    assert (stored == merged_away).sum() == 0 and (stored == survivor).sum() > 0
    assert far in dictionary and table[0] in dictionary
    assert sorted(dictionary.label(int(k)) for k in dictionary.keys).count("chair") == 2
    assert merge_regions(volume, dictionary, MergeParams()).merged == 0  # nothing left to merge


def test_unmatched_part_of_a_known_region_joins_it_instead_of_starting_a_new_one() -> None:
    """The map shows one region over the whole view; the frame has it in two segments of the same
    class (one-to-one assignment matches only one). The other joins the same key with the join rule,
    and starts a new region without it; a segment of another class never joins."""
    h, w = 20, 40
    rendered = RenderedView(np.zeros((h, w), np.int32), np.ones((h, w), np.float32), np.ones((h, w), np.float32))
    left, right = np.zeros((h, w), np.float32), np.zeros((h, w), np.float32)
    left[:, : w // 2], right[:, w // 2 :] = 0.9, 0.9

    def obs(label: str) -> SimpleObservation:
        emb = np.stack([category_embedding("wall", DIM), category_embedding(label, DIM)])
        return SimpleObservation(np.stack([left, right]), emb, SPACE, ["wall", label])

    for params, label, new in ((MatchParams(), "wall", 0), (MatchParams(join_min_coverage=None), "wall", 1),
                               (MatchParams(), "door", 1)):
        d = dictionary_with(("wall", 4))
        plan = plan_update(obs(label), rendered, d, params)
        assert len(plan.new_keys) == new, (params, label)
        if new == 0:
            assert sorted(plan.matched) == [(0, 0), (1, 0)] and d.count(0) == 6


def test_the_in_process_pipeline_merges_every_n_frames_and_at_the_end() -> None:
    """map_scene with an encoder that splits every object on frame 0: a pass after the 3rd semantic
    frame and one at the end; fragments are merged and no voxel keeps a merged-away key."""
    from openfusion.mapping.pipeline import map_scene
    from openfusion.sources import open_source
    from openfusion.testing.encoders import SplittingEncoder

    result = map_scene(open_source("synthetic:frames=4,width=160,height=120"),
                       region_encoder=SplittingEncoder(split_on=[0]),
                       volume_params=VolumeParams(initial_block_count=2048), merge_params=MergeParams(merge_every=3))
    assert result.stats.merge_passes == 2 and result.stats.regions_merged > 0
    stored = set(np.unique(result.volume.to_arrays()["key"]).tolist()) - {-1}
    assert stored and stored <= set(result.dictionary.keys.tolist())
    assert len(result.dictionary) == (result.dictionary.next_key - result.stats.regions_merged
                                      - result.stats.regions_pruned)
