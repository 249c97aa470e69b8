#!/usr/bin/env python3
"""Run every benchmark script in bench/ and collect their tables into one markdown report.

    python bench/run_all.py                 # --quick size (CI-sized), report to stdout + bench-report.md
    python bench/run_all.py --full          # full size
    python bench/run_all.py --only eval,codec --out /tmp/report.md

Each ``bench/bench_*.py`` is run as its own process with ``--quick`` (default) or ``--full``;
its stdout (the markdown tables it prints) goes into the report under its name, with its exit
code and wall time. Expected scripts that do not exist are listed as missing; a script that
fails or times out is reported (with the tail of its stderr) and the others still run. Exit
code 0 when every script that exists passed, 1 otherwise.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import os
import platform
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

BENCH_DIR = Path(__file__).resolve().parent
#: The benchmark scripts the project expects (others found in bench/ run too).
EXPECTED = ("codec", "mapping", "sources", "encoders", "eval")


@dataclass
class BenchResult:
    name: str
    path: Path | None
    returncode: int | None  # None = missing
    wall_s: float = 0.0
    stdout: str = ""
    stderr_tail: str = ""
    timed_out: bool = False


def discover(only: list[str] | None, bench_dir: Path = BENCH_DIR) -> list[tuple[str, Path | None]]:
    """(name, path or None if missing) for the expected scripts plus any other bench_*.py."""
    found = {p.stem.removeprefix("bench_"): p for p in sorted(bench_dir.glob("bench_*.py"))}
    names = list(EXPECTED) + sorted(n for n in found if n not in EXPECTED)
    if only:
        unknown = [n for n in only if n not in names]
        if unknown:
            raise SystemExit(f"run_all: unknown benchmark(s) {unknown}; known: {', '.join(names)}")
        names = [n for n in names if n in only]
    return [(n, found.get(n)) for n in names]


def run_one(
    name: str, path: Path, *, size_flag: str, timeout_s: float, extra_env: dict[str, str]
) -> BenchResult:
    """Run one script; never raises for the script's own failures."""
    env = {**os.environ, **extra_env}
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(
            [sys.executable, str(path), size_flag],
            cwd=path.parent.parent,
            env=env,
            capture_output=True,
            text=True,
            timeout=timeout_s,
            check=False,
        )
    except subprocess.TimeoutExpired as exc:
        out = exc.stdout.decode(errors="replace") if isinstance(exc.stdout, bytes) else (exc.stdout or "")
        err = exc.stderr.decode(errors="replace") if isinstance(exc.stderr, bytes) else (exc.stderr or "")
        return BenchResult(name, path, -1, time.perf_counter() - t0, out, err[-2000:], timed_out=True)
    return BenchResult(
        name, path, proc.returncode, time.perf_counter() - t0, proc.stdout, proc.stderr[-2000:]
    )


def render_report(results: list[BenchResult], *, size: str) -> str:
    lines = [
        "# OpenFusion-Z benchmark report",
        "",
        f"Size `{size}`, {_dt.datetime.now().isoformat(timespec='seconds')}, Python {platform.python_version()}, "
        f"{platform.machine()}, {os.cpu_count()} CPU(s).",
        "",
        "| benchmark | status | wall (s) |",
        "|---|---|---|",
    ]
    for r in results:
        if r.returncode is None:
            status = "missing"
        elif r.timed_out:
            status = "**timed out**"
        elif r.returncode == 0:
            status = "ok"
        else:
            status = f"**failed (exit {r.returncode})**"
        lines.append(f"| {r.name} | {status} | {'' if r.returncode is None else f'{r.wall_s:.1f}'} |")
    lines.append("")
    for r in results:
        if r.returncode is None:
            continue
        lines += [f"## {r.name} (`bench/{r.path.name if r.path else ''}`)", ""]
        lines.append(r.stdout.strip() or "_(no output)_")
        lines.append("")
        if r.returncode != 0:
            lines += ["stderr (tail):", "", "```", r.stderr_tail.strip(), "```", ""]
    missing = [r.name for r in results if r.returncode is None]
    if missing:
        lines += ["Missing benchmark scripts: " + ", ".join(f"`bench/bench_{n}.py`" for n in missing), ""]
    return "\n".join(lines)


def main(argv: list[str] | None = None, *, bench_dir: Path = BENCH_DIR) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    size = parser.add_mutually_exclusive_group()
    size.add_argument("--quick", action="store_true", help="CI-sized runs (default)")
    size.add_argument("--full", action="store_true", help="full-size runs")
    parser.add_argument("--only", default=None, help="comma-separated benchmark names (e.g. eval,codec)")
    parser.add_argument(
        "--timeout", type=float, default=None, help="seconds per script (default 600 quick, 7200 full)"
    )
    parser.add_argument(
        "--out", default="bench-report.md", help="report file (default bench-report.md); '-' = stdout only"
    )
    args = parser.parse_args(argv)
    size_flag = "--full" if args.full else "--quick"
    timeout_s = args.timeout if args.timeout is not None else (7200.0 if args.full else 600.0)
    only = (
        [n.strip().removeprefix("bench_").removesuffix(".py") for n in args.only.split(",")]
        if args.only
        else None
    )

    results = []
    for name, path in discover(only, bench_dir):
        if path is None:
            print(f"[run_all] {name}: missing (bench/bench_{name}.py)", file=sys.stderr)
            results.append(BenchResult(name, None, None))
            continue
        print(f"[run_all] {name}: running {path.name} {size_flag} ...", file=sys.stderr, flush=True)
        r = run_one(name, path, size_flag=size_flag, timeout_s=timeout_s, extra_env={"HF_HUB_OFFLINE": "1"})
        state = "timed out" if r.timed_out else f"exit {r.returncode}"
        print(f"[run_all] {name}: {state} in {r.wall_s:.1f} s", file=sys.stderr, flush=True)
        results.append(r)

    report = render_report(results, size=size_flag.removeprefix("--"))
    print(report)
    if args.out != "-":
        out = Path(args.out)
        tmp = out.with_name(f".{out.name}.tmp")
        tmp.write_text(report + "\n", encoding="utf-8")
        tmp.replace(out)
        print(f"[run_all] report written to {out}", file=sys.stderr)
    failed = [r.name for r in results if r.returncode not in (None, 0)]
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
