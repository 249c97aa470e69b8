"""``openfusion query --map-dir`` as a user runs it (subprocesses): answers from the map's region
summaries equal those from the whole map, small fragments are not answers, maps saved before
summaries still answer, and a text query loads neither the volume nor torch."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from openfusion.encoders import make_text_encoder
from openfusion.mapping import load_map, query_regions, save_map
from openfusion.testing.bus import subprocess_env
from openfusion.testing.maps import (
    SyntheticMapSpec,
    build_synthetic_map,
    plant_small_region,
    strip_region_summaries,
)

ROOT = next(p for p in Path(__file__).resolve().parents if (p / "pyproject.toml").is_file())
_SCRIPT = Path(sys.executable).parent / "openfusion"
OPENFUSION = [str(_SCRIPT)] if _SCRIPT.exists() else [sys.executable, "-m", "openfusion.app.cli"]
HEAVY = ("torch", "transformers", "sentence_transformers", "open3d", "scipy", "zenoh")

pytestmark = pytest.mark.timeout(240)


@pytest.fixture(scope="module")
def maps(tmp_path_factory: pytest.TempPathFactory) -> dict[str, object]:
    """A small MiniLM map of the synthetic room plus a 'chair fragment': a region of a few points
    with the chair's embedding (it ties with the chair at score 1); saved with summaries
    (``new``) and as maps were saved before them (``old``)."""
    tmp = tmp_path_factory.mktemp("saved-maps")
    built = load_map(build_synthetic_map(tmp / "built", SyntheticMapSpec(text_encoder="minilm")))
    chair = next(int(k) for k in built.dictionary.snapshot().keys if built.dictionary.label(int(k)) == "chair")
    volume, dictionary, fragment = plant_small_region(built.volume, built.dictionary, like_key=chair,
                                                      label="chair fragment")
    new = save_map(tmp / "new", volume, dictionary).parent
    old = strip_region_summaries(new, tmp / "old").parent
    office_chair = next(int(k) for k in dictionary.snapshot().keys if dictionary.label(int(k)) == "office chair")
    return {"new": new, "old": old, "volume": volume, "dictionary": dictionary, "chair": chair,
            "office_chair": office_chair, "fragment": fragment}


def _query(map_dir: Path, cache: Path, *args: str) -> subprocess.CompletedProcess[str]:
    proc = subprocess.run(
        [*OPENFUSION, "query", "--map-dir", str(map_dir), *args],
        capture_output=True, text=True, timeout=180, cwd=ROOT,
        env=subprocess_env(HF_HUB_OFFLINE="1", OPENFUSION_CACHE=str(cache)),
    )
    assert proc.returncode == 0, proc.stderr
    return proc


def _regions(proc: subprocess.CompletedProcess[str]) -> list[dict]:
    return json.loads(proc.stdout)["regions"]


def test_summary_answer_equals_the_full_map_answer_and_leaves_out_the_fragment(maps, minilm_onnx_cache) -> None:
    """The command's top regions (keys, scores, counts, boxes) are those of loading the whole map
    and querying it in process with the same text encoder (MiniLM through onnxruntime, which
    embeds like sentence-transformers: tests/unit/test_encoders_text.py); the few-point fragment
    that ties with the chair is not among them unless --min-region-points lets it in."""
    text = make_text_encoder("minilm", backend="onnxruntime", device="cpu", cache_dir=minilm_onnx_cache)
    for query in ("chair", "something to sit on"):
        got = _regions(_query(maps["new"], minilm_onnx_cache, query, "--json", "--top-k", "5"))
        want = query_regions(maps["dictionary"], maps["volume"], text.encode([query])[0], 5)
        assert [r["key"] for r in got] == [r.key for r in want] and len(got) == 5
        for g, w in zip(got, want, strict=True):
            assert g["score"] == pytest.approx(w.score, abs=1e-4) and g["num_points"] == w.num_points
            np.testing.assert_allclose(g["bbox_min"], w.bbox_min, atol=1.5e-3)
            np.testing.assert_allclose(g["bbox_max"], w.bbox_max, atol=1.5e-3)
        assert maps["fragment"] not in [r["key"] for r in got]
        assert all(r["num_points"] >= 50 for r in got)
    chair = _regions(_query(maps["new"], minilm_onnx_cache, "chair", "--json", "--top-k", "3"))
    assert chair[0]["key"] == maps["chair"] and chair[0]["score"] == pytest.approx(1.0, abs=1e-4)
    small = _regions(_query(maps["new"], minilm_onnx_cache, "chair", "--json", "--top-k", "3",
                            "--min-region-points", "1"))
    assert maps["fragment"] in [r["key"] for r in small[:2]]


def test_map_saved_before_summaries_still_answers(maps, minilm_onnx_cache) -> None:
    """A map without summaries gives the same answer (from the whole map) with one line saying so."""
    new = _query(maps["new"], minilm_onnx_cache, "chair", "--json")
    old = _query(maps["old"], minilm_onnx_cache, "chair", "--json")
    assert _regions(old) == _regions(new)
    assert "no region summaries" in old.stderr and "no region summaries" not in new.stderr


def test_points_come_from_the_whole_map(maps, minilm_onnx_cache, tmp_path) -> None:
    """--out needs the points, so it reads the volume; the ranking is the same."""
    out = tmp_path / "chair.ply"
    proc = _query(maps["new"], minilm_onnx_cache, "chair", "--json", "--top-k", "2", "--out", str(out))
    assert [r["key"] for r in _regions(proc)] == [maps["chair"], maps["office_chair"]]
    assert out.stat().st_size > 0 and f"to {out}" in proc.stderr


def test_a_text_query_of_a_saved_map_imports_no_torch_and_no_volume(maps, minilm_onnx_cache) -> None:
    """With the MiniLM export cached, answering reads the summaries and runs onnxruntime: neither
    torch, transformers, sentence-transformers, Open3D, SciPy nor Zenoh gets imported."""
    code = (
        "import json, sys\n"
        "from openfusion.app.cli import main\n"
        f"rc = main(['query', '--map-dir', {str(maps['new'])!r}, 'chair', '--json'])\n"
        f"heavy = sorted({{m.split('.')[0] for m in sys.modules}} & set({HEAVY!r}))\n"
        "print(json.dumps({'rc': rc, 'heavy': heavy}))\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=ROOT,
                          env=subprocess_env(HF_HUB_OFFLINE="1", OPENFUSION_CACHE=str(minilm_onnx_cache)))
    assert proc.returncode == 0, proc.stderr
    report = json.loads(proc.stdout.strip().splitlines()[-1])
    assert report == {"rc": 0, "heavy": []}, proc.stderr
