"""Benchmark the region and text encoders at 640x480 (markdown tables on stdout).

Region encoders: frames/s and regions/s of each backend, with the plain ground-truth mask
downsampling (what every gt frame costs at minimum) as the baseline measured in the same run.
Model backends use tiny random-weight models built here (they measure the pipeline: proposals,
crops, batching, runtime overhead, not a real network's FLOPs); real CLIP ViT-B/32 is added when
its weights are in the local Hugging Face cache.

Real-size models (``--models``, random weights of the released sizes, built in memory): ms per
640x480 frame of ``clip-regions`` (one tower pass per region crop) and ``clip-dense`` (one pass over
the frame) at 10, 30 and 60 regions, per backend (torch-fp32, onnx-int8; cuda-fp16 on a GPU), with
the ratio regions / dense measured in the same run: the two encoders are timed in turns (a round of
all frames each, order alternating) on the same frames, and each figure is a median (the machine
may be shared). Both get the same
masks (the frames' ground truth, so the region count is exact; graph-segmentation proposals, ~7 ms,
are left out of both, and the ground-truth masks' own ~5 ms is in both). ``--json FILE`` writes
those rows with the keys encoder, backend, model, regions, ms_per_frame (medians).
``--profile`` adds where clip-dense's time goes (masks, resize + normalise, tower, pooling, the
whole call). ``--dense-sizes 320,384,448`` adds clip-dense at those input sizes: ms per frame and the cosine of
each region's embedding against the one at the largest size.

    HF_HUB_OFFLINE=1 .venv/bin/python bench/bench_encoders.py --quick
    HF_HUB_OFFLINE=1 .venv/bin/python bench/bench_encoders.py --device cuda --frames 100
    HF_HUB_OFFLINE=1 .venv/bin/python bench/bench_encoders.py --skip-small --models vit-b-32,vit-b-16 --json enc.json
    HF_HUB_OFFLINE=1 .venv/bin/python bench/bench_encoders.py --skip-small --models vit-b-32 --dense-sizes 384,448
"""

from __future__ import annotations

import argparse
import atexit
import logging
import os
import platform
import shutil
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from openfusion.encoders import EncoderError, make_region_encoder, make_text_encoder, select_device
from openfusion.encoders.base import DEFAULT_DENSE_INPUT_LONG_SIDE_PX
from openfusion.encoders.clip_export import export_clip_to_onnx
from openfusion.encoders.clip_regions import DEFAULT_CLIP_MODEL
from openfusion.encoders.graph_segmentation import GraphSegmentationProposer
from openfusion.encoders.masks import area_downsample_labels, label_ids
from openfusion.frame import Frame
from openfusion.testing.images import grid_boxes, make_box_frame
from openfusion.testing.models import (
    CLIP_PRESETS,
    build_tiny_clip,
    build_tiny_region_onnx,
    build_tiny_text_onnx,
)

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
    ap.add_argument("--full", action="store_true", help="the default size (bench/run_all.py --full passes it)")
    ap.add_argument("--frames", type=int, default=None, help="timed frames per backend (default 40, quick 6)")
    ap.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda"])
    ap.add_argument("--text", default=None, choices=["minilm", "hash"], help="text encoder of the gt backend")
    ap.add_argument("--models", default=None,
                    help=f"real-size random-weight CLIP towers to time, comma-separated from {', '.join(CLIP_PRESETS)} "
                    "(default vit-b-32; quick: vit-b-32 at 30 regions only; 'none' skips)")
    ap.add_argument("--regions", default=None, help="region counts for --models (default 10,30,60; quick 30)")
    ap.add_argument("--backends", default=None, help="backends for --models: torch-fp32, onnx-int8, cuda-fp16 "
                    "(default: torch-fp32,onnx-int8, plus cuda-fp16 on a GPU)")
    ap.add_argument("--skip-small", action="store_true", help="only the real-size model table")
    ap.add_argument("--json", type=Path, default=None, help="write the real-size rows to this JSON file")
    ap.add_argument("--rounds", type=int, default=None,
                    help="rounds over the frames for --models (default 3, quick 1; medians over all)")
    ap.add_argument("--dense-long-side", type=int, default=None,
                    help=f"clip-dense input, px on the longer side (default {DEFAULT_DENSE_INPUT_LONG_SIDE_PX})")
    ap.add_argument("--profile", action="store_true",
                    help="also print where clip-dense's time goes per frame: masks, resize + normalise, tower, "
                    "pooling, and the whole encode call (medians)")
    ap.add_argument("--dense-sizes", default=None,
                    help="also time clip-dense at these input sizes (px, comma-separated, e.g. 320,384,448) and "
                    "compare its region embeddings with the largest")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    n = args.frames or (6 if args.quick else 40)
    warmup = 1 if args.quick else 3
    device = select_device(args.device)
    text_name = args.text or ("hash" if args.quick else "minilm")
    work = Path(tempfile.mkdtemp(prefix="bench_encoders_"))
    atexit.register(shutil.rmtree, work, True)  # real-size exports take ~1 GB
    if args.skip_small:
        return real_size_models(args, device, work)
    frames = make_frames(n)
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
    return real_size_models(args, device, work)


