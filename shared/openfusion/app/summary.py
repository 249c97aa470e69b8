"""``run.json``: what one ``openfusion run`` did, typed, from either kind of run.

The multi-process run reads the services' health counters (:mod:`openfusion.wire.counters`);
the in-process run reads :class:`~openfusion.mapping.pipeline.PipelineStats`. Both compute
3D-Rec and Sem-3D-Rec with the one definition,
:func:`~openfusion.mapping.pipeline.reconstruction_rates`.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel

from openfusion.mapping.pipeline import PipelineStats, reconstruction_rates
from openfusion.wire.counters import SKIPPED_PREFIX, BridgeCounter, GeometryCounter, SemanticCounter
from openfusion.wire.schemas import HealthStats


def _round(value: float | None) -> float | None:
    return round(value, 2) if value else None


class RunSummary(BaseModel):
    """The fields of ``run.json`` (README, "Two commands")."""

    mode: Literal["services", "in-process"]
    source: str
    encoder: str
    noise: str
    semantic_every: int
    frames_read: int
    frames_skipped: dict[str, int]
    frames_published: int
    frames_integrated: int
    semantic_frames: int
    semantic_failed: int = 0
    regions: int
    rec_fps: float | None
    sem_rec_fps: float | None
    wall_s: float
    map_dir: str = "map"

    @classmethod
    def from_health(
        cls, stats: dict[str, HealthStats], *, source: str, encoder: str, noise: str, semantic_every: int, wall_s: float
    ) -> RunSummary:
        """From the last health stats of the run's services."""

        def c(service: str, name: str) -> float:
            s = stats.get(service)
            return s.counter(name) if s is not None else 0.0

        rec, sem = reconstruction_rates(
            frames_integrated=c("geometry", GeometryCounter.FRAMES_INTEGRATED),
            integrate_s=c("geometry", GeometryCounter.INTEGRATE_BUSY_S),
            semantic_frames=c("semantic", SemanticCounter.SEMANTIC_FRAMES),
            semantic_s=c("semantic", SemanticCounter.BUSY_S),
        )
        bridge = stats.get("bridge")
        skipped = {k.removeprefix(SKIPPED_PREFIX): int(v) for k, v in (bridge.counters.items() if bridge else [])
                   if k.startswith(SKIPPED_PREFIX)}
        return cls(
            mode="services", source=source, encoder=encoder, noise=noise, semantic_every=semantic_every,
            frames_read=int(c("bridge", BridgeCounter.FRAMES_READ)),
            frames_skipped=skipped,
            frames_published=int(c("bridge", BridgeCounter.FRAMES_PUBLISHED)),
            frames_integrated=int(c("geometry", GeometryCounter.FRAMES_INTEGRATED)),
            semantic_frames=int(c("semantic", SemanticCounter.SEMANTIC_FRAMES)),
            semantic_failed=int(c("semantic", SemanticCounter.FRAMES_FAILED)),
            regions=int(c("semantic", SemanticCounter.REGIONS)),
            rec_fps=_round(rec), sem_rec_fps=_round(sem), wall_s=round(wall_s, 1),
        )

    @classmethod
    def from_pipeline(
        cls, stats: PipelineStats, *, regions: int, source: str, encoder: str, noise: str, semantic_every: int,
        wall_s: float,
    ) -> RunSummary:
        """From the in-process pipeline's stats."""
        return cls(
            mode="in-process", source=source, encoder=encoder, noise=noise, semantic_every=semantic_every,
            frames_read=stats.frames_read, frames_skipped=dict(stats.frames_skipped),
            frames_published=stats.frames_integrated, frames_integrated=stats.frames_integrated,
            semantic_frames=stats.semantic_frames, semantic_failed=stats.semantic_failed, regions=regions,
            rec_fps=_round(stats.rec_fps), sem_rec_fps=_round(stats.sem_rec_fps), wall_s=round(wall_s, 1),
        )
