"""``run.json``: what one ``openfusion run`` did, typed, from either kind of run.

The multi-process run reads the services' health counters (:mod:`openfusion.wire.counters`);
the in-process run reads :class:`~openfusion.mapping.pipeline.PipelineStats`. Both compute
3D-Rec and Sem-3D-Rec with the one definition,
:func:`~openfusion.mapping.pipeline.reconstruction_rates`.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, Field, ValidationInfo, field_validator

from openfusion.mapping.pipeline import PipelineStats, reconstruction_rates
from openfusion.wire.counters import (
    ENCODED_BY_PREFIX,
    SKIPPED_PREFIX,
    BridgeCounter,
    GeometryCounter,
    PoolCounter,
    SemanticCounter,
    semantic_frame_outcomes,
)
from openfusion.wire.schemas import HealthStats
from openfusion.wire.schemas.base import DEFAULT_ROBOT as _DEFAULT_ROBOT


def _round(value: float | None) -> float | None:
    return round(value, 2) if value else None


def _rate(frames: float, first_s: float, last_s: float) -> float | None:
    """Frames per second between the first and the last of ``frames`` events (None for < 2)."""
    return (frames - 1) / (last_s - first_s) if frames >= 2 and last_s > first_s else None


class RobotRun(BaseModel):
    """One robot of the run (``run.json`` ``robots``): its source and bridge's counts, and its
    stream as geometry reports it (:class:`~openfusion.wire.schemas.admin.RobotStatus`): joined or
    held, frames integrated, frames skipped by reason (the source's, the bridge's and geometry's),
    lag, and the transform from its odometry frame to the map's in use (row-major 4x4)."""

    source: str = ""
    state: str = "unknown"
    frames_read: int = 0
    frames_published: int = 0
    frames_integrated: int = 0
    frames_held: int = 0
    frames_replayed: int = 0
    frames_skipped: dict[str, int] = Field(default_factory=dict)
    lag_s: float = 0.0
    T_map_odom: list[float] = Field(default_factory=list)
    join_method: str = ""
    join_fitness: float = 0.0
    join_attempts: int = 0
    corrections: int = 0


def _bridges(stats: dict[str, HealthStats]) -> list[str]:
    """The run's bridges' service names (``bridge``, ``bridge-ROBOT``)."""
    return sorted(name for name in stats if name == "bridge" or name.startswith("bridge-"))


def _robots(stats: dict[str, HealthStats], sources: dict[str, str]) -> dict[str, RobotRun]:
    """Per robot: its bridge's counts and geometry's view of its stream."""
    geometry = stats.get("geometry")
    streams = geometry.robots if geometry is not None else {}
    robots: dict[str, RobotRun] = {}
    for name in list(sources) + [r for r in streams if r not in sources]:
        bridge = stats.get("bridge" if name == _DEFAULT_ROBOT else f"bridge-{name}")
        counters = bridge.counters if bridge is not None else {}
        status = streams.get(name)
        skipped = {k.removeprefix(SKIPPED_PREFIX): int(v) for k, v in counters.items() if k.startswith(SKIPPED_PREFIX)}
        if status is not None:
            for reason, n in status.skipped.items():
                skipped[reason] = skipped.get(reason, 0) + int(n)
        robots[name] = RobotRun(
            source=sources.get(name, ""),
            state=status.state if status is not None else "unknown",
            frames_read=int(counters.get(BridgeCounter.FRAMES_READ, 0)),
            frames_published=int(counters.get(BridgeCounter.FRAMES_PUBLISHED, 0)),
            frames_replayed=int(counters.get(BridgeCounter.FRAMES_REPLAYED, 0)),
            frames_integrated=status.frames_integrated if status is not None else 0,
            frames_held=status.frames_held if status is not None else 0,
            frames_skipped=skipped,
            lag_s=status.lag_s if status is not None else 0.0,
            T_map_odom=list(status.T_map_odom) if status is not None else [],
            join_method=status.join_method if status is not None else "",
            join_fitness=status.join_fitness if status is not None else 0.0,
            join_attempts=status.join_attempts if status is not None else 0,
            corrections=status.corrections if status is not None else 0,
        )
    return robots


class RunSummary(BaseModel):
    """The fields of ``run.json`` (README, "Two commands").

    ``frames_requested``: ``--frames``; ``frames_played``: frames the source gave and the run sent
    into the map (the bridge's published frames, or the frames the in-process loop took), fewer
    than requested when the source is shorter or the run was interrupted; ``interrupted``: the run
    was stopped by SIGINT/SIGTERM, and the map of the ``frames_integrated`` frames was saved.

    Supervision (services run only): ``restarts``: how many times each service was restarted after
    it died; ``frames_replayed``: frames the bridge published again after a restarted geometry
    announced the last frame its checkpoint holds (not in ``frames_published``, which counts each
    frame once); ``frames_duplicate``: frames geometry received and dropped because it already held
    them. ``frames_integrated`` counts each frame once, restarts or not. ``error``: the run failed
    (a service died past the restart limit, a timeout).

    ``map_saved``: where the map went (the absolute path of the map folder, ``OUT/map``) on every
    path that saved one: a finished run, an interrupted one, one that failed after saving what
    geometry held; null when no map was saved (nothing integrated yet, or the run failed before it
    could save). ``semantic_frames`` adds up over restarts of the semantic service, as the
    progress line does. A ``run.json`` written before (``map_saved`` true or false) still loads.
    """

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
    frames_requested: int | None = None
    frames_played: int | None = None
    interrupted: bool = False
    #: encoder workers of the pool (``--encoder-workers``; 0: the semantic service encodes) and the
    #: frames each one encoded that were applied to the map
    encoder_workers: int = 0
    #: query services serving the map (``--query-services``; each client request answered by one)
    query_services: int = 1
    frames_encoded_per_worker: dict[str, int] = Field(default_factory=dict)
    #: frames sent again after their worker died, and frames lost (their workers died twice, or a
    #: newer frame's result had been applied before they could go again)
    encoder_frames_resent: int = 0
    encoder_frames_lost: int = 0
    #: encoded frames whose result came after a newer frame's was applied (dropped: wasted work)
    encoder_results_stale: int = 0
    #: semantic frames per second of mapping time (first to last fused frame): with encoder workers
    #: the semantic service waits on them, so its busy time no longer bounds its rate
    semantic_rate_hz: float | None = None
    #: frame selection (``semantic.select``): frames the region encoder encoded (``encoder_calls``), the
    #: regions it embedded over them (``encoder_regions``) and those it fused without an embedding
    #: because they added nothing (``regions_not_embedded``, ``semantic.select_embed_share``), the
    #: embedded ones per region of the final map (``calls_per_region``), and frames not encoded because
    #: they added too little (``skipped_no_gain``); of the frames scored (``frames_scored``), those
    #: scored on their still camera's last render of the map instead of a new one (``renders_reused``,
    #: ``semantic.select_still_s``)
    select: str = "coverage"
    encoder_calls: int = 0
    encoder_regions: int = 0
    regions_not_embedded: int = 0
    calls_per_region: float | None = None
    skipped_no_gain: int = 0
    frames_scored: int = 0
    renders_reused: int = 0
    #: what became of every frame the semantic service received (``semantic_frames_received``): each
    #: ends in one outcome (``semantic_outcomes``, by counter name: ``semantic_frames`` fused,
    #: ``skipped_no_gain``, ``frames_superseded``, ``frames_dropped`` ...; wire.counters.SEMANTIC_FRAME_OUTCOMES);
    #: ``semantic_frames_pending``: received with none yet when the run ended
    semantic_frames_received: int = 0
    semantic_outcomes: dict[str, int] = Field(default_factory=dict)
    semantic_frames_pending: int = 0
    restarts: dict[str, int] = {}
    frames_replayed: int = 0
    frames_duplicate: int = 0
    error: str | None = None
    map_saved: str | None = None
    #: geometry's memory (MiB): its grid's voxel buffers (the memory budget when one is set) and the
    #: peaks of its resident memory, sampled once a second (RSS; RssAnon without mapped file pages)
    geometry_grid_mb: float | None = None
    geometry_rss_peak_mb: float | None = None
    geometry_rss_anon_peak_mb: float | None = None
    #: each robot's stream by robot name (one robot: ``robot0``, or ``--robot``); README "Several robots"
    robots: dict[str, RobotRun] = Field(default_factory=dict)
    #: geometry shards of the run (``--geometry-shards``, docs/SHARDS.md) and each shard's own counts
    #: (frames integrated, blocks, integrate busy seconds, ...) by its service name; empty for one
    geometry_shards: int = 1
    shards: dict[str, dict[str, float]] = Field(default_factory=dict)

    @field_validator("map_saved", mode="before")
    @classmethod
    def _legacy_map_saved(cls, value: object, info: ValidationInfo) -> object:
        """``run.json`` before issue 32: ``true`` (saved to ``map_dir``) or ``false``/null (not saved)."""
        if isinstance(value, bool):
            return info.data.get("map_dir", "map") if value else None
        return value

    @classmethod
    def from_health(
        cls, stats: dict[str, HealthStats], *, source: str, encoder: str, noise: str, semantic_every: int, wall_s: float,
        frames_requested: int | None = None, interrupted: bool = False, encoder_workers: int = 0,
        restarts: dict[str, int] | None = None, error: str | None = None, robot_sources: dict[str, str] | None = None,
        select: str = "coverage",
    ) -> RunSummary:
        """From the last health stats of the run's services. After an interrupt the bridge was
        stopped and its last stats can lag by a second of frames; playback loses no frame, so every
        frame geometry took (integrated or refused) was published, and that count is used when larger."""

        bridges = _bridges(stats)

        def c(service: str, name: str) -> float:
            if service == "bridge":  # every robot's bridge
                return sum(stats[b].counter(name) for b in bridges)
            s = stats.get(service)
            return s.counter(name) if s is not None else 0.0

        rec, sem = reconstruction_rates(
            frames_integrated=c("geometry", GeometryCounter.FRAMES_INTEGRATED),
            integrate_s=c("geometry", GeometryCounter.INTEGRATE_BUSY_S),
            semantic_frames=c("semantic", SemanticCounter.SEMANTIC_FRAMES),
            semantic_s=c("semantic", SemanticCounter.BUSY_S),
        )
        skipped: dict[str, int] = {}
        for b in bridges:
            for k, v in stats[b].counters.items():
                if k.startswith(SKIPPED_PREFIX):
                    skipped[k.removeprefix(SKIPPED_PREFIX)] = skipped.get(k.removeprefix(SKIPPED_PREFIX), 0) + int(v)
        published = int(c("bridge", BridgeCounter.FRAMES_PUBLISHED))
        read = int(c("bridge", BridgeCounter.FRAMES_READ))
        if interrupted:
            taken = int(c("geometry", GeometryCounter.FRAMES_INTEGRATED) + c("geometry", GeometryCounter.CAPACITY_REFUSED))
            read += max(0, taken - published)
            published = max(published, taken)
        return cls(
            mode="services", source=source, encoder=encoder, noise=noise, semantic_every=semantic_every,
            frames_read=read,
            frames_skipped=skipped,
            frames_published=published,
            frames_requested=frames_requested, frames_played=published, interrupted=interrupted,
            frames_integrated=int(c("geometry", GeometryCounter.FRAMES_INTEGRATED)),
            semantic_frames=int(c("semantic", SemanticCounter.SEMANTIC_FRAMES)),
            semantic_failed=int(c("semantic", SemanticCounter.FRAMES_FAILED)),
            regions=int(c("semantic", SemanticCounter.REGIONS)),
            rec_fps=_round(rec), sem_rec_fps=_round(sem), wall_s=round(wall_s, 1),
            encoder_workers=encoder_workers,
            encoder_frames_resent=int(c("semantic", PoolCounter.FRAMES_RESENT)),
            encoder_frames_lost=int(c("semantic", PoolCounter.FRAMES_LOST)),
            encoder_results_stale=int(c("semantic", PoolCounter.RESULTS_STALE)),
            frames_encoded_per_worker={k.removeprefix(ENCODED_BY_PREFIX): int(v) for k, v in
                                       (stats["semantic"].counters.items() if "semantic" in stats else [])
                                       if k.startswith(ENCODED_BY_PREFIX)},
            geometry_grid_mb=_round(c("geometry", GeometryCounter.RESIDENT_MB)),
            geometry_rss_peak_mb=_round(c("geometry", GeometryCounter.RSS_PEAK_MB)),
            geometry_rss_anon_peak_mb=_round(c("geometry", GeometryCounter.RSS_ANON_PEAK_MB)),
            semantic_rate_hz=_round(_rate(c("semantic", SemanticCounter.SEMANTIC_FRAMES),
                                          c("semantic", SemanticCounter.FIRST_FUSED_AT_S),
                                          c("semantic", SemanticCounter.LAST_FUSED_AT_S))),
            **_selection(select, c("semantic", SemanticCounter.ENCODER_CALLS),
                         c("semantic", SemanticCounter.ENCODER_REGIONS), c("semantic", SemanticCounter.REGIONS),
                         c("semantic", SemanticCounter.SKIPPED_NO_GAIN),
                         c("semantic", SemanticCounter.REGIONS_NOT_EMBEDDED), c("semantic", SemanticCounter.FRAMES_SCORED),
                         c("semantic", SemanticCounter.RENDERS_REUSED)),
            **_outcomes(stats.get("semantic")),
            restarts=dict(restarts or {}),
            frames_replayed=int(c("bridge", BridgeCounter.FRAMES_REPLAYED)),
            frames_duplicate=int(c("geometry", GeometryCounter.FRAMES_DUPLICATE)),
            error=error,
            robots=_robots(stats, robot_sources or {_DEFAULT_ROBOT: source}),
        )

    @classmethod
    def from_pipeline(
        cls, stats: PipelineStats, *, regions: int, source: str, encoder: str, noise: str, semantic_every: int,
        wall_s: float, frames_requested: int | None = None, frames_played: int | None = None, interrupted: bool = False,
    ) -> RunSummary:
        """From the in-process pipeline's stats (``frames_played``: the frames the loop took from
        the source; default: those integrated)."""
        return cls(
            mode="in-process", source=source, encoder=encoder, noise=noise, semantic_every=semantic_every,
            frames_read=stats.frames_read, frames_skipped=dict(stats.frames_skipped),
            frames_published=stats.frames_integrated, frames_integrated=stats.frames_integrated,
            semantic_frames=stats.semantic_frames, semantic_failed=stats.semantic_failed, regions=regions,
            rec_fps=_round(stats.rec_fps), sem_rec_fps=_round(stats.sem_rec_fps), wall_s=round(wall_s, 1),
            frames_requested=frames_requested,
            frames_played=stats.frames_integrated if frames_played is None else frames_played, interrupted=interrupted,
            **_selection(stats.select, stats.encoder_calls, stats.encoder_regions, regions, stats.skipped_no_gain,
                         stats.regions_not_embedded, stats.frames_scored, stats.renders_reused),
        )


def _outcomes(semantic: HealthStats | None) -> dict:
    """run.json's account of the semantic service's frames (services only)."""
    if semantic is None:
        return {}
    outcomes = semantic_frame_outcomes(semantic.counters)
    received = int(semantic.counter(SemanticCounter.FRAMES_RECEIVED))
    return {"semantic_frames_received": received, "semantic_outcomes": outcomes,
            "semantic_frames_pending": max(0, received - sum(outcomes.values()))}


def _selection(select: str, calls: float, regions_encoded: float, regions: float, skipped: float,
               not_embedded: float, scored: float, reused: float) -> dict:
    """run.json's frame-selection fields (the same from health counters and from pipeline stats)."""
    return {"select": select, "encoder_calls": int(calls), "encoder_regions": int(regions_encoded),
            "regions_not_embedded": int(not_embedded),
            "calls_per_region": _round(regions_encoded / regions) if regions else None,
            "skipped_no_gain": int(skipped), "frames_scored": int(scored), "renders_reused": int(reused)}
