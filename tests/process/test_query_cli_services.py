"""``openfusion query`` against running services, as a user runs it (a subprocess): the answer
alone on stdout and nothing on stderr, one text as always, several texts in one round trip (one
request, one encoder call in the query service) printed one block per text in order, ``--json``
one object or a list. The query service runs in this process on a real bus (hash text encoder, a
dictionary and region summaries given to it, so no other service is needed)."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from openfusion.app.outputs import region_record
from openfusion.bus import RequestError
from openfusion.encoders import make_text_encoder
from openfusion.mapping import RegionDictionary
from openfusion.services.query.service import QueryConfig, QueryService, RegionSummaries
from openfusion.testing.bus import (
    ServiceThread,
    free_port,
    loopback_args,
    loopback_config,
    subprocess_env,
    unique_map_id,
)
from openfusion.testing.encoders import CountingTextEncoder
from openfusion.wire.counters import QueryCounter
from openfusion.wire.schemas import RegionSummaryReply, TextQuery

ROOT = next(p for p in Path(__file__).resolve().parents if (p / "pyproject.toml").is_file())
_SCRIPT = Path(sys.executable).parent / "openfusion"
OPENFUSION = [str(_SCRIPT)] if _SCRIPT.exists() else [sys.executable, "-m", "openfusion.app.cli"]
TEXT = make_text_encoder("hash")
NAMES = ("chair", "table", "lamp", "sofa", "plant")

pytestmark = pytest.mark.timeout(180)




@pytest.fixture(scope="module")
def service() -> Iterator[tuple[ServiceThread, int]]:
    """The query service listening on a free loopback port, and that port."""
    port = free_port()
    base = loopback_config(unique_map_id("cli"), listen=[port]).model_dump()
    # no text cache: every request's texts reach the encoder (the tests count its calls)
    config = QueryConfig.model_validate({**base, "query": {"text_encoder": "hash", "summary_max_age_s": 3600,
                                                            "summary_refresh_s": 3600, "text_cache_size": 0}})
    app = QueryService(config, text_encoder=CountingTextEncoder())
    dictionary = RegionDictionary(TEXT.embedding_space, TEXT.dim)
    for name in NAMES:
        dictionary.add(TEXT.encode([name])[0], label=name)
    app.replica.apply_snapshot(dictionary.snapshot())
    n = len(NAMES)
    lo = np.arange(n * 3, dtype=np.float32).reshape(n, 3)
    app.summaries = RegionSummaries(
        RegionSummaryReply(map_version=1, key_horizon=n, keys=np.arange(n, dtype=np.int32), bbox_min=lo,
                           bbox_max=lo + 1.0, num_points=np.full(n, 100, np.int64)),
        fetched_at=time.monotonic(),
    )
    with ServiceThread(app, config, "query") as thread:
        yield thread, port


def _query(service: tuple[ServiceThread, int], *args: str) -> str:
    """stdout of ``openfusion query ARGS`` against the service; it must succeed and print nothing on stderr."""
    thread, port = service
    proc = subprocess.run(
        [*OPENFUSION, "query", *args, *loopback_args(thread.runner.config.map_id, connect=[port])],
        capture_output=True, text=True, timeout=120, cwd=ROOT, env=subprocess_env(),
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr == "", proc.stderr
    return proc.stdout


def test_a_query_of_running_services_prints_its_answer_and_nothing_else(service) -> None:
    """One text: the one-text endpoint, its answer as before; several: one request and one encoder
    call for all, one block per text in order (the concatenation of the one-text outputs), and
    --json a list of the one-text objects."""
    thread, _port = service
    encoder = thread.app.text_encoder
    texts = ["table", "chair", "lamp"]
    one = json.loads(_query(service, "chair", "--top-k", "2", "--json"))
    want = thread.app.handle_text(TextQuery(text="chair", top_k=2))
    assert one == {"query": "chair", "embedding_space": TEXT.embedding_space,
                   "regions": [region_record(r) for r in want.regions]}
    alone = [_query(service, t, "--top-k", "2") for t in texts]
    assert alone[0].startswith(f"'table' in {TEXT.embedding_space}:\n  key      1  score 1.000  table")
    encoder.calls.clear()
    queries = thread.counter(QueryCounter.QUERIES)
    assert _query(service, *texts, "--top-k", "2") == "".join(alone)
    assert encoder.calls == [texts] and thread.counter(QueryCounter.QUERIES) == queries + 3
    objects = [json.loads(_query(service, t, "--top-k", "2", "--json")) for t in texts]
    listed = _query(service, *texts, "--top-k", "2", "--json")
    assert listed.count("\n") == 1 and json.loads(listed) == objects
    assert [o["regions"][0]["label"] for o in objects] == texts


def _refused(service: tuple[ServiceThread, int], *args: str) -> str:
    """The one stderr line of ``openfusion query ARGS`` against the service; it must exit 2 with
    nothing on stdout and no traceback."""
    thread, port = service
    proc = subprocess.run(
        [*OPENFUSION, "query", *args, *loopback_args(thread.runner.config.map_id, connect=[port])],
        capture_output=True, text=True, timeout=120, cwd=ROOT, env=subprocess_env(),
    )
    assert proc.returncode == 2 and proc.stdout == "", (proc.returncode, proc.stdout, proc.stderr)
    lines = proc.stderr.splitlines()
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert lines[0].startswith("openfusion query: error: "), lines[0]
    return lines[0].removeprefix("openfusion query: error: ")


def test_a_value_past_a_limit_is_one_line_and_exit_2_wherever_it_is_caught(service, monkeypatch) -> None:
    """Issue 32: `--top-k 1000000000` (or 20000) printed a pydantic traceback and exited 1, while
    -1 and 0 gave one line and exit 2; a 600-character text was refused by the service (exit 1) and
    a 5000-character one by the command (exit 2). Now every value past a limit of
    openfusion.wire.limits is one line and exit 2, the same line the page and the Python client
    give, before anything reaches the service; and a refusal of the service itself for a limit
    (code too_large, as an older service with other limits would answer) is exit 2 too."""
    thread, _port = service
    before = thread.counter(QueryCounter.QUERIES)
    for top_k in ("1000000000", "20000", "101", "0", "-1"):
        assert _refused(service, "chair", "--top-k", top_k) == f"--top-k must be from 1 to 100, got {top_k}"
    for n in (513, 600, 5000):
        assert _refused(service, "x" * n) == f"the query text has {n} characters; the limit is 512"
    assert _refused(service, "chair", "x" * 600) == "the query text 2 of 2 has 600 characters; the limit is 512"
    assert thread.counter(QueryCounter.QUERIES) == before  # nothing reached the service

    def tighter(top_k: int, max_points: int) -> None:
        raise RequestError("too_large", "top_k must be from 1 to 3, got 5")

    monkeypatch.setattr(thread.app, "_check_limits", tighter)
    assert _refused(service, "chair", "--top-k", "5") == "top_k must be from 1 to 3, got 5"
