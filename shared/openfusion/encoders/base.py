"""Region / text encoder interface shared by every backend (docs/ARCHITECTURE.md, "Encoders").

A region encoder turns one :class:`~openfusion.frame.Frame` into a :class:`RegionObservation`:
``n`` confidence maps at the encoder's output resolution (by default a quarter of the input,
640x480 -> 160x120) and one unit-norm embedding per region, all in one named embedding space.
A text encoder maps query strings into the same space. The map does not care which backend
produced an observation; it only checks that embedding spaces agree.
"""

from __future__ import annotations

import abc
import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from openfusion.errors import OpenFusionError, UserError
from openfusion.frame import CameraIntrinsics, Frame
from openfusion.mapping.region_gate import gate_observation

logger = logging.getLogger(__name__)

#: Default output size as a fraction of the input image (H/4 x W/4, as Open-Fusion's region encoder).
DEFAULT_OUTPUT_SCALE = 0.25

#: Backends of the ``clip-dense`` region encoder (:mod:`openfusion.encoders.clip_dense`).
CLIP_DENSE_BACKENDS = ("torch", "onnx", "onnx-int8")
#: Default longer side of the ``clip-dense`` tower's input: 448 px (480x640 -> 320x448, 10x14 patches
#: of 32 px). 384 px is 23 % fewer tokens but moved region embeddings too far (docs/ENCODERS.md).
DEFAULT_DENSE_INPUT_LONG_SIDE_PX = 448

#: Embeddings whose L2 norm is below this are treated as invalid (cannot be normalised).
MIN_EMBEDDING_NORM = 1e-8


class EncoderError(OpenFusionError, ValueError):
    """Bad input to an encoder (a frame without ground truth, an empty query, ...)."""


class EncoderConfigError(EncoderError, UserError):
    """An encoder that cannot be built as configured: an unknown name, a missing model file or
    folder, an option that does not apply (the message names it and what would be valid)."""


@dataclass
class RegionObservation:
    """Regions seen in one frame.

    ``conf_maps`` is (n, h, w) float32 in [0, 1]: how confident the encoder is that each pixel
    of the output grid belongs to region i. ``embeddings`` is (n, d) float32, unit L2 norm, in
    the space named ``embedding_space``. ``labels`` are optional per-region texts (the gt
    encoder fills in raw category names; vision backends leave it None).

    ``embedded`` (bool (n,), None = every region) says which regions carry an embedding: a frame
    encoded with :meth:`RegionEncoder.encode_where` embeds only the regions that show what the view
    adds (:mod:`openfusion.mapping.region_gate`); the others keep their confidence map (their
    pixels still update the map's region keys) and a zero row in ``embeddings``.
    """

    conf_maps: np.ndarray
    embeddings: np.ndarray
    embedding_space: str
    labels: list[str] | None = None
    embedded: np.ndarray | None = None

    @property
    def embedded_mask(self) -> np.ndarray:
        """bool (n,): the regions that carry an embedding (every one when ``embedded`` is None)."""
        if self.embedded is None:
            return np.ones(self.num_regions, bool)
        return np.asarray(self.embedded, bool)

    @property
    def num_embedded(self) -> int:
        """Regions embedded (what an encoder call paid for, OVI-MAP's VLM calls)."""
        return self.num_regions if self.embedded is None else int(np.count_nonzero(self.embedded))

    @property
    def num_regions(self) -> int:
        return int(self.conf_maps.shape[0])

    @property
    def output_size(self) -> tuple[int, int]:
        """(h, w) of the confidence maps."""
        return int(self.conf_maps.shape[1]), int(self.conf_maps.shape[2])

    def validate(self, *, dim: int | None = None, norm_tolerance: float = 1e-3) -> None:
        """Raise :class:`EncoderError` naming the first inconsistency."""
        c, e = self.conf_maps, self.embeddings
        if not isinstance(c, np.ndarray) or c.ndim != 3 or c.dtype != np.float32:
            raise EncoderError(f"conf_maps must be (n, h, w) float32, got {_describe(c)}")
        if not isinstance(e, np.ndarray) or e.ndim != 2 or e.dtype != np.float32:
            raise EncoderError(f"embeddings must be (n, d) float32, got {_describe(e)}")
        if c.shape[0] != e.shape[0]:
            raise EncoderError(f"{c.shape[0]} confidence maps but {e.shape[0]} embeddings")
        if dim is not None and e.shape[1] != dim:
            raise EncoderError(f"embeddings have dimension {e.shape[1]}, expected {dim}")
        if c.size and (not np.isfinite(c).all() or c.min() < 0.0 or c.max() > 1.0):
            raise EncoderError("conf_maps must be finite and within [0, 1]")
        if self.embedded is not None:
            m = self.embedded
            if not isinstance(m, np.ndarray) or m.dtype != bool or m.shape != (c.shape[0],):
                raise EncoderError(f"embedded must be ({c.shape[0]},) bool, got {_describe(m)}")
        if e.size:
            if not np.isfinite(e).all():
                raise EncoderError("embeddings contain NaN or inf")
            norms = np.linalg.norm(e, axis=1)
            unit = np.abs(norms - 1.0) <= norm_tolerance
            if self.embedded is not None:  # a region not embedded has a zero row
                unit = np.where(self.embedded, unit, norms == 0.0)
            bad = np.flatnonzero(~unit)
            if bad.size:
                want = "1" if self.embedded is None or self.embedded[bad[0]] else "0 (not embedded)"
                raise EncoderError(f"embedding {int(bad[0])} has norm {norms[bad[0]]:.4f}, expected {want}")
        if not self.embedding_space:
            raise EncoderError("embedding_space must be a non-empty string")
        if self.labels is not None and len(self.labels) != c.shape[0]:
            raise EncoderError(f"{len(self.labels)} labels for {c.shape[0]} regions")

    @classmethod
    def empty(cls, embedding_space: str, dim: int, h: int, w: int) -> RegionObservation:
        """An observation with no regions (a frame where nothing was found)."""
        return cls(
            np.zeros((0, h, w), np.float32), np.zeros((0, dim), np.float32), embedding_space, labels=[]
        )


