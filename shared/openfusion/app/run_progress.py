"""Following a run with services until it is done: the progress bar from the services' health, the
bridges stopped after a first stop signal, dead services restarted, and the wait until geometry
has taken every published frame and geometry and semantic have settled (:func:`follow_progress`).
A restarted service counts from 0: its earlier process's counts are carried over
(:func:`carry_over`, :func:`with_carried`), so the progress line and ``run.json`` count the same."""

from __future__ import annotations

import argparse
import logging
import sys
import time
from typing import Any

from openfusion.app.launcher import Cluster, RunError, StopSignals
from openfusion.app.shard_run import combined_geometry
from openfusion.bus import collect_health
from openfusion.progress import progress_bar
from openfusion.wire.counters import BridgeCounter, CommonCounter, GeometryCounter, SemanticCounter

logger = logging.getLogger(__name__)

#: geometry and semantic have settled when their counters did not change for this long.
SETTLE_S = 2.0
#: Counters of a service that add up over its restarts in run.json (a restarted process counts from 0).
CARRIED_COUNTERS: dict[str, tuple[str, ...]] = {
    "semantic": (SemanticCounter.SEMANTIC_FRAMES, SemanticCounter.BUSY_S, SemanticCounter.FRAMES_FAILED),
}


def _counter(stats: dict[str, Any], service: str, name: str) -> float:
    s = stats.get(service)
    return s.counter(name) if s is not None else 0.0


def carry_over(stats: dict[str, Any], fresh: dict[str, Any], carried: dict[str, dict[str, float]]) -> None:
    """Before ``fresh`` stats replace ``stats``: a service whose ``restarts`` went up leaves its
    last counts of :data:`CARRIED_COUNTERS` in ``carried`` (geometry restores its own from its
    checkpoint)."""
    for name, counters in CARRIED_COUNTERS.items():
        old, new = stats.get(name), fresh.get(name)
        if old is None or new is None or new.counter(CommonCounter.RESTARTS) <= old.counter(CommonCounter.RESTARTS):
            continue
        into = carried.setdefault(name, {})
        for counter in counters:
            into[counter] = into.get(counter, 0.0) + old.counter(counter)


def refresh_stats(client: Any, stats: dict[str, Any], carried: dict[str, dict[str, float]]) -> None:
    """One more health poll into ``stats`` (a service that does not answer keeps its last stats)."""
    import zenoh

    try:
        fresh = collect_health(client.session, client.keys, timeout_s=1.0)
    except zenoh.ZError as exc:
        logger.warning("could not ask the services for their last stats: %s", exc)
        return
    carry_over(stats, fresh, carried)
    stats.update(fresh)
    stats.update(combined_geometry(stats))  # geometry shards: one view of them (app/shard_run.py)


def progress_counts(stats: dict[str, Any]) -> dict[str, int]:
    """The progress line's semantic counts, from the stats run.json is made of (with the counts of
    earlier processes of a restarted service added: :func:`with_carried`), so the line ends on
    the ``semantic_frames`` that run.json says."""
    return {"semantic": int(_counter(stats, "semantic", SemanticCounter.SEMANTIC_FRAMES)),
            "regions": int(_counter(stats, "semantic", SemanticCounter.REGIONS))}


def with_carried(stats: dict[str, Any], carried: dict[str, dict[str, float]]) -> dict[str, Any]:
    """``stats`` with the counts of earlier processes of a restarted service added."""
    out = dict(stats)
    for name, extra in carried.items():
        if name in out:
            counters = dict(out[name].counters)
            for counter, value in extra.items():
                counters[counter] = counters.get(counter, 0.0) + value
            out[name] = out[name].model_copy(update={"counters": counters})
    return out


def _current(stats: dict[str, Any], cluster: Cluster) -> bool:
    """Every service is running and the stats held for it come from its current process (its
    ``restarts`` counter matches the launcher's count): a dead or restarted service's last stats
    must not make the run look finished."""
    if cluster.restarting:
        return False
    for name, sp in cluster.processes.items():
        if sp.stopped:
            continue
        s = stats.get(name)
        if not sp.alive() or s is None or int(s.counter(CommonCounter.RESTARTS)) != sp.restarts:
            return False
    return True


