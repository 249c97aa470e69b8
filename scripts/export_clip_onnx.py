#!/usr/bin/env python3
"""Export the clip-regions backend (CLIP image tower for region crops + text tower) to the ONNX contract.

Writes clip_image.onnx (kind crop-embedder), clip_text.onnx (kind text-model) and tokenizer.json
into OUT_DIR, checks them against torch, and prints how to use them:

    HF_HUB_OFFLINE=1 .venv/bin/python scripts/export_clip_onnx.py openai/clip-vit-base-patch32 models/clip-b32
    .venv/bin/python scripts/export_clip_onnx.py /path/to/saved-clip-folder out/ --embedding-space my-clip

With ``--dense`` it also exports the ``clip-dense`` tower (MaskCLIP value path, one pass per frame)
for one frame size, in fp32 and int8 (onnxruntime dynamic quantisation), into the export cache the
encoder reads (``$OPENFUSION_CACHE``/clip-dense, or ``--cache-dir``), so the first frame of a
``--set semantic.encoder_backend=onnx-int8`` run does not pay for the export:

    .venv/bin/python scripts/export_clip_onnx.py openai/clip-vit-base-patch32 models/clip-b32 --dense --frame-size 480x640

The model is a Hugging Face hub name (weights must be in the local cache when offline) or a folder
written by ``save_pretrained`` (model + tokenizer). See docs/ENCODERS.md for the contract.
"""

from __future__ import annotations

import argparse
import logging
import sys

from openfusion.encoders import EncoderError
from openfusion.encoders.clip_export import export_clip_to_onnx
from openfusion.encoders.clip_regions import DEFAULT_CLIP_MODEL


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="Export CLIP towers to the OpenFusion ONNX encoder contract.")
    ap.add_argument("model", nargs="?", default=DEFAULT_CLIP_MODEL, help=f"hub name or local folder (default {DEFAULT_CLIP_MODEL})")
    ap.add_argument("out_dir", nargs="?", default="clip_onnx", help="output folder (default ./clip_onnx)")
    ap.add_argument("--embedding-space", default=None, help="space id for weights that are not a known hub name")
    ap.add_argument("--opset", type=int, default=17)
    ap.add_argument("--no-check", action="store_true", help="skip comparing the ONNX outputs with torch")
    ap.add_argument("--dense", action="store_true", help="also export the clip-dense tower (fp32 and int8)")
    ap.add_argument("--frame-size", default="480x640", help="HxW of the frames the dense tower will see (default 480x640)")
    ap.add_argument("--input-long-side-px", type=int, default=None, help="clip-dense input size (default the encoder's)")
    ap.add_argument("--cache-dir", default=None, help="clip-dense export cache (default $OPENFUSION_CACHE or ~/.cache/openfusion)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        paths = export_clip_to_onnx(
            args.model, args.out_dir, embedding_space=args.embedding_space, opset=args.opset, check=not args.no_check
        )
    except (EncoderError, RuntimeError) as exc:
        print(f"export failed: {exc}", file=sys.stderr)
        return 1
    print(f"image tower (crop-embedder): {paths['image']}")
    print(f"text tower (text-model):     {paths['text']}")
    print(f"tokenizer:                   {paths['tokenizer']}")
    if args.dense:
        from openfusion.encoders.clip_dense import DEFAULT_INPUT_LONG_SIDE_PX, dense_input_size, export_dense_onnx
        from openfusion.encoders.clip_regions import load_clip

        try:
            h, w = (int(v) for v in args.frame_size.lower().split("x"))
        except ValueError:
            print(f"--frame-size {args.frame_size!r}: expected HxW, e.g. 480x640", file=sys.stderr)
            return 2
        clip = load_clip(args.model, device="cpu", embedding_space=args.embedding_space)
        size = dense_input_size(h, w, patch_px=int(clip.model.config.vision_config.patch_size),
                                long_side_px=args.input_long_side_px or DEFAULT_INPUT_LONG_SIDE_PX)
        for int8 in (False, True):
            path = export_dense_onnx(clip, args.model, size, int8=int8, cache_dir=args.cache_dir)
            print(f"clip-dense tower ({'int8' if int8 else 'fp32'}, input {size[0]}x{size[1]}): {path}")
    print("use with:")
    print(f"  make_region_encoder('onnx', model_path='{paths['image']}')")
    print(f"  make_text_encoder('onnx', model_path='{paths['text']}')")
    return 0


if __name__ == "__main__":
    sys.exit(main())