def blank_frame(height_px: int = 480, width_px: int = 640) -> Frame:
    """A mid-grey frame with flat 1 m depth at the usual camera size: what a warm-up encodes (its
    result is thrown away; it only makes the model's first run, whatever the weights)."""
    intrinsics = CameraIntrinsics(width_px, height_px, 0.8 * width_px, 0.8 * width_px, width_px / 2, height_px / 2)
    return Frame(frame_id=-1, stamp_ns=0, color=np.full((height_px, width_px, 3), 128, np.uint8),
                 depth=np.ones((height_px, width_px), np.float32), depth_scale=1.0, intrinsics=intrinsics,
                 T_world_cam=np.eye(4))


class RegionEncoder(abc.ABC):
    """Frame -> :class:`RegionObservation`. Subclasses set ``name``, ``embedding_space``, ``dim``,
    and ``needs_instances = True`` when they read ``frame.instance`` (the semantic service then
    joins each frame with its :class:`~openfusion.wire.schemas.InstanceFrame` from the bus)."""

    name: str = ""
    embedding_space: str = ""
    dim: int = 0
    needs_instances: bool = False

    def __init__(self, *, output_scale: float = DEFAULT_OUTPUT_SCALE) -> None:
        if not (0.0 < output_scale <= 1.0):
            raise ValueError(f"output_scale must be in (0, 1], got {output_scale}")
        self.output_scale = float(output_scale)

    def output_size(self, height_px: int, width_px: int) -> tuple[int, int]:
        """(h, w) of the confidence maps for an input of ``height_px`` x ``width_px``."""
        return output_size_for(height_px, width_px, self.output_scale)

    @abc.abstractmethod
    def encode(self, frame: Frame) -> RegionObservation:
        """Regions of ``frame`` at :meth:`output_size` of its image size."""

    def encode_where(self, frame: Frame, wanted_px: np.ndarray | None, min_share: float | None) -> RegionObservation:
        """:meth:`encode`, embedding only the regions with at least ``min_share`` of their pixels in
        ``wanted_px`` (bool (h, w), any size: what the view adds, from the frame selection); the
        others come back with ``embedded`` False (:mod:`openfusion.mapping.region_gate`).
        ``wanted_px`` or ``min_share`` None: every region is embedded, as :meth:`encode`.

        This default encodes every region and then drops the embeddings of the others, for
        encoders that describe a frame at once (``clip-dense``: no saving) and for stand-ins (the gt
        encoder stands for a crop encoder); an encoder that embeds region crops one by one
        overrides it and does not compute the skipped ones
        (:class:`~openfusion.encoders.proposal_encoder.ProposalRegionEncoder`)."""
        return gate_observation(self.encode(frame), wanted_px, min_share)

    def warm_up(self, vocabulary: Sequence[str] = ()) -> None:
        """Do the first call's one-off work now (lazy model start-up, caches), so the first
        frames cost what later ones do. A service calls it before it announces itself: an encoder
        worker whose first frames took seconds was sent frames as if it were fast. ``vocabulary``:
        category names it may meet (the gt encoder embeds them now; others ignore them). The
        default does nothing."""
        return None

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.name!r}, space={self.embedding_space!r}, dim={self.dim})"


