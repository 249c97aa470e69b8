"""Export the ``clip-regions`` backend's towers to the ONNX contract (docs/ENCODERS.md).

Writes into ``out_dir``:

- ``clip_image.onnx``: kind ``crop-embedder``: input ``crops`` float32 [B,3,S,S] (dynamic B) ->
  ``embeddings`` float32 [B,d];
- ``clip_text.onnx``: kind ``text-model``: ``input_ids`` / ``attention_mask`` int64 [B,L] (L = the
  model's context length, dynamic B) -> ``text_embeddings`` float32 [B,d];
- ``tokenizer.json``: the CLIP BPE tokenizer (HF ``tokenizers`` format) the text model names.

Metadata (embedding_space, dim, crop_size, mean, std, max_length, pad_id, tokenizer) is stored in
each model's ``metadata_props``. The resulting pair runs with ``make_region_encoder("onnx",
model_path=".../clip_image.onnx")`` (graph-segmentation proposals) and
``make_text_encoder("onnx", model_path=".../clip_text.onnx")``.

Uses the TorchScript-based exporter (``dynamo=False``): the dynamo exporter needs the
``onnxscript`` package, which is not a dependency.
"""

from __future__ import annotations

import logging
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from openfusion.encoders.clip_regions import DEFAULT_CLIP_MODEL, _features, load_clip

logger = logging.getLogger(__name__)

IMAGE_FILE = "clip_image.onnx"
TEXT_FILE = "clip_text.onnx"
TOKENIZER_FILE = "tokenizer.json"


def set_onnx_metadata(path: str | Path, metadata: dict[str, Any]) -> None:
    """Add/replace ``metadata_props`` of an ONNX file in place (values stored as strings)."""
    import onnx

    model = onnx.load(str(path))
    existing = {p.key: p for p in model.metadata_props}
    for key, value in metadata.items():
        text = ",".join(str(v) for v in value) if isinstance(value, list | tuple) else str(value)
        if key in existing:
            existing[key].value = text
        else:
            entry = model.metadata_props.add()
            entry.key, entry.value = key, text
    onnx.save(model, str(path))


def _export(module: Any, args: tuple, path: Path, input_names: list[str], output_names: list[str], dynamic_axes: dict, opset: int) -> None:
    import torch

    with warnings.catch_warnings():
        # the TorchScript exporter announces its own deprecation and traces python control flow
        warnings.simplefilter("ignore")
        torch.onnx.export(
            module,
            args,
            str(path),
            input_names=input_names,
            output_names=output_names,
            dynamic_axes=dynamic_axes,
            opset_version=opset,
            dynamo=False,
        )


def image_tower(net: Any) -> Any:
    """A torch module: (b, 3, S, S) preprocessed crops -> (b, d) image embeddings of a transformers
    ``CLIPModel`` (what the crop-embedder ONNX export runs)."""
    import torch

    class ImageTower(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.net = net

        def forward(self, crops: torch.Tensor) -> torch.Tensor:
            return _features(self.net.get_image_features(pixel_values=crops))

    return ImageTower().eval()


def export_clip_to_onnx(
    model: str = DEFAULT_CLIP_MODEL,
    out_dir: str | Path = "clip_onnx",
    *,
    embedding_space: str | None = None,
    opset: int = 17,
    check: bool = True,
) -> dict[str, Path]:
    """Export image and text towers of ``model`` (hub name or folder) into ``out_dir``.

    With ``check`` the exported models are run once with onnxruntime and compared with torch
    (max abs difference of normalised embeddings < 1e-3), so a broken export fails here, not in a
    deployment.
    """
    import torch

    clip = load_clip(model, device="cpu", embedding_space=embedding_space)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    net = clip.model


    class TextTower(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.net = net

        def forward(self, input_ids: torch.Tensor, attention_mask: torch.Tensor) -> torch.Tensor:
            return _features(self.net.get_text_features(input_ids=input_ids, attention_mask=attention_mask))

    s = clip.crop_spec.size
    length = clip.max_text_length
    tok = clip.tokenizer
    pad_id = int(tok.pad_token_id if tok.pad_token_id is not None else tok.eos_token_id)
    example_crops = torch.zeros(2, 3, s, s)
    enc = tok(["a chair", "a photo of a table"], padding="max_length", max_length=length, truncation=True, return_tensors="pt")
    example_text = (enc["input_ids"].long(), enc["attention_mask"].long())

    image_path, text_path, tok_path = out / IMAGE_FILE, out / TEXT_FILE, out / TOKENIZER_FILE
    with torch.inference_mode(False), torch.no_grad():
        _export(image_tower(net), (example_crops,), image_path, ["crops"], ["embeddings"],
                {"crops": {0: "batch"}, "embeddings": {0: "batch"}}, opset)
        _export(TextTower().eval(), example_text, text_path, ["input_ids", "attention_mask"], ["text_embeddings"],
                {"input_ids": {0: "batch"}, "attention_mask": {0: "batch"}, "text_embeddings": {0: "batch"}}, opset)
    tok.backend_tokenizer.save(str(tok_path))
    common = {"embedding_space": clip.embedding_space, "dim": clip.dim, "source_model": str(model)}
    set_onnx_metadata(
        image_path,
        {**common, "kind": "crop-embedder", "crop_size": s, "mean": list(clip.crop_spec.mean), "std": list(clip.crop_spec.std)},
    )
    set_onnx_metadata(
        text_path, {**common, "kind": "text-model", "max_length": length, "pad_id": pad_id, "tokenizer": TOKENIZER_FILE}
    )
    if check:
        _check_export(clip, image_path, text_path, example_crops.numpy(), example_text)
    logger.info("exported %s to %s (space %s, %d-d)", model, out, clip.embedding_space, clip.dim)
    return {"image": image_path, "text": text_path, "tokenizer": tok_path}


def _check_export(clip: Any, image_path: Path, text_path: Path, crops: np.ndarray, text: tuple) -> None:
    import onnxruntime as ort
    import torch

    rng = np.random.default_rng(0)
    crops = rng.standard_normal(crops.shape).astype(np.float32)
    with torch.no_grad():
        ref_img = _features(clip.model.get_image_features(pixel_values=torch.from_numpy(crops))).numpy()
        ref_txt = _features(clip.model.get_text_features(input_ids=text[0], attention_mask=text[1])).numpy()
    got_img = ort.InferenceSession(str(image_path), providers=["CPUExecutionProvider"]).run(None, {"crops": crops})[0]
    got_txt = ort.InferenceSession(str(text_path), providers=["CPUExecutionProvider"]).run(
        None, {"input_ids": text[0].numpy(), "attention_mask": text[1].numpy()}
    )[0]

    def unit(x: np.ndarray) -> np.ndarray:
        return x / np.linalg.norm(x, axis=1, keepdims=True)

    for what, ref, got in (("image", ref_img, got_img), ("text", ref_txt, got_txt)):
        err = float(np.abs(unit(ref) - unit(got)).max())
        if err > 1e-3:
            raise RuntimeError(f"exported CLIP {what} tower differs from torch by {err:.2e} (max abs, unit vectors)")
