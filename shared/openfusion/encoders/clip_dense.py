"""The ``clip-dense`` backend: one pass of the CLIP image tower over the whole frame gives a grid of
patch features in the text space; a region's embedding is the confidence-weighted mean of those
features under its mask. The cost does not grow with the number of regions (``clip-regions`` runs
the tower once per region crop).

Construction (MaskCLIP, Zhou et al. 2022): the image tower runs as usual up to its last block; in
the last block the attention is replaced by its value path (``out_proj(v_proj(ln_1(x)))``), so every
patch token keeps its own content instead of being pooled into the class token; then the tower's
final layer norm and the visual projection map each patch into the joint image-text space. We
leave out the last block's residual and MLP (``dense_mode="value"``, the default): ClearCLIP
(Lan et al. 2024) measured that both add noise to dense features; ``dense_mode="value-residual"``
keeps them (MaskCLIP's original block). Weights are the released CLIP weights, unchanged.

Resolution: the frame is resized (not cropped) to ``input_long_side_px`` on its longer side,
both sides rounded to a multiple of the patch size, and the position embeddings are interpolated
to that grid (transformers' ``interpolate_pos_encoding``). Sliding windows of the training size
were the other option; they cost ``windows x`` one pass (6 windows of 224 cover 480x640 at 32 px
overlap) for the same patch density, so the interpolated single pass is the default
(docs/ENCODERS.md has the figures).

Pooling is exact bilinear upsampling of the patch grid to the mask grid followed by a masked sum,
computed without materialising the upsampled features: with separable interpolation matrices
``A_h`` (h x gh) and ``A_w`` (w x gw), sum_yx m[y, x] up[y, x] = sum_ij (A_h^T m A_w)[i, j] F[i, j],
so each mask is first projected onto the patch grid (n x gh x gw) and one matrix product gives all
embeddings. Written by hand because it is three lines of numpy and no library offers the
projected form.

Backends (``backend``):

- ``torch``: fp32 on CPU; on CUDA fp16 with PyTorch's scaled-dot-product attention.
- ``onnx``: the dense tower exported once per (weights, input size) to ONNX and run by
  onnxruntime (CPU, or the CUDA / TensorRT providers when installed).
- ``onnx-int8``: the same export with onnxruntime dynamic int8 quantisation of the matrix
  multiplications (CPU).

Exports are cached in ``$OPENFUSION_CACHE`` (default ``~/.cache/openfusion``) under
``clip-dense/``; ``scripts/export_clip_dense.py`` makes them ahead of time.
"""

from __future__ import annotations

import copy
import functools
import hashlib
import logging
import os
import re
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from openfusion.blas import single_thread_blas
from openfusion.encoders.base import (
    CLIP_DENSE_BACKENDS,
    DEFAULT_DENSE_INPUT_LONG_SIDE_PX,
    DEFAULT_OUTPUT_SCALE,
    MIN_EMBEDDING_NORM,
    EncoderConfigError,
    EncoderError,
    ImageQueryEncoder,
    RegionEncoder,
    RegionObservation,
    check_rgb,
)
from openfusion.encoders.clip_regions import DEFAULT_CLIP_MODEL, LoadedClip, _features, load_clip
from openfusion.encoders.crops import preprocess_image
from openfusion.encoders.proposers import make_proposer
from openfusion.frame import Frame

logger = logging.getLogger(__name__)

DENSE_MODES = ("value", "value-residual")


def dense_input_size(height_px: int, width_px: int, *, patch_px: int, long_side_px: int) -> tuple[int, int]:
    """(H, W) of the tower input for a frame: the longer side ``long_side_px``, aspect kept, both
    rounded to a multiple of ``patch_px`` (at least one patch)."""
    if height_px < 1 or width_px < 1:
        raise EncoderError(f"frame size must be positive, got {height_px}x{width_px}")
    if long_side_px < patch_px:
        raise EncoderConfigError(f"input_long_side_px ({long_side_px}) must be at least the patch size ({patch_px})")
    scale = long_side_px / max(height_px, width_px)

    def snap(v: float) -> int:
        return max(patch_px, int(round(v * scale / patch_px)) * patch_px)

    return snap(height_px), snap(width_px)