class TextEncoder(abc.ABC):
    """Texts -> (k, d) float32 unit-norm embeddings in ``embedding_space``."""

    embedding_space: str = ""
    dim: int = 0

    @abc.abstractmethod
    def encode(self, texts: list[str]) -> np.ndarray:
        """Embed ``texts``; returns (len(texts), dim) float32 with unit rows."""

    def __repr__(self) -> str:
        return f"{type(self).__name__}(space={self.embedding_space!r}, dim={self.dim})"


class ImageQueryEncoder(abc.ABC):
    """Optional: an RGB image (a query by example) -> (d,) float32 unit-norm embedding."""

    embedding_space: str = ""
    dim: int = 0

    @abc.abstractmethod
    def encode_image(self, rgb: np.ndarray) -> np.ndarray:
        """Embed an HxWx3 uint8 RGB image; returns (dim,) float32 with unit norm."""


def output_size_for(height_px: int, width_px: int, scale: float) -> tuple[int, int]:
    """(h, w) = round(scale * input), at least 1 pixel each."""
    if height_px <= 0 or width_px <= 0:
        raise EncoderError(f"image size must be positive, got {width_px}x{height_px}")
    return max(1, int(round(height_px * scale))), max(1, int(round(width_px * scale)))


def check_texts(texts: list[str]) -> list[str]:
    """Validate a text batch: a list of non-empty strings (an empty list is allowed)."""
    if isinstance(texts, str):
        raise EncoderError("texts must be a list of strings, got a single string (wrap it in a list)")
    out = list(texts)
    for i, t in enumerate(out):
        if not isinstance(t, str):
            raise EncoderError(f"text {i} is {type(t).__name__}, expected str")
        if not t.strip():
            raise EncoderError(f"text {i} is empty")
    return out


def check_rgb(rgb: np.ndarray) -> np.ndarray:
    """Validate an HxWx3 uint8 RGB image."""
    if not isinstance(rgb, np.ndarray) or rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise EncoderError(f"image must be HxWx3 uint8 RGB, got {_describe(rgb)}")
    if rgb.shape[0] < 1 or rgb.shape[1] < 1:
        raise EncoderError(f"image is empty: {rgb.shape}")
    return rgb


def normalize_rows(x: np.ndarray, *, what: str = "embeddings") -> np.ndarray:
    """Rows of ``x`` scaled to unit L2 norm, as float32; a (near-)zero row is an error."""
    x = np.asarray(x, dtype=np.float32)
    if x.ndim != 2:
        raise EncoderError(f"{what} must be 2-D, got shape {x.shape}")
    if not np.isfinite(x).all():
        raise EncoderError(f"{what} contain NaN or inf")
    norms = np.linalg.norm(x, axis=1, keepdims=True)
    if x.shape[0] and float(norms.min()) < MIN_EMBEDDING_NORM:
        raise EncoderError(f"{what}: row {int(np.argmin(norms))} has zero norm and cannot be normalised")
    return (x / np.maximum(norms, MIN_EMBEDDING_NORM)).astype(np.float32)


def _describe(a: object) -> str:
    if isinstance(a, np.ndarray):
        return f"{a.dtype} array of shape {a.shape}"
    return type(a).__name__
