"""Flags that do what their help says (docs/CLI.md), where the fix was a behaviour and not a
refusal (refusals are in tests/unit/test_cli_errors.py's table): a live source capped by
``--rate-hz`` without waiting, ``--max-frames`` of a live source, ``openfusion run --in-process
--timeout-s``, a run's progress on stderr; and valid combinations next to the refused ones still
accepted."""

from __future__ import annotations

import time
from dataclasses import dataclass

import pytest

from openfusion.app import cli
from openfusion.app.launcher import RunError, StopSignals
from openfusion.app.outputs import say_progress
from openfusion.app.run_in_process import _UntilStopped
from openfusion.bus.stats import ServiceStats
from openfusion.services.bridge.service import BridgeConfig, BridgeSection, BridgeService, Pacer
from openfusion.sources.base import FrameSource
from openfusion.wire.counters import BridgeCounter


def test_a_live_source_keeps_to_rate_hz_by_dropping_frames_never_by_waiting() -> None:
    """A 30 Hz sensor at --rate-hz 10: exactly 10 frames a second go out, each as it comes;
    after a pause the next frame goes at once; no rate (None or 0) keeps every frame."""
    pacer = Pacer(10.0)
    arrivals = [i / 30.0 for i in range(90)]  # 3 s of a 30 Hz camera
    kept = [t for t in arrivals if pacer.take_live(t)]
    assert len(kept) == 30
    assert pacer.take_live(10.0)  # after a pause: at once, not held back by the schedule
    assert not pacer.take_live(10.05)
    for rate in (None, 0.0):
        assert all(Pacer(rate).take_live(t) for t in arrivals)


@dataclass
class _Item:
    frame_id: int
    stamp_ns: int


class _LiveSource(FrameSource):
    live = True

    def __init__(self, n: int) -> None:
        super().__init__("live:test")
        self.n = n

    def _produce(self):  # noqa: ANN202
        for i in range(self.n):
            yield _Item(i, i * 1_000_000)  # a frame every millisecond: far faster than any rate here


class _Runner:
    """What BridgeService.loop uses of a ServiceRunner, without a bus; fails if the bridge waits."""

    def __init__(self) -> None:
        self.stats = ServiceStats()
        self.stopping = False

    def wait(self, timeout_s: float | None = None) -> bool:
        assert timeout_s is None, f"the bridge waited {timeout_s} s for a live source"
        return True


class _Pub:
    key = "test/sensor/rgbd"

    def wait_for_subscribers(self, timeout_s: float) -> bool:
        return True


def _play_live(n: int, **section) -> tuple[list[int], ServiceStats, _LiveSource]:
    source = _LiveSource(n)
    bridge = BridgeService(BridgeConfig(bridge=BridgeSection(wait_for_subscribers_s=0, **section)), source=source)
    bridge._pub = bridge._instance_pub = _Pub()  # type: ignore[assignment]
    published: list[int] = []
    bridge._publish = lambda runner, frame: published.append(frame.frame_id)  # type: ignore[method-assign]
    runner = _Runner()
    bridge.loop(runner)  # type: ignore[arg-type]
    return published, runner.stats, source


def test_the_bridge_never_waits_for_a_live_source_and_counts_what_the_rate_dropped() -> None:
    published, stats, _ = _play_live(20, rate_hz=2.0)
    assert published == [0]  # 20 frames within 20 ms: one turn at 2 Hz
    assert stats.counters[BridgeCounter.FRAMES_THROTTLED] == 19
    assert stats.counters[BridgeCounter.FRAMES_READ] == 20


def test_max_frames_of_a_live_source_counts_published_frames() -> None:
    published, _stats, source = _play_live(20, max_frames=5)
    assert published == [0, 1, 2, 3, 4]
    assert source.stats.read == 5  # stops reading the sensor there


def test_in_process_run_gives_up_after_timeout_s() -> None:
    """--timeout-s applies to --in-process too: a source slower than the deadline ends the run with
    the service run's RunError (exit 1), naming the frames it got."""
    def slow():  # noqa: ANN202
        for i in range(100):
            time.sleep(0.05)
            yield i

    with StopSignals() as signals:
        frames = _UntilStopped(slow(), signals, timeout_s=0.12)
        with pytest.raises(RunError, match=r"did not finish within 0.12 s \(integrated [1-3] frames\)"):
            list(frames)
        assert list(_UntilStopped(iter(range(3)), signals, timeout_s=None)) == [0, 1, 2]


def test_run_progress_goes_to_stderr_and_quiet_says_nothing(capsys) -> None:
    """stdout of `openfusion run` (both modes) is the run summary alone; --quiet silences progress."""
    say = say_progress(False)
    assert say is not None
    say("query 'chair': region 3")
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err == "query 'chair': region 3\n"
    assert say_progress(True) is None


def _parsed(argv: list[str]):  # noqa: ANN202
    parser, _loaded = cli.build_parser(argv)
    return parser.parse_args(argv)


def test_valid_combinations_next_to_the_refused_ones_still_pass(tmp_path) -> None:
    from openfusion.app.eval_cmd import config_from_args as eval_config
    from openfusion.app.query_cmd import _check_query_options
    from openfusion.app.viz_args import check_colour_arguments

    _check_query_options(_parsed(["query", "--map-dir", str(tmp_path), "--text-encoder", "minilm",
                                  "--min-region-points", "10", "--log-level", "INFO", "--json", "--top-k", "3",
                                  "--out", str(tmp_path / "q.ply"), "chair"]))
    _check_query_options(_parsed(["query", "--map", "lab", "--connect", "tcp/127.0.0.1:7447", "--timeout", "5",
                                  "chair"]))
    several = _parsed(["query", "--map-dir", str(tmp_path), "--verbose", "--json", "chair", "table", "lamp"])
    _check_query_options(several)
    assert several.text == ["chair", "table", "lamp"] and several.verbose
    # at the limits (openfusion.wire.limits), in both modes
    _check_query_options(_parsed(["query", "--connect", "tcp/127.0.0.1:7447", "--top-k", "100", "chair", "x" * 512]))
    _check_query_options(_parsed(["query", "--map-dir", str(tmp_path), "--top-k", "100", "x" * 512]))
    args = _parsed(["render", "--map-dir", str(tmp_path), "--out", str(tmp_path / "x.png"), "--query", "chair",
                    "--top-k", "2", "--text-encoder", "minilm"])
    check_colour_arguments(args)
    assert args.top_k == 2
    args = _parsed(["export", "--map-dir", str(tmp_path), "--out", str(tmp_path / "x.ply"), "--query", "chair"])
    check_colour_arguments(args)
    assert args.top_k == 1  # the default
    config = eval_config(_parsed(["eval", "--exclude-background", "--background-classes", "wall,floor"]))
    assert config.excluded_classes == ("wall", "floor")
    assert eval_config(_parsed(["eval", "--encoder", "clip-regions", "--noise", "off"])).encoder == "clip-regions"
    assert eval_config(_parsed(["eval"])).select.select_embed_share == 0.3
    assert eval_config(_parsed(["eval", "--embed-share", "none"])).select.select_embed_share is None
    gated = eval_config(_parsed(["eval", "--embed-share", "0.5", "--select", "coverage"])).select
    assert gated.select_embed_share == 0.5 and gated.select == "coverage"
    assert eval_config(_parsed(["eval"])).background_classes == eval_config(
        _parsed(["eval", "--exclude-background"])).background_classes
