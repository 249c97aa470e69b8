"""Messages of the semantic service: updates and the region dictionary."""

from __future__ import annotations

from typing import ClassVar

import numpy as np
from pydantic import Field, model_validator

from openfusion.poses import check_pose
from openfusion.wire.codec import ndarray
from openfusion.wire.message import Message
from openfusion.wire.schemas.base import (
    DEFAULT_ROBOT,
    FloatMap,
    KeyList,
    KeyMap,
    PinholeMessage,
    Pose4x4,
    RobotName,
)


class SemanticUpdate(PinholeMessage):
    """Per-pixel region keys and confidences to fuse into the volume, seen from ``T_world_cam``
    (v2: in ``robot``'s odometry frame, as its frame was; geometry applies the robot's join).

    v3: ``source`` (the semantic service process that sent it, a name new for each process) and
    ``seq`` (1, 2, ... in the order it sent them; 0: not numbered): its next render asks geometry
    to apply this update first (:attr:`RenderRequest.after_update_seq`)."""

    schema_name: ClassVar[str] = "semantic.update"
    schema_version: ClassVar[int] = 3

    frame_id: int = Field(ge=0)
    T_world_cam: Pose4x4
    key_map: KeyMap
    conf_map: FloatMap
    new_keys: KeyList
    # The frame's depth resampled to the key map (metres, 0 = none): enables the update's depth
    # gate, so labels of an object's outline do not land on the background behind it.
    depth_m: FloatMap | None = None
    robot: RobotName = DEFAULT_ROBOT
    source: str = Field("", max_length=64)
    seq: int = Field(0, ge=0)

    @model_validator(mode="after")
    def _check(self) -> SemanticUpdate:
        check_pose(self.T_world_cam)
        if self.seq and not self.source:
            raise ValueError("a numbered update (seq > 0) must name its source")
        self._check_image("key_map", self.key_map)
        self._check_image("conf_map", self.conf_map)
        if self.depth_m is not None:
            self._check_image("depth_m", self.depth_m)
        return self


def _check_dictionary_rows(
    *, dim: int, keys: np.ndarray, embeddings: np.ndarray, counts: np.ndarray, labels: list[str]
) -> None:
    m = len(keys)
    if embeddings.shape != (m, dim):
        raise ValueError(f"embeddings must be ({m}, {dim}) for {m} keys of dim {dim}, got {embeddings.shape}")
    if len(counts) != m or len(labels) != m:
        raise ValueError(f"keys ({m}), counts ({len(counts)}) and labels ({len(labels)}) differ in length")
    if len(np.unique(keys)) != m:
        raise ValueError("keys must be unique")


class DictionaryRequest(Message):
    """Ask the semantic service for a full :class:`DictionarySnapshot`."""

    schema_name: ClassVar[str] = "semantic.dictionary_request"
    schema_version: ClassVar[int] = 1


class DictionarySnapshot(Message):
    """The whole region dictionary: key -> running-mean embedding (not normalised), observation
    count, label ("" = none); ``next_key`` is the key the owner allocates next.

    ``merged_keys`` / ``merged_into`` (version 2): every key merged away so far and the live key it
    ended in. A replica that resyncs from a snapshot after missing a delta learns the merges it
    missed from them: geometry relabels those keys' voxels, and updates planned before a merge
    resolve to the survivor."""

    schema_name: ClassVar[str] = "semantic.dictionary"
    schema_version: ClassVar[int] = 2

    embedding_space: str = Field(min_length=1)
    dim: int = Field(gt=0)
    version: int = Field(ge=0)
    next_key: int = Field(ge=0)
    keys: KeyList
    embeddings: ndarray("float32", shape=(None, None))
    counts: ndarray("int64", shape=(None,))
    labels: list[str]
    merged_keys: KeyList = Field(default_factory=lambda: np.zeros(0, np.int32))
    merged_into: KeyList = Field(default_factory=lambda: np.zeros(0, np.int32))

    @model_validator(mode="after")
    def _check(self) -> DictionarySnapshot:
        _check_dictionary_rows(
            dim=self.dim, keys=self.keys, embeddings=self.embeddings, counts=self.counts, labels=self.labels
        )
        if len(self.merged_into) != len(self.merged_keys):
            raise ValueError(
                f"merged_into ({len(self.merged_into)}) must have one entry per merged key ({len(self.merged_keys)})"
            )
        if np.isin(self.merged_keys, self.keys).any():
            raise ValueError("a merged key cannot also be a live key")
        if len(self.merged_into) and not np.isin(self.merged_into, self.keys).all():
            raise ValueError("every merged key must end in a live key of the snapshot")
        return self


class MergeRequest(Message):
    """Ask the semantic service for a merge pass now (geometry asks before it saves a map)."""

    schema_name: ClassVar[str] = "semantic.merge_request"
    schema_version: ClassVar[int] = 1


class MergeReply(Message):
    """What a requested merge pass did; ``dictionary_version`` is the version after it (its delta,
    when it changed anything, was published before this reply)."""

    schema_name: ClassVar[str] = "semantic.merge_reply"
    schema_version: ClassVar[int] = 1

    ok: bool  # False: geometry gave no contacts (``message`` says why); nothing changed
    regions_merged: int = Field(ge=0)
    regions_pruned: int = Field(ge=0)
    dictionary_version: int = Field(ge=0)
    message: str = ""


class DictionaryDelta(Message):
    """Changes from dictionary ``prev_version`` to ``version``: upserted rows, removed keys and
    what each removed key was merged into (-1 = deleted)."""

    schema_name: ClassVar[str] = "semantic.dictionary_delta"
    schema_version: ClassVar[int] = 1

    embedding_space: str = Field(min_length=1)
    dim: int = Field(gt=0)
    version: int = Field(ge=0)
    prev_version: int = Field(ge=0)
    next_key: int = Field(ge=0)
    keys: KeyList
    embeddings: ndarray("float32", shape=(None, None))
    counts: ndarray("int64", shape=(None,))
    labels: list[str]
    removed_keys: KeyList
    merged_into: KeyList

    @model_validator(mode="after")
    def _check(self) -> DictionaryDelta:
        if self.version <= self.prev_version:
            raise ValueError(
                f"version ({self.version}) must be greater than prev_version ({self.prev_version})"
            )
        _check_dictionary_rows(
            dim=self.dim, keys=self.keys, embeddings=self.embeddings, counts=self.counts, labels=self.labels
        )
        if len(self.merged_into) != len(self.removed_keys):
            raise ValueError(
                f"merged_into ({len(self.merged_into)}) must have one entry per removed key ({len(self.removed_keys)})"
            )
        return self