def preprocess_dense(rgb: np.ndarray, size_hw: tuple[int, int], mean: tuple, std: tuple) -> np.ndarray:
    """HxWx3 uint8 -> (1, 3, H', W') float32: resized (bicubic, whole frame, no crop), normalised."""
    check_rgb(rgb)
    h, w = size_hw
    img = np.asarray(Image.fromarray(rgb).resize((w, h), Image.Resampling.BICUBIC))
    # one table lookup per channel instead of float arithmetic on every pixel
    lut = (np.arange(256, dtype=np.float32)[None, :] / 255.0 - np.asarray(mean, np.float32)[:, None]) / np.asarray(
        std, np.float32)[:, None]
    out = np.empty((1, 3, h, w), np.float32)
    for c in range(3):
        out[0, c] = lut[c][img[..., c]]
    return out


@functools.lru_cache(maxsize=32)
def bilinear_matrix(out_len: int, in_len: int) -> np.ndarray:
    """(out_len, in_len) float32 weights of 1-D bilinear resampling, half-pixel centres
    (``align_corners=False``, as torch's ``interpolate``), clamped at the borders; each row sums to 1.
    Computed once per size pair (cached, read-only)."""
    src = (np.arange(out_len, dtype=np.float64) + 0.5) * (in_len / out_len) - 0.5
    src = np.clip(src, 0.0, in_len - 1)
    i0 = np.floor(src).astype(np.int64)
    i1 = np.minimum(i0 + 1, in_len - 1)
    frac = src - i0
    m = np.zeros((out_len, in_len), np.float64)
    rows = np.arange(out_len)
    np.add.at(m, (rows, i0), 1.0 - frac)
    np.add.at(m, (rows, i1), frac)
    out = m.astype(np.float32)
    out.flags.writeable = False
    return out


