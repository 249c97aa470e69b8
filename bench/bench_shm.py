"""Zenoh shared memory between two processes on one host: CPU per 1.5 MB frame (640x480 color +
depth) for the publisher and the subscriber, three ways, in one run:

- ``off``: ``transport/shared_memory/enabled = false`` (every byte through the TCP link);
- ``default``: Zenoh 1.x's default config, a plain ``put(bytes)``: messages over 3 KB go through a
  shared-memory pool (``transport_optimization``) when both ends are on one host; what every
  OpenFusion-Z service does unless ``zenoh.shared_memory`` is false;
- ``explicit``: the publisher writes into a ``zenoh.shm.ShmProvider`` buffer itself.

    .venv/bin/python bench/bench_shm.py            # 300 frames per way
    .venv/bin/python bench/bench_shm.py --quick    # 100

CPU seconds come from ``time.process_time`` of each process (all its threads), so a busy machine
changes them less than wall time. Each process reads the payload's bytes, as a decoder does.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time

SIZE = 640 * 480 * 3 + 640 * 480 * 2


def child(mode: str, role: str, port: int, n: int) -> None:
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints" if role == "pub" else "connect/endpoints",
                      json.dumps([f"tcp/127.0.0.1:{port}"]))
    conf.insert_json5("transport/shared_memory/enabled", "false" if mode == "off" else "true")
    session = zenoh.open(conf)
    key = "bench/shm/frames"
    if role == "sub":
        got: list[int] = []
        sub = session.declare_subscriber(key, lambda sample: got.append(len(sample.payload.to_bytes())))
        print("ready", flush=True)
        c0 = time.process_time()
        while len(got) < n:
            time.sleep(0.005)
        print(json.dumps({"cpu_s": time.process_time() - c0, "received": len(got)}), flush=True)
        sub.undeclare()
    else:
        import os

        pub = session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
        while not pub.matching_status.matching:
            time.sleep(0.01)
        data = os.urandom(SIZE)
        provider = None
        if mode == "explicit":
            import zenoh.shm as shm

            provider = shm.ShmProvider.default_backend(64 * 1024 * 1024)
        c0 = time.process_time()
        for _ in range(n):
            if provider is not None:
                buf = provider.alloc(SIZE, shm.BlockOn(shm.GarbageCollect()))
                buf[0:SIZE] = data
                pub.put(buf)
            else:
                pub.put(data)
            time.sleep(0.004)  # a camera, not a flood: the subscriber keeps up
        print(json.dumps({"cpu_s": time.process_time() - c0}), flush=True)
        time.sleep(1.0)
        pub.undeclare()
    session.close()


def measure(mode: str, n: int) -> tuple[float, float]:
    from openfusion.bus import free_loopback_port

    port = free_loopback_port()
    pub = subprocess.Popen([sys.executable, __file__, "--child", mode, "pub", str(port), str(n)],
                           stdout=subprocess.PIPE, text=True)
    sub = subprocess.Popen([sys.executable, __file__, "--child", mode, "sub", str(port), str(n)],
                           stdout=subprocess.PIPE, text=True)
    sub_out, _ = sub.communicate(timeout=300)
    pub_out, _ = pub.communicate(timeout=300)
    p = json.loads(pub_out.strip().splitlines()[-1])
    s = json.loads(sub_out.strip().splitlines()[-1])
    return 1e3 * p["cpu_s"] / n, 1e3 * s["cpu_s"] / n


def main() -> int:
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        child(sys.argv[2], sys.argv[3], int(sys.argv[4]), int(sys.argv[5]))
        return 0
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="100 frames per way")
    ap.add_argument("--frames", type=int, default=None)
    ap.add_argument("--full", action="store_true", help="the default size (bench/run_all.py --full passes it)")
    args = ap.parse_args()
    n = args.frames or (100 if args.quick else 300)
    results = {mode: measure(mode, n) for mode in ("off", "default", "explicit")}
    base = results["off"]
    print(f"## Zenoh shared memory, {SIZE / 1e6:.2f} MB frames between two processes ({n} frames each way)\n")
    print("| path | publisher CPU ms/frame | subscriber CPU ms/frame | x off (sum) |")
    print("|---|---:|---:|---:|")
    for mode, (p, s) in results.items():
        print(f"| {mode} | {p:.2f} | {s:.2f} | {(p + s) / sum(base):.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
