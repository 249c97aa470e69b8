"""Query service: text (one or several) / image / 3D-point queries → ranked regions, for remote clients.

| key | direction | message |
|---|---|---|
| ``…/semantic/dictionary`` | queries (snapshot on start and after a gap) | DictionaryRequest → DictionarySnapshot |
| ``…/semantic/dictionary/delta`` | subscribes | :class:`~openfusion.wire.schemas.DictionaryDelta` |
| ``…/geometry/regions`` | queries (cached region summaries, see below) | RegionSummaryRequest → RegionSummaryReply |
| ``…/geometry/points`` | queries (points of the top regions, ``with_points`` only; point queries) | PointsRequest → PointsReply |
| ``…/query/text`` | queryable | TextQuery → QueryReply |
| ``…/query/text_batch`` | queryable (several texts, one round trip, one encoder call) | TextQueryBatch → QueryBatchReply |
| ``…/query/image`` | queryable | ImageQuery → QueryReply (encoders with an image tower only) |
| ``…/query/point`` | queryable | PointQuery → QueryReply |
| ``…/health/query`` | liveliness + stats | counters ``queries`` (one per text), ``regions``, ``dictionary_resyncs``, ``summary_fetches``, ``summary_failures`` |

It answers from the latest dictionary it has and never blocks mapping. Regions the cached
summary knows to have fewer than ``min_region_points`` (default 50) surface points (stray
fragments of a few voxels, regions whose voxels were taken over by other regions) are left out of
rankings, so ``top_k`` answers are regions with geometry (see ``drop_empty_regions``); the parameter
is declared once in :class:`~openfusion.mapping.params.QueryParams`, which ``openfusion query
--map-dir`` applies to saved maps too. A query whose
embedding space differs from the map's is refused with ``reply_err`` (code
``embedding_space_mismatch``) naming both spaces.

Bounding boxes and point counts come from a cache of geometry's per-region summaries, so a
text or image query without points makes no round trip to geometry. Staleness bound: a
summary used in a reply was requested from geometry at most ``summary_max_age_s`` (default 2 s)
before the query (plus geometry's own ``regions_min_interval_s``, 0.5 s, and one summary
computation); while queries keep coming, the service refreshes it in the background every
``summary_refresh_s`` (1 s), so queries do not wait for it, until ``summary_keep_warm_s`` (10 s)
after the last query (each refresh of a changed map costs geometry one surface extraction); an
older cache is refreshed before answering. A region newer than the cached summary (its key is at or above the summary's
``key_horizon``) makes the query fetch a fresh summary first, at most once per
``summary_recheck_s`` (0.25 s); a region that geometry still does not know then comes back
with ``num_points`` 0 and a zero box. If geometry does not answer, the query is answered with
what the cache holds (zero boxes when nothing) and the failure is logged and counted; the next
synchronous try waits ``summary_max_age_s``. With ``with_points`` the box and count come from
the points geometry returns (the current map).

The text encoder runs with ``torch_threads`` intra-op threads (default 1: a one-sentence
MiniLM forward gains little from a second thread and loses a lot when the other services keep
the cores busy). One query text takes the MiniLM encoder's single-text path (tokenize +
forward, see ``openfusion.encoders.text_minilm``); a batch (``query/text_batch``) embeds all its
texts in one encoder call and, with ``with_points``, asks geometry once for the points of every
text's regions. Text length, ``top_k`` and points are held to :mod:`openfusion.wire.limits` (the
one set every surface uses; refused ``too_large`` with its one line, naming which text of a batch);
the whole reply to the message-size limit (``reply_too_large``).
"""

from __future__ import annotations

import logging
import sys
import threading
import time
from typing import Any

import numpy as np
from pydantic import Field, field_validator

