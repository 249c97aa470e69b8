#!/usr/bin/env python3
"""End-to-end speed over Zenoh, each against a baseline measured in the same run.

1. 3D-Rec fps over the bus: a bridge process replays pre-rendered 640x480 synthetic frames (a
   recording, so rendering is not measured) as fast as it can to a geometry service process;
   frames/s from the first to the last integrated frame. Baseline: ``SemanticVolume.integrate``
   of the same frames in this process. Targets: >= 50 fps and ratio >= 0.8.
2. Sem-3D-Rec fps with the gt encoder: geometry + semantic services, the same frames played at
   the rate geometry sustains; 1 / (integration time per frame + semantic step time per semantic
   frame) from the services' own stats, and the semantic service's frames/s.
3. Text-query latency over Zenoh with MiniLM at 10,000 regions: a query service fed a 10,000-region
   dictionary snapshot; p50/p99 of ``OpenFusionClient.query_text`` (top 5, no points). Baseline:
   the same query in-process (MiniLM encode + top-k). Target p50 <= 20 ms.

    .venv/bin/python bench/bench_services.py --quick   # 40 frames, 50 queries
    .venv/bin/python bench/bench_services.py           # 150 frames, 200 queries
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np

os.environ.setdefault("HF_HUB_OFFLINE", "1")

from openfusion.bus import Queryable, collect_health, open_session  # noqa: E402
from openfusion.client import OpenFusionClient  # noqa: E402
from openfusion.config import ServiceConfig, ZenohSettings  # noqa: E402
from openfusion.embedded import Cluster, free_port, wait_for_services  # noqa: E402
from openfusion.encoders import make_text_encoder  # noqa: E402
from openfusion.mapping import RegionDictionary, SemanticVolume, VolumeParams  # noqa: E402
from openfusion.messages import DictionaryRequest  # noqa: E402
from openfusion.services.dictionary_sync import snapshot_message  # noqa: E402
from openfusion.sources.record import FrameRecorder  # noqa: E402
from openfusion.sources.synthetic import SyntheticSource, SyntheticWorld  # noqa: E402


class Bus:
    def __init__(self, tmp: Path, map_id: str) -> None:
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.router = open_session(ServiceConfig(map_id=map_id, zenoh=ZenohSettings(
            mode="router", listen=[self.endpoint], multicast_scouting=False)))
        self.cluster = Cluster(map_id, self.endpoint, tmp / f"logs-{map_id}")
        self.client = OpenFusionClient.from_config(ServiceConfig(map_id=map_id, zenoh=ZenohSettings(
            mode="client", connect=[self.endpoint], multicast_scouting=False)), timeout_s=30.0)

    def counter(self, service: str, name: str) -> float:
        s = collect_health(self.client.session, self.client.keys, timeout_s=1.0).get(service)
        return float(s.counters.get(name, 0.0)) if s else 0.0

    def close(self) -> None:
        self.cluster.stop()
        self.client.close()
        self.router.close()


def play_and_time(bus: Bus, recording: Path, n: int, rate_hz: float = 0.0) -> tuple[float, float]:
    """(seconds from the first to the last integrated frame, frames integrated) for ``n`` frames."""
    base = bus.counter("geometry", "frames_integrated")
    bus.cluster.start("bridge", ["--source", f"replay:{recording}", "--rate-hz", str(rate_hz)])
    t_first = None
    last_change, last_done = time.monotonic(), -1.0
    while True:
        done = bus.counter("geometry", "frames_integrated") - base
        now = time.monotonic()
        if done >= 1 and t_first is None:
            t_first = now
        if done != last_done:
            last_change, last_done = now, done
        if done >= n or now - last_change > 10.0:  # all frames, or a frame was lost on the way
            break
        time.sleep(0.02)
    bus.cluster.stop("bridge")
    bus.cluster.processes.pop("bridge")
    return now - (t_first or now), done


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="CI size")
    args = parser.parse_args()
    n_frames, n_queries = (40, 50) if args.quick else (150, 200)
    tmp = Path(tempfile.mkdtemp(prefix="bench-services-"))
    frames = list(SyntheticSource(SyntheticWorld(0), num_frames=n_frames, width_px=640, height_px=480))
    recording = tmp / "frames.ofrec"
    with FrameRecorder(recording) as rec:
        for f in frames:
            rec.write(f)

    def inproc_integrate_fps() -> float:
        vol = SemanticVolume(VolumeParams())
        t0 = time.perf_counter()
        for f in frames:
            vol.integrate(f)
        return n_frames / (time.perf_counter() - t0)

    # 1. in-process baseline, measured before and after the bus run (best of the two), so load
    # from other processes on a shared machine hits candidate and baseline alike.
    inproc_fps = inproc_integrate_fps()

    rows = []
    bus = Bus(tmp, "bench-geo")
    try:
        bus.cluster.start("geometry", ["--checkpoint-period-s", "0"])
        wait_for_services(bus.client, bus.cluster, {"geometry"}, 240)
        # The first frames of the replay (n - 1 intervals) measure steady throughput.
        dt, done = play_and_time(bus, recording, n_frames)
        bus_fps = (done - 1) / dt if dt > 0 else float("nan")
    finally:
        bus.close()
    inproc_fps = max(inproc_fps, inproc_integrate_fps())
    rows.append(("3D-Rec fps, 640x480, frames over Zenoh", f"{bus_fps:.1f}", "in-process integrate",
                 f"{inproc_fps:.1f}", f"{bus_fps / inproc_fps:.2f}", ">= 50 fps, >= 0.8"))

    # 2. Sem-3D-Rec with gt
    bus = Bus(tmp, "bench-sem")
    try:
        bus.cluster.start("geometry", ["--checkpoint-period-s", "0"])
        bus.cluster.start("semantic", ["--encoder", "gt"])
        wait_for_services(bus.client, bus.cluster, {"geometry", "semantic"}, 240)
        play_and_time(bus, recording, n_frames, rate_hz=10.0)
        time.sleep(2.0)
        integ = bus.counter("geometry", "frames_integrated")
        integ_s = bus.counter("geometry", "integrate_busy_s")
        sem = bus.counter("semantic", "semantic_frames")
        sem_s = bus.counter("semantic", "busy_s")
    finally:
        bus.close()
    sem_rec = 1.0 / (integ_s / integ + sem_s / sem) if sem and integ else float("nan")
    rows.append(("Sem-3D-Rec fps (gt encoder), 640x480", f"{sem_rec:.1f}", "3D-Rec (geometry only, same run)",
                 f"{integ / integ_s:.1f}", f"{sem_rec / (integ / integ_s):.2f}", "paper (GPU): 4.5"))
    rows.append(("semantic service frames/s (encode + render + match + update)", f"{sem / sem_s:.1f}", "", "", "", ""))

    # 3. text-query latency at 10,000 regions
    text = make_text_encoder("minilm")
    rng = np.random.default_rng(0)
    dictionary = RegionDictionary(text.embedding_space, text.dim)
    with dictionary.batch():
        for i in range(10_000):
            dictionary.add(rng.standard_normal(text.dim).astype(np.float32), label=f"region {i}")
    snapshot = snapshot_message(dictionary)
    queries = [f"object number {i}" for i in range(n_queries)]

    def inproc_query_ms() -> list[float]:
        out = []
        for q in queries:
            t = time.perf_counter()
            dictionary.top_k(text.encode([q])[0], 5)
            out.append((time.perf_counter() - t) * 1e3)
        return out

    text.encode(["warm up"])
    bus = Bus(tmp, "bench-query")
    session = open_session(ServiceConfig(map_id="bench-query", zenoh=ZenohSettings(
        mode="client", connect=[bus.endpoint], multicast_scouting=False)))
    try:
        fake_semantic = Queryable(session, bus.client.keys.semantic_dictionary, DictionaryRequest, lambda _r: snapshot)
        bus.cluster.start("geometry", ["--checkpoint-period-s", "0"])
        bus.cluster.start("query", [])
        wait_for_services(bus.client, bus.cluster, {"geometry", "query"}, 240)
        while bus.counter("query", "regions") < 10_000:
            time.sleep(0.2)
        bus.client.query_text("warm up")
        lat = []
        for q in queries:
            t = time.perf_counter()
            bus.client.query_text(q, top_k=5)
            lat.append((time.perf_counter() - t) * 1e3)
        fake_semantic.close()
    finally:
        session.close()
        bus.close()
    t_in = inproc_query_ms()  # after the services stopped: the same machine state as the bus run
    p50, p99 = np.percentile(lat, 50), np.percentile(lat, 99)
    b50 = np.percentile(t_in, 50)
    rows.append(("text query over Zenoh, 10,000 regions, p50 ms", f"{p50:.1f}", "in-process encode + top-k p50 ms",
                 f"{b50:.1f}", f"{p50 / b50:.2f}", "<= 20 ms"))
    rows.append(("text query over Zenoh, 10,000 regions, p99 ms", f"{p99:.1f}", "", "", "", ""))

    print(f"\n## Services over Zenoh ({n_frames} frames 640x480, {n_queries} queries; {os.cpu_count()} CPUs)\n")
    print("| measurement | value | baseline (same run) | baseline value | ratio | target |")
    print("|---|---:|---|---:|---:|---|")
    for r in rows:
        print("| " + " | ".join(r) + " |")


if __name__ == "__main__":
    main()
