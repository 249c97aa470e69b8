#!/usr/bin/env python3
"""Export the clip-regions backend (CLIP image tower for region crops + text tower) to the ONNX contract.

Writes clip_image.onnx (kind crop-embedder), clip_text.onnx (kind text-model) and tokenizer.json
into OUT_DIR, checks them against torch, and prints how to use them:

    HF_HUB_OFFLINE=1 .venv/bin/python scripts/export_clip_onnx.py openai/clip-vit-base-patch32 models/clip-b32
    .venv/bin/python scripts/export_clip_onnx.py /path/to/saved-clip-folder out/ --embedding-space my-clip

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
    print("use with:")
    print(f"  make_region_encoder('onnx', model_path='{paths['image']}')")
    print(f"  make_text_encoder('onnx', model_path='{paths['text']}')")
    return 0


if __name__ == "__main__":
    sys.exit(main())