from openfusion.bus import QueryError, RequestError, ServiceRunner
from openfusion.config import ServiceConfig, one_of
from openfusion.encoders import TEXT_ENCODER_NAMES, make_text_encoder
from openfusion.encoders.registry import MINILM_BACKENDS
from openfusion.mapping.answers import (
    MAX_ANCHORS,
    RELATION_CANDIDATES,
    TextAnswer,
    answer_text,
    pool_size,
    texts_to_embed,
    texts_to_rank,
)
from openfusion.mapping.params import QueryParams
from openfusion.mapping.queries import candidates_for
from openfusion.mapping.relations import Nearby, parse_relation_query
from openfusion.mapping.relevancy import RelevancyScorer
from openfusion.services.common import ServiceDefinition
from openfusion.services.dictionary_replica import DictionaryReplica
from openfusion.services.query.caches import (
    DEFAULT_TEXT_CACHE_SIZE,
    RankCache,
    TextEmbeddings,
)
from openfusion.services.query.instances import MAX_QUERY_INSTANCES, query_service_name
from openfusion.services.query.region_hits import RegionSummaries, drop_empty_regions, region_hits
from openfusion.shard_client import reader_for
from openfusion.wire import limits
from openfusion.wire.counters import QueryCounter
from openfusion.wire.endpoints import (
    DICTIONARY_DELTA,
    QUERY_IMAGE,
    QUERY_POINT,
    QUERY_TEXT,
    QUERY_TEXT_BATCH,
    SEMANTIC_DICTIONARY,
)
from openfusion.wire.schemas import (
    DictionaryDelta,
    ImageQuery,
    PointQuery,
    PointsReply,
    PointsRequest,
    QueryBatchReply,
    QueryReply,
    RegionSummaryRequest,
    RelationQueryInfo,
    TextQuery,
    TextQueryBatch,
)

logger = logging.getLogger(__name__)


class QuerySection(QueryParams):
    """The query service's settings (``min_region_points`` comes from :class:`QueryParams`)."""

    text_encoder: str = Field(
        "minilm", description=f"text encoder of the map's embedding space: {', '.join(TEXT_ENCODER_NAMES)}"
    )
    text_backend: str = Field(
        "onnxruntime", description="MiniLM runtime: onnxruntime (~3 ms a text, same embeddings; falls back, "
        "logged, when unavailable) or sentence-transformers (torch, ~11 ms)")
    text_cache_size: int = Field(
        DEFAULT_TEXT_CACHE_SIZE, ge=0, description="texts whose embeddings and rankings are kept (0: none)")
    model_path: str | None = Field(None, description="model of the clip-regions / onnx text encoder")
    device: str = Field("auto", description="text encoder device: auto, cpu or cuda")
    torch_threads: int = Field(1, ge=0, description="intra-op threads of a torch text encoder (0 = torch's default)")
    geometry_timeout_s: float = Field(5.0, gt=0, description="wait this long for geometry's summaries or points")
    resync_period_s: float = Field(5.0, gt=0, description="without a dictionary, ask the semantic service this often")
    summary_max_age_s: float = Field(2.0, gt=0, description="a region summary used in a reply is at most this old")
    summary_refresh_s: float = Field(1.0, gt=0, description="background refresh of the summaries while queries come")
    summary_recheck_s: float = Field(
        0.25, ge=0, description="a region newer than the summaries triggers a fresh fetch at most this often"
    )
    summary_keep_warm_s: float = Field(10.0, ge=0, description="keep refreshing this long after the last query")

    instance: int | None = Field(
        None, ge=1, le=MAX_QUERY_INSTANCES,
        description="this query service's number when several serve one map (health: query-N; none: query)")

    @field_validator("text_encoder")
    @classmethod
    def _text_encoder(cls, value: str) -> str:
        return one_of(value, TEXT_ENCODER_NAMES, "text encoder")

    @field_validator("text_backend")
    @classmethod
    def _text_backend(cls, value: str) -> str:
        return one_of(value, MINILM_BACKENDS, "MiniLM backend")


class QueryConfig(ServiceConfig):
    query: QuerySection = Field(default_factory=QuerySection)


def text_encoder_from_section(section: QuerySection) -> Any:
    """The text encoder a query section describes (the service and the in-process run)."""
    opts: dict[str, Any] = {}
    if section.text_encoder != "hash":
        opts["device"] = section.device
    if section.text_encoder in ("minilm", "gt"):
        opts["backend"] = section.text_backend
    if section.model_path:
        opts["model_path" if section.text_encoder == "onnx" else "model"] = section.model_path
    return make_text_encoder(section.text_encoder, **opts)


