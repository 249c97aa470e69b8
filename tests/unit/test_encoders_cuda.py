"""The CUDA paths of the CLIP encoders, on a tiny random-weight CLIP saved by the test.

Skipped where torch sees no GPU (CI, the 2-core box); run on a GPU machine with
``python -m pytest tests/unit/test_encoders_cuda.py``. What a user on a GPU box would notice if it
broke: the model does not load onto the GPU, loads with eager attention (slower, not the fused
scaled-dot-product kernels), or answers with other embeddings than the CPU does for the same frame.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from openfusion.encoders import make_region_encoder, select_device
from openfusion.encoders.device import cuda_available
from openfusion.testing.images import grid_boxes, make_box_frame
from openfusion.testing.models import build_tiny_clip

pytestmark = [pytest.mark.gpu, pytest.mark.skipif(not cuda_available(), reason="needs a CUDA GPU")]


@pytest.fixture(scope="module")
def clip_dir(tmp_path_factory):
    return build_tiny_clip(tmp_path_factory.mktemp("clip") / "tiny-clip")


@pytest.fixture(scope="module")
def frame():
    return make_box_frame(grid_boxes(height_px=480, width_px=640, rows=2, cols=3, categories=["x"], gap_px=8, seed=3))


def _cosines(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    assert a.shape == b.shape
    return np.sum(a * b, axis=1) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))


def test_auto_picks_the_gpu():
    assert select_device("auto") == "cuda"


def test_clip_regions_on_cuda_uses_sdpa_and_answers_as_on_cpu(clip_dir, frame):
    gpu = make_region_encoder("clip-regions", model=str(clip_dir), device="cuda")
    cpu = make_region_encoder("clip-regions", model=str(clip_dir), device="cpu")
    model = gpu.embedder.clip.model
    assert next(model.parameters()).device.type == "cuda"
    assert model.config._attn_implementation == "sdpa"
    assert cpu.embedder.clip.model.config._attn_implementation == "eager"  # what the ONNX export traces
    on_gpu, on_cpu = gpu.encode(frame), cpu.encode(frame)
    np.testing.assert_array_equal(on_gpu.conf_maps, on_cpu.conf_maps)  # proposals run on the CPU in both
    assert _cosines(on_gpu.embeddings, on_cpu.embeddings).min() > 0.999


def test_clip_dense_on_cuda_runs_fp16_and_answers_as_fp32_on_cpu(clip_dir, frame):
    gpu = make_region_encoder("clip-dense", model=str(clip_dir), device="cuda", backend="torch")
    cpu = make_region_encoder("clip-dense", model=str(clip_dir), device="cpu", backend="torch")
    gpu.warm_up()
    on_gpu, on_cpu = gpu.encode(frame), cpu.encode(frame)
    assert on_gpu.num_regions == on_cpu.num_regions > 0
    assert _cosines(on_gpu.embeddings, on_cpu.embeddings).min() > 0.99  # fp16 tower against fp32
    # the loaded CLIP is shared in the process: clip-dense's fp16 tower must leave it fp32 for the
    # text encoder and clip-regions
    regions = make_region_encoder("clip-regions", model=str(clip_dir), device="cuda")
    assert regions.embedder.clip.model is gpu.clip.model
    assert {p.dtype for p in gpu.clip.model.parameters()} == {torch.float32}
    assert regions.encode(frame).num_regions > 0
