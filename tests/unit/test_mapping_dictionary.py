"""Region dictionary: running means, counts, ranking, merge, versioned deltas and snapshots."""

from __future__ import annotations

import numpy as np
import pytest

from openfusion.mapping import EmbeddingSpaceError, RegionDictionary, StaleVersionError


def unit(v) -> np.ndarray:
    v = np.asarray(v, np.float32)
    return v / np.linalg.norm(v)


def test_running_mean_and_counts() -> None:
    """The stored embedding is the mean of all matched observations (re-normalised), not the first."""
    d = RegionDictionary("s", 3)
    k = d.add(unit([1, 0, 0]), label="mug")
    d.observe(k, unit([0, 1, 0]))
    d.observe(k, unit([0, 0, 1]))
    assert d.count(k) == 3
    np.testing.assert_allclose(d.mean_embedding(k), [1 / 3, 1 / 3, 1 / 3], atol=1e-6)
    np.testing.assert_allclose(d.embedding(k), unit([1, 1, 1]), atol=1e-6)
    assert d.label(k) == "mug"


def test_keys_are_never_reused() -> None:
    """A removed or merged-away key stays dead: a later region gets a fresh key."""
    d = RegionDictionary("s", 2)
    a, b = d.add(unit([1, 0])), d.add(unit([0, 1]))
    d.merge(a, b)
    c = d.add(unit([1, 1]))
    assert (a, b, c) == (0, 1, 2) and b not in d and list(d.keys) == [0, 2]


def test_top_k_matches_brute_force() -> None:
    """Ranking over many regions equals a brute-force cosine sort; ties broken by key."""
    rng = np.random.default_rng(0)
    d = RegionDictionary("s", 16)
    vecs = rng.standard_normal((300, 16)).astype(np.float32)
    for v in vecs:
        d.add(v)
    q = rng.standard_normal(16).astype(np.float32)
    keys, scores = d.top_k(q, 10)
    cos = (vecs / np.linalg.norm(vecs, axis=1, keepdims=True)) @ unit(q)
    np.testing.assert_array_equal(keys, np.argsort(-cos)[:10])
    np.testing.assert_allclose(scores, np.sort(cos)[::-1][:10], atol=1e-5)
    assert len(d.top_k(q, 1000)[0]) == 300


def test_top_k_equal_scores_rank_the_most_observed_region_first() -> None:
    """Three regions with the same embedding (a chair seen whole 5 times, and two fragments seen
    once, one with an older key): the main region ranks first, also when the tie sits at the k-th
    place (the fragment with the older key must not take the only slot)."""
    d = RegionDictionary("s", 3)
    fragment_old = d.add(unit([1, 0, 0]))
    other = d.add(unit([0, 1, 0]))
    main = d.add(unit([1, 0, 0]))
    fragment_new = d.add(unit([1, 0, 0]))
    for _ in range(4):
        d.observe(main, unit([1, 0, 0]))
    keys, scores = d.top_k(unit([1, 0, 0]), 1)
    assert list(keys) == [main] and scores[0] == pytest.approx(1.0)
    keys, _ = d.top_k(unit([1, 0, 0]), 4)
    assert list(keys) == [main, fragment_old, fragment_new, other]


def test_top_k_rejects_wrong_dimension_and_zero_vectors() -> None:
    """A query from another embedding size, or an all-zero vector, is a clear error."""
    d = RegionDictionary("s", 4)
    d.add(unit([1, 0, 0, 0]))
    with pytest.raises(EmbeddingSpaceError, match="dimension 3"):
        d.top_k(np.ones(3), 1)
    with pytest.raises(ValueError, match="zero norm"):
        d.top_k(np.zeros(4), 1)
    with pytest.raises(ValueError, match="NaN"):
        d.add(np.array([np.nan, 0, 0, 1]))
    with pytest.raises(EmbeddingSpaceError):
        d.check_space("other-space")


def test_merge_is_count_weighted() -> None:
    """merge(a, b): mean weighted by observation counts, counts summed, b gone, a's label kept."""
    d = RegionDictionary("s", 2)
    a = d.add(unit([1, 0]), label="sofa")
    d.observe(a, unit([1, 0]))
    d.observe(a, unit([1, 0]))  # a: 3 observations of [1, 0]
    b = d.add(unit([0, 1]), label="couch")  # b: 1 observation of [0, 1]
    d.merge(a, b)
    assert d.count(a) == 4 and b not in d and d.label(a) == "sofa"
    np.testing.assert_allclose(d.mean_embedding(a), [0.75, 0.25], atol=1e-6)
    with pytest.raises(KeyError, match="not in the dictionary"):
        d.merge(a, b)
    with pytest.raises(ValueError, match="itself"):
        d.merge(a, a)


def test_versions_increment_once_per_batch() -> None:
    """Each change outside a batch is one version; a batch of changes is one version."""
    d = RegionDictionary("s", 2)
    d.add(unit([1, 0]))
    assert d.version == 1
    with d.batch():
        k = d.add(unit([0, 1]))
        d.observe(k, unit([1, 1]))
        d.set_label(k, "x")
    assert d.version == 2
    with d.batch():
        pass
    assert d.version == 2


