#!/usr/bin/env python3
"""Bridge publish rate: the real bridge service process playing a ScanNet-layout dataset as fast
as it can, frames/s received by a subscriber over Zenoh on loopback, next to plain decoding of the
same files with Pillow (color JPEG + depth PNG) and to the ScanNet reader alone, in the same run.

    .venv/bin/python bench/bench_bridge.py --quick   # 30 frames
    .venv/bin/python bench/bench_bridge.py           # 120 frames
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")

from PIL import Image  # noqa: E402

from openfusion.app.launcher import Cluster  # noqa: E402
from openfusion.bus import Subscriber, open_session  # noqa: E402
from openfusion.bus import free_loopback_port as free_port  # noqa: E402
from openfusion.config import ServiceConfig, ZenohSettings  # noqa: E402
from openfusion.sources import open_source  # noqa: E402
from openfusion.sources.scannet_writer import write_scannet_layout  # noqa: E402
from openfusion.wire.endpoints import SENSOR_RGBD
from openfusion.wire.schemas import RgbdFrame  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--full", action="store_true", help="the default size (bench/run_all.py --full passes it)")
    args = parser.parse_args()
    n = 30 if args.quick else 120
    tmp = Path(tempfile.mkdtemp(prefix="bench-bridge-"))
    scene = tmp / "scene"
    write_scannet_layout(open_source(f"synthetic:frames={n}"), scene, ground_truth_spacing_m=None)

    t0 = time.perf_counter()
    for i in range(n):
        with Image.open(scene / "color" / f"{i}.jpg") as im:
            im.load()
        with Image.open(scene / "depth" / f"{i}.png") as im:
            im.load()
    pillow_fps = n / (time.perf_counter() - t0)
    t0 = time.perf_counter()
    read = sum(1 for _ in open_source(f"scannet:{scene}"))
    reader_fps = read / (time.perf_counter() - t0)

    map_id = "bench-bridge"
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    session = open_session(ServiceConfig(map_id=map_id, zenoh=ZenohSettings(
        mode="router", listen=[endpoint], multicast_scouting=False)))
    stamps: list[float] = []
    sub = Subscriber(session, SENSOR_RGBD.key(ServiceConfig(map_id=map_id).keys), RgbdFrame,
                     lambda _m: stamps.append(time.perf_counter()), queue_size=1024)
    cluster = Cluster(map_id, endpoint, tmp / "logs")
    try:
        cluster.start("bridge", ["--source", f"scannet:{scene}", "--rate-hz", "0"])
        deadline = time.monotonic() + 300
        while len(stamps) < n and time.monotonic() < deadline:
            time.sleep(0.05)
    finally:
        cluster.stop()
        sub.close()
        session.close()
    bridge_fps = (len(stamps) - 1) / (stamps[-1] - stamps[0]) if len(stamps) > 1 else float("nan")
    print(f"\n## Bridge publish rate ({n} ScanNet-layout frames, color 640x480 JPEG + depth PNG; {os.cpu_count()} CPUs)\n")
    print("| path | frames/s | x Pillow decode |")
    print("|---|---:|---:|")
    print(f"| Pillow decode of color + depth (baseline) | {pillow_fps:.1f} | 1.00 |")
    print(f"| ScanNet reader (decode, checks, frame assembly) | {reader_fps:.1f} | {reader_fps / pillow_fps:.2f} |")
    print(f"| bridge service → subscriber over Zenoh (received {len(stamps)}) | {bridge_fps:.1f} | "
          f"{bridge_fps / pillow_fps:.2f} |")


if __name__ == "__main__":
    main()