class QueryService:
    """Dictionary replica + text encoder; handlers are plain methods (tests call them without a bus)."""

    def __init__(self, config: QueryConfig, *, text_encoder: Any = None) -> None:
        self.config = config
        self.section = config.query
        self.text_encoder = text_encoder if text_encoder is not None else text_encoder_from_section(self.section)
        # relevancy of the encoder's space (the map's, or the query is refused): negatives embedded once
        self.scorer = RelevancyScorer(self.text_encoder)
        # query texts already embedded (LRU) and their candidate lists at the current dictionary version
        self.texts = TextEmbeddings(self.text_encoder.encode, max_texts=self.section.text_cache_size)
        self.rankings = RankCache(max_entries=self.section.text_cache_size)
        self.replica = DictionaryReplica()
        self._runner: ServiceRunner | None = None
        self._resync_lock = threading.Lock()
        self.summaries: RegionSummaries | None = None
        self._summary_lock = threading.Lock()
        self._summary_failed_at: float | None = None
        self._last_query_at: float | None = None

    # ----------------------------------------------------------------- dictionary
    def resync(self) -> bool:
        if self._runner is None:
            return False
        with self._resync_lock:
            snap = self.replica.fetch_snapshot(self._runner, SEMANTIC_DICTIONARY)
            if snap is None:
                return False
            self.replica.apply_snapshot(snap)
            self._runner.stats.incr(QueryCounter.DICTIONARY_RESYNCS)
            self._runner.stats.set(QueryCounter.REGIONS, len(self.replica))
            return True

    def on_delta(self, msg: DictionaryDelta) -> None:
        if not self.replica.apply_delta(msg):
            self.resync()
        if self._runner is not None:
            self._runner.stats.set(QueryCounter.REGIONS, len(self.replica))

    # -------------------------------------------------------------------- queries
    def _check_space(self, requested: str | None) -> str:
        space = self.replica.embedding_space
        if space is None:
            raise RequestError(
                "no_map", "the query service has no dictionary yet: is the semantic service running?"
            )
        if requested is not None and requested != space:
            raise RequestError(
                "embedding_space_mismatch",
                f"query asks for embedding space {requested!r} but the map is in {space!r}",
            )
        return space

    def _check_text_space(self, space: str) -> None:
        if self.text_encoder.embedding_space != space:
            raise RequestError(
                "embedding_space_mismatch",
                f"the query service's text encoder is {self.text_encoder.embedding_space!r} but the "
                f"map is in {space!r}: start the query service with the matching --text-encoder",
            )

    def _check_limits(self, top_k: int, max_points: int) -> None:
        """The request's ``top_k`` and ``max_points`` within :mod:`openfusion.wire.limits` (the
        schema checks them when a message is decoded; a handler called directly is held to them too)."""
        try:
            limits.check_top_k(top_k)
            limits.check_max_points(max_points)
        except limits.LimitError as exc:
            raise RequestError("too_large", str(exc)) from None

    def _points_of(self, keys: list[int] | None, max_points: int) -> PointsReply | None:
        if self._runner is None or (keys is not None and not keys):
            return None
        try:
            return reader_for(self._runner).points(PointsRequest(keys=keys, max_points=max_points),
                                                   timeout_s=self.section.geometry_timeout_s)
        except QueryError as exc:
            logger.warning("query: no points from geometry (%s); answering without geometry", exc.reason)
            return None

    # ------------------------------------------------------------- region summaries
    def refresh_summaries(self, *, fresh: bool = False, newer_than: float | None = None) -> bool:
        """Fetch geometry's region summaries into the cache; False when geometry did not answer.
        ``newer_than``: skip when another thread fetched after that monotonic time meanwhile."""
        if self._runner is None:
            return False
        with self._summary_lock:
            cache = self.summaries
            if newer_than is not None and cache is not None and cache.fetched_at >= newer_than:
                return True
            asked_at = time.monotonic()
            try:
                reply = reader_for(self._runner).regions(RegionSummaryRequest(fresh=fresh),
                                                         timeout_s=self.section.geometry_timeout_s)
            except QueryError as exc:
                self._summary_failed_at = time.monotonic()
                self._runner.stats.incr(QueryCounter.SUMMARY_FAILURES)
                logger.warning(
                    "query: no region summaries from geometry (%s); answering from the cache", exc.reason
                )
                return False
            fresh_summaries = RegionSummaries(reply, asked_at)
            if cache is not None and fresh_summaries.same_boxes(cache):  # an unchanged map: keep its nearby lists
                fresh_summaries.derived = cache.derived
            self.summaries = fresh_summaries
            self._summary_failed_at = None
            self._runner.stats.incr(QueryCounter.SUMMARY_FETCHES)
            return True

    def _summaries_for(self, keys: list[int]) -> RegionSummaries | None:
        """The cache, refreshed first when it is too old or does not know one of ``keys``."""
        now = time.monotonic()
        self._last_query_at = now
        cache = self.summaries
        if self._runner is None or not keys:
            return cache
        failed = self._summary_failed_at
        if failed is not None and now - failed < self.section.summary_max_age_s:
            return cache  # geometry did not answer a moment ago: do not make every query wait for it
        if cache is None or now - cache.fetched_at > self.section.summary_max_age_s:
            self.refresh_summaries(newer_than=now)
        elif (
            not all(cache.covers(k) for k in keys) and now - cache.fetched_at > self.section.summary_recheck_s
        ):
            self.refresh_summaries(fresh=True, newer_than=now)
        return self.summaries

    def _keep_summaries_warm(self) -> None:
        """Background refresh (loop thread) while queries keep coming."""
        now = time.monotonic()
        last, cache = self._last_query_at, self.summaries
        if last is None or now - last > self.section.summary_keep_warm_s:
            return
        if cache is None or now - cache.fetched_at >= self.section.summary_refresh_s:
            self.refresh_summaries(newer_than=now)

    def _rank(
        self, vector: np.ndarray, *, top_k: int, with_points: bool, max_points: int, space: str, query: str
    ) -> QueryReply:
        return self._rank_many(
            {query: vector}, [query], top_k=top_k, with_points=with_points, max_points=max_points, space=space
        )[0]

    def _rank_many(
        self,
        vectors: dict[str, np.ndarray],
        queries: list[str],
        *,
        top_k: int,
        with_points: bool,
        max_points: int,
        space: str,
        by_text: bool = False,
    ) -> list[QueryReply]:
        """One reply per query (``vectors`` holds the embedding of each, and of the X and Y of
        relation queries, :func:`~openfusion.mapping.answers.texts_to_embed`): the summaries
        checked once for every ranked key, and with ``with_points`` ONE points request to geometry
        for the regions of all of them. Relevancy, match, nearby regions and relations:
        :func:`~openfusion.mapping.answers.answer_text`, as every query path. ``by_text``: the
        keys of ``vectors`` are the texts embedded (candidate lists cached per dictionary version)."""
        # the X of "X next to Y" looks at more candidates; the head rule's parts are scored, never ranked
        targets = {rq.target for rq in map(parse_relation_query, queries) if rq is not None}
        candidates = {text: self._candidates(text, vectors[text], candidates_for(
            top_k + RELATION_CANDIDATES if text in targets else pool_size(max(top_k, MAX_ANCHORS))), by_text=by_text)
            for text in texts_to_rank(queries)}
        summaries = self._summaries_for(sorted({k for ranked in candidates.values() for k, _ in ranked}))
        least = self.section.min_region_points
        usable = {text: drop_empty_regions(ranked, summaries, min_points=least) for text, ranked in candidates.items()}
        by_vector = {id(vectors[text]): ranked for text, ranked in usable.items()}

        def rank(vector: np.ndarray, n: int) -> list[tuple[int, float]]:
            return by_vector[id(vector)][:n]

        boxes = summaries.boxes(min_points=least) if summaries is not None else None
        up_axis = self.section.up_axis

        def nearby(key: int) -> list[Nearby]:  # memoised per set of summaries
            assert summaries is not None and boxes is not None
            return summaries.derived.nearby(key, boxes, up_axis=up_axis)

        answers: list[TextAnswer] = [
            answer_text(text, vectors, rank=rank, embeddings=self.replica.embeddings_for, scorer=self.scorer,
                        boxes=boxes, top_k=top_k, up_axis=up_axis, nearby=nearby if boxes is not None else None)
            for text in queries
        ]
        keys = sorted({r.key for a in answers for r in a.regions})
        points = None
        if with_points:  # the points themselves: only geometry has them (box and count from them too)
            points = self._points_of(keys, limits.MAX_QUERY_POINTS)
        named = set(keys) | {n.key for a in answers for r in a.regions for n in r.nearby} | {
            k for a in answers for k in a.anchors}
        labels = self.replica.labels_for(sorted(named))
        return [
            QueryReply(
                embedding_space=space,
                query=query,
                regions=region_hits(
                    answer.regions, labels, points, with_points=with_points, max_points=max_points, summaries=summaries
                ),
                match_threshold=self.scorer.calibration.threshold,
                relation=None if answer.relation is None else RelationQueryInfo(
                    target=answer.relation.target, relation=answer.relation.relation, anchor=answer.relation.anchor,
                    anchor_keys=answer.anchors),
            )
            for query, answer in zip(queries, answers, strict=True)
        ]

    def _candidates(self, text: str, vector: np.ndarray, n: int, *, by_text: bool) -> list[tuple[int, float]]:
        """The ``n`` regions closest to ``vector`` ((key, cosine), best first); by text from the
        cache of the current dictionary version when ``by_text``."""
        if not by_text:
            return self.replica.top_k(vector, n)
        cached = self.rankings.get(self.replica.state, text, n)
        if cached is not None:
            return cached
        state, ranked = self.replica.top_k_at_state(vector, n)
        self.rankings.put(state, text, n, ranked)
        return ranked

    def _check_text(self, text: str, which: str = "") -> None:
        try:
            limits.check_text(text, which=which)
        except limits.LimitError as exc:
            raise RequestError("too_large", str(exc)) from None

    def _answer_texts(self, texts: list[str], req: TextQuery | TextQueryBatch, *, numbered: bool) -> list[QueryReply]:
        """Every text checked first (``numbered``: errors say which of a batch), all embedded in ONE
        encoder call, each ranked: what a text query and a batch of them both do."""
        for i, text in enumerate(texts):
            self._check_text(text, f"text {i + 1} of {len(texts)} " if numbered else "")
        self._check_limits(req.top_k, req.max_points)
        space = self._check_space(req.embedding_space)
        self._check_text_space(space)
        wanted = texts_to_embed(texts)  # the texts, then the X and Y of "X next to Y" queries
        vectors = np.asarray(self.texts.encode(wanted), np.float32).reshape(len(wanted), -1)
        return self._rank_many(
            dict(zip(wanted, vectors, strict=True)),
            list(texts),
            top_k=req.top_k,
            with_points=req.with_points,
            max_points=req.max_points,
            space=space,
            by_text=True,
        )

    def handle_text(self, req: TextQuery) -> QueryReply:
        started = time.monotonic()
        reply = self._answer_texts([req.text], req, numbered=False)[0]
        self._note(started)
        return reply

    def handle_text_batch(self, req: TextQueryBatch) -> QueryBatchReply:
        """Several texts: embedded in one encoder call, each ranked as :meth:`handle_text` ranks one
        (the same replies, in the order of ``texts``)."""
        started = time.monotonic()
        replies = self._answer_texts(list(req.texts), req, numbered=True)
        self._note(started, len(req.texts))
        return QueryBatchReply(replies=replies)

    def handle_image(self, req: ImageQuery) -> QueryReply:
        started = time.monotonic()
        self._check_limits(req.top_k, req.max_points)
        space = self._check_space(req.embedding_space)
        encode_image = getattr(self.text_encoder, "encode_image", None)
        if encode_image is None:
            raise RequestError(
                "unsupported",
                f"the {self.text_encoder.embedding_space!r} encoder has no image "
                "tower: image queries need a CLIP-style encoder (--text-encoder clip-regions)",
            )
        self._check_text_space(space)
        vector = np.asarray(encode_image(req.image), np.float32).reshape(-1)
        reply = self._rank(
            vector,
            top_k=req.top_k,
            with_points=req.with_points,
            max_points=req.max_points,
            space=space,
            query=f"image {req.image.shape[1]}x{req.image.shape[0]}",
        )
        self._note(started)
        return reply

    def handle_point(self, req: PointQuery) -> QueryReply:
        started = time.monotonic()
        self._check_limits(req.top_k, req.max_points)
        space = self._check_space(None)
        points = self._points_of(None, limits.MAX_QUERY_POINTS)
        if points is None:
            raise RequestError("no_geometry", "the geometry service did not answer: is it running?")
        dist = np.linalg.norm(points.points.astype(np.float64) - req.point_world[None, :], axis=1)
        near = (dist <= req.radius_m) & (points.keys >= 0)
        keys, counts = np.unique(points.keys[near], return_counts=True)
        order = np.argsort(-counts)[: req.top_k]
        total = max(int(near.sum()), 1)
        ranked = [(int(keys[i]), float(counts[i]) / total) for i in order]
        hits = region_hits(
            ranked,
            self.replica.labels_for([k for k, _ in ranked]),
            points,
            with_points=req.with_points,
            max_points=req.max_points,
        )
        self._note(started)
        x, y, z = (float(v) for v in req.point_world)
        return QueryReply(
            embedding_space=space,
            query=f"point ({x:.3f}, {y:.3f}, {z:.3f}) r={req.radius_m:g} m",
            regions=hits,
        )

    def _note(self, started: float, queries: int = 1) -> None:
        if self._runner is not None:
            self._runner.stats.incr(QueryCounter.QUERIES, queries)

    # ------------------------------------------------------------------------ wiring
    def setup(self, runner: ServiceRunner) -> None:
        self._runner = runner
        set_torch_threads(self.section.torch_threads)
        runner.subscriber(DICTIONARY_DELTA, self.on_delta, queue_size=256)
        self.resync()
        # several query services may declare these (services/query/instances.py): left to the session's close
        for endpoint, handler in ((QUERY_TEXT, self.handle_text), (QUERY_TEXT_BATCH, self.handle_text_batch),
                                  (QUERY_IMAGE, self.handle_image), (QUERY_POINT, self.handle_point)):
            runner.queryable(endpoint, handler, undeclare_on_close=False)
            # ... and on this instance's own key, where clients that spread their requests ask it by name
            runner.queryable_at(endpoint.instance_key(runner.keys, runner.service), endpoint.request, endpoint.reply,
                                handler, undeclare_on_close=False)
        runner.stats.set(QueryCounter.REGIONS, len(self.replica))

    def loop(self, runner: ServiceRunner) -> None:
        period = min(self.section.summary_refresh_s, self.section.resync_period_s)
        last_resync_check = time.monotonic()
        while not runner.wait(period):
            try:
                self._keep_summaries_warm()
                if time.monotonic() - last_resync_check >= self.section.resync_period_s:
                    last_resync_check = time.monotonic()
                    if self.replica.embedding_space is None:
                        self.resync()
            except Exception:  # one failed refresh or resync: logged, counted, tried again next period
                logger.exception("query: background refresh failed; trying again in %.1f s", period)
                runner.stats.add_error()

    def close(self) -> None:
        return None


def set_torch_threads(n: int) -> None:
    """Intra-op threads of torch in this process (when the text encoder uses torch; 0 = default)."""
    torch = sys.modules.get("torch")
    if n > 0 and torch is not None and torch.get_num_threads() != n:
        torch.set_num_threads(n)
        logger.info("query: torch uses %d intra-op thread(s)", n)


DEFINITION = ServiceDefinition(
    name="query",
    help="answer text, image and 3D-point queries with ranked regions",
    config_model=QueryConfig,
    build=QueryService,
    instance_name=lambda config: query_service_name(config.query.instance),
)
