"""Codec and bus throughput for 640x480 RGB-D frames (uint8 color + uint16 depth), each against a
baseline measured in the same run.

1. In process: ``codec.encode`` / ``codec.decode`` of an :class:`RgbdFrame` vs a plain bytes
   copy of the same arrays (one ``b"".join`` of both arrays' buffers; ``np.frombuffer`` back).
2. Between two processes over Zenoh on loopback (publisher process -> subscriber process,
   congestion control BLOCK): frames/s of full frames through the bus helpers
   (``Publisher.put`` = encode + put; ``Subscriber`` = queue + decode + validation) vs the same
   bytes sent raw (concatenated array bytes, ``np.frombuffer`` on arrival).

Targets: >= 200 frames/s through the bus and >= 0.5x the raw throughput.

    .venv/bin/python bench/bench_codec.py           # ~1 minute
    .venv/bin/python bench/bench_codec.py --quick   # CI-sized, ~20 s
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import statistics
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

HEIGHT, WIDTH = 480, 640
TARGET_FPS = 200.0
TARGET_RATIO = 0.5


def make_frame_message(seed: int = 0) -> Any:
    from openfusion.wire.schemas import RgbdFrame

    rng = np.random.default_rng(seed)
    return RgbdFrame(
        frame_id=0,
        stamp_ns=0,
        width_px=WIDTH,
        height_px=HEIGHT,
        fx=525.0,
        fy=525.0,
        cx=319.5,
        cy=239.5,
        T_world_cam=np.eye(4),
        depth_scale=1000.0,
        color=rng.integers(0, 256, (HEIGHT, WIDTH, 3), dtype=np.uint8),
        depth=rng.integers(0, 6000, (HEIGHT, WIDTH), dtype=np.uint16),
        source="bench",
    )


def _median_ms(fn: Callable[[], Any], iterations: int) -> float:
    fn()  # warm up
    times = []
    for _ in range(iterations):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times) * 1000.0


def bench_in_process(iterations: int) -> list[dict[str, Any]]:
    from openfusion.wire.codec import decode, encode
    from openfusion.wire.schemas import RgbdFrame

    msg = make_frame_message()
    color, depth = msg.color, msg.depth
    raw_bytes = color.nbytes + depth.nbytes
    data = encode(msg)
    raw = b"".join((color.data, depth.data))

    def raw_pack() -> bytes:
        return b"".join((color.data, depth.data))

    def raw_unpack() -> tuple[np.ndarray, np.ndarray]:
        c = np.frombuffer(raw, np.uint8, color.size).reshape(color.shape)
        d = np.frombuffer(raw, np.uint16, depth.size, offset=color.nbytes).reshape(depth.shape)
        return c, d

    rows = []
    base_pack = _median_ms(raw_pack, iterations)
    base_unpack = _median_ms(raw_unpack, iterations)
    enc = _median_ms(lambda: encode(msg), iterations)
    dec = _median_ms(lambda: decode(data, expected=RgbdFrame), iterations)
    for name, ms, base in (
        ("bytes copy: join of both arrays (baseline)", base_pack, base_pack),
        ("codec.encode(RgbdFrame)", enc, base_pack),
        ("bytes view: frombuffer (baseline)", base_unpack, base_unpack),
        ("codec.decode(RgbdFrame)", dec, base_unpack),
        ("round trip, baseline", base_pack + base_unpack, base_pack + base_unpack),
        ("round trip, codec", enc + dec, base_pack + base_unpack),
    ):
        rows.append({"operation": name, "ms": ms, "MB_s": raw_bytes / 1e6 / (ms / 1000.0), "x_baseline": ms / base})
    rows.append({"operation": f"payload bytes: codec {len(data)} vs raw {len(raw)}", "ms": float("nan"),
                 "MB_s": float("nan"), "x_baseline": len(data) / len(raw)})
    return rows


# --------------------------------------------------------------------------------- two processes


def _config(port: int, *, listen: bool) -> Any:
    from openfusion.config import ServiceConfig

    ep = f"tcp/127.0.0.1:{port}"
    return ServiceConfig.model_validate(
        {"map_id": "bench", "zenoh": {"mode": "peer", "multicast_scouting": False,
                                      ("listen" if listen else "connect"): [ep]}}
    )


def _mark_cpu(cpu_at: list[float]) -> None:
    if len(cpu_at) < 2:
        cpu_at.append(time.process_time())
    else:
        cpu_at[1] = time.process_time()


def run_subscriber(mode: str, port: int, timeout_s: float) -> dict[str, Any]:
    """Receive frames until the publisher's end marker; report processed frames/s."""
    import zenoh

    from openfusion.bus import Subscriber, open_session
    from openfusion.wire.schemas import RgbdFrame

    session = open_session(_config(port, listen=True))
    key = "openfusion/bench/sensor/rgbd"
    done_at: list[float] = []
    cpu_at: list[float] = []  # process CPU time at the first and latest processed frame
    ended = threading.Event()
    published: list[int] = []
    end_sub = session.declare_subscriber(
        "openfusion/bench/end", zenoh.handlers.Callback(lambda s: (published.append(int(s.payload.to_string())), ended.set()))
    )
    color_n, depth_n = HEIGHT * WIDTH * 3, HEIGHT * WIDTH
    drops = 0
    if mode == "codec":

        def on_frame(msg: RgbdFrame) -> None:
            assert msg.depth.shape == (HEIGHT, WIDTH)
            done_at.append(time.perf_counter())
            _mark_cpu(cpu_at)

        sub = Subscriber(session, key, RgbdFrame, on_frame, queue_size=8)
    else:
        queue: collections.deque[Any] = collections.deque()
        cond = threading.Condition()
        raw_drops = [0]

        def on_sample(sample: Any) -> None:
            payload = sample.payload
            with cond:
                if len(queue) >= 8:
                    queue.popleft()
                    raw_drops[0] += 1
                queue.append(payload)
                cond.notify()

        def worker() -> None:
            while True:
                with cond:
                    while not queue:
                        cond.wait(0.2)
                        if ended.is_set() and not queue:
                            return
                    payload = queue.popleft()
                buf = payload.to_bytes()
                np.frombuffer(buf, np.uint8, color_n).reshape(HEIGHT, WIDTH, 3)
                d = np.frombuffer(buf, np.uint16, depth_n, offset=color_n).reshape(HEIGHT, WIDTH)
                assert d.shape == (HEIGHT, WIDTH)
                done_at.append(time.perf_counter())
                _mark_cpu(cpu_at)

        sub = session.declare_subscriber(key, zenoh.handlers.Callback(on_sample))
        thread = threading.Thread(target=worker, daemon=True)
        thread.start()
    print("ready", flush=True)
    ended.wait(timeout_s)
    time.sleep(0.5)  # let the worker drain what is queued
    if mode == "codec":
        drops = sub.drops
        sub.close()
    else:
        drops = raw_drops[0]
        sub.undeclare()
    end_sub.undeclare()
    session.close()
    n = len(done_at)
    fps = (n - 1) / (done_at[-1] - done_at[0]) if n > 1 and done_at[-1] > done_at[0] else 0.0
    cpu_ms = (cpu_at[-1] - cpu_at[0]) * 1000.0 / (n - 1) if n > 1 else float("nan")
    return {"mode": mode, "received": n, "drops": drops, "published": published[0] if published else -1, "fps": fps,
            "sub_cpu_ms": cpu_ms}