class GroundTruthProposer:
    """The frame's instance masks at the output grid: the same, exactly known regions for both encoders."""

    name = "ground-truth masks"

    def propose(self, frame: Frame, out_hw: tuple[int, int]) -> np.ndarray:
        ids = label_ids(frame.instance)
        return area_downsample_labels(frame.instance, ids[ids > 0], out_hw)


def frames_with_regions(count: int, n_frames: int) -> list[Frame]:
    """640x480 box frames with exactly ``count`` regions (a grid of boxes)."""
    rows = int(np.floor(np.sqrt(count * 3 / 4))) or 1
    cols = int(np.ceil(count / rows))
    out = []
    for i in range(n_frames):
        boxes = grid_boxes(height_px=480, width_px=640, rows=rows, cols=cols, categories=CATEGORIES, gap_px=4,
                           seed=i)[:count]  # fmt: skip
        out.append(make_box_frame(boxes, height_px=480, width_px=640, frame_id=i))
    return out


def _regions_encoder(model: str, backend: str, device: str, work: Path):  # noqa: ANN202
    """clip-regions with ``backend``: torch (fp32, or fp16 on CUDA), or its image tower exported to
    ONNX and int8-quantised, run as an onnx crop embedder."""
    from openfusion.encoders.clip_regions import load_clip
    from openfusion.encoders.onnx_backend import make_onnx_region_encoder

    if backend != "onnx-int8":
        enc = make_region_encoder("clip-regions", model=model, device=device)
        if backend == "cuda-fp16":
            enc.embedder.clip.model.half()
            embed = enc.embedder.embed_crops

            def embed_half(crops: np.ndarray) -> np.ndarray:
                return embed(crops.astype(np.float16))

            enc.embedder.embed_crops = embed_half  # type: ignore[method-assign]
        return enc
    import torch
    from onnxruntime.quantization import QuantType, quantize_dynamic

    from openfusion.encoders.clip_export import _export, image_tower, set_onnx_metadata

    clip = load_clip(model, device="cpu")

    s = clip.crop_spec.size
    fp32, int8 = work / f"{model.replace('/', '-')}-crops.onnx", work / f"{model.replace('/', '-')}-crops-int8.onnx"
    with torch.no_grad():
        _export(image_tower(clip.model.float()), (torch.zeros(2, 3, s, s),), fp32, ["crops"], ["embeddings"],
                {"crops": {0: "batch"}, "embeddings": {0: "batch"}}, 17)
    quantize_dynamic(str(fp32), str(int8), weight_type=QuantType.QInt8, op_types_to_quantize=["MatMul", "Gemm"])
    set_onnx_metadata(int8, {"embedding_space": clip.embedding_space, "dim": clip.dim, "kind": "crop-embedder",
                             "crop_size": s, "mean": list(clip.crop_spec.mean), "std": list(clip.crop_spec.std)})
    return make_onnx_region_encoder(model_path=int8, device="cpu")


