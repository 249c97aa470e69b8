"""Benchmark the region and text encoders at 640x480 (markdown tables on stdout).

Region encoders: frames/s and regions/s of each backend, with the plain ground-truth mask
downsampling (what every gt frame costs at minimum) as the baseline measured in the same run.
Model backends use tiny random-weight models built here (they measure the pipeline: proposals,
crops, batching, runtime overhead, not a real network's FLOPs); real CLIP ViT-B/32 is added when
its weights are in the local Hugging Face cache.

    HF_HUB_OFFLINE=1 .venv/bin/python bench/bench_encoders.py --quick
    HF_HUB_OFFLINE=1 .venv/bin/python bench/bench_encoders.py --device cuda --frames 100
"""

from __future__ import annotations

import argparse
import logging
import platform
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from openfusion.encoders import EncoderError, make_region_encoder, make_text_encoder, select_device
from openfusion.encoders.clip_export import export_clip_to_onnx
from openfusion.encoders.clip_regions import DEFAULT_CLIP_MODEL
from openfusion.encoders.graph_segmentation import GraphSegmentationProposer
from openfusion.encoders.masks import area_downsample_labels
from openfusion.frame import Frame
from openfusion.testing.images import grid_boxes, make_box_frame
from openfusion.testing.models import build_tiny_clip, build_tiny_region_onnx, build_tiny_text_onnx

CATEGORIES = ["office chair", "table", "sofa", "bed", "bookshelf", "cabinet", "lamp", "monitor", "plant", "door"]


def make_frames(n: int, *, height_px: int = 480, width_px: int = 640, seed: int = 0) -> list[Frame]:
    """Box scenes (12 objects + background) with shading and sensor noise, different per frame."""
    rng = np.random.default_rng(seed)
    frames = []
    for i in range(n):
        boxes = grid_boxes(height_px=height_px, width_px=width_px, rows=3, cols=4, categories=CATEGORIES,
                           gap_px=int(rng.integers(4, 20)), seed=int(rng.integers(1 << 30)))  # fmt: skip
        f = make_box_frame(boxes, height_px=height_px, width_px=width_px, frame_id=i)
        ramp = (np.arange(height_px) / height_px * 30.0)[:, None, None]
        f.color = np.clip(f.color + ramp + rng.normal(0, 3.0, f.color.shape), 0, 255).astype(np.uint8)
        frames.append(f)
    return frames