def follow_progress(args: argparse.Namespace, client: Any, cluster: Cluster,
                     signals: StopSignals | None = None, stats: dict[str, Any] | None = None,
                     carried: dict[str, dict[str, float]] | None = None) -> dict[str, Any]:
    """Show progress until geometry has taken every frame the bridge published and geometry and
    semantic have settled (no counter changed for :data:`SETTLE_S`); the last stats of each service
    (also kept in ``stats``, so a caller has them when this raises).

    Services that die are restarted (:meth:`Cluster.check_alive` with the run's restart policy);
    the run is not finished while one is down or its stats are from before its restart.
    After a stop signal (``signals.requested``) the bridge is stopped (no more frames) and the same
    wait lets geometry and semantic finish the frames they already have; the bridge's last stats
    are kept."""
    bar = progress_bar(args.frames, "frames integrated", disable=args.quiet)
    try:
        stable_since: float | None = None
        last_key: tuple[float, ...] = ()
        stats = {} if stats is None else stats
        playback_stopped = False
        deadline = time.monotonic() + args.timeout_s
        while True:
            if signals is not None and signals.requested and not playback_stopped:
                if not args.quiet:
                    bar.write(f"{signals.requested}: stopping playback; finishing the frames in flight, then saving the "
                              "map (press Ctrl-C again to abort)", file=sys.stderr)
                for name in bridge_names(cluster):
                    cluster.stop(name)
                playback_stopped = True
                stable_since = None
            cluster.check_alive()
            fresh = collect_health(client.session, client.keys, timeout_s=1.0)
            carried = {} if carried is None else carried
            carry_over(stats, fresh, carried)
            stats.update(fresh)
            stats.update(combined_geometry(stats))  # geometry shards: one view of them (app/shard_run.py)
            integrated = _counter(stats, "geometry", GeometryCounter.FRAMES_INTEGRATED)
            refused = (_counter(stats, "geometry", GeometryCounter.CAPACITY_REFUSED)
                       + _counter(stats, "geometry", GeometryCounter.FRAMES_FAILED))
            bar.n = int(integrated)
            bar.set_postfix(**progress_counts(with_carried(stats, carried)))
            bar.refresh()
            bridges = bridge_names(cluster)
            done = playback_stopped or all(_counter(stats, b, BridgeCounter.PLAYBACK_DONE) >= 1 for b in bridges)
            published = sum(_counter(stats, b, BridgeCounter.FRAMES_PUBLISHED) for b in bridges)
            # Frames of robots not joined yet wait in their submaps: taken, not integrated (yet).
            refused += _held_now(stats)
            key = (integrated, refused, _counter(stats, "semantic", SemanticCounter.SEMANTIC_FRAMES),
                   _counter(stats, "geometry", GeometryCounter.UPDATES_APPLIED), *cluster.restarts.values())
            if done and _joins_pending(stats):  # a held robot may still join: its frames would go in
                stable_since = None
            elif done and integrated + refused >= published and _current(stats, cluster):
                if key == last_key and stable_since is not None and time.monotonic() - stable_since > SETTLE_S:
                    break
                if key != last_key or stable_since is None:
                    stable_since = time.monotonic()
            last_key = key
            if time.monotonic() > deadline:
                raise RunError(f"the run did not finish within {args.timeout_s:.0f} s "
                               f"(integrated {integrated:.0f} of {published:.0f} published frames)")
            time.sleep(0.5)
    finally:  # the bar ends its line whatever ends the wait (an error, a second Ctrl-C)
        bar.close()
    return stats


def bridge_names(cluster: Cluster) -> list[str]:
    """The run's bridges (one per robot: ``bridge``, ``bridge-ROBOT``)."""
    return [name for name in cluster.processes if name == "bridge" or name.startswith("bridge-")] or ["bridge"]


def _held_now(stats: dict[str, Any]) -> float:
    """Frames of held robots waiting in geometry's holds now (taken, not in the map yet)."""
    geometry = stats.get("geometry")
    return float(sum(r.frames_held for r in geometry.robots.values())) if geometry is not None else 0.0


def _joins_pending(stats: dict[str, Any]) -> bool:
    """A held robot's registration runs or is due in geometry."""
    geometry = stats.get("geometry")
    return geometry is not None and any(r.join_pending for r in geometry.robots.values())
