"""Region summaries: geometry's per-region boxes/counts (``geometry/regions``) and the query
service's cache of them. Services run in this process (geometry + query on ServiceRunners, a
router session, a stand-in semantic queryable), with the hash text encoder (no model)."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import pytest

from openfusion.bus import Queryable, ServiceRunner, collect_health
from openfusion.client import OpenFusionClient
from openfusion.encoders import make_text_encoder
from openfusion.frame import Frame
from openfusion.mapping import RegionDictionary
from openfusion.mapping.queries import query_regions, region_summaries
from openfusion.services.geometry.service import GeometryConfig, GeometrySection, GeometryService
from openfusion.services.query.region_hits import RegionSummaries, region_hits
from openfusion.services.query.service import QueryConfig, QuerySection, QueryService
from openfusion.sources.synthetic import SyntheticSource, SyntheticWorld
from openfusion.testing.bus import LoopbackRouter, wait_until
from openfusion.wire.endpoints import SEMANTIC_DICTIONARY
from openfusion.wire.schemas import (
    ControlRequest,
    DictionaryRequest,
    PointsRequest,
    RegionSummaryRequest,
    RgbdFrame,
    SemanticUpdate,
)

pytestmark = pytest.mark.timeout(120)

WORLD = SyntheticWorld(0)
FRAMES = list(SyntheticSource(WORLD, num_frames=6, width_px=160, height_px=120))
TEXT = make_text_encoder("hash")


def _dictionary(n_keys: int) -> RegionDictionary:
    """Key i = instance id i + 1 of the synthetic world, embedded from its category name."""
    d = RegionDictionary(TEXT.embedding_space, TEXT.dim)
    for key in range(n_keys):
        name = WORLD.categories[key + 1]
        d.add(TEXT.encode([name])[0], label=name)
    return d


def _update(frame: Frame, max_key: int) -> SemanticUpdate:
    """Instance ids as region keys (id - 1), keeping keys <= ``max_key``."""
    keys = frame.instance.astype(np.int32) - 1
    keys[keys > max_key] = -1
    return SemanticUpdate(
        frame_id=frame.frame_id,
        T_world_cam=frame.T_world_cam,
        **SemanticUpdate.intrinsics_fields(frame.intrinsics),
        key_map=keys,
        conf_map=np.where(keys >= 0, 0.9, 0.0).astype(np.float32),
        new_keys=np.zeros(0, np.int32),
    )


def _geometry(max_key: int, frames: list[Frame] = FRAMES, **section: object) -> GeometryService:
    geo = GeometryService(
        GeometryConfig(map_id="unit", geometry=GeometrySection(load_on_start=False, **section))
    )
    for f in frames:
        geo.on_frame(RgbdFrame.from_frame(f))
        geo.on_update(_update(f, max_key))
    return geo


def _expected(geo: GeometryService, key: int) -> tuple[np.ndarray, np.ndarray, int]:
    pts = geo.volume.extract_points(keys=[key])
    if not len(pts.points):
        return np.zeros(3, np.float32), np.zeros(3, np.float32), 0
    lo, hi = np.percentile(pts.points, [1.0, 99.0], axis=0)
    return lo.astype(np.float32), hi.astype(np.float32), len(pts.points)


# ------------------------------------------------------------------------- geometry, no bus


def test_region_summaries_match_the_points_of_each_region() -> None:
    """Boxes are the 1st-99th percentile per axis (np.percentile's), min/max with percentile=0;
    a region of one point is that point; unlabelled points (-1) count nowhere."""
    rng = np.random.default_rng(0)
    points = rng.normal(size=(500, 3)).astype(np.float32)
    keys = rng.integers(-1, 7, 500).astype(np.int32)
    keys[0], points[0] = 40, (1.0, 2.0, 3.0)  # a region of one point
    k, lo, hi, n = region_summaries(keys, points)
    assert k.tolist() == sorted(set(keys.tolist()) - {-1})
    for i, key in enumerate(k):
        mine = points[keys == key]
        np.testing.assert_allclose(lo[i], np.percentile(mine, 1.0, axis=0), rtol=0, atol=1e-6)
        np.testing.assert_allclose(hi[i], np.percentile(mine, 99.0, axis=0), rtol=0, atol=1e-6)
        assert n[i] == len(mine)
    np.testing.assert_array_equal(lo[k == 40][0], [1.0, 2.0, 3.0])
    k0, lo0, hi0, _ = region_summaries(keys, points, percentile=0.0)
    for i, key in enumerate(k0):
        np.testing.assert_array_equal(lo0[i], points[keys == key].min(axis=0))
        np.testing.assert_array_equal(hi0[i], points[keys == key].max(axis=0))
    empty = region_summaries(np.full(3, -1, np.int32), points[:3])
    assert all(len(a) == 0 for a in empty)


def test_a_query_reports_the_same_box_in_process_and_through_the_query_service() -> None:
    """`openfusion query --map-dir` (library) and a remote query (query service: from geometry's
    cached summaries, or from the points when points are asked for) give one box per region."""
    geo = _geometry(max_key=16)
    dictionary = _dictionary(17)
    vector = TEXT.encode(["chair"])[0]
    library = query_regions(dictionary, geo.volume, vector, top_k=5)
    assert library
    ranked = [(r.key, r.score) for r in library]
    labels = {r.key: r.label or "" for r in library}
    summaries = RegionSummaries(geo.handle_regions(RegionSummaryRequest()), fetched_at=0.0)
    from_summary = region_hits(ranked, labels, None, with_points=False, max_points=0, summaries=summaries)
    points = geo.handle_points(PointsRequest(keys=[k for k, _ in ranked], max_points=100_000))
    from_points = region_hits(ranked, labels, points, with_points=True, max_points=50)
    for lib, a, b in zip(library, from_summary, from_points, strict=True):
        for hit in (a, b):
            assert hit.key == lib.key and hit.num_points == lib.num_points
            np.testing.assert_allclose(hit.bbox_min, lib.bbox_min, atol=1e-6)
            np.testing.assert_allclose(hit.bbox_max, lib.bbox_max, atol=1e-6)
        assert b.points is not None and len(b.points) == min(50, lib.num_points)


def test_geometry_summary_is_cached_per_map_version_and_recomputed_after_changes() -> None:
    geo = _geometry(max_key=16, frames=FRAMES[:3], regions_min_interval_s=0.0)
    calls = []
    table = geo.volume.region_table

    def counting(*args: object, **kwargs: object) -> object:  # the whole map's summary, per tile
        calls.append(1)
        return table(*args, **kwargs)

    geo.volume.region_table = counting  # type: ignore[method-assign]
    first = geo.handle_regions(RegionSummaryRequest())
    again = geo.handle_regions(RegionSummaryRequest(keys=[int(first.keys[0])]))
    assert len(calls) == 1, "an unchanged map must be answered from the cache"
    assert again.map_version == first.map_version and again.keys.tolist() == [int(first.keys[0])]
    assert first.key_horizon == max(int(_update(f, 16).key_map.max()) for f in FRAMES[:3]) + 1
    for i, key in enumerate(first.keys.tolist()):
        lo, hi, n = _expected(geo, key)
        np.testing.assert_array_equal(first.bbox_min[i], lo)
        np.testing.assert_array_equal(first.bbox_max[i], hi)
        assert first.num_points[i] == n
        # the centroid is the mean of the region's surface points, not the middle of its box
        region = geo.volume.extract_points(keys=[key])
        np.testing.assert_allclose(first.centroid[i], np.asarray(region.points, np.float64).mean(axis=0), atol=1e-4)
    # New frames + an update with keys up to 25: a new version, recomputed, horizon moved on.
    for f in FRAMES[3:]:
        geo.on_frame(RgbdFrame.from_frame(f))
        geo.on_update(_update(f, 25))
    later = geo.handle_regions(RegionSummaryRequest())
    assert len(calls) == 2 and later.map_version > first.map_version
    horizon = (
        max(int(_update(f, k).key_map.max()) for f, k in zip(FRAMES, [16, 16, 16, 25, 25, 25], strict=True))
        + 1
    )
    assert later.key_horizon == horizon
    for i, key in enumerate(later.keys.tolist()):
        assert later.num_points[i] == _expected(geo, key)[2]
    # Reset: empty map, nothing covered.
    geo.handle_control(ControlRequest(action="reset"), action="reset")
    after_reset = geo.handle_regions(RegionSummaryRequest())
    assert len(after_reset.keys) == 0 and after_reset.key_horizon == 0


def test_geometry_summary_min_interval_unless_fresh() -> None:
    geo = _geometry(max_key=16, frames=FRAMES[:2], regions_min_interval_s=3600.0)
    first = geo.handle_regions(RegionSummaryRequest())
    geo.on_frame(RgbdFrame.from_frame(FRAMES[2]))
    cached = geo.handle_regions(RegionSummaryRequest())
    assert cached.map_version == first.map_version  # within the interval: the cached summary, with its age
    fresh = geo.handle_regions(RegionSummaryRequest(fresh=True))
    assert fresh.map_version == geo.map_version > first.map_version


# ------------------------------------------------------------------------------- over the bus


@dataclass
class Cluster:
    geo: GeometryService | None
    query: QueryService
    client: OpenFusionClient
    semantic_dictionary: RegionDictionary

    def query_counter(self, name: str) -> float:
        stats = collect_health(self.client.session, self.client.keys, timeout_s=2.0).get("query")
        return float(stats.counters.get(name, 0.0)) if stats else 0.0


@pytest.fixture
def make_cluster() -> Iterator:
    closers: list = []

    def make(*, geometry: GeometryService | None, dictionary: RegionDictionary, **query: object) -> Cluster:
        router = LoopbackRouter("summaries", health_period_s=0.2)
        closers.append(router.close)
        sem = router.open_client()
        closers.append(sem.close)
        holder = {"dictionary": dictionary}
        qbl = Queryable(
            sem,
            SEMANTIC_DICTIONARY.key(router.keys),
            DictionaryRequest,
            lambda _r: holder["dictionary"].snapshot(),
        )
        closers.append(qbl.close)
        if geometry is not None:
            geometry.config = router.config(GeometryConfig, geometry=geometry.section)
            runner = ServiceRunner(geometry.config, "geometry").start()
            closers.append(runner.close)
            geometry.setup(runner)
            runner.ready()
        qs = QueryService(
            router.config(QueryConfig, query=QuerySection(text_encoder="hash", **query)), text_encoder=TEXT
        )
        qrunner = ServiceRunner(qs.config, "query").start()
        closers.append(qrunner.close)
        qs.setup(qrunner)
        qrunner.ready()
        client = OpenFusionClient.from_config(router.config(), timeout_s=20.0)
        closers.append(client.close)
        wait_until(lambda: "query" in client.live_services(timeout_s=1.0), timeout_s=20)
        return Cluster(geometry, qs, client, dictionary)

    yield make
    for close in reversed(closers):
        close()


def _check_hits(cluster: Cluster, reply: object) -> None:
    assert cluster.geo is not None
    for hit in reply.regions:  # type: ignore[attr-defined]
        lo, hi, n = _expected(cluster.geo, hit.key)
        assert hit.num_points == n, (hit.key, hit.num_points, n)
        np.testing.assert_array_equal(hit.bbox_min, lo)
        np.testing.assert_array_equal(hit.bbox_max, hi)


def test_query_boxes_match_the_map_and_repeat_queries_need_no_geometry_round_trip(make_cluster) -> None:
    geo = _geometry(max_key=25)
    seen = max(int(f.instance.max()) for f in FRAMES)  # keys 0..seen-1: all below geometry's horizon
    cluster = make_cluster(
        geometry=geo, dictionary=_dictionary(seen), summary_max_age_s=3600.0, summary_refresh_s=3600.0
    )
    reply = cluster.client.query_text("table", top_k=5)
    assert reply.regions[0].label == "table" and reply.regions[0].num_points > 0
    _check_hits(cluster, reply)
    for text in ("chair", "plant", "bookshelf", "floor"):
        _check_hits(cluster, cluster.client.query_text(text, top_k=5))
    wait_until(lambda: cluster.query_counter("queries") >= 5, timeout_s=10)
    assert cluster.query_counter("summary_fetches") == 1
    # with_points still asks geometry for the points, and box/count agree with them.
    with_points = cluster.client.query_text("table", top_k=2, with_points=True)
    _check_hits(cluster, with_points)
    best = with_points.regions[0]
    assert best.points is not None and len(best.points) == best.num_points
    # The client can read the same summaries directly.
    summary = cluster.client.regions(keys=[best.key])
    assert summary.keys.tolist() == [best.key] and summary.num_points[0] == best.num_points


def test_query_cache_follows_new_integration_and_new_regions(make_cluster) -> None:
    geo = _geometry(max_key=16, frames=FRAMES[:2], regions_min_interval_s=0.0)
    dictionary = _dictionary(17)
    cluster = make_cluster(
        geometry=geo,
        dictionary=dictionary,
        summary_max_age_s=0.3,
        summary_refresh_s=3600.0,
        summary_recheck_s=0.0,
    )
    wait_until(lambda: len(cluster.query.replica) == 17, timeout_s=10)
    before = cluster.client.query_text("office chair", top_k=3)
    _check_hits(cluster, before)
    version = cluster.query.summaries.map_version
    # More frames integrated and labelled: after the staleness bound the boxes follow the map.
    for f in FRAMES[2:4]:
        geo.on_frame(RgbdFrame.from_frame(f))
        geo.on_update(_update(f, 16))
    cluster.query.section.summary_max_age_s = 1e-6  # the cache is now past its staleness bound
    after = cluster.client.query_text("office chair", top_k=3)
    assert cluster.query.summaries.map_version > version
    _check_hits(cluster, after)
    # A region newer than the cached summary (key 20, "table") is fetched before answering, even
    # though the cache is younger than summary_max_age_s (now too long to expire in this test).
    cluster.query.section.summary_max_age_s = 3600.0
    cached = cluster.query.summaries
    assert cached is not None and not cached.covers(20)
    since = dictionary.version
    for key in range(17, 26):
        dictionary.add(TEXT.encode([WORLD.categories[key + 1]])[0], label=WORLD.categories[key + 1])
    for f in FRAMES[:4]:
        geo.on_update(_update(f, 25))
    cluster.query.on_delta(dictionary.delta_since(since))
    assert len(cluster.query.replica) == 26
    table = cluster.client.query_text("table", top_k=1).regions[0]
    assert table.key == 20 and table.num_points > 0
    assert cluster.query.summaries is not cached and cluster.query.summaries.covers(20)
    _check_hits(cluster, cluster.client.query_text("table", top_k=3))


def test_query_without_geometry_answers_zero_boxes_and_does_not_wait_every_time(make_cluster) -> None:
    cluster = make_cluster(
        geometry=None, dictionary=_dictionary(26), geometry_timeout_s=0.3, summary_max_age_s=3600.0
    )
    first = cluster.client.query_text("table", top_k=2)
    second = cluster.client.query_text("chair", top_k=2)
    for reply in (first, second):
        assert reply.regions and all(h.num_points == 0 for h in reply.regions)
    wait_until(lambda: cluster.query_counter("queries") >= 2, timeout_s=10)
    assert cluster.query_counter("summary_failures") == 1


def test_ranked_regions_known_to_be_empty_are_dropped() -> None:
    """Ranking keeps the regions with surface points and those the summary does not know yet (newer
    than it); a key below the horizon that is not listed, or listed with 0 points, is dropped."""
    from openfusion.services.query.region_hits import RegionSummaries, drop_empty_regions
    from openfusion.wire.schemas import RegionSummaryReply

    reply = RegionSummaryReply(
        map_version=3,
        key_horizon=10,
        keys=np.array([1, 4], np.int32),
        bbox_min=np.zeros((2, 3), np.float32),
        bbox_max=np.ones((2, 3), np.float32),
        num_points=np.array([120, 0], np.int64),
    )
    summaries = RegionSummaries(reply, fetched_at=0.0)
    ranked = [(4, 0.9), (1, 0.8), (2, 0.7), (12, 0.6)]
    assert drop_empty_regions(ranked, summaries) == [(1, 0.8), (12, 0.6)]
    assert drop_empty_regions(ranked, None) == ranked


def test_query_service_leaves_out_regions_below_min_region_points() -> None:
    """The query service and saved-map queries share one declaration (QueryParams, default 50):
    a region the summary knows to have 2 surface points is not an answer, even at score 1."""
    from openfusion.mapping.params import QueryParams
    from openfusion.wire.schemas import RegionSummaryReply, TextQuery

    assert QuerySection().min_region_points == QueryParams().min_region_points == 50
    dictionary = RegionDictionary(TEXT.embedding_space, TEXT.dim)
    for name in ("chair", "table", "lamp"):
        dictionary.add(TEXT.encode([name])[0], label=name)
    fragment = dictionary.add(dictionary.embedding(0), label="chair")  # ties with key 0 at score 1
    service = QueryService(QueryConfig(map_id="unit"), text_encoder=TEXT)
    service.replica.apply_snapshot(dictionary.snapshot())
    reply = RegionSummaryReply(
        map_version=1,
        key_horizon=fragment + 1,
        keys=np.array([0, 1, 2, fragment], np.int32),
        bbox_min=np.zeros((4, 3), np.float32),
        bbox_max=np.ones((4, 3), np.float32),
        num_points=np.array([400, 300, 200, 2], np.int64),
    )
    service.summaries = RegionSummaries(reply, fetched_at=0.0)
    text = "chair"
    answer = service.handle_text(TextQuery(text=text, top_k=3))
    assert fragment not in [h.key for h in answer.regions] and answer.regions[0].key == 0
    loose = QueryService(QueryConfig(map_id="unit", query=QuerySection(min_region_points=1)), text_encoder=TEXT)
    loose.replica.apply_snapshot(dictionary.snapshot())
    loose.summaries = service.summaries
    assert fragment in [h.key for h in loose.handle_text(TextQuery(text=text, top_k=3)).regions[:2]]
