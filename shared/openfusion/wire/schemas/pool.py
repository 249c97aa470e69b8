"""Messages of the encoder pool (``{prefix}/@pool/encoder/{worker_id}/...``, outside any map):
a worker's :class:`WorkerInfo`, and :class:`EncodeRequest` -> :class:`EncodeReply`."""

from __future__ import annotations

from typing import Any, ClassVar

from pydantic import Field, model_validator

from openfusion.wire.codec import ndarray
from openfusion.wire.message import Message
from openfusion.wire.schemas.sensor import InstanceFrame, RgbdFrame


class WorkerInfoRequest(Message):
    """Ask a worker what it holds."""

    schema_name: ClassVar[str] = "pool.worker_info_request"
    schema_version: ClassVar[int] = 1


class WorkerInfo(Message):
    """What an encoder worker holds: answered on ``…/@pool/encoder/{worker_id}/info``."""

    schema_name: ClassVar[str] = "pool.worker_info"
    schema_version: ClassVar[int] = 1

    worker_id: str
    encoder: str
    embedding_space: str
    dim: int = Field(ge=1)
    device: str
    needs_instances: bool = False
    max_in_flight: int = Field(2, ge=1)


class EncodeRequest(RgbdFrame):
    """One frame to encode for the map ``map_id``, whose dictionary is in ``embedding_space``: a
    worker holding another space refuses it (``reply_err`` ``wrong_space``). The frame's instance
    image travels with it when the worker's encoder reads them (gt). ``embed_where`` (bool (h, w),
    any size) with ``embed_share``: embed only the regions with at least that share of their
    pixels in it (:mod:`openfusion.mapping.region_gate`); absent: every region."""

    schema_name: ClassVar[str] = "pool.encode_request"
    schema_version: ClassVar[int] = 2  # 2: embed_where, embed_share

    map_id: str
    embedding_space: str
    embed_where: ndarray("bool", shape=(None, None)) | None = None
    embed_share: float | None = Field(None, ge=0, le=1)

    @model_validator(mode="after")
    def _check_gate(self) -> EncodeRequest:
        if (self.embed_where is None) != (self.embed_share is None):
            raise ValueError("embed_where and embed_share come together (or neither)")
        if self.embed_where is not None and self.embed_where.size == 0:
            raise ValueError("embed_where is empty")
        return self

    @classmethod
    def of(cls, msg: RgbdFrame, instance: InstanceFrame | None, *, map_id: str, embedding_space: str,
           embed_where: Any = None, embed_share: float | None = None) -> EncodeRequest:
        fields = {name: getattr(msg, name) for name in RgbdFrame.model_fields}
        if instance is not None:
            fields["instance"], fields["instance_categories"] = instance.instance, dict(instance.instance_categories)
        if embed_where is None or embed_share is None:
            embed_where = embed_share = None
        return cls(**fields, map_id=map_id, embedding_space=embedding_space, embed_where=embed_where,
                   embed_share=embed_share)

    def rgbd(self) -> RgbdFrame:
        """The frame as the semantic service saw it (for the update it sends after matching)."""
        return RgbdFrame.model_construct(**{name: getattr(self, name) for name in RgbdFrame.model_fields})


class EncodeReply(Message):
    """A frame's regions: ``conf_maps`` (n, h, w) in [0, 1], ``embeddings`` (n, d) unit rows;
    ``embedded`` (bool (n,)): which regions carry one (the others a zero row; absent: all)."""

    schema_name: ClassVar[str] = "pool.encode_reply"
    schema_version: ClassVar[int] = 2  # 2: embedded

    frame_id: int = Field(ge=0)
    worker_id: str
    embedding_space: str
    conf_maps: ndarray("float32", shape=(None, None, None))
    embeddings: ndarray("float32", shape=(None, None))
    encode_ms: float = Field(ge=0)
    embedded: ndarray("bool", shape=(None,)) | None = None

    @model_validator(mode="after")
    def _check(self) -> EncodeReply:
        if self.conf_maps.shape[0] != self.embeddings.shape[0]:
            raise ValueError(f"{self.conf_maps.shape[0]} confidence maps but {self.embeddings.shape[0]} embeddings")
        if self.embedded is not None and self.embedded.shape[0] != self.conf_maps.shape[0]:
            raise ValueError(f"{self.conf_maps.shape[0]} confidence maps but {self.embedded.shape[0]} embedded flags")
        return self
