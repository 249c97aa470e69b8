"""Queries and their ranked answers. What a query may ask for (text length, ``top_k``, points,
texts per batch) is declared once in :mod:`openfusion.wire.limits`; these schemas check it with
its functions, so a refused message names the limit as every other surface does."""

from __future__ import annotations

from typing import ClassVar, Literal

import numpy as np
from pydantic import Field, field_validator, model_validator

from openfusion.wire import limits
from openfusion.wire.message import Message, Record
from openfusion.wire.schemas.base import (
    ImageRGB8,
    Points3f,
    Vec3f32,
    Vec3f64,
)

# re-exported: the limits of a query (declared in openfusion.wire.limits)
MAX_TEXT_CHARS = limits.MAX_TEXT_CHARS
MAX_BATCH_TEXTS = limits.MAX_BATCH_TEXTS
#: The spatial relations a hit names (:mod:`openfusion.mapping.relations` computes them).
RELATIONS: tuple[str, ...] = ("on", "under", "above", "next to")
Relation = Literal["on", "under", "above", "next to"]


class _QueryOptions(Message):
    top_k: int = 5  # 1 to limits.MAX_TOP_K
    with_points: bool = False
    max_points: int = 20_000  # points of each region, 1 to limits.MAX_QUERY_POINTS
    embedding_space: str | None = None

    @field_validator("top_k")
    @classmethod
    def _top_k(cls, value: int) -> int:
        return limits.check_top_k(value)

    @field_validator("max_points")
    @classmethod
    def _max_points(cls, value: int) -> int:
        return limits.check_max_points(value)


class TextQuery(_QueryOptions):
    """Rank the map's regions against ``text``. ``embedding_space``: refuse a map of another space."""

    schema_name: ClassVar[str] = "query.text"
    schema_version: ClassVar[int] = 1

    text: str  # 1 to limits.MAX_TEXT_CHARS characters, not blank

    @field_validator("text")
    @classmethod
    def _text(cls, value: str) -> str:
        return limits.check_text(value)


class TextQueryBatch(_QueryOptions):
    """Rank the map's regions against each of ``texts`` in one round trip (1 to
    :data:`MAX_BATCH_TEXTS` texts, each 1 to :data:`MAX_TEXT_CHARS` characters); the options apply
    to every text. Answered with a :class:`QueryBatchReply`: one :class:`QueryReply` per text, in order."""

    schema_name: ClassVar[str] = "query.text_batch"
    schema_version: ClassVar[int] = 1

    texts: list[str]  # 1 to limits.MAX_BATCH_TEXTS texts, each as TextQuery's

    @field_validator("texts")
    @classmethod
    def _texts(cls, value: list[str]) -> list[str]:
        return limits.check_batch(value)


class ImageQuery(_QueryOptions):
    """Rank the map's regions against an RGB image."""

    schema_name: ClassVar[str] = "query.image"
    schema_version: ClassVar[int] = 1

    image: ImageRGB8

    @model_validator(mode="after")
    def _check(self) -> ImageQuery:
        if self.image.shape[0] == 0 or self.image.shape[1] == 0:
            raise ValueError(f"image must not be empty, got shape {self.image.shape}")
        return self


class PointQuery(Message):
    """Regions within ``radius_m`` of a world point (metres), best ``top_k``."""

    schema_name: ClassVar[str] = "query.point"
    schema_version: ClassVar[int] = 1

    point_world: Vec3f64
    radius_m: float = Field(default=0.1, gt=0)
    top_k: int = 5  # 1 to limits.MAX_TOP_K
    with_points: bool = False
    max_points: int = 20_000  # 1 to limits.MAX_QUERY_POINTS

    @field_validator("top_k")
    @classmethod
    def _top_k(cls, value: int) -> int:
        return limits.check_top_k(value)

    @field_validator("max_points")
    @classmethod
    def _max_points(cls, value: int) -> int:
        return limits.check_max_points(value)

    @model_validator(mode="after")
    def _check(self) -> PointQuery:
        if not np.isfinite(self.point_world).all():
            raise ValueError("point_world must be finite")
        return self


class NearbyRegion(Record):
    """A region related to a hit: the hit is ``relation`` it (``on`` the desk, ``next to`` the
    table); ``distance_m`` between the two boxes (0 when they touch)."""

    key: int
    label: str | None = None
    relation: Relation
    distance_m: float = Field(ge=0)


class RelationQueryInfo(Record):
    """How a query of the form "X REL Y" was read: X (``target``), the relation, Y (``anchor``),
    and the regions taken as Y (the best Y matches; a text whose Y matches no region is answered as
    a plain query, without this record)."""

    target: str
    relation: Relation
    anchor: str
    anchor_keys: list[int] = Field(default_factory=list)


class RegionHit(Record):
    """One ranked region: key, similarity ``score`` (cosine), ``relevancy`` in [0, 1] against the
    canonical negative phrases and the query-side contrast categories, ``match`` (what was asked:
    relevancy at or above the embedding space's calibrated threshold and a margin at least a share
    of the query's best; see :mod:`openfusion.mapping.relevancy`),
    label, axis-aligned bbox and
    centroid (world, metres), up to three ``nearby`` regions with the hit's relation to each, and
    for a relation query the anchor region it stands in the relation to (``relation``)."""

    key: int
    score: float
    label: str | None = None
    bbox_min: Vec3f32
    bbox_max: Vec3f32
    num_points: int = Field(ge=0)
    points: Points3f | None = None
    relevancy: float | None = Field(default=None, ge=0.0, le=1.0)
    match: bool | None = None
    centroid: Vec3f32 | None = None
    nearby: list[NearbyRegion] = Field(default_factory=list, max_length=16)
    relation: NearbyRegion | None = None


class QueryReply(Message):
    """Regions ranked best first for the ``query`` (text, or a description of the image/point query)."""

    schema_name: ClassVar[str] = "query.reply"
    schema_version: ClassVar[int] = 2  # 2: relevancy, match, centroid, nearby, relation

    embedding_space: str
    query: str
    regions: list[RegionHit] = Field(default_factory=list)
    #: The relevancy a hit needs to be a ``match`` in this space (None: not computed, e.g. point queries).
    match_threshold: float | None = Field(default=None, ge=0.0, le=1.0)
    relation: RelationQueryInfo | None = None

    @property
    def matched(self) -> bool:
        """Whether any region is a match (False for "no match")."""
        return any(bool(r.match) for r in self.regions)


class QueryBatchReply(Message):
    """The answer to a :class:`TextQueryBatch`: one :class:`QueryReply` per text, in the order of
    the request's ``texts``."""

    schema_name: ClassVar[str] = "query.batch_reply"
    schema_version: ClassVar[int] = 2  # 2: its replies are QueryReply 2

    replies: list[QueryReply] = Field(max_length=MAX_BATCH_TEXTS)
