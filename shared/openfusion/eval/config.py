"""What one evaluation run measures (:class:`EvalConfig`; :data:`QUICK` for CI, :data:`FULL`) and
the maps it compares, in table order (:data:`MAP_NAMES`)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

from openfusion.eval.classes import DEFAULT_BACKGROUND_CLASSES
from openfusion.mapping.params import MatchParams, MergeParams, SelectParams, VolumeParams

#: Maps compared in every run, in table order.
MAP_NAMES = ("region_map", "region_map_nn_fill", "point_features", "block_samples_16")
MAP_TITLES = {
    "region_map": "region map (ours: per-voxel key + region dictionary)",
    "region_map_nn_fill": "region map + nearest-labelled fill (diagnostic)",
    "point_features": "per-point features (ConceptFusion-style)",
    "block_samples_16": "16 samples per block (reference storage)",
}


@dataclass(frozen=True)
class EvalConfig:
    """Everything that decides what one evaluation run measures."""

    encoder: str = "gt"
    noise: str = "off"
    text_encoder: str = "minilm"
    region_text: str = "caption"  # the gt encoder's region embeddings: "caption" or "name"
    frames: int = 24
    width_px: int = 640
    height_px: int = 480
    # The map's parameters: the same models (and defaults) as the geometry and semantic services.
    volume: VolumeParams = field(default_factory=VolumeParams)
    match: MatchParams = field(default_factory=MatchParams)
    merge: MergeParams = field(default_factory=MergeParams)
    select: SelectParams = field(default_factory=SelectParams)  # which frames are encoded (coverage)
    semantic_every: int = 1
    exclude_background: bool = False
    background_classes: tuple[str, ...] = DEFAULT_BACKGROUND_CLASSES
    unlabelled: str = "miss"
    gt_spacing_m: float = 0.03
    completeness_voxels: float = 2.0
    baselines: bool = True
    raw_open3d_baseline: bool = True
    samples_per_block: int = 16
    encoder_seed: int = 0
    query_repeats: int = 5

    def __post_init__(self) -> None:
        if self.frames < 1:
            raise ValueError(f"frames must be >= 1, got {self.frames}")
        if self.semantic_every < 1:
            raise ValueError(f"semantic_every must be >= 1, got {self.semantic_every}")
        for name in ("gt_spacing_m", "completeness_voxels"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        if self.unlabelled not in ("miss", "ignore"):
            raise ValueError(f"unlabelled must be 'miss' or 'ignore', got {self.unlabelled!r}")

    @property
    def excluded_classes(self) -> tuple[str, ...]:
        return tuple(self.background_classes) if self.exclude_background else ()

    @property
    def voxel_size_m(self) -> float:
        return self.volume.voxel_size_m

    def to_dict(self) -> dict:
        """Plain JSON (results.json): the volume's and matching parameters flattened into the top level."""
        d = {k: v for k, v in self.__dict__.items() if k not in ("volume", "match", "merge", "select")}
        d.update(self.volume.to_dict())
        d.update(self.match.model_dump())
        d.update(self.merge.model_dump())
        d.update(self.select.model_dump())
        d["background_classes"] = list(self.background_classes)
        return d


#: CI-sized run: a 24-frame lap of 640x480 frames per scene (about a minute per scene on a
#: 2-core CPU). Smaller images are not used to save time: the encoder works at a quarter of the
#: input size, and at 320x240 (80x60 regions) boundaries are too coarse for the quality targets.
QUICK = EvalConfig()
#: Full size: a 150-frame lap of 640x480 frames, 2 cm ground-truth sampling.
FULL = replace(QUICK, frames=150, gt_spacing_m=0.02)
