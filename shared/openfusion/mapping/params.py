"""Parameters of the semantic TSDF volume, with units in every name and validation in one place."""

from __future__ import annotations

import math
import re
from dataclasses import asdict, dataclass
from typing import Any, Literal

_DEVICE_RE = re.compile(r"^(CPU|CUDA):(\d+)$")

WhenFull = Literal["raise", "drop_new"]

#: Blocks a long-running map (the geometry service, ``openfusion run --in-process``, the evaluation)
#: allocates at start: 16384 blocks of 8^3 voxels x 28 B = 230 MiB, a furnished room at 2 cm. The
#: grid doubles when full and each doubling copies every block while integration waits (~0.5 s
#: measured), so these start big enough for a room; the library default stays small for tests.
ROOM_SCALE_INITIAL_BLOCKS = 16384


def normalise_device(device: str) -> str:
    """Return an Open3D device string ``"CPU:0"`` / ``"CUDA:n"``; accepts ``cpu``, ``cuda``, ``cuda:1``."""
    text = str(device).strip().upper()
    if text in ("CPU", "CUDA"):
        text += ":0"
    if not _DEVICE_RE.match(text):
        raise ValueError(f"device must be 'CPU:0' or 'CUDA:<n>', got {device!r}")
    return text


@dataclass(frozen=True)
class VolumeParams:
    """Geometry and semantic-fusion parameters of a :class:`SemanticVolume`.

    - ``voxel_size_m``: voxel edge length in metres (2 cm default).
    - ``block_resolution``: voxels per block edge (Open3D allocates blocks of ``block_resolution**3``).
    - ``trunc_voxels``: TSDF truncation distance in voxels (paper: 4); passed to Open3D as
      ``trunc_voxel_multiplier`` (whose own default is 8).
    - ``depth_min_m`` / ``depth_max_m``: depth measurements outside this range are ignored.
    - ``initial_block_count``: blocks allocated up front; the grid grows by doubling when needed.
    - ``max_blocks``: block budget; ``None`` lets the grid grow. When set, a frame that needs more
      blocks than the budget allows is refused (``when_full="raise"``: :class:`CapacityError`, nothing
      written) or integrated into its already allocated blocks only (``when_full="drop_new"``).
    - ``min_weight``: a voxel counts as observed surface (for render, update and extraction) once it
      has at least this many depth observations.
    - ``conf_history_weight`` (w >= 0): the weight of a voxel's stored semantic confidence against
      one new observation (``openfusion.mapping.update_rule``): the same key averages,
      ``(w * conf + c) / (w + 1)``; another key removes ``c / (w + 1)`` and takes the voxel only
      when that uses the stored confidence up. Default 3: a voxel at confidence 1 needs 4
      full-confidence contrary observations to change key; 0 reacts to every single observation.
    - ``label_fill_radius_m``: when surface points are read out (queries, segmentation, exports), a
      point with no labelled voxel among the 8 corners of its cell takes the key of the nearest
      labelled surface point within this distance (0 turns it off). The update labels voxels at the
      ray hits of the encoder-sized view (e.g. 160x120), so structures thinner than a pixel there
      (lamp poles, plant stems, chair legs) are otherwise never labelled.
    - ``device``: ``"CPU:0"`` or ``"CUDA:0"`` (when the installed Open3D has CUDA).
    """

    voxel_size_m: float = 0.02
    block_resolution: int = 8
    trunc_voxels: float = 4.0
    depth_min_m: float = 0.1
    depth_max_m: float = 6.0
    initial_block_count: int = 4096
    max_blocks: int | None = None
    when_full: WhenFull = "raise"
    min_weight: float = 1.0
    conf_history_weight: float = 3.0
    label_fill_radius_m: float = 0.06
    device: str = "CPU:0"

    def __post_init__(self) -> None:
        def finite_positive(name: str, value: float) -> None:
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a finite positive number, got {value!r}")

        finite_positive("voxel_size_m", self.voxel_size_m)
        if self.voxel_size_m > 1.0:
            raise ValueError(f"voxel_size_m must be at most 1 m, got {self.voxel_size_m}")
        if not isinstance(self.block_resolution, int) or not 2 <= self.block_resolution <= 32:
            raise ValueError(f"block_resolution must be an int in [2, 32], got {self.block_resolution!r}")
        finite_positive("trunc_voxels", self.trunc_voxels)
        if not (math.isfinite(self.depth_min_m) and self.depth_min_m >= 0):
            raise ValueError(f"depth_min_m must be finite and >= 0, got {self.depth_min_m}")
        finite_positive("depth_max_m", self.depth_max_m)
        if self.depth_max_m <= self.depth_min_m:
            raise ValueError(f"depth_max_m ({self.depth_max_m}) must exceed depth_min_m ({self.depth_min_m})")
        if not isinstance(self.initial_block_count, int) or self.initial_block_count < 1:
            raise ValueError(f"initial_block_count must be an int >= 1, got {self.initial_block_count!r}")
        if self.max_blocks is not None and (not isinstance(self.max_blocks, int) or self.max_blocks < 1):
            raise ValueError(f"max_blocks must be None or an int >= 1, got {self.max_blocks!r}")
        if self.when_full not in ("raise", "drop_new"):
            raise ValueError(f"when_full must be 'raise' or 'drop_new', got {self.when_full!r}")
        finite_positive("min_weight", self.min_weight)
        if not (math.isfinite(self.conf_history_weight) and self.conf_history_weight >= 0):
            raise ValueError(f"conf_history_weight must be finite and >= 0, got {self.conf_history_weight}")
        if not (
            isinstance(self.label_fill_radius_m, (int, float))
            and math.isfinite(self.label_fill_radius_m)
            and self.label_fill_radius_m >= 0
        ):
            raise ValueError(f"label_fill_radius_m must be finite and >= 0, got {self.label_fill_radius_m!r}")
        object.__setattr__(self, "device", normalise_device(self.device))

    @property
    def trunc_m(self) -> float:
        """TSDF truncation distance in metres."""
        return self.trunc_voxels * self.voxel_size_m

    @property
    def block_size_m(self) -> float:
        """Edge length of one block in metres."""
        return self.block_resolution * self.voxel_size_m

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON form (for map files and messages)."""
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> VolumeParams:
        """Inverse of :meth:`to_dict`; unknown keys are refused so a typo is not silently ignored."""
        known = set(cls.__dataclass_fields__)
        unknown = set(data) - known
        if unknown:
            raise ValueError(f"unknown VolumeParams fields: {sorted(unknown)}")
        return cls(**data)
