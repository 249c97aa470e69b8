"""bench/run_all.py: runs every bench script, collects their tables, reports missing and failing ones."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

ROOT = next(p for p in Path(__file__).resolve().parents if (p / "pyproject.toml").is_file())


def _load_run_all():
    spec = importlib.util.spec_from_file_location("run_all", ROOT / "bench" / "run_all.py")
    module = importlib.util.module_from_spec(spec)
    assert spec.loader is not None
    sys.modules["run_all"] = module
    spec.loader.exec_module(module)
    return module


def test_report_collects_tables_and_flags_missing_and_failing(tmp_path: Path) -> None:
    """A script that fails must not stop the others, must make the exit code 1 and show its
    stderr; expected scripts that do not exist are listed as missing; --full reaches the scripts."""
    run_all = _load_run_all()
    bench = tmp_path / "bench"
    bench.mkdir()
    (bench / "bench_eval.py").write_text(
        "import sys\nprint('| size | value |')\nprint('|---|---|')\nprint(f'| {sys.argv[1]} | 42 |')\n"
    )
    (bench / "bench_codec.py").write_text("import sys\nprint('boom', file=sys.stderr)\nsys.exit(3)\n")
    (bench / "bench_extra.py").write_text("print('extra table')\n")
    out = tmp_path / "report.md"
    rc = run_all.main(["--full", "--out", str(out)], bench_dir=bench)
    assert rc == 1
    report = out.read_text()
    assert "| --full | 42 |" in report  # the eval script's table, run with --full
    assert "| codec | **failed (exit 3)** |" in report and "boom" in report
    assert "| mapping | missing |" in report and "`bench/bench_sources.py`" in report
    assert "extra table" in report  # scripts beyond the expected ones run too


def test_unknown_only_name_is_refused(tmp_path: Path) -> None:
    """A typo in --only is an error naming the known benchmarks, not a silent empty report."""
    run_all = _load_run_all()
    with pytest.raises(SystemExit, match="unknown benchmark"):
        run_all.main(["--only", "evl", "--out", "-"], bench_dir=tmp_path)


def test_every_bench_script_takes_the_size_flags_run_all_passes() -> None:
    """run_all passes --quick or --full to every bench script; a script that does not declare one
    fails under it with an argparse error (bench_bridge, _encoders, _mapping and _services did)."""
    scripts = sorted((ROOT / "bench").glob("bench_*.py"))
    assert scripts
    missing = [p.name for p in scripts
               if not all(f'add_argument("{flag}"' in p.read_text() for flag in ("--quick", "--full"))]
    assert not missing, f"bench scripts without --quick or --full: {missing}"