def pool_region_features(conf_maps: np.ndarray, patch_features: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Confidence-weighted mean of bilinearly upsampled patch features under each mask.

    ``conf_maps`` (n, h, w) in [0, 1]; ``patch_features`` (gh, gw, d). Returns (embeddings (n, d)
    unit norm, ok (n,) bool): a region whose mask is empty or whose pooled feature has no norm
    is not ok (its row is zero).

    The three products run on one BLAS thread: they take about a millisecond, and OpenBLAS's
    worker threads, once woken for them, busy-wait afterwards and halve the speed of the next
    tower pass on a 2-core machine (measured: the int8 frame went from 53 to 103 ms between 10
    and 30 regions, the tower alone staying at 42 ms).
    """
    n, h, w = conf_maps.shape
    gh, gw, d = patch_features.shape
    if n == 0:
        return np.zeros((0, d), np.float32), np.zeros(0, bool)
    a_h = bilinear_matrix(h, gh)
    a_w = bilinear_matrix(w, gw)
    with single_thread_blas():
        # (n, h, w) -> (n, gh, gw): A_h^T m A_w for every mask at once
        on_grid = np.matmul(a_h.T, np.matmul(conf_maps.astype(np.float32, copy=False), a_w)).reshape(n, gh * gw)
        pooled = on_grid @ patch_features.reshape(gh * gw, d).astype(np.float32, copy=False)
    mass = on_grid.sum(axis=1)
    norms = np.linalg.norm(pooled, axis=1)
    ok = (mass > MIN_EMBEDDING_NORM) & np.isfinite(norms) & (norms > MIN_EMBEDDING_NORM)
    out = np.zeros((n, d), np.float32)
    out[ok] = pooled[ok] / norms[ok, None]
    return out, ok


def _dense_tower(clip: Any, dense_mode: str) -> Any:
    """A torch module: (1, 3, H, W) normalised pixels -> (1, gh * gw, d) patch features in the joint
    space (not normalised), built from a transformers ``CLIPModel`` (weights shared, not copied)."""
    import torch

    if dense_mode not in DENSE_MODES:
        raise EncoderConfigError(f"unknown dense_mode {dense_mode!r}; known: {', '.join(DENSE_MODES)}")

    class DenseTower(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.vision = clip.vision_model
            self.projection = clip.visual_projection
            self.keep_residual = dense_mode == "value-residual"

        def forward(self, pixel_values: torch.Tensor) -> torch.Tensor:
            x = self.vision.embeddings(pixel_values, interpolate_pos_encoding=True)
            x = self.vision.pre_layrnorm(x)
            layers = self.vision.encoder.layers
            for layer in layers[:-1]:
                out = layer(x, None)
                x = out[0] if isinstance(out, tuple) else out
            last = layers[-1]
            attn = last.self_attn
            v = attn.out_proj(attn.v_proj(last.layer_norm1(x)))
            if self.keep_residual:
                v = x + v
                v = v + last.mlp(last.layer_norm2(v))
            v = self.vision.post_layernorm(v[:, 1:, :])
            return self.projection(v)

    return DenseTower().eval()


def cache_root() -> Path:
    return Path(os.environ.get("OPENFUSION_CACHE") or Path.home() / ".cache" / "openfusion")


def _weights_fingerprint(model: str) -> str:
    """Names a model's weights for the export cache: hub name, or a local folder's files (name, size, mtime)."""
    folder = Path(model).expanduser()
    h = hashlib.sha256(str(model).encode())
    if folder.is_dir():
        for p in sorted(folder.iterdir()):
            if p.is_file():
                st = p.stat()
                h.update(f"{p.name}:{st.st_size}:{st.st_mtime_ns}".encode())
    return h.hexdigest()[:16]


def export_dense_onnx(
    clip: LoadedClip,
    model: str,
    size_hw: tuple[int, int],
    *,
    dense_mode: str = "value",
    int8: bool = False,
    cache_dir: str | Path | None = None,
) -> Path:
    """Export (once, cached) the dense tower for ``size_hw`` to ONNX, optionally int8-quantised
    (onnxruntime dynamic quantisation of MatMul/Gemm weights). Returns the .onnx path."""
    import torch

    root = Path(cache_dir) if cache_dir is not None else cache_root()
    slug = re.sub(r"[^A-Za-z0-9_.-]+", "-", Path(str(model)).name or str(model))[:40]
    base = f"{slug}-{_weights_fingerprint(model)}-{size_hw[0]}x{size_hw[1]}-{dense_mode}"
    out_dir = root / "clip-dense"
    fp32 = out_dir / f"{base}.onnx"
    target = out_dir / f"{base}-int8.onnx" if int8 else fp32
    if target.is_file():
        return target
    out_dir.mkdir(parents=True, exist_ok=True)
    if not fp32.is_file():
        tower = _dense_tower(clip.model.float().cpu(), dense_mode)
        dummy = torch.zeros(1, 3, *size_hw, dtype=torch.float32)
        tmp = fp32.with_suffix(f".tmp{os.getpid()}.onnx")
        import warnings

        with warnings.catch_warnings(), torch.inference_mode():
            warnings.simplefilter("ignore")  # the TorchScript exporter announces its own deprecation
            torch.onnx.export(tower, (dummy,), str(tmp), input_names=["pixel_values"],
                              output_names=["patch_features"], opset_version=17, dynamo=False)
        os.replace(tmp, fp32)
        if clip.device != "cpu":
            clip.model.to(clip.device)
        logger.info("clip-dense: exported %s", fp32)
    if int8:
        from onnxruntime.quantization import QuantType, quantize_dynamic

        tmp = target.with_suffix(f".tmp{os.getpid()}.onnx")
        root_logger = logging.getLogger()
        level = root_logger.level
        root_logger.setLevel(logging.ERROR)  # the quantiser's advice to pre-process goes to the root logger
        try:
            quantize_dynamic(str(fp32), str(tmp), weight_type=QuantType.QInt8, op_types_to_quantize=["MatMul", "Gemm"])
        finally:
            root_logger.setLevel(level)
        os.replace(tmp, target)
        logger.info("clip-dense: quantised %s", target)
    return target


class _TorchDense:
    def __init__(self, clip: LoadedClip, dense_mode: str) -> None:
        import torch

        self.clip = clip
        self.half = clip.device == "cuda"
        self.tower = _dense_tower(clip.model, dense_mode)
        if self.half:
            # an fp16 copy: the loaded CLIP is shared (cached per process) with the text encoder and
            # clip-regions, which run it in fp32; halving it in place would break them
            self.tower = copy.deepcopy(self.tower).half()
        self._torch = torch

    def __call__(self, pixels: np.ndarray) -> np.ndarray:
        torch = self._torch
        with torch.inference_mode():
            x = torch.from_numpy(pixels).to(self.clip.device)
            if self.half:
                x = x.half()
            return self.tower(x)[0].float().cpu().numpy()


class _OnnxDense:
    def __init__(self, path: Path, device: str, *, spinning: bool = True) -> None:
        import onnxruntime as ort

        from openfusion.encoders.device import onnx_providers

        providers = onnx_providers(device)
        if device == "cuda" and "TensorrtExecutionProvider" in ort.get_available_providers():
            providers = ["TensorrtExecutionProvider", *providers]
        options = ort.SessionOptions()
        options.log_severity_level = 3
        options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL  # one chain of blocks: nothing to overlap
        # Idle workers busy-wait between operators (onnxruntime's default, as the crop embedder of
        # clip-regions): 50 against 54-71 ms per int8 frame on a 2-core machine with only niced
        # neighbours, but 1.4x slower when other processes of the same priority want the cores
        # (spinning=False, e.g. beside the geometry service). docs/ENCODERS.md has the figures.
        options.add_session_config_entry("session.intra_op.allow_spinning", "1" if spinning else "0")
        self.session = ort.InferenceSession(str(path), sess_options=options, providers=providers)
        self.path = path

    def __call__(self, pixels: np.ndarray) -> np.ndarray:
        return self.session.run(None, {"pixel_values": pixels})[0][0]


class ClipDenseRegionEncoder(RegionEncoder, ImageQueryEncoder):
    """Proposals (graph segmentation, or an ONNX mask proposer) + per-region means of dense CLIP
    patch features from one pass over the frame; name ``clip-dense``. Options as ``clip-regions``
    (``model``: hub name or ``save_pretrained`` folder; ``device``) plus ``backend``,
    ``input_long_side_px``, ``dense_mode``, ``cache_dir``, ``onnx_spinning`` (onnxruntime's idle
    workers busy-wait: faster alone on a machine, slower beside other busy processes)."""

    def __init__(
        self,
        model: str = DEFAULT_CLIP_MODEL,
        *,
        device: str = "auto",
        embedding_space: str | None = None,
        output_scale: float = DEFAULT_OUTPUT_SCALE,
        mask_model_path: str | Path | None = None,
        proposer_options: dict[str, Any] | None = None,
        backend: str = "torch",
        input_long_side_px: int = DEFAULT_DENSE_INPUT_LONG_SIDE_PX,
        dense_mode: str = "value",
        cache_dir: str | Path | None = None,
        onnx_spinning: bool = True,
    ) -> None:
        super().__init__(output_scale=output_scale)
        backend = str(backend).strip().lower()
        if backend not in CLIP_DENSE_BACKENDS:
            raise EncoderConfigError(f"unknown clip-dense backend {backend!r}; known: {', '.join(CLIP_DENSE_BACKENDS)}")
        if dense_mode not in DENSE_MODES:
            raise EncoderConfigError(f"unknown dense_mode {dense_mode!r}; known: {', '.join(DENSE_MODES)}")
        self.name = "clip-dense"
        self.model_name = str(model)
        self.clip = load_clip(model, device=device, embedding_space=embedding_space)
        self.embedding_space = self.clip.embedding_space
        self.dim = self.clip.dim
        self.backend = backend
        self.dense_mode = dense_mode
        self.input_long_side_px = int(input_long_side_px)
        self.cache_dir = cache_dir
        self.onnx_spinning = bool(onnx_spinning)
        self.patch_px = int(self.clip.model.config.vision_config.patch_size)
        proposer = make_proposer(mask_model_path, proposer_options, device=self.clip.device)
        self.proposer = proposer
        self._runners: dict[tuple[int, int], Any] = {}
        self._lock = threading.Lock()
        self.stats: dict[str, int] = {"frames": 0, "regions": 0, "dropped_zero_embedding": 0}

    def _runner(self, size_hw: tuple[int, int]) -> Any:
        with self._lock:
            runner = self._runners.get(size_hw)
            if runner is None:
                if self.backend == "torch":
                    runner = _TorchDense(self.clip, self.dense_mode)
                else:
                    path = export_dense_onnx(self.clip, self.model_name, size_hw, dense_mode=self.dense_mode,
                                             int8=self.backend == "onnx-int8", cache_dir=self.cache_dir)
                    runner = _OnnxDense(path, "cpu" if self.backend == "onnx-int8" else self.clip.device,
                                        spinning=self.onnx_spinning)
                self._runners[size_hw] = runner
            return runner

    def patch_features(self, rgb: np.ndarray) -> np.ndarray:
        """(gh, gw, d) dense patch features of a whole image (not normalised)."""
        h, w = rgb.shape[:2]
        size_hw = dense_input_size(h, w, patch_px=self.patch_px, long_side_px=self.input_long_side_px)
        spec = self.clip.crop_spec
        pixels = preprocess_dense(rgb, size_hw, spec.mean, spec.std)
        feats = np.asarray(self._runner(size_hw)(pixels), dtype=np.float32)
        gh, gw = size_hw[0] // self.patch_px, size_hw[1] // self.patch_px
        if feats.shape != (gh * gw, self.dim):
            raise EncoderError(f"dense tower returned {feats.shape}, expected ({gh * gw}, {self.dim})")
        return feats.reshape(gh, gw, self.dim)

    def warm_up(self, vocabulary: Sequence[str] = ()) -> None:
        """One tower pass over a blank 640x480 frame (the usual camera size): builds the runner of
        that input size (the onnx session or the torch graph's first run)."""
        self.patch_features(np.zeros((480, 640, 3), np.uint8))

    def encode(self, frame: Frame) -> RegionObservation:
        check_rgb(frame.color)
        out_hw = self.output_size(*frame.color.shape[:2])
        masks = np.clip(np.asarray(self.proposer.propose(frame, out_hw), dtype=np.float32), 0.0, 1.0)
        if masks.ndim != 3 or masks.shape[1:] != out_hw:
            raise EncoderError(f"proposer {self.proposer.name!r} returned masks {masks.shape}, expected (n, {out_hw[0]}, {out_hw[1]})")
        self.stats["frames"] += 1
        if masks.shape[0] == 0:
            return RegionObservation.empty(self.embedding_space, self.dim, *out_hw)
        emb, ok = pool_region_features(masks, self.patch_features(frame.color))
        if not ok.all():
            self.stats["dropped_zero_embedding"] += int((~ok).sum())
            logger.warning("frame %s: %d region(s) with an empty mask or zero pooled feature dropped",
                           frame.frame_id, int((~ok).sum()))
            masks, emb = masks[ok], emb[ok]
        self.stats["regions"] += int(ok.sum())
        return RegionObservation(
            conf_maps=np.ascontiguousarray(masks, dtype=np.float32),
            embeddings=np.ascontiguousarray(emb, dtype=np.float32),
            embedding_space=self.embedding_space,
            labels=None,
        )

    def encode_image(self, rgb: np.ndarray) -> np.ndarray:
        """An image query: the standard pooled CLIP image embedding (the same as ``clip-regions``)."""
        import torch

        batch = preprocess_image(rgb, self.clip.crop_spec)
        with torch.inference_mode():
            x = torch.from_numpy(batch).to(self.clip.device)
            e = _features(self.clip.model.get_image_features(pixel_values=x)).float().cpu().numpy()[0]
        n = float(np.linalg.norm(e))
        if not np.isfinite(n) or n < MIN_EMBEDDING_NORM:
            raise EncoderError("the image embedding has zero or non-finite norm")
        return (e / n).astype(np.float32)
