"""A fixed per-frame cost added to any region encoder, for tests and benches.

``DelayedRegionEncoder(inner, delay_ms)`` encodes with ``inner`` and then sleeps ``delay_ms``: it
models an encoder on a remote GPU (the semantic service waits, the local CPU stays free), not CPU
load. ``openfusion run --encoder-delay-ms MS`` and ``semantic.encoder_delay_ms`` use it; the pool
benches use it to give every worker the same known cost.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from openfusion.encoders.base import RegionEncoder, RegionObservation
from openfusion.frame import Frame


class DelayedRegionEncoder(RegionEncoder):
    """``inner``'s observations, each one ``delay_ms`` later (sleeping)."""

    def __init__(self, inner: RegionEncoder, delay_ms: float) -> None:
        if delay_ms < 0:
            raise ValueError(f"delay_ms must be >= 0, got {delay_ms}")
        self.inner = inner
        self.delay_s = float(delay_ms) / 1000.0
        self.name = getattr(inner, "name", type(inner).__name__)
        self.embedding_space = inner.embedding_space
        self.dim = inner.dim
        self.output_scale = inner.output_scale

    @property
    def needs_instances(self) -> bool:
        return bool(getattr(self.inner, "needs_instances", False))

    def output_size(self, height_px: int, width_px: int) -> tuple[int, int]:
        return self.inner.output_size(height_px, width_px)

    def warm_up(self, vocabulary: Sequence[str] = ()) -> None:
        self.inner.warm_up(vocabulary)  # no delay: the delay models a frame's cost

    def encode(self, frame: Frame) -> RegionObservation:
        return self.encode_where(frame, None, None)

    def encode_where(self, frame: Frame, wanted_px: np.ndarray | None, min_share: float | None) -> RegionObservation:
        obs = self.inner.encode_where(frame, wanted_px, min_share)
        if self.delay_s > 0:
            time.sleep(self.delay_s)  # a frame's cost: a real crop encoder's share of it is per region
        return obs

    def __getattr__(self, name: str) -> Any:  # everything else (stats, encode_image, ...) is the inner encoder's
        if name == "inner":
            raise AttributeError(name)
        return getattr(self.inner, name)