def test_delta_replica_tracks_the_owner() -> None:
    """A replica built from a snapshot and fed deltas equals the owner: adds, observations, merges,
    removals; an out-of-order delta is refused with StaleVersionError (fetch a snapshot)."""
    owner = RegionDictionary("s", 3)
    a = owner.add(unit([1, 0, 0]), label="a")
    b = owner.add(unit([0, 1, 0]))
    replica = RegionDictionary.from_snapshot(owner.snapshot())
    v0 = owner.version
    owner.observe(a, unit([0, 0, 1]))
    c = owner.add(unit([1, 1, 1]), label="c")
    delta1 = owner.delta_since(v0)
    v1 = owner.version
    owner.merge(a, b)
    owner.remove(c)
    delta2 = owner.delta_since(v1)
    assert RegionDictionary.merges_of(delta2) == {b: a}  # b merged into a, c deleted
    np.testing.assert_array_equal(np.sort(delta2.removed_keys), [b, c])
    with pytest.raises(StaleVersionError, match="snapshot"):
        replica.apply_delta(delta2)  # delta1 missing
    replica.apply_delta(delta1)
    replica.apply_delta(delta2)
    replica.apply_delta(delta2)  # replay is harmless
    assert replica.version == owner.version
    mine, theirs = owner.snapshot(), replica.snapshot()
    order_o, order_r = np.argsort(mine.keys), np.argsort(theirs.keys)
    np.testing.assert_array_equal(mine.keys[order_o], theirs.keys[order_r])
    np.testing.assert_allclose(mine.embeddings[order_o], theirs.embeddings[order_r])
    np.testing.assert_array_equal(mine.counts[order_o], theirs.counts[order_r])
    assert [mine.labels[i] for i in order_o] == [theirs.labels[i] for i in order_r]
    assert owner.delta_since(owner.version) is None  # nothing changed since
    with pytest.raises(StaleVersionError):
        owner.delta_since(owner.version + 1)
    with pytest.raises(StaleVersionError, match="history"):
        replica.delta_since(0)  # a replica's history starts at its snapshot


def test_a_snapshot_carries_the_merges_to_their_final_survivor() -> None:
    """A replica that missed the merge deltas and takes a snapshot knows every merge, chains
    resolved to the live key (b -> a, then a -> d: b ends in d), and resolves old keys with it;
    a key whose survivor was deleted is left out (its voxels are gone)."""
    owner = RegionDictionary("s", 3)
    a, b, c, d = (owner.add(unit(v)) for v in ([1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0]))
    e, f = owner.add(unit([1, 0, 1])), owner.add(unit([0, 1, 1]))
    owner.merge(a, b)
    owner.merge(d, a)
    owner.merge(e, f)
    owner.remove(e)
    snap = owner.snapshot()
    assert dict(zip(snap.merged_keys.tolist(), snap.merged_into.tolist(), strict=True)) == {a: d, b: d}
    replica = RegionDictionary.from_snapshot(snap)
    assert replica.merge_table() == {a: d, b: d}
    np.testing.assert_array_equal(replica.resolve_keys(np.array([b, a, c, -1])), [d, d, c, -1])
    assert replica.survivor_of(f) is None and sorted(replica.keys.tolist()) == [c, d]


def test_from_snapshot_rejects_inconsistent_arrays() -> None:
    """A snapshot whose arrays disagree is refused by the message itself; one whose keys reach
    past next_key (a bad owner) is refused by the dictionary; neither is half-built."""
    snap = RegionDictionary("s", 2).snapshot()
    with pytest.raises(ValueError, match="differ in length|must be"):
        snap.model_validate({**snap.model_dump(), "keys": np.array([0], np.int32)})
    owner = RegionDictionary("s", 2)
    owner.add(unit([1, 0]))
    bad = owner.snapshot().model_copy(update={"next_key": 0})
    with pytest.raises(ValueError, match="below next_key"):
        RegionDictionary.from_snapshot(bad)


def test_delta_of_other_space_is_refused() -> None:
    """A delta from a dictionary in another embedding space never touches the replica."""
    owner = RegionDictionary("clip", 2)
    owner.add(unit([1, 0]))
    replica = RegionDictionary("minilm", 2)
    with pytest.raises(EmbeddingSpaceError):
        replica.apply_delta(owner.delta_since(0))
    assert len(replica) == 0


def test_observe_many_equals_repeated_observe() -> None:
    """The vectorised update used per frame gives the same means, counts and labels as one by one."""
    rng = np.random.default_rng(4)
    start = rng.standard_normal((5, 8)).astype(np.float32)
    a, b = RegionDictionary("s", 8), RegionDictionary("s", 8)
    for v in start:
        a.add(v)
        b.add(v)
    obs = rng.standard_normal((3, 8)).astype(np.float32)
    keys = np.array([4, 0, 2])
    a.observe_many(keys, obs, ["x", None, "z"])
    for k, v, lab in zip(keys, obs, ["x", None, "z"], strict=True):
        b.observe(int(k), v, label=lab)
    for k in range(5):
        np.testing.assert_allclose(a.mean_embedding(k), b.mean_embedding(k), atol=1e-6)
        np.testing.assert_allclose(a.embedding(k), b.embedding(k), atol=1e-6)
        assert a.count(k) == b.count(k) and a.label(k) == b.label(k)
    assert a.version == 6  # one version for the batch
    with pytest.raises(ValueError, match="distinct"):
        a.observe_many(np.array([1, 1]), obs[:2])
