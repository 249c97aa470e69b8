"""The one place that picks compute devices for encoders (torch and onnxruntime)."""

from __future__ import annotations

import logging

logger = logging.getLogger(__name__)

DEVICE_PREFERENCES = ("auto", "cpu", "cuda")


def cuda_available() -> bool:
    """True when torch is importable and sees a CUDA device."""
    try:
        import torch
    except ImportError:
        return False
    return bool(torch.cuda.is_available())


def select_device(preference: str = "auto") -> str:
    """Return ``"cpu"`` or ``"cuda"``.

    ``"auto"`` picks CUDA when torch sees a GPU, else CPU. ``"cuda"`` without a GPU is an error
    (asking for a GPU and silently running on CPU hides a misconfigured deployment).
    """
    pref = str(preference).strip().lower()
    if pref not in DEVICE_PREFERENCES:
        raise ValueError(f"device preference must be one of {', '.join(DEVICE_PREFERENCES)}, got {preference!r}")
    if pref == "cpu":
        return "cpu"
    has_cuda = cuda_available()
    if pref == "cuda" and not has_cuda:
        raise RuntimeError("device 'cuda' requested but torch sees no CUDA device (torch.cuda.is_available() is False)")
    device = "cuda" if has_cuda else "cpu"
    logger.debug("select_device(%r) -> %s", preference, device)
    return device


def select_onnx_device(preference: str = "auto") -> str:
    """Return ``"cpu"`` or ``"cuda"`` for a model run by onnxruntime, without importing torch where
    it cannot matter.

    ``"auto"`` is CPU when the installed onnxruntime has no CUDA provider (the plain ``onnxruntime``
    package); otherwise (``onnxruntime-gpu``) and for ``"cuda"`` the choice is :func:`select_device`'s.
    """
    pref = str(preference).strip().lower()
    if pref == "auto":
        import onnxruntime as ort

        if "CUDAExecutionProvider" not in ort.get_available_providers():
            return "cpu"
    return select_device(pref)


def onnx_providers(device: str) -> list[str]:
    """onnxruntime execution providers for ``device`` ("cpu" or "cuda"), best first.

    For "cuda" this is ``["CUDAExecutionProvider", "CPUExecutionProvider"]`` when the installed
    onnxruntime has the CUDA provider (package onnxruntime-gpu), else CPU only with a warning.
    """
    if device not in ("cpu", "cuda"):
        raise ValueError(f"device must be 'cpu' or 'cuda' (see select_device), got {device!r}")
    import onnxruntime as ort

    available = ort.get_available_providers()
    if device == "cuda":
        if "CUDAExecutionProvider" in available:
            return ["CUDAExecutionProvider", "CPUExecutionProvider"]
        logger.warning(
            "device 'cuda' selected but onnxruntime has no CUDAExecutionProvider (providers: %s); "
            "install onnxruntime-gpu. Running ONNX models on CPU.",
            ", ".join(available),
        )
    return ["CPUExecutionProvider"]
