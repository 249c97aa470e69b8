"""How the openfusion command reports errors, in this process: a user error is one line and exit
code 2, a bug keeps its traceback, OPENFUSION_DEBUG=1 shows every traceback."""

from __future__ import annotations

import os
import subprocess

import pytest
import zenoh

from openfusion.app import cli
from openfusion.sources.base import SourceError

pytestmark = pytest.mark.timeout(120)


class _FailingCommand:
    """A subcommand whose library call refuses bad input (a UserError) or hits a bug."""

    @staticmethod
    def add_arguments(parser) -> None:
        parser.add_argument("--spec", default="nosuch:/x")
        parser.add_argument("--bug", action="store_true")

    @staticmethod
    def run(args) -> int:
        if args.bug:
            raise KeyError("a bug")
        raise SourceError(f"unknown source scheme in {args.spec!r}")


def test_user_errors_are_one_line_exit_2_and_bugs_keep_their_traceback(monkeypatch, capsys) -> None:
    """A UserError from library code (bad user input) ends as one stderr line and exit code 2;
    OPENFUSION_DEBUG=1 brings the traceback back; an exception outside the package's error tree
    (a bug) is not swallowed into one line."""
    monkeypatch.setattr(cli, "SUBCOMMANDS", [cli.Subcommand("failing", f"{__name__}:_FailingCommand", "fails")])
    monkeypatch.delenv("OPENFUSION_DEBUG", raising=False)
    assert cli.main(["failing"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["openfusion failing: error: unknown source scheme in 'nosuch:/x'"]
    with pytest.raises(KeyError, match="a bug"):
        cli.main(["failing", "--bug"])
    monkeypatch.setenv("OPENFUSION_DEBUG", "1")
    with pytest.raises(SourceError, match="unknown source scheme"):
        cli.main(["failing"])


class _Started(BaseException):
    """Raised where a bad argument got as far as starting something (outside every except clause)."""


#: One bad argument (or more) per subcommand: (argv, text the error line must contain). ``{tmp}`` is
#: a fresh empty folder. Where the command takes a value our code checks, that value (not only an
#: argparse choice) is used; the run's cases were refused only after its services had started.
BAD_ARGUMENTS = [
    (["version", "--bogus"], "unrecognized arguments: --bogus"),
    (["router", "--listen", "notanendpoint", "--no-multicast"], "endpoint 'notanendpoint' is not of the form"),
    # docs/CLI.md: flags that were parsed and then ignored, or could not be honoured, are refused.
    (["router", "--mode", "peer", "--no-multicast"], "--mode peer: openfusion router always runs in router mode"),
    (["router", "--map", "lab", "--no-multicast"], "--map: a router routes every map"),
    (["health", "--map", "bad/map id", "--no-multicast"], "map id 'bad/map id' is not a valid key segment"),
    (["service", "nosuch"], "invalid choice: 'nosuch'"),
    (["service", "geometry", "--voxel-size-m", "-1", "--no-multicast"], "geometry.voxel_size_m = -1.0"),
    # 1 cm voxels keep the default 8-voxel blocks of 8 cm: the read-out's fill and vote reach past the halo
    (["service", "geometry", "--voxel-size-m", "0.01", "--no-multicast"],
     "label_fill_radius_m (0.06) + label_vote_radius_m (0.045) + voxel_size_m (0.01) = 0.115 m exceeds one block"),
    (["service", "semantic", "--encoder", "onnx", "--noise", "light", "--no-multicast"],
     "semantic.noise = 'light' (from command line): noise applies to the gt encoder only, not to 'onnx'"),
    (["run", "--encoder", "nosuch"], "unknown region encoder 'nosuch'; known: gt"),
    (["run", "--source", "scannet:{tmp}/missing"], "scannet source: {tmp}/missing does not exist"),
    (["run", "--source", "nosuch:/x"], "unknown source scheme 'nosuch' in 'nosuch:/x'; known: synthetic"),
    (["run", "--source", "synthetic:seed"], "synthetic option 'seed' must look like key=value"),
    (["run", "--source", "synthetic:sed=1"], "unknown synthetic option 'sed'; known: fps, frames"),
    (["run", "--source", "synthetic:lap=x"], "synthetic option lap='x' is not a valid int"),
    (["run", "--top-k", "0"], "--top-k must be from 1 to 100, got 0"),
    (["run", "--top-k", "1000"], "--top-k must be from 1 to 100, got 1000"),
    (["run", "--query", ""], "--query '': the query text is empty"),
    (["run", "--rerun", "bogus"], "unknown rerun sink 'bogus'"),
    (["run", "--in-process", "--web"], "--web serves the page of the running services; --in-process runs none"),
    (["run", "--web", "99999"], "--web PORT must be between 0 and 65535, got 99999"),
    (["run", "--timeout-s", "0"], "--timeout-s must be positive, got 0"),
    (["run", "--encoder-workers", "-1"], "--encoder-workers must be between 0 and 16, got -1"),
    (["run", "--in-process", "--encoder-workers", "2"], "--encoder-workers starts encoder services; --in-process has none"),
    (["run", "--encoder-delay-ms", "-5"], "semantic.encoder_delay_ms = -5.0"),
    (["run", "--query-services", "0"], "--query-services must be between 1 and 8, got 0"),
    (["run", "--in-process", "--query-services", "2"], "--query-services starts query services; --in-process has none"),
    (["run", "--geometry-shards", "0"], "--geometry-shards must be between 1 and 64, got 0"),
    (["run", "--in-process", "--geometry-shards", "2"], "--geometry-shards starts geometry services; --in-process has none"),
    (["service", "geometry", "--shard", "2/2", "--no-multicast"], "shard index must be 0..1 for 2 shards"),
    (["service", "geometry", "--shard", "half", "--no-multicast"], "is not of the form I/N"),
    (["service", "geometry", "--replica", "10", "--no-multicast"], "geometry.replica = 10"),
    (["service", "query", "--instance", "0", "--no-multicast"], "query.instance = 0"),
    (["service", "query", "--text-backend", "tensorflow", "--no-multicast"], "unknown MiniLM backend 'tensorflow'"),
    (["service", "encoder", "--worker-id", "a/b", "--no-multicast"], "worker id 'a/b' is not a valid key segment"),
    (["service", "encoder", "--encoder", "clip-dense", "--encoder-backend", "int4", "--no-multicast"],
     "unknown clip-dense backend 'int4'"),
    (["run", "--in-process", "--rate-hz", "5"], "--rate-hz paces the bridge service; --in-process has none"),
    (["run", "--encoder", "clip-regions", "--noise", "heavy"], "noise applies to the gt encoder only, not to 'clip-regions'"),
    (["run", "--text-encoder", "hash"], "--text-encoder 'hash' cannot query the regions of the gt encoder"),
    (["run", "--source", "rosbag:{tmp}/nobag"], "rosbag source: {tmp}/nobag does not exist"),
    (["run", "--source", "ros2:domain=3"], "unknown ros2 option(s) domain; known: layout"),
    (["ros-publish", "--every", "0", "chair"], "--every must be positive, got 0"),
    (["ros-publish", "--top-k", "500", "chair"], "--top-k must be from 1 to 100, got 500"),
    (["ros-publish", "--layout", "dds", "chair"], "invalid choice: 'dds'"),
    (["query", "--map-dir", "{tmp}/nomap", "chair"], "no map at {tmp}/nomap"),
    # the one set of limits (openfusion.wire.limits), both modes, the same line as the page and the service
    (["query", "--top-k", "0", "chair"], "--top-k must be from 1 to 100, got 0"),
    (["query", "--top-k", "-1", "chair"], "--top-k must be from 1 to 100, got -1"),
    (["query", "--top-k", "1000000000", "chair", "--mode", "client", "--connect", "tcp/127.0.0.1:7447"],
     "--top-k must be from 1 to 100, got 1000000000"),
    (["query", "--top-k", "20000", "chair"], "--top-k must be from 1 to 100, got 20000"),
    (["query", "--map-dir", "{tmp}/nomap", "--top-k", "101", "chair"], "--top-k must be from 1 to 100, got 101"),
    (["query", "--map-dir", "{tmp}/nomap", ""], "the query text is empty"),
    (["query", "--map-dir", "{tmp}/nomap", "chair", " ", "lamp"], "query text 2 of 3 is empty"),
    (["query", "chair", "x" * 600], "the query text 2 of 2 has 600 characters; the limit is 512"),
    (["query", "x" * 5000], "the query text has 5000 characters; the limit is 512"),
    (["query", "--map-dir", "{tmp}/nomap", "x" * 600], "the query text has 600 characters; the limit is 512"),
    (["query", "--map-dir", "{tmp}/nomap", "--map", "lab", "--connect", "tcp/127.0.0.1:7447", "chair"],
     "--map, --connect find a running map; --map-dir reads a saved one"),
    (["query", "--map-dir", "{tmp}/nomap", "--timeout", "5", "chair"], "--timeout finds a running map"),
    (["query", "--text-encoder", "hash", "chair"], "--text-encoder applies to a saved map (--map-dir)"),
    (["query", "--min-region-points", "10", "chair"], "--min-region-points applies to a saved map (--map-dir)"),
    (["query", "--timeout", "0", "chair"], "--timeout must be positive, got 0"),
    (["query", "--map-dir", "{tmp}", "--out", "{tmp}/missing/q.ply", "chair"], "--out: folder {tmp}/missing does not exist"),
    (["web", "--port", "70000", "--no-multicast"], "--port must be between 0 and 65535, got 70000"),
    (["web", "--max-points", "0", "--no-multicast"], "--max-points must be between 1 and 500,000, got 0"),
    (["web", "--timeout", "0", "--no-multicast"], "--timeout must be positive, got 0"),
    (["segment", "--map-dir", "{tmp}/nomap", "--classes", "a", "--out", "{tmp}/seg.ply"], "no map at {tmp}/nomap"),
    (["segment", "--map-dir", "{tmp}", "--classes", "a", "--out", "{tmp}/missing/seg.ply"],
     "--out: folder {tmp}/missing does not exist"),
    (["eval", "--scenes", "nosuch:1", "--out", "{tmp}/eval"], "bad scene 'nosuch:1'"),
    (["eval", "--scenes", "scannet:{tmp}/missing", "--out", "{tmp}/eval"], "scene folder {tmp}/missing does not exist"),
    (["eval", "--encoder", "nosuch", "--out", "{tmp}/eval"], "unknown region encoder 'nosuch'"),
    (["eval", "--encoder", "clip-regions", "--noise", "heavy", "--out", "{tmp}/eval"],
     "--noise applies to --encoder gt only, not 'clip-regions'"),
    (["eval", "--encoder", "clip-regions", "--text-encoder", "hash", "--out", "{tmp}/eval"],
     "--text-encoder applies to --encoder gt only"),
    (["eval", "--encoder", "clip-regions", "--region-text", "name", "--out", "{tmp}/eval"],
     "--region-text applies to --encoder gt only"),
    (["eval", "--region-text", "label", "--out", "{tmp}/eval"], "invalid choice: 'label'"),
    (["eval", "--background-classes", "wall", "--out", "{tmp}/eval"],
     "--background-classes names the classes --exclude-background drops"),
    (["eval", "--width", "0", "--out", "{tmp}/eval"], "--width must be >= 1, got 0"),
    (["eval", "--embed-share", "1.5", "--out", "{tmp}/eval"],
     "--embed-share must be a share between 0 and 1 or none, got '1.5'"),
    (["eval", "--embed-share", "half", "--out", "{tmp}/eval"],
     "--embed-share must be a share between 0 and 1 or none, got 'half'"),
    (["render", "--map-dir", "{tmp}/nomap", "--out", "{tmp}/x.png"], "map folder {tmp}/nomap does not exist"),
    (["render", "--map-dir", "{tmp}/nomap", "--out", "{tmp}/x.png", "--top-k", "2"],
     "--top-k says how many regions --query highlights"),
    (["render", "--map-dir", "{tmp}/nomap", "--out", "{tmp}/x.png", "--fov-deg", "200"],
     "field of view must be between 5 and 150 degrees, got 200.0"),
    (["export", "--map-dir", "{tmp}/nomap", "--out", "{tmp}/x.ply"], "map folder {tmp}/nomap does not exist"),
    (["export", "--map-dir", "{tmp}/nomap", "--out", "{tmp}/x.ply", "--text-model", "m.onnx"],
     "--text-model embeds the text of --query or --classes"),
    (["config", "--show", "nosuch"], "invalid choice: 'nosuch'"),
    (["config", "--show", "run", "--set", "semantic.encoder=nosuch"], "semantic.encoder = 'nosuch'"),
]


def test_every_subcommand_is_fed_a_bad_argument() -> None:
    """The table below covers every registered subcommand."""
    assert {argv[0] for argv, _ in BAD_ARGUMENTS} == {c.name for c in cli.SUBCOMMANDS}


@pytest.mark.parametrize(("argv", "expected"), BAD_ARGUMENTS, ids=[" ".join(a) for a, _ in BAD_ARGUMENTS])
def test_a_bad_argument_is_one_line_exit_2_and_starts_nothing(
    argv: list[str], expected: str, tmp_path, monkeypatch, capsys
) -> None:
    """Exit code 2, nothing on stdout, and stderr is exactly one line ``openfusion CMD: error: ...``
    naming the bad value (argparse's errors too: the parser prints no usage block), no traceback;
    and the value is refused before anything starts: no Zenoh session, no process, no output."""
    def started(what: str):
        def refuse(*_args, **_kwargs):
            raise _Started(f"{' '.join(argv)}: {what} before the bad argument was refused")

        return refuse

    monkeypatch.setattr(zenoh, "open", started("a Zenoh session was opened"))
    monkeypatch.setattr(subprocess, "Popen", started("a process was started"))
    for name in [n for n in os.environ if n.startswith("OPENFUSION_")]:
        monkeypatch.delenv(name)
    tmp = str(tmp_path)
    argv = [a.replace("{tmp}", tmp) for a in argv]
    expected = expected.replace("{tmp}", tmp)
    out = tmp_path / "out"
    if argv[0] == "run":
        argv += ["--out", str(out), "--quiet"]
    try:
        code = cli.main(argv)
    except SystemExit as exc:  # argparse's own errors
        code = exc.code
    captured = capsys.readouterr()
    lines = captured.err.splitlines()
    assert code == 2, captured.err
    assert captured.out == ""
    assert len(lines) == 1, captured.err
    assert lines[0].startswith(f"openfusion {argv[0]}") and ": error: " in lines[0], lines[0]
    # The program name is the subcommand's (``openfusion service geometry`` for a service's own option).
    assert lines[0].split(": error: ")[0] in (f"openfusion {argv[0]}", f"openfusion {' '.join(argv[:2])}"), lines[0]
    assert expected in lines[0], lines[0]
    assert "Traceback" not in captured.err
    assert sorted(p.name for p in tmp_path.iterdir()) == [], "the command wrote files for a bad argument"


@pytest.mark.parametrize("where", ["file", "under_a_file"])
def test_run_refuses_an_output_folder_it_could_not_write(where: str, tmp_path, monkeypatch, capsys) -> None:
    """``--out`` naming a file, or a folder below a file: one line naming it, exit 2, before any
    session or process starts (the map of a long run would otherwise be lost at the end). A folder
    without write permission is refused the same way (not exercised here: tests run as root, for
    whom every folder is writable)."""
    monkeypatch.setattr(zenoh, "open", lambda *_a, **_k: pytest.fail("a Zenoh session was opened"))
    monkeypatch.setattr(subprocess, "Popen", lambda *_a, **_k: pytest.fail("a process was started"))
    blocker = tmp_path / "a-file"
    blocker.write_text("x")
    out = blocker if where == "file" else blocker / "out"
    assert cli.main(["run", "--out", str(out), "--quiet"]) == 2
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"openfusion run: error: --out {out}: "), lines
    assert ("is not a folder" if where == "file" else f"{blocker} is a file") in lines[0]