def run_publisher(mode: str, port: int, duration_s: float) -> dict[str, Any]:
    """Publish frames as fast as the bus takes them (congestion control BLOCK) for ``duration_s``."""
    import zenoh

    from openfusion.bus import Publisher, open_session

    session = open_session(_config(port, listen=False))
    key = "openfusion/bench/sensor/rgbd"
    msg = make_frame_message()
    if mode == "codec":
        pub = Publisher(session, key, congestion_control=zenoh.CongestionControl.BLOCK)
        wait = pub.wait_for_subscribers

        def send(i: int) -> None:
            msg.frame_id = i
            pub.put(msg)
    else:
        raw_pub = session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)

        def wait(timeout_s: float) -> bool:
            deadline = time.monotonic() + timeout_s
            while not bool(getattr(raw_pub.matching_status, "matching", raw_pub.matching_status)):
                if time.monotonic() > deadline:
                    return False
                time.sleep(0.01)
            return True

        def send(i: int) -> None:
            raw_pub.put(b"".join((msg.color.data, msg.depth.data)))

    if not wait(20.0):
        raise SystemExit("the subscriber process never matched")
    n = 0
    t0 = time.perf_counter()
    cpu0 = time.process_time()
    while time.perf_counter() - t0 < duration_s:
        send(n)
        n += 1
    elapsed = time.perf_counter() - t0
    cpu_ms = (time.process_time() - cpu0) * 1000.0 / max(n, 1)
    time.sleep(0.3)
    session.put("openfusion/bench/end", str(n))
    time.sleep(0.3)
    session.close()
    return {"mode": mode, "published": n, "fps": n / elapsed, "pub_cpu_ms": cpu_ms}


