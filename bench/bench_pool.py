"""Encoder pool scaling: Sem-3D-Rec rate of ``openfusion run --encoder-workers N`` for N = 1, 2, 4
with a fixed encoder cost (``--encoder-delay-ms``, sleeping: a remote GPU, not local CPU), against
N times one worker's rate measured in the same run, and the f-mIoU of each run's map against the
synthetic scene's ground truth (a pool must not change what the map says).

    HF_HUB_OFFLINE=1 .venv/bin/python bench/bench_pool.py            # 240 frames, 250 ms, N = 1 2 4
    HF_HUB_OFFLINE=1 .venv/bin/python bench/bench_pool.py --quick    # 120 frames

A second table checks that the pool does not change the map: one worker and the largest pool at
a camera rate one worker keeps up with (80 % of 1 / delay), so both fuse every frame, in frame
order; their f-mIoU must agree within 0.02. (At the fast camera rate each pool size fuses a
different subset of frames, latest-only, so the maps differ for that reason alone.)

The semantic rate is the one in run.json (``semantic_rate_hz``: fused frames per second between
the first and the last fused frame). The camera plays at ``--rate-hz`` (30): faster than four
workers can take frames, so the pool, not the camera, bounds the rate.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def run_once(out: Path, workers: int, *, frames: int, delay_ms: float, rate_hz: float, size: str) -> dict:
    cmd = [sys.executable, "-m", "openfusion.app.cli", "run", "--out", str(out), "--source", f"synthetic:seed=1,{size}",
           "--frames", str(frames), "--rate-hz", str(rate_hz), "--encoder-workers", str(workers),
           "--encoder-delay-ms", str(delay_ms), "--quiet", "--query", "chair"]
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, env={**os.environ, "HF_HUB_OFFLINE": "1"})
    if proc.returncode != 0:
        raise SystemExit(f"run with {workers} workers failed:\n{proc.stderr[-3000:]}")
    return json.loads((out / "run.json").read_text())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="120 frames")
    ap.add_argument("--workers", default="1,2,4", help="pool sizes (default 1,2,4)")
    ap.add_argument("--full", action="store_true", help="the default size (bench/run_all.py --full passes it)")
    ap.add_argument("--delay-ms", type=float, default=250.0, help="encoder cost per frame (default 250)")
    ap.add_argument("--rate-hz", type=float, default=30.0, help="camera rate (default 30)")
    ap.add_argument("--frames", type=int, default=None, help="frames per run (default 240, quick 120)")
    ap.add_argument("--size", default="width=320,height=240", help="synthetic frame size options")
    ap.add_argument("--quality-frames", type=int, default=None, help="frames of the quality pair (default 40, quick 24)")
    ap.add_argument("--skip-quality", action="store_true", help="only the scaling table")
    args = ap.parse_args(argv)
    from openfusion.encoders import make_text_encoder
    from openfusion.eval.saved_map import synthetic_map_quality
    from openfusion.mapping import load_map

    frames = args.frames or (120 if args.quick else 240)
    counts = [int(n) for n in args.workers.split(",")]
    text = make_text_encoder("minilm")
    work = Path(tempfile.mkdtemp(prefix="bench_pool_"))
    rows = []
    for n in counts:
        summary = run_once(work / f"w{n}", n, frames=frames, delay_ms=args.delay_ms, rate_hz=args.rate_hz,
                           size=args.size)
        loaded = load_map(work / f"w{n}" / "map")
        quality = synthetic_map_quality(loaded.volume, loaded.dictionary, seed=1, text_encoder=text)
        rows.append((n, summary, quality))
    base = rows[0][1]["semantic_rate_hz"] or float("nan")
    print(f"## Encoder pool scaling ({frames} frames at {args.rate_hz:g} Hz, {args.size}, encoder "
          f"{args.delay_ms:g} ms per frame, {len(os.sched_getaffinity(0))} cores)\n")
    print("| workers | semantic frames | semantic rate (Hz) | x one worker | / (N x one worker) | frames per worker "
          "| resent | lost | stale | f-mIoU | mAcc |")
    print("|---:|---:|---:|---:|---:|---|---:|---:|---:|---:|---:|")
    for n, s, q in rows:
        rate = s["semantic_rate_hz"] or float("nan")
        per = ", ".join(f"{k} {v}" for k, v in sorted(s["frames_encoded_per_worker"].items()))
        print(f"| {n} | {s['semantic_frames']} | {rate:.2f} | {rate / base:.2f} | {rate / (n * base):.2f} | {per} "
              f"| {s['encoder_frames_resent']} | {s['encoder_frames_lost']} | {s.get('encoder_results_stale', 'n/a')} "
              f"| {q['f_mIoU']:.3f} | {q['mAcc']:.3f} |")
    if args.skip_quality:
        return 0
    # the same frames fused by one worker and by the largest pool: the maps must agree
    slow_hz = 0.8 * 1000.0 / args.delay_ms
    qframes = args.quality_frames or (24 if args.quick else 40)
    pair = []
    for n in sorted({counts[0], counts[-1]}):
        out = work / f"q{n}"
        summary = run_once(out, n, frames=qframes, delay_ms=args.delay_ms, rate_hz=slow_hz, size=args.size)
        loaded = load_map(out / "map")
        pair.append((n, summary, synthetic_map_quality(loaded.volume, loaded.dictionary, seed=1, text_encoder=text)))
    print(f"\n## Same frames, one worker vs {counts[-1]} ({qframes} frames at {slow_hz:.1f} Hz)\n")
    print("| workers | semantic frames | f-mIoU | mAcc | surface points |")
    print("|---:|---:|---:|---:|---:|")
    for n, s, q in pair:
        print(f"| {n} | {s['semantic_frames']} | {q['f_mIoU']:.3f} | {q['mAcc']:.3f} | {q['points']} |")
    if len(pair) == 2:
        print(f"\nf-mIoU difference: {abs(pair[0][2]['f_mIoU'] - pair[1][2]['f_mIoU']):.3f} (target <= 0.02)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
