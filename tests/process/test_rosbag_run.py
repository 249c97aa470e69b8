"""``openfusion run --source rosbag:...`` as a user runs it: a rosbag2 of the synthetic scene (instances
as a 32SC1 topic, categories as a String), written by the test with rosbags, maps to the f-mIoU of
the synthetic source mapped directly (within 0.01), and the run says which topics it used. Bad input
tried: a bag without camera topics (one line naming what it has, exit 2, nothing started)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from rosbag_support import synthetic_f_miou, write_frames_bag

from openfusion.app.run_sources import builtin_scene_spec
from openfusion.sources import open_source
from openfusion.testing.bus import subprocess_env

ROOT = next(p for p in Path(__file__).resolve().parents if (p / "pyproject.toml").is_file())
SPEC = "synthetic:seed=1,frames=12,width=160,height=120"


def _run(*args: str, timeout: float = 600) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "openfusion.app.cli", "run", *args], capture_output=True, text=True,
                          timeout=timeout, cwd=ROOT, env=subprocess_env(HF_HUB_OFFLINE="1"))


@pytest.mark.slow
def test_a_bag_of_the_scene_maps_to_the_scenes_f_miou(tmp_path: Path) -> None:
    from openfusion.encoders import make_text_encoder
    from openfusion.mapping import load_map

    bag = tmp_path / "scene"
    # the frames `openfusion run --source SPEC --frames 12` plays (the run walks its own lap of the
    # room, ``builtin_scene_spec``), so both runs map the very same frames
    write_frames_bag(bag, list(open_source(builtin_scene_spec(SPEC, 12))), storage="mcap", distro="jazzy")
    text = make_text_encoder("minilm")
    scores = []
    for name, source in (("scene", SPEC), ("bag", f"rosbag:{bag}")):
        result = _run("--in-process", "--out", str(tmp_path / name), "--source", source, "--frames", "12")
        assert result.returncode == 0, result.stderr[-3000:]
        if name == "bag":
            assert "using color=/camera/color/image_raw" in result.stderr and "instance=/gt/instance" in result.stderr
        loaded = load_map(tmp_path / name / "map")
        scores.append(synthetic_f_miou(loaded.volume, loaded.dictionary, seed=1, text_encoder=text))
    assert scores[0] > 0.3
    assert abs(scores[0] - scores[1]) <= 0.01, scores


def test_a_bag_without_camera_topics_is_refused_before_anything_starts(tmp_path: Path) -> None:
    from rosbag_support import PLUGINS, RosbagsMessages
    from rosbags.rosbag2 import Writer

    m = RosbagsMessages("jazzy")
    bag = tmp_path / "chatter"
    with Writer(bag, version=9, storage_plugin=PLUGINS["mcap"]) as w:
        c = w.add_connection("/chatter", "std_msgs/msg/String", typestore=m.ts)
        w.write(c, 1, m.cdr(m.string("hello")))
    result = _run("--out", str(tmp_path / "out"), "--source", f"rosbag:{bag}", "--frames", "2", timeout=120)
    assert result.returncode == 2, result.stderr
    assert "Traceback" not in result.stderr
    assert "has no color, no depth, no camera_info, no odometry or tf topic; it has /chatter (std_msgs/msg/String)" \
        in result.stderr
    assert not (tmp_path / "out" / "run.json").exists()
