#!/usr/bin/env python3
"""Many clients at once against one and two query services (issue 30), loopback only.

A Zenoh router in this process; stand-ins for the semantic service (a 10,000-region MiniLM-space
dictionary snapshot) and geometry (region summaries of those 10,000 regions: boxes in a 20 m
room); query services as processes (``openfusion service query``, ``--instance 2`` for the
second). ``--clients`` concurrent clients (default 32), each its own Zenoh session, spread over
``--client-processes`` processes (default 4, so the clients' own Python does not serialise on
one GIL), each sending text queries (top 5, relevancy and nearby regions in every hit) one after
the other for ``--seconds`` (bounded: at most ``--max-requests`` each), the texts drawn from a
pool of ``--texts`` (default 100: a fleet asks the same few things again and again, so answers
come from the caches; ``--texts 1000000``: every text new, each costs an encoder call).

Each client asks as :class:`~openfusion.client.OpenFusionClient` does: the live query services
in turn by name (:mod:`openfusion.bus.instances`), the shared key when the one picked is gone;
with two services also a row with the shared key only (Zenoh's BEST_MATCHING picks one). Every
request is sent with :func:`openfusion.bus.get_all`, which waits for EVERY reply of the query:
0 replies = lost, 2 or more = duplicated (both must be 0), error replies counted apart.
Printed: a row per number of query services with replies/s, p50/p99 latency, lost, duplicated,
errors, the share each service answered (its ``queries`` counter), and replies/s against the
one-service row of the same run; with two services the shared-key-only and the spread rows are
taken in turn (``--rounds``) and their medians compared (the same processes: only where the
requests go differs).

    scripts/dev.sh exec python bench/bench_query_load.py --quick   # 3 s per row
    scripts/dev.sh exec python bench/bench_query_load.py           # 10 s per row
    scripts/dev.sh exec python bench/bench_query_load.py --quick --texts 1000000
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from openfusion.app.launcher import Cluster, wait_for_services
from openfusion.bus import Queryable, QueryError, collect_health, get_all, open_session
from openfusion.bus import free_loopback_port as free_port
from openfusion.bus.instances import InstancePicker
from openfusion.bus.query import RETRY_UNANSWERED_S
from openfusion.client import OpenFusionClient
from openfusion.config import ServiceConfig, ZenohSettings
from openfusion.mapping import RegionDictionary
from openfusion.wire.endpoints import GEOMETRY_REGIONS, QUERY_TEXT, SEMANTIC_DICTIONARY, is_query_service
from openfusion.wire.schemas import (
    DictionaryRequest,
    QueryReply,
    RegionSummaryReply,
    RegionSummaryRequest,
    TextQuery,
)

MAP_ID = "bench-query-load"
N_REGIONS = 10_000
MINILM_SPACE, MINILM_DIM = "minilm-l6-v2", 384


def _client_config(endpoint: str) -> ServiceConfig:
    return ServiceConfig(map_id=MAP_ID, zenoh=ZenohSettings(mode="client", connect=[endpoint],
                                                            multicast_scouting=False))


def _client_process(endpoint: str, n_clients: int, first_id: int, seconds: float, max_requests: int,
                    n_texts: int, start_at: float, spread: bool, out: mp.Queue) -> None:
    """``n_clients`` client threads, each with its own session; puts (latencies ms, replies per
    request, errors) on ``out``."""
    config = _client_config(endpoint)
    key = QUERY_TEXT.key(config.keys)
    sessions = [open_session(config) for _ in range(n_clients)]
    pickers = [InstancePicker(s, config.keys, is_query_service) if spread else None for s in sessions]
    lat: list[float] = []
    counts: list[int] = []
    errors: list[str] = []
    lock = threading.Lock()

    def one(i: int) -> None:
        rng = np.random.default_rng(first_id + i)
        mine_lat, mine_counts, mine_err = [], [], []
        time.sleep(max(0.0, start_at - time.time()))
        stop_at = time.monotonic() + seconds
        n = 0
        while time.monotonic() < stop_at and n < max_requests:
            text = f"object number {int(rng.integers(n_texts))}"
            request = TextQuery(text=text, top_k=5)
            t = time.perf_counter()
            # as OpenFusionClient asks: a live query service by name in turn, the shared key when it is gone
            name = pickers[i].pick() if pickers[i] is not None else None
            got = [] if name is None else get_all(sessions[i], QUERY_TEXT.instance_key(config.keys, name), request,
                                                  QueryReply, timeout_s=20.0)
            if name is not None and not got:
                pickers[i].forget(name)  # type: ignore[union-attr]
            if not got:
                got = get_all(sessions[i], key, request, QueryReply, timeout_s=20.0,
                              retry_unanswered_s=RETRY_UNANSWERED_S)
            mine_lat.append((time.perf_counter() - t) * 1e3)
            ok = [r for r in got if isinstance(r, QueryReply)]
            mine_counts.append(len(ok))
            mine_err += [str(r) for r in got if isinstance(r, QueryError)]
            n += 1
        with lock:
            lat.extend(mine_lat)
            counts.extend(mine_counts)
            errors.extend(mine_err)

    threads = [threading.Thread(target=one, args=(i,)) for i in range(n_clients)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for s in sessions:
        s.close()
    out.put((lat, counts, errors))


def _summaries(rng: np.random.Generator) -> RegionSummaryReply:
    lo = rng.uniform(0, 20, (N_REGIONS, 3)).astype(np.float32)
    hi = (lo + rng.uniform(0.05, 0.8, (N_REGIONS, 3))).astype(np.float32)
    return RegionSummaryReply(map_version=1, key_horizon=N_REGIONS, age_s=0.0,
                              keys=np.arange(N_REGIONS, dtype=np.int32), bbox_min=lo, bbox_max=hi,
                              num_points=np.full(N_REGIONS, 200, np.int64), centroid=(lo + hi) / 2)


def load(endpoint: str, args: argparse.Namespace, *, spread: bool) -> dict:
    """One phase: every client process started, all clients begin together; merged results."""
    ctx = mp.get_context("spawn")
    out: mp.Queue = ctx.Queue()
    per = [args.clients // args.client_processes + (1 if i < args.clients % args.client_processes else 0)
           for i in range(args.client_processes)]
    start_at = time.time() + 4.0  # every process has opened its sessions by then
    procs = []
    first = 0
    for n in per:
        p = ctx.Process(target=_client_process, args=(endpoint, n, first, args.seconds, args.max_requests, args.texts,
                                                      start_at, spread, out))
        p.start()
        procs.append(p)
        first += n
    lat: list[float] = []
    counts: list[int] = []
    errors: list[str] = []
    for _ in procs:
        a, b, c = out.get(timeout=args.seconds + 120)
        lat += a
        counts += b
        errors += c
    for p in procs:
        p.join(30)
    counts_arr = np.asarray(counts)
    return {
        "requests": len(counts),
        "replies_per_s": int((counts_arr == 1).sum()) / args.seconds,
        "p50": float(np.percentile(lat, 50)) if lat else float("nan"),
        "p99": float(np.percentile(lat, 99)) if lat else float("nan"),
        "lost": int((counts_arr == 0).sum()),
        "duplicated": int((counts_arr > 1).sum()),
        "errors": len(errors),
        "first_error": errors[0] if errors else "",
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="3 s per phase (CI size)")
    parser.add_argument("--full", action="store_true", help="the default size (bench/run_all.py --full passes it)")
    parser.add_argument("--clients", type=int, default=32)
    parser.add_argument("--client-processes", type=int, default=4)
    parser.add_argument("--seconds", type=float, default=None, help="per phase (default 10, --quick 3)")
    parser.add_argument("--max-requests", type=int, default=2_000, help="most requests per client per phase")
    parser.add_argument("--rounds", type=int, default=2, help="shared-key and spread rows taken in turn")
    parser.add_argument("--texts", type=int, default=100, help="distinct query texts the clients draw from")
    args = parser.parse_args()
    args.seconds = args.seconds or (3.0 if args.quick else 10.0)
    if not 1 <= args.clients <= 256 or not 1 <= args.client_processes <= args.clients:
        parser.error("--clients must be 1..256 and --client-processes 1..clients")
    warm_texts = [f"object number {i}" for i in range(min(args.texts, 100))]
    rng = np.random.default_rng(0)
    dictionary = RegionDictionary(MINILM_SPACE, MINILM_DIM)
    with dictionary.batch():
        for i in range(N_REGIONS):
            dictionary.add(rng.standard_normal(MINILM_DIM).astype(np.float32), label=f"region {i}")
    snapshot, summaries = dictionary.snapshot(), _summaries(rng)

    tmp = Path(tempfile.mkdtemp(prefix="bench-query-load-"))
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(ServiceConfig(map_id=MAP_ID, zenoh=ZenohSettings(mode="router", listen=[endpoint],
                                                                           multicast_scouting=False)))
    stand_in = open_session(_client_config(endpoint))
    keys = _client_config(endpoint).keys
    qbls = [Queryable(stand_in, SEMANTIC_DICTIONARY.key(keys), DictionaryRequest, lambda _r: snapshot),
            Queryable(stand_in, GEOMETRY_REGIONS.key(keys), RegionSummaryRequest, lambda _r: summaries)]
    client = OpenFusionClient.from_config(_client_config(endpoint), timeout_s=30.0)
    cluster = Cluster(MAP_ID, endpoint, tmp / "logs")
    load_before = os.getloadavg()[0]
    results = []
    names: list[str] = []

    def served() -> dict[str, float]:
        health = collect_health(client.session, client.keys, timeout_s=1.0)
        return {n: float(health[n].counters.get("queries", 0.0)) if n in health else float("nan") for n in names}

    try:
        for n_services in (1, 2):
            name = "query" if n_services == 1 else f"query-{n_services}"
            cluster.start(name, [] if n_services == 1 else ["--instance", str(n_services)], service="query")
            names.append(name)
            wait_for_services(client, cluster, set(names), 240)


            deadline = time.monotonic() + 120
            while any(v < N_REGIONS for v in (float(collect_health(client.session, client.keys, timeout_s=1.0)
                                                    .get(n).counters.get("regions", 0.0)) for n in names)):
                if time.monotonic() > deadline:
                    raise RuntimeError("the query services did not load the dictionary")
                time.sleep(0.2)
            for text in warm_texts:  # warm: every service's first queries are not what is measured
                client.query_text(text, top_k=5)
            # two services: the shared key only (one of them answers) and spread over both, taken in
            # turn for --rounds rounds, so a shared machine's drift hits both alike
            modes = [True] if n_services == 1 else [False, True] * args.rounds
            for spread in modes:
                before = served()
                result = load(endpoint, args, spread=spread)
                time.sleep(1.5)  # one health period: the counters include the last requests
                after = served()
                result["services"] = n_services
                result["spread"] = spread
                result["how"] = ("one service" if n_services == 1 else "each client asks them in turn" if spread
                                 else "shared key only (Zenoh BEST_MATCHING: one answers)")
                result["share"] = {n: after[n] - before[n] for n in names}
                results.append(result)
    finally:
        client.close()
        cluster.stop()
        for q in qbls:
            q.close()
        stand_in.close()
        router.close()

    base = results[0]["replies_per_s"]  # the first one-service row
    print(f"\n## Query services under load ({args.clients} clients in {args.client_processes} processes, "
          f"{args.seconds:g} s per row, {args.texts} texts, {N_REGIONS:,} regions, top 5 with relevancy and "
          f"nearby regions; {os.cpu_count()} CPUs; load average {load_before:.2f} at start, "
          f"{os.getloadavg()[0]:.2f} at end)\n")
    print("| query services | how requests are sent | requests | replies/s | ratio vs 1 service | p50 ms | p99 ms | lost | duplicated "
          "| errors | answered by |")
    print("|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---|")
    for r in results:
        share = ", ".join(f"{n} {int(v)}" for n, v in r["share"].items())
        print(f"| {r['services']} | {r['how']} | {r['requests']} | {r['replies_per_s']:.0f} | {r['replies_per_s'] / base:.2f} "
              f"| {r['p50']:.1f} | {r['p99']:.1f} | {r['lost']} | {r['duplicated']} | {r['errors']} | {share} |")
    two = [r for r in results if r["services"] == 2]
    spread = np.median([r["replies_per_s"] for r in two if r["spread"]])
    shared = np.median([r["replies_per_s"] for r in two if not r["spread"]])
    print(f"\nTwo services, spread over both ÷ shared key only (one answers), medians of {args.rounds} rounds: "
          f"{spread / shared:.2f} ({spread:.0f} / {shared:.0f} replies/s); lost {sum(r['lost'] for r in results)}, "
          f"duplicated {sum(r['duplicated'] for r in results)}, errors {sum(r['errors'] for r in results)} in all rows.")
    for r in results:
        if r["first_error"]:
            print(f"\nfirst error with {r['services']} service(s): {r['first_error']}")


if __name__ == "__main__":
    main()