def interleaved_ms(encoders: dict[str, object], frames: list[Frame], rounds: int) -> dict[str, float]:
    """Median ms per frame of each encoder, timed in turns on the same frames, so that a burst of
    load on a shared machine hits all of them alike: every round times each encoder over all the
    frames after one untimed call (the order alternates every round). Turns are per round, not per
    frame: two onnxruntime sessions in one process each keep idle threads spinning for a while
    after a run, and alternating frame by frame added ~30 ms to every 50 ms clip-dense frame, a
    cost no deployment has (one encoder per process)."""
    samples: dict[str, list[float]] = {label: [] for label in encoders}
    order = list(encoders.items())
    for r in range(rounds):
        for label, enc in order if r % 2 == 0 else order[::-1]:
            enc.encode(frames[0])  # type: ignore[attr-defined]
            for f in frames:
                t0 = time.perf_counter()
                enc.encode(f)  # type: ignore[attr-defined]
                samples[label].append(time.perf_counter() - t0)
    return {label: 1e3 * float(np.median(v)) for label, v in samples.items()}


def real_size_models(args: argparse.Namespace, device: str, work: Path) -> int:
    """The clip-regions vs clip-dense table on real-size random-weight towers (module docstring)."""
    import json

    from openfusion.testing.models import register_random_clip

    spec = args.models or "vit-b-32"
    if spec == "none":
        return 0
    models = [m.strip() for m in spec.split(",") if m.strip()]
    counts = [int(c) for c in (args.regions or ("30" if args.quick else "10,30,60")).split(",")]
    backends = (args.backends or ("torch-fp32,onnx-int8" + (",cuda-fp16" if device == "cuda" else ""))).split(",")
    n = args.frames or (2 if args.quick else 5)
    rounds = args.rounds or (1 if args.quick else 3)
    long_side = args.dense_long_side or DEFAULT_DENSE_INPUT_LONG_SIDE_PX
    rows: list[dict] = []
    proposer = GroundTruthProposer()
    print(f"\n## Real-size CLIP towers (random weights), 640x480 frames, ground-truth masks ({n} frames x "
          f"{rounds} rounds, medians, encoders timed in turns; clip-dense input {long_side} px on the longer "
          f"side; {platform.machine()}, {len(os.sched_getaffinity(0))} cores)\n")
    print("| model | backend | regions | clip-regions ms/frame | clip-dense ms/frame | regions / dense |")
    print("|---|---|---:|---:|---:|---:|")
    agreement: list[str] = []
    size_rows: list[str] = []
    profile_rows: list[str] = []
    sizes = [int(v) for v in args.dense_sizes.split(",")] if args.dense_sizes else []
    for preset in models:
        probe = frames_with_regions(30, 1)[0]
        probe_emb: dict[str, np.ndarray] = {}
        for backend in backends:
            dev = "cuda" if backend == "cuda-fp16" else "cpu"
            name = register_random_clip(preset, device=dev)
            dense_backend = "onnx-int8" if backend == "onnx-int8" else "torch"
            dense = make_region_encoder("clip-dense", model=name, device=dev, backend=dense_backend, cache_dir=work,
                                        input_long_side_px=long_side)
            regions = _regions_encoder(name, backend, dev, work)
            dense.proposer = regions.proposer = proposer
            probe_emb[backend] = dense.encode(probe).embeddings
            for count in counts:
                ms = interleaved_ms({"clip-regions": regions, "clip-dense": dense}, frames_with_regions(count, n),
                                    rounds)
                for label in ("clip-regions", "clip-dense"):
                    rows.append({"encoder": label, "backend": backend, "model": preset, "regions": count,
                                 "ms_per_frame": round(ms[label], 2)})
                print(f"| {preset} | {backend} | {count} | {ms['clip-regions']:.0f} | {ms['clip-dense']:.0f} "
                      f"| {ms['clip-regions'] / ms['clip-dense']:.1f} |", flush=True)
            if args.profile:
                profile_rows += dense_profile(preset, backend, dense, counts, n, rounds)
            if sizes:
                size_rows += dense_sizes(preset, name, dev, dense_backend, backend, sizes, n, rounds, work)
        for other in ("onnx-int8", "cuda-fp16"):
            if "torch-fp32" in probe_emb and other in probe_emb:
                cos = np.sum(probe_emb["torch-fp32"] * probe_emb[other], axis=1)
                agreement.append(f"{preset}: clip-dense region embeddings, {other} vs torch-fp32 on 30 regions: "
                                 f"cosine min {cos.min():.4f}, mean {cos.mean():.4f}")
    for line in agreement:
        print(f"\n{line}")
    if profile_rows:
        print("\n## Where clip-dense's time goes (ms per frame, medians of each stage timed alone, then the "
              "whole encode call)\n")
        print("| model | backend | regions | masks | resize + normalise | tower | pooling | sum | encode |")
        print("|---|---|---:|---:|---:|---:|---:|---:|---:|")
        for line in profile_rows:
            print(line)
    if size_rows:
        print(f"\n## clip-dense input size (30 regions; cosine of each region's embedding against the "
              f"{max(sizes)} px one, same frames)\n")
        print("| model | backend | longer side px | input | tokens | ms/frame | x largest | cosine min | cosine mean |")
        print("|---|---|---:|---|---:|---:|---:|---:|---:|")
        for line in size_rows:
            print(line)
    if args.json is not None:
        args.json.write_text(json.dumps(rows, indent=1) + "\n", encoding="utf-8")
    return 0


