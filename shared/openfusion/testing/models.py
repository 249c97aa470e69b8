"""Tiny random-weight models written to disk, for tests and CPU benchmarks of the model backends.

They check loading, shapes and plumbing, not quality (quality is measured with the gt encoder).
Everything is built locally: a tiny CLIP (transformers ``CLIPModel`` from a small ``CLIPConfig``
plus a small BPE ``CLIPTokenizer``), and tiny ONNX region / mask / text models that follow the
contract in docs/ENCODERS.md (exported with torch's TorchScript exporter, ``dynamo=False``).
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path
from typing import Any

from openfusion.encoders.clip_export import set_onnx_metadata
from openfusion.encoders.crops import CLIP_MEAN, CLIP_STD

TINY_WORDS = [
    "chair", "office", "table", "sofa", "bed", "lamp", "door", "wall", "floor", "plant",
    "a", "photo", "of", "the", "red", "blue",
]  # fmt: skip


def build_tiny_clip(
    folder: str | Path,
    *,
    projection_dim: int = 16,
    image_size: int = 32,
    patch_size: int = 8,
    embedding_space: str | None = "tiny-clip-random",
    seed: int = 0,
) -> Path:
    """Save a random-weight CLIPModel + CLIPTokenizer (a few hundred KB) into ``folder``.

    With ``embedding_space`` an ``openfusion_encoder.json`` naming it is written too.
    """
    import torch
    from transformers import CLIPConfig, CLIPModel, CLIPTokenizer

    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    letters = [chr(c) for c in range(ord("a"), ord("z") + 1)]
    vocab: dict[str, int] = {"<|startoftext|>": 0, "<|endoftext|>": 1}
    for tok in letters + [f"{c}</w>" for c in letters]:
        vocab[tok] = len(vocab)
    merges = [("c", "h"), ("a", "i"), ("ch", "ai"), ("t", "a"), ("b", "l"), ("l", "e</w>")]
    for a, b in merges:
        vocab.setdefault(a + b, len(vocab))
    tokenizer = CLIPTokenizer(vocab=vocab, merges=merges)
    config = CLIPConfig(
        text_config=dict(
            vocab_size=len(vocab),
            hidden_size=32,
            intermediate_size=37,
            num_hidden_layers=2,
            num_attention_heads=2,
            max_position_embeddings=16,
            bos_token_id=0,
            eos_token_id=1,
            pad_token_id=1,
        ),
        vision_config=dict(
            hidden_size=32,
            intermediate_size=37,
            num_hidden_layers=2,
            num_attention_heads=2,
            image_size=image_size,
            patch_size=patch_size,
        ),
        projection_dim=projection_dim,
    )
    torch.manual_seed(seed)
    model = CLIPModel(config).eval()
    model.save_pretrained(str(out))
    tokenizer.save_pretrained(str(out))
    if embedding_space:
        (out / "openfusion_encoder.json").write_text(json.dumps({"embedding_space": embedding_space}), encoding="utf-8")
    return out


def _export(module: Any, args: tuple, path: Path, input_names: list[str], output_names: list[str], dynamic_axes: dict) -> None:
    import torch

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the TorchScript exporter warns about its own deprecation
        torch.onnx.export(
            module, args, str(path), input_names=input_names, output_names=output_names,
            dynamic_axes=dynamic_axes, opset_version=17, dynamo=False,
        )  # fmt: skip


def build_tiny_region_onnx(
    path: str | Path,
    *,
    dim: int = 16,
    num_regions: int = 6,
    input_hw: tuple[int, int] = (48, 64),
    embedding_space: str = "tiny-onnx-random",
    output_names: tuple[str, str] = ("conf_maps", "embeddings"),
    with_valid: bool = True,
    squeeze_embeddings: bool = False,
    conf_logits: bool = False,
    metadata: dict[str, Any] | None = None,
    seed: int = 0,
) -> Path:
    """A ``region-model``: image [1,3,H,W] -> conf_maps [1,N,H/4,W/4], embeddings [1,N,dim] (+ valid [1,N]).

    ``output_names``, ``squeeze_embeddings`` (rank-2 embeddings) and ``metadata`` let tests build
    models that break the contract on purpose.
    """
    import torch
    from torch import nn

    torch.manual_seed(seed)

    class TinyRegions(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.backbone = nn.Sequential(
                nn.Conv2d(3, 8, 3, stride=2, padding=1), nn.ReLU(), nn.Conv2d(8, 8, 3, stride=2, padding=1), nn.ReLU()
            )
            self.mask_head = nn.Conv2d(8, num_regions, 1)
            self.proj = nn.Linear(8, dim)

        def forward(self, image: torch.Tensor):  # noqa: ANN201
            feats = self.backbone(image)  # 1,8,h,w
            logits = self.mask_head(feats) * 4.0  # 1,N,h,w
            conf = torch.sigmoid(logits)
            pooled = torch.einsum("bnhw,bchw->bnc", conf, feats) / (conf.sum(dim=(2, 3))[..., None] + 1e-6)
            emb = self.proj(pooled)  # 1,N,dim
            if squeeze_embeddings:
                emb = emb[0]
            outs = (logits if conf_logits else conf, emb)
            if with_valid:
                outs = outs + (conf.amax(dim=(2, 3)) > 0.5,)
            return outs

    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    names = list(output_names) + (["valid"] if with_valid else [])
    _export(TinyRegions().eval(), (torch.zeros(1, 3, *input_hw),), out, ["image"], names, {})
    meta = {
        "kind": "region-model",
        "embedding_space": embedding_space,
        "dim": dim,
        "input_height": input_hw[0],
        "input_width": input_hw[1],
        "mean": list(CLIP_MEAN),
        "std": list(CLIP_STD),
        "conf_maps_are": "logits" if conf_logits else "probability",
    }
    meta.update(metadata or {})
    set_onnx_metadata(out, meta)
    return out


def build_tiny_mask_proposer_onnx(
    path: str | Path, *, num_masks: int = 5, input_hw: tuple[int, int] = (48, 64), seed: int = 0
) -> Path:
    """A SAM-style ``mask-proposer``: image [1,3,H,W] -> masks (logits) [1,N,H/2,W/2], scores [1,N]."""
    import torch
    from torch import nn

    torch.manual_seed(seed)

    class TinyMasks(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.net = nn.Sequential(nn.Conv2d(3, 8, 3, stride=2, padding=1), nn.ReLU(), nn.Conv2d(8, num_masks, 1))

        def forward(self, image: torch.Tensor):  # noqa: ANN201
            logits = self.net(image) * 4.0
            return logits, torch.sigmoid(logits).mean(dim=(2, 3))

    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    _export(TinyMasks().eval(), (torch.zeros(1, 3, *input_hw),), out, ["image"], ["masks", "scores"], {})
    set_onnx_metadata(
        out,
        {
            "kind": "mask-proposer",
            "input_height": input_hw[0],
            "input_width": input_hw[1],
            "mean": list(CLIP_MEAN),
            "std": list(CLIP_STD),
            "masks_are": "logits",
        },
    )
    return out


def build_tiny_text_onnx(
    folder: str | Path,
    *,
    dim: int = 16,
    embedding_space: str = "tiny-onnx-random",
    words: list[str] | None = None,
    file_name: str = "text.onnx",
    output_name: str = "text_embeddings",
    seed: int = 0,
) -> Path:
    """A ``text-model`` (bag of word embeddings -> linear) and its WordLevel ``tokenizer.json``."""
    import torch
    from tokenizers import Tokenizer, models, normalizers, pre_tokenizers
    from torch import nn

    torch.manual_seed(seed)
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    vocab = {"[PAD]": 0, "[UNK]": 1}
    for w in words or TINY_WORDS:
        vocab.setdefault(w, len(vocab))
    tok = Tokenizer(models.WordLevel(vocab=vocab, unk_token="[UNK]"))
    tok.normalizer = normalizers.Lowercase()
    tok.pre_tokenizer = pre_tokenizers.Whitespace()
    tok.save(str(out / "tokenizer.json"))

    class TinyText(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.embed = nn.Embedding(len(vocab), 16)
            self.proj = nn.Linear(16, dim)

        def forward(self, input_ids: torch.Tensor, attention_mask: torch.Tensor) -> torch.Tensor:
            m = attention_mask.unsqueeze(-1).float()
            pooled = (self.embed(input_ids) * m).sum(1) / m.sum(1).clamp(min=1.0)
            return self.proj(pooled)

    path = out / file_name
    ids = torch.ones(2, 5, dtype=torch.long)
    _export(
        TinyText().eval(),
        (ids, torch.ones_like(ids)),
        path,
        ["input_ids", "attention_mask"],
        [output_name],
        {"input_ids": {0: "batch", 1: "length"}, "attention_mask": {0: "batch", 1: "length"}, output_name: {0: "batch"}},
    )
    set_onnx_metadata(path, {"kind": "text-model", "embedding_space": embedding_space, "dim": dim, "pad_id": 0})
    return path


#: Real CLIP image-tower sizes (transformers ``CLIPVisionConfig`` fields) for benches with random
#: weights: the same compute as the released models, no download.
CLIP_PRESETS: dict[str, dict[str, int]] = {
    "vit-b-32": dict(hidden_size=768, intermediate_size=3072, num_hidden_layers=12, num_attention_heads=12,
                     image_size=224, patch_size=32, projection_dim=512),
    "vit-b-16": dict(hidden_size=768, intermediate_size=3072, num_hidden_layers=12, num_attention_heads=12,
                     image_size=224, patch_size=16, projection_dim=512),
    "vit-l-14-336": dict(hidden_size=1024, intermediate_size=4096, num_hidden_layers=24, num_attention_heads=16,
                         image_size=336, patch_size=14, projection_dim=768),
}


def register_random_clip(preset: str, *, device: str = "cpu", seed: int = 0) -> str:
    """Build a random-weight CLIP with a real-size image tower (``CLIP_PRESETS``; a tiny text tower)
    in memory and register it with :func:`openfusion.encoders.clip_regions.load_clip` under the name
    ``random/<preset>`` (space ``random-<preset>``), so ``make_region_encoder("clip-dense",
    model="random/<preset>")`` uses it without writing gigabytes of weights. Returns that name."""
    import torch
    from transformers import CLIPConfig, CLIPModel

    from openfusion.encoders import clip_regions
    from openfusion.encoders.crops import CropSpec

    spec = dict(CLIP_PRESETS[preset])
    projection_dim = spec.pop("projection_dim")
    name, space = f"random/{preset}", f"random-{preset}"
    config = CLIPConfig(
        text_config=dict(vocab_size=64, hidden_size=32, intermediate_size=37, num_hidden_layers=1,
                         num_attention_heads=2, max_position_embeddings=16, bos_token_id=0, eos_token_id=1,
                         pad_token_id=1),
        vision_config=spec,
        projection_dim=projection_dim,
    )
    torch.manual_seed(seed)
    model = CLIPModel(config).eval().to(device)
    loaded = clip_regions.LoadedClip(
        model=model, tokenizer=None, embedding_space=space, dim=projection_dim,
        crop_spec=CropSpec(size=spec["image_size"], mean=CLIP_MEAN, std=CLIP_STD), device=device, max_text_length=16,
    )
    with clip_regions._LOCK:
        clip_regions._CACHE[(name, device, "")] = loaded
    return name