def bench_two_processes(mode: str, duration_s: float) -> dict[str, Any]:
    from openfusion.bus import free_loopback_port

    port = free_loopback_port()
    me = os.path.abspath(__file__)
    sub = subprocess.Popen(
        [sys.executable, me, "--role", "sub", "--mode", mode, "--port", str(port), "--duration", str(duration_s)],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert sub.stdout is not None
        line = sub.stdout.readline().strip()
        if line != "ready":
            raise SystemExit(f"subscriber process failed to start: {line!r}")
        pub = subprocess.run(
            [sys.executable, me, "--role", "pub", "--mode", mode, "--port", str(port), "--duration", str(duration_s)],
            capture_output=True,
            text=True,
            timeout=duration_s + 60,
        )
        if pub.returncode != 0:
            raise SystemExit(f"publisher process failed:\n{pub.stderr}")
        out, _ = sub.communicate(timeout=duration_s + 60)
    finally:
        if sub.poll() is None:
            sub.kill()
            sub.wait()
    result = json.loads(out.strip().splitlines()[-1])
    pub_result = json.loads(pub.stdout.strip().splitlines()[-1])
    result["pub_fps"] = pub_result["fps"]
    result["pub_cpu_ms"] = pub_result["pub_cpu_ms"]
    return result


# -------------------------------------------------------------------------------------- report


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    size = parser.add_mutually_exclusive_group()
    size.add_argument("--quick", action="store_true", help="CI-sized run")
    size.add_argument("--full", action="store_true", help="full-size run (the default)")
    parser.add_argument("--role", choices=["main", "pub", "sub"], default="main", help=argparse.SUPPRESS)
    parser.add_argument("--mode", choices=["codec", "raw"], default="codec", help=argparse.SUPPRESS)
    parser.add_argument("--port", type=int, default=0, help=argparse.SUPPRESS)
    parser.add_argument("--duration", type=float, default=0.0, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.role == "sub":
        print(json.dumps(run_subscriber(args.mode, args.port, timeout_s=args.duration + 60)), flush=True)
        return {}
    if args.role == "pub":
        print(json.dumps(run_publisher(args.mode, args.port, args.duration)), flush=True)
        return {}

    iterations = 30 if args.quick else 200
    duration_s = 1.5 if args.quick else 4.0
    rounds = 3 if args.quick else 5
    rows = bench_in_process(iterations)
    print(f"## Codec, one 640x480 RGB-D frame (uint8 color + uint16 depth), median of {iterations}\n")
    print("| operation | ms / frame | MB/s | x baseline |")
    print("|---|---:|---:|---:|")
    for r in rows:
        ms = "" if np.isnan(r["ms"]) else f"{r['ms']:.3f}"
        mbs = "" if np.isnan(r["MB_s"]) else f"{r['MB_s']:.0f}"
        print(f"| {r['operation']} | {ms} | {mbs} | {r['x_baseline']:.2f} |")

    # Rounds alternate raw / codec so that load from other processes hits both paths alike;
    # each path is reported by its median round.
    runs: dict[str, list[dict[str, Any]]] = {"raw": [], "codec": []}
    for _ in range(rounds):
        for mode in ("raw", "codec"):
            runs[mode].append(bench_two_processes(mode, duration_s))
    raw = sorted(runs["raw"], key=lambda r: r["fps"])[len(runs["raw"]) // 2]
    codec = sorted(runs["codec"], key=lambda r: r["fps"])[len(runs["codec"]) // 2]
    frame_mb = (HEIGHT * WIDTH * 5) / 1e6
    ratio = codec["fps"] / raw["fps"] if raw["fps"] > 0 else float("nan")
    print(
        f"\n## Two processes over Zenoh on loopback (publisher -> subscriber), median of {rounds} alternating "
        f"rounds of {duration_s:g} s\n"
    )
    print(
        "| path | frames/s received | MB/s | frames published | dropped at subscriber "
        "| CPU ms/frame publisher | CPU ms/frame subscriber | x raw |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for name, r in (("raw bytes (baseline)", raw), ("bus + codec (RgbdFrame)", codec)):
        print(
            f"| {name} | {r['fps']:.0f} | {r['fps'] * frame_mb:.0f} | {r['published']} | {r['drops']} | "
            f"{r['pub_cpu_ms']:.2f} | {r['sub_cpu_ms']:.2f} | "
            f"{r['fps'] / raw['fps'] if raw['fps'] else float('nan'):.2f} |"
        )
    per_round = ", ".join(f"{c['fps'] / r['fps']:.2f}" for r, c in zip(runs["raw"], runs["codec"], strict=True))
    print(f"\nPer-round ratios codec/raw: {per_round}. CPU ms/frame: process CPU time (all threads) per frame while streaming.")
    ok_fps = codec["fps"] >= TARGET_FPS
    ok_ratio = ratio >= TARGET_RATIO
    print(
        f"\nTargets: >= {TARGET_FPS:.0f} frames/s: {'PASS' if ok_fps else 'FAIL'} ({codec['fps']:.0f}); "
        f">= {TARGET_RATIO}x raw: {'PASS' if ok_ratio else 'FAIL'} ({ratio:.2f}x)"
    )
    return {"in_process": rows, "raw": raw, "codec": codec, "ratio": ratio}


if __name__ == "__main__":
    main()
