"""openfusion.viz.rerun_log: sink parsing, a real .rrd recording read back, and a clear error
when rerun-sdk is missing."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from openfusion.mapping import load_map, query_regions
from openfusion.sources import open_source
from openfusion.testing.maps import cached_synthetic_map
from openfusion.viz.errors import MissingDependencyError, VizError
from openfusion.viz.rerun_log import DEFAULT_SERVE_PORT, RerunLogger, parse_sink


def test_parse_sink_accepts_the_documented_forms(tmp_path):
    """save:FILE.rrd, spawn, serve, serve:PORT, connect:URL parse; anything else is one clear VizError."""
    s = parse_sink(f"save:{tmp_path / 'a.rrd'}")
    assert s.kind == "save" and s.path == tmp_path / "a.rrd"
    assert parse_sink("spawn").kind == "spawn"
    assert parse_sink("serve").port == DEFAULT_SERVE_PORT
    assert parse_sink("serve:9000").port == 9000
    assert parse_sink("connect:rerun+http://10.0.0.2:9876/proxy").url == "rerun+http://10.0.0.2:9876/proxy"
    for bad, msg in [
        ("save:", "needs a file name"),
        (f"save:{tmp_path / 'a.txt'}", ".rrd"),
        (f"save:{tmp_path / 'missing' / 'a.rrd'}", "does not exist"),
        ("serve:http", "port 1-65535"),
        ("serve:70000", "port 1-65535"),
        ("show", "unknown rerun sink"),
    ]:
        with pytest.raises(VizError, match=msg):
            parse_sink(bad)


def test_missing_rerun_sdk_is_a_clear_error(tmp_path, monkeypatch):
    """Without rerun-sdk importable, RerunLogger names the package and how to install it."""
    monkeypatch.setitem(sys.modules, "rerun", None)
    with pytest.raises(MissingDependencyError, match="rerun-sdk.*pip install"):
        RerunLogger(f"save:{tmp_path / 'x.rrd'}")
    assert not (tmp_path / "x.rrd").exists()


def test_recording_holds_frames_trajectory_mesh_regions_and_query(tmp_path, tmp_path_factory):
    """save:FILE.rrd: the file is written, non-empty, and read back with rerun's own reader it holds
    the camera, images, trajectory, mesh, region points and query entities; a closed logger refuses
    more data."""
    rr = pytest.importorskip("rerun", reason="rerun logging needs the optional rerun-sdk package")
    RrdReader = pytest.importorskip("rerun.chunk", reason="reading .rrd back needs rerun-sdk >= 0.41").RrdReader

    loaded = load_map(cached_synthetic_map(tmp_path_factory.getbasetemp()))
    from openfusion.encoders import make_text_encoder

    text = make_text_encoder("hash")
    results = query_regions(loaded.dictionary, loaded.volume, text.encode(["chair"])[0], 2, with_points=True)
    path = tmp_path / "run.rrd"
    frames = list(open_source("synthetic:seed=1,frames=12,width=80,height=60"))
    with RerunLogger(f"save:{path}", image_every=2) as log:
        hook = log.frame_hook(mesh_source=loaded.volume.extract_mesh, mesh_every=12)
        for frame in frames:
            hook(frame, None)
        log.log_regions(loaded.volume.extract_points(max_points=2000), labels={1: "wall"})
        log.log_query("chair", results)
    with pytest.raises(VizError, match="closed"):
        log.log_frame(frames[0])
    assert path.stat().st_size > 50_000
    store = RrdReader(str(path)).store()
    entities = set(store.schema().entity_paths())
    for wanted in (
        "/world/camera",
        "/world/camera/image",
        "/world/camera/depth",
        "/world/camera/instances",
        "/world/trajectory",
        "/world/map/mesh",
        "/world/map/regions",
        "/world/query/1/points",
        "/world/query/1/box",
        "/log/queries",
    ):
        assert wanted in entities, (wanted, sorted(entities))
    assert rr.__version__


def test_log_mesh_refuses_unknown_colour_mode(tmp_path):
    """A colour mode the logger does not know is refused before anything is logged."""
    pytest.importorskip("rerun", reason="rerun logging needs the optional rerun-sdk package")
    from openfusion.mapping import SurfaceMesh

    mesh = SurfaceMesh(
        np.zeros((3, 3), np.float32), np.array([[0, 1, 2]], np.int32), np.zeros((3, 3), np.uint8),
        np.zeros((3, 3), np.float32), np.zeros(3, np.int32), np.zeros(3, np.float32),
    )  # fmt: skip
    with RerunLogger(f"save:{tmp_path / 'm.rrd'}") as log:
        with pytest.raises(VizError, match="rgb' or 'region"):
            log.log_mesh(mesh, colour="label")
        log.log_mesh(mesh, colour="region")
    assert (tmp_path / "m.rrd").stat().st_size > 0


def test_serve_sink_hosts_a_grpc_proxy_on_the_given_port():
    """serve:PORT starts an in-process server whose URL a viewer can connect to."""
    pytest.importorskip("rerun", reason="rerun logging needs the optional rerun-sdk package")
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with RerunLogger(f"serve:{port}") as log:
        assert log.server_url == f"rerun+http://127.0.0.1:{port}/proxy"


def test_log_query_accepts_a_query_reply_message(tmp_path):
    """A QueryReply from the query service (boxes, no points) is logged as boxes + a text line;
    anything else without results is refused."""
    pytest.importorskip("rerun", reason="rerun logging needs the optional rerun-sdk package")
    RrdReader = pytest.importorskip("rerun.chunk", reason="reading .rrd back needs rerun-sdk >= 0.41").RrdReader

    from openfusion.wire.schemas import QueryReply, RegionHit

    hit = RegionHit(
        key=3, score=0.8, label="chair", bbox_min=np.zeros(3, np.float32), bbox_max=np.ones(3, np.float32), num_points=10
    )
    reply = QueryReply(embedding_space="minilm-l6-v2", query="chair", regions=[hit])
    path = tmp_path / "q.rrd"
    with RerunLogger(f"save:{path}") as log:
        log.log_query(reply)
        with pytest.raises(VizError, match="QueryReply"):
            log.log_query("chair")
    entities = set(RrdReader(str(path)).store().schema().entity_paths())
    assert "/world/query/1/box" in entities and "/log/queries" in entities
    assert "/world/query/1/points" not in entities