def dense_profile(preset: str, backend: str, dense, counts: list[int], n: int, rounds: int) -> list[str]:  # noqa: ANN001
    """Table rows: each stage of clip-dense's encode timed alone (medians), against the whole call."""
    from openfusion.encoders.clip_dense import dense_input_size, pool_region_features, preprocess_dense

    spec = dense.clip.crop_spec
    out = []
    for count in counts:
        frames = frames_with_regions(count, n)
        size_hw = dense_input_size(480, 640, patch_px=dense.patch_px, long_side_px=dense.input_long_side_px)
        out_hw = dense.output_size(480, 640)
        runner = dense._runner(size_hw)
        stages: dict[str, list[float]] = {k: [] for k in ("masks", "pre", "tower", "pool", "encode")}
        for _ in range(rounds):
            for f in frames:
                t0 = time.perf_counter()
                masks = dense.proposer.propose(f, out_hw)
                t1 = time.perf_counter()
                pixels = preprocess_dense(f.color, size_hw, spec.mean, spec.std)
                t2 = time.perf_counter()
                feats = np.asarray(runner(pixels), np.float32).reshape(size_hw[0] // dense.patch_px,
                                                                        size_hw[1] // dense.patch_px, -1)
                t3 = time.perf_counter()
                pool_region_features(masks, feats)
                t4 = time.perf_counter()
                dense.encode(f)
                t5 = time.perf_counter()
                for k, a, b in (("masks", t0, t1), ("pre", t1, t2), ("tower", t2, t3), ("pool", t3, t4),
                                ("encode", t4, t5)):
                    stages[k].append(1e3 * (b - a))
        med = {k: float(np.median(v)) for k, v in stages.items()}
        parts = sum(med[k] for k in ("masks", "pre", "tower", "pool"))
        out.append(f"| {preset} | {backend} | {count} | {med['masks']:.1f} | {med['pre']:.1f} | {med['tower']:.1f} "
                   f"| {med['pool']:.1f} | {parts:.1f} | {med['encode']:.1f} |")
    return out


def dense_sizes(preset: str, name: str, dev: str, dense_backend: str, backend: str, sizes: list[int], n: int,
                rounds: int, work: Path) -> list[str]:
    """Table rows: clip-dense at each input size, ms per frame (timed in turns) and how close its
    region embeddings stay to those at the largest size."""
    from openfusion.encoders.clip_dense import dense_input_size

    encs = {}
    for px in sorted(sizes):
        enc = make_region_encoder("clip-dense", model=name, device=dev, backend=dense_backend, cache_dir=work,
                                  input_long_side_px=px)
        enc.proposer = GroundTruthProposer()
        encs[px] = enc
    frames = frames_with_regions(30, n)
    ref = encs[max(sizes)]
    ref_emb = [ref.encode(f).embeddings for f in frames]
    ms = interleaved_ms({str(px): e for px, e in encs.items()}, frames, rounds)
    out = []
    for px, enc in encs.items():
        cos = np.concatenate([np.sum(enc.encode(f).embeddings * r, axis=1) for f, r in zip(frames, ref_emb, strict=True)])
        h, w = dense_input_size(480, 640, patch_px=enc.patch_px, long_side_px=px)
        tokens = (h // enc.patch_px) * (w // enc.patch_px) + 1
        out.append(f"| {preset} | {backend} | {px} | {w}x{h} | {tokens} | {ms[str(px)]:.0f} "
                   f"| {ms[str(px)] / ms[str(max(sizes))]:.2f} | {cos.min():.4f} | {cos.mean():.4f} |")
    return out


if __name__ == "__main__":
    sys.exit(main())
