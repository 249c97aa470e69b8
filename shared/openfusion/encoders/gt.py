"""Ground-truth region encoder: regions from instance images, embeddings from category names.

This measures **fusion**, not vision. The regions are the dataset's instance masks (area-averaged
to the output grid, so boundary cells get soft confidences) and each embedding is the text
encoder's embedding of the region's raw category (e.g. "office chair", not the benchmark class it
is later scored against): its name and, for a category :mod:`openfusion.encoders.captions` knows
(the built-in room's), six captions of what it is, is for and looks like, as a captioning region
encoder would give (``region_text="caption"``, the default; ``"name"``: the name alone). Optional noise (see :mod:`openfusion.encoders.noise`) stresses
the matcher and the update rule with the errors a real encoder makes.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Sequence

import numpy as np

from openfusion.encoders.base import (
    DEFAULT_OUTPUT_SCALE,
    EncoderError,
    RegionEncoder,
    RegionObservation,
    TextEncoder,
)
from openfusion.encoders.captions import region_text_embeddings
from openfusion.encoders.masks import area_downsample_labels, label_ids
from openfusion.encoders.noise import NoiseProfile, NoiseReport, apply_region_noise, get_noise_profile
from openfusion.frame import Frame

logger = logging.getLogger(__name__)

#: What a region's embedding is made of (:class:`GroundTruthRegionEncoder` ``region_text``).
REGION_TEXTS = ("caption", "name")


class GroundTruthRegionEncoder(RegionEncoder):
    """Regions = ground-truth instances of the frame; embeddings = text embeddings of raw categories.

    Options: ``noise`` (profile name or :class:`NoiseProfile`), ``seed`` (noise is a function of
    seed and frame id only), ``output_scale`` (default 1/4), ``min_area_px`` (regions with less
    confidence mass on the output grid are skipped; default 1 output pixel), ``region_text``
    ("caption": name and captions where known; "name": the name alone).
    """

    name = "gt"
    needs_instances = True

    def __init__(
        self,
        text_encoder: TextEncoder,
        *,
        noise: str | NoiseProfile | None = "off",
        seed: int = 0,
        output_scale: float = DEFAULT_OUTPUT_SCALE,
        min_area_px: float = 1.0,
        region_text: str = "caption",
    ) -> None:
        super().__init__(output_scale=output_scale)
        if not isinstance(text_encoder, TextEncoder):
            raise TypeError(f"text_encoder must be a TextEncoder, got {type(text_encoder).__name__}")
        if min_area_px < 0:
            raise ValueError(f"min_area_px must be >= 0, got {min_area_px}")
        if region_text not in REGION_TEXTS:
            raise ValueError(f"region_text must be one of {REGION_TEXTS}, got {region_text!r}")
        self.region_text = region_text
        self.text_encoder = text_encoder
        self.embedding_space = text_encoder.embedding_space
        self.dim = text_encoder.dim
        self.noise = get_noise_profile(noise)
        self.seed = int(seed)
        self.min_area_px = float(min_area_px)
        self.last_noise_report: NoiseReport | None = None
        self.stats: dict[str, int] = {"frames": 0, "regions": 0, "regions_without_category": 0}
        self._embedding_cache: dict[str, np.ndarray] = {}
        self._lock = threading.Lock()

    def category_embeddings(self, categories: list[str]) -> np.ndarray:
        """(k, d) embeddings of raw categories (name, and captions with ``region_text="caption"``),
        computed once per distinct name."""
        with self._lock:
            missing = sorted({c for c in categories if c not in self._embedding_cache})
            if missing:
                emb = region_text_embeddings(self.text_encoder.encode, missing,
                                             captions=None if self.region_text == "caption" else {})
                for c, e in zip(missing, emb, strict=True):
                    self._embedding_cache[c] = e
            if not categories:
                return np.zeros((0, self.dim), np.float32)
            return np.stack([self._embedding_cache[c] for c in categories]).astype(np.float32)

    def warm_up(self, vocabulary: Sequence[str] = ()) -> None:
        """Embed ``vocabulary`` now (the text model's first call included: about a second for
        MiniLM), so a frame that shows one of those categories first costs no text encoding."""
        names = sorted({str(v) for v in vocabulary})
        if names:
            self.category_embeddings(names)
        else:
            self.text_encoder.encode(["object"])

    def _rng_for(self, frame_id: int) -> np.random.Generator:
        fid = int(frame_id)
        return np.random.default_rng(np.random.SeedSequence([self.seed & 0xFFFFFFFF, fid & 0xFFFFFFFF, (fid >> 32) & 0xFFFFFFFF]))

    def encode(self, frame: Frame) -> RegionObservation:
        instance = frame.instance
        where = f"frame {frame.frame_id}" + (f" from {frame.source!r}" if frame.source else "")
        if instance is None:
            raise EncoderError(
                f"{where} has no ground-truth instance image; the gt encoder needs a source with "
                "instance labels (synthetic, ScanNet instance-filt, Replica)"
            )
        if instance.ndim != 2 or instance.dtype != np.int32:
            raise EncoderError(f"{where}: instance image must be HxW int32, got {instance.dtype} {instance.shape}")
        if frame.color.shape[:2] != instance.shape:
            raise EncoderError(f"{where}: instance image is {instance.shape}, color is {frame.color.shape[:2]}")
        H, W = instance.shape
        out_hw = self.output_size(H, W)

        ids = label_ids(instance)
        ids = ids[ids > 0]
        categories = frame.instance_categories or {}
        known = np.array([int(i) in categories for i in ids], bool) if ids.size else np.zeros(0, bool)
        if not known.all():
            unknown = ids[~known]
            self.stats["regions_without_category"] += int(unknown.size)
            logger.warning(
                "%s: %d instance id(s) without a category skipped (e.g. %s)", where, unknown.size, unknown[:5].tolist()
            )
            ids = ids[known]

        conf = area_downsample_labels(instance, ids, out_hw)
        mass = conf.reshape(conf.shape[0], -1).sum(axis=1)
        big = mass >= self.min_area_px
        conf = conf[big]
        ids = ids[big]
        labels = [str(categories[int(i)]) for i in ids]
        emb = self.category_embeddings(labels)

        if not self.noise.is_off:
            conf, emb, labels, report = apply_region_noise(
                conf, emb, labels, self.noise, self._rng_for(frame.frame_id), min_area_px=self.min_area_px
            )
        else:
            report = NoiseReport(input_regions=len(labels), output_regions=len(labels))
        self.last_noise_report = report
        self.stats["frames"] += 1
        self.stats["regions"] += len(labels)
        return RegionObservation(
            conf_maps=np.ascontiguousarray(conf, dtype=np.float32),
            embeddings=np.ascontiguousarray(emb, dtype=np.float32),
            embedding_space=self.embedding_space,
            labels=labels,
        )