def time_frames(fn: Callable[[Frame], int], frames: list[Frame], warmup: int) -> tuple[float, int]:
    """Seconds for ``fn`` over ``frames`` (after ``warmup`` untimed calls) and total regions returned."""
    for f in frames[:warmup]:
        fn(f)
    t0 = time.perf_counter()
    regions = sum(fn(f) for f in frames)
    return time.perf_counter() - t0, regions


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="CI-sized run (few frames, hashed text encoder)")
    ap.add_argument("--frames", type=int, default=None, help="timed frames per backend (default 40, quick 6)")
    ap.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda"])
    ap.add_argument("--text", default=None, choices=["minilm", "hash"], help="text encoder of the gt backend")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    n = args.frames or (6 if args.quick else 40)
    warmup = 1 if args.quick else 3
    device = select_device(args.device)
    text_name = args.text or ("hash" if args.quick else "minilm")
    frames = make_frames(n)
    work = Path(tempfile.mkdtemp(prefix="bench_encoders_"))
    rows: list[tuple[str, float, int, str]] = []
    notes: list[str] = []

    def add(label: str, fn: Callable[[Frame], int], note: str = "") -> None:
        secs, regions = time_frames(fn, frames, warmup)
        rows.append((label, secs, regions, note))

    # baseline: what any gt frame costs at least (masks -> 160x120 coverage maps)
    def baseline(f: Frame) -> int:
        ids = np.unique(f.instance)
        ids = ids[ids > 0]
        return area_downsample_labels(f.instance, ids, (120, 160)).shape[0]

    add("baseline: gt mask downsampling", baseline, "numpy")
    gt = make_region_encoder("gt", text_encoder=text_name, text_options={} if text_name == "hash" else {"device": device})
    add(f"gt (text {text_name}, cached per category)", lambda f: gt.encode(f).num_regions)
    gt_noisy = make_region_encoder("gt", text_encoder=gt.text_encoder, noise="standard", seed=0)
    add("gt + standard noise", lambda f: gt_noisy.encode(f).num_regions)
    proposer = GraphSegmentationProposer()
    add("graph segmentation proposals only", lambda f: proposer.propose(f, (120, 160)).shape[0], "160x120 grid")

    region_onnx = build_tiny_region_onnx(work / "region.onnx", input_hw=(480, 640), num_regions=16, dim=64)
    onnx_enc = make_region_encoder("onnx", model_path=region_onnx, device=device)
    add("onnx region-model (tiny, 640x480 input)", lambda f: onnx_enc.encode(f).num_regions,
        ",".join(p.replace("ExecutionProvider", "") for p in onnx_enc.model.providers))  # fmt: skip

    clip_dir = build_tiny_clip(work / "tiny-clip", image_size=224, patch_size=32)
    clip_enc = make_region_encoder("clip-regions", model=str(clip_dir), device=device)
    add("clip-regions (tiny CLIP, 224 crops, torch)", lambda f: clip_enc.encode(f).num_regions, "2-layer ViT")
    exported = export_clip_to_onnx(str(clip_dir), work / "tiny-clip-onnx")
    crop_enc = make_region_encoder("onnx", model_path=exported["image"], device=device)
    add("onnx crop-embedder (tiny CLIP export)", lambda f: crop_enc.encode(f).num_regions, "graph proposals")

    real_text = None
    try:
        real = make_region_encoder("clip-regions", model=DEFAULT_CLIP_MODEL, device=device)
        real_text = make_text_encoder("clip", model=DEFAULT_CLIP_MODEL, device=device)
        add("clip-regions (real CLIP ViT-B/32)", lambda f: real.encode(f).num_regions, "pretrained")
    except EncoderError as exc:
        notes.append(f"real CLIP ViT-B/32 not measured: weights not available offline ({str(exc).split(':')[0]}).")

    base_secs = rows[0][1]
    print(f"## Region encoders, 640x480 input -> 160x120 maps ({n} frames, device {device}, "
          f"{platform.machine()}, python {platform.python_version()})\n")  # fmt: skip
    print("| backend | regions/frame | frames/s | regions/s | ms/frame | x baseline time | note |")
    print("|---|---:|---:|---:|---:|---:|---|")
    for label, secs, regions, note in rows:
        print(
            f"| {label} | {regions / n:.1f} | {n / secs:.1f} | {regions / secs:.0f} | {1e3 * secs / n:.1f} "
            f"| {secs / base_secs:.1f} | {note} |"
        )

    # text encoders: query latency
    texts = ["a chair", "office chair", "the red sofa next to the window", "lamp"]
    text_rows = []
    encoders: list[tuple[str, object]] = [("hash", make_text_encoder("hash"))]
    if not args.quick or args.text == "minilm":
        encoders.append(("minilm", gt.text_encoder if text_name == "minilm" else make_text_encoder("minilm", device=device)))
    encoders.append(("onnx text-model (tiny)", make_text_encoder("onnx", model_path=build_tiny_text_onnx(work / "text"), device=device)))
    encoders.append(("clip text tower (tiny, torch)", make_text_encoder("clip", model=str(clip_dir), device=device)))
    encoders.append(("clip text tower (tiny, onnx)", make_text_encoder("onnx", model_path=exported["text"], device=device)))
    if real_text is not None:
        encoders.append(("clip text tower (real ViT-B/32)", real_text))
    reps = 5 if args.quick else 30
    for name, enc in encoders:
        enc.encode(texts)  # type: ignore[attr-defined]
        t0 = time.perf_counter()
        for _ in range(reps):
            enc.encode(texts[:1])  # type: ignore[attr-defined]
        one = (time.perf_counter() - t0) / reps
        t0 = time.perf_counter()
        for _ in range(reps):
            enc.encode(texts)  # type: ignore[attr-defined]
        four = (time.perf_counter() - t0) / reps
        text_rows.append((name, enc.embedding_space, enc.dim, one, four))  # type: ignore[attr-defined]
    print(f"\n## Text encoders (query latency, {reps} repetitions)\n")
    print("| encoder | space | dim | ms / 1 text | ms / batch of 4 |")
    print("|---|---|---:|---:|---:|")
    for name, space, dim, one, four in text_rows:
        print(f"| {name} | {space} | {dim} | {1e3 * one:.2f} | {1e3 * four:.2f} |")
    if args.quick and args.text != "minilm":
        notes.append("quick run: MiniLM omitted from the text table (pass --text minilm to include it).")
    for note in notes:
        print(f"\nNote: {note}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
