"""Encoder doubles: a real encoder that misbehaves on chosen frames (part of :mod:`openfusion.testing`)."""

from __future__ import annotations

from collections.abc import Collection
from typing import Any

import numpy as np

from openfusion.encoders import EncoderError, RegionObservation, make_region_encoder, make_text_encoder
from openfusion.frame import Frame


class FlakyEncoder:
    """The gt encoder (hash text space), except: no region at all on the frame ids in ``empty_on``
    and an :class:`~openfusion.encoders.EncoderError` on those in ``fail_on``."""

    def __init__(self, *, empty_on: Collection[int] = (2,), fail_on: Collection[int] = (3,), **gt_options: Any) -> None:
        self.inner = make_region_encoder("gt", text_encoder="hash", **gt_options)
        self.name = "flaky-gt"
        self.embedding_space, self.dim = self.inner.embedding_space, self.inner.dim
        self.needs_instances = True
        self.empty_on, self.fail_on = set(empty_on), set(fail_on)

    def output_size(self, height_px: int, width_px: int) -> tuple[int, int]:
        return self.inner.output_size(height_px, width_px)

    def encode(self, frame: Frame) -> RegionObservation:
        if frame.frame_id in self.fail_on:
            raise EncoderError(f"the model crashed on frame {frame.frame_id}")
        obs = self.inner.encode(frame)
        if frame.frame_id in self.empty_on:
            h, w = obs.conf_maps.shape[1:]
            return RegionObservation(np.zeros((0, h, w), np.float32), np.zeros((0, self.dim), np.float32),
                                     self.embedding_space, [])
        return obs


class SplittingEncoder:
    """The gt encoder (hash text space) that splits every region into a left and a right half (by
    the median column of its pixels) on the frame ids in ``split_on``: two touching fragments of one
    object, with the object's embedding, that the map's region merging should join again."""

    def __init__(self, *, split_on: Collection[int] = (0,), **gt_options: Any) -> None:
        self.inner = make_region_encoder("gt", text_encoder="hash", **gt_options)
        self.name = "splitting-gt"
        self.embedding_space, self.dim = self.inner.embedding_space, self.inner.dim
        self.needs_instances = True
        self.split_on = set(split_on)

    def output_size(self, height_px: int, width_px: int) -> tuple[int, int]:
        return self.inner.output_size(height_px, width_px)

    def encode(self, frame: Frame) -> RegionObservation:
        obs = self.inner.encode(frame)
        if frame.frame_id not in self.split_on or len(obs.conf_maps) == 0:
            return obs
        maps, embeddings, labels = [], [], []
        cols = np.arange(obs.conf_maps.shape[2])[None, :]
        for i, conf in enumerate(obs.conf_maps):
            label = obs.labels[i] if obs.labels is not None else None
            on = np.nonzero(conf > 0)[1]
            cut = np.median(on) if len(on) else 0
            for half in (np.where(cols < cut, conf, 0), np.where(cols >= cut, conf, 0)):
                if half.any():
                    maps.append(half.astype(np.float32))
                    embeddings.append(obs.embeddings[i])
                    labels.append(label)
        return RegionObservation(np.stack(maps), np.stack(embeddings), self.embedding_space, labels)


class CountingTextEncoder:
    """The hash text encoder, recording the texts of every ``encode`` call (``calls``): what a
    test checks to prove several texts went to the encoder in one call."""

    def __init__(self) -> None:
        self.inner = make_text_encoder("hash")
        self.embedding_space = self.inner.embedding_space
        self.dim = self.inner.dim
        self.calls: list[list[str]] = []

    def encode(self, texts: list[str]) -> np.ndarray:
        self.calls.append(list(texts))
        return self.inner.encode(texts)
