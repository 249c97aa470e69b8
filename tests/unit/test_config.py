"""The one config loader: defaults < file < environment < command line, typed service sections,
and errors that name the field, the bad value and where it came from."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import pytest
from pydantic import Field

from openfusion.config import (
    ConfigError,
    ConfigSection,
    ServiceConfig,
    add_config_arguments,
    config_from_args,
    load_config,
    zenoh_config,
)
from openfusion.wire.endpoints import SENSOR_RGBD


class _VolumeSection(ConfigSection):
    voxel_size_m: float = Field(default=0.02, gt=0)
    max_blocks: int | None = None


class _VolumeServiceConfig(ServiceConfig):
    """What a later service does: add its own typed section."""

    volume: _VolumeSection = Field(default_factory=_VolumeSection)


def _parse(argv: list[str], model: type[ServiceConfig] = ServiceConfig, environ: dict[str, str] | None = None):
    parser = add_config_arguments(argparse.ArgumentParser())
    return config_from_args(parser.parse_args(argv), model, environ=environ or {})


def test_defaults_when_nothing_is_given() -> None:
    """No file, no env, no options: the documented defaults (Zenoh discovery left to Zenoh)."""
    cfg = load_config(environ={})
    assert cfg == ServiceConfig()
    assert (cfg.map_id, cfg.prefix, cfg.health_period_s, cfg.log_level) == ("default", "openfusion", 1.0, "INFO")
    assert cfg.zenoh.mode is None and cfg.zenoh.multicast_scouting is None and cfg.zenoh.connect == []
    assert SENSOR_RGBD.key(cfg.keys) == "openfusion/default/sensor/rgbd"


def test_precedence_defaults_file_env_cli_per_leaf(tmp_path: Path) -> None:
    """Each leaf comes from the highest source that sets it; lower sources fill in the rest."""
    cfg_file = tmp_path / "site.toml"
    cfg_file.write_text(
        'map_id = "from-file"\nprefix = "fileprefix"\nhealth_period_s = 2.5\n'
        '[zenoh]\nconnect = ["tcp/10.0.0.1:7447"]\nmode = "client"\n'
    )
    env = {"OPENFUSION_MAP_ID": "from-env", "OPENFUSION_ZENOH__CONNECT": "tcp/10.0.0.2:7447,tcp/10.0.0.3:7447"}
    cfg = _parse(["--config", str(cfg_file), "--map", "from-cli", "--log-level", "debug"], environ=env)
    assert cfg.map_id == "from-cli"  # cli > env > file
    assert cfg.zenoh.connect == ["tcp/10.0.0.2:7447", "tcp/10.0.0.3:7447"]  # env > file
    assert cfg.prefix == "fileprefix" and cfg.health_period_s == 2.5 and cfg.zenoh.mode == "client"  # file > default
    assert cfg.log_level == "DEBUG"  # normalised
    cfg = _parse(["--config", str(cfg_file)], environ=env)
    assert cfg.map_id == "from-env"
    cfg = _parse(["--config", str(cfg_file), "--connect", "tcp/127.0.0.1:1", "--connect", "tcp/127.0.0.1:2"], environ=env)
    assert cfg.zenoh.connect == ["tcp/127.0.0.1:1", "tcp/127.0.0.1:2"]  # lists replaced, not merged


@pytest.mark.parametrize("suffix", [".toml", ".json", ".yaml"])
def test_file_formats_and_config_file_from_environment(tmp_path: Path, suffix: str) -> None:
    """TOML, JSON and YAML files give the same config; $OPENFUSION_CONFIG names the file."""
    data = {"map_id": "lab", "zenoh": {"listen": ["tcp/127.0.0.1:7447"], "multicast_scouting": False}}
    text = {
        ".toml": 'map_id = "lab"\n[zenoh]\nlisten = ["tcp/127.0.0.1:7447"]\nmulticast_scouting = false\n',
        ".json": json.dumps(data),
        ".yaml": "map_id: lab\nzenoh:\n  listen: [tcp/127.0.0.1:7447]\n  multicast_scouting: false\n",
    }[suffix]
    path = tmp_path / f"c{suffix}"
    path.write_text(text)
    cfg = load_config(environ={"OPENFUSION_CONFIG": str(path)})
    assert cfg.map_id == "lab" and cfg.zenoh.listen == ["tcp/127.0.0.1:7447"] and cfg.zenoh.multicast_scouting is False


def test_typed_service_section_from_every_source(tmp_path: Path) -> None:
    """A service's own section is set from file, env (SECTION__FIELD) and --set, in that order."""
    path = tmp_path / "c.toml"
    path.write_text("[volume]\nvoxel_size_m = 0.05\nmax_blocks = 10\n[other_service]\nanything = 1\n")
    cfg = load_config(_VolumeServiceConfig, config_file=path, environ={})
    assert cfg.volume.voxel_size_m == 0.05 and cfg.volume.max_blocks == 10  # [other_service] ignored
    env = {"OPENFUSION_VOLUME__VOXEL_SIZE_M": "0.04", "OPENFUSION_VOLUME__MAX_BLOCKS": ""}
    cfg = load_config(_VolumeServiceConfig, config_file=path, environ=env)
    assert cfg.volume.voxel_size_m == 0.04 and cfg.volume.max_blocks is None  # empty env -> None
    cfg = _parse(["--config", str(path), "--set", "volume.voxel_size_m=0.03"], _VolumeServiceConfig, env)
    assert cfg.volume.voxel_size_m == 0.03


def test_environment_parsing_lists_json_and_unrelated_variables() -> None:
    """Lists take a comma list or JSON; OPENFUSION_* variables of other tools are ignored."""
    env = {
        "OPENFUSION_ZENOH__LISTEN": '["tcp/127.0.0.1:1", "tcp/127.0.0.1:2"]',
        "OPENFUSION_ZENOH__MULTICAST_SCOUTING": "false",
        "OPENFUSION_HEALTH_PERIOD_S": "0.5",
        "OPENFUSION_VENV": "/somewhere",
        "OPENFUSION_TORCH_SPEC": "torch",
        "openfusion_map_id": "lower-case-ok",
    }
    cfg = load_config(environ=env)
    assert cfg.zenoh.listen == ["tcp/127.0.0.1:1", "tcp/127.0.0.1:2"]
    assert cfg.zenoh.multicast_scouting is False and cfg.health_period_s == 0.5 and cfg.map_id == "lower-case-ok"


@pytest.mark.parametrize(
    ("kwargs", "expected"),
    [
        ({"environ": {"OPENFUSION_ZENOH__MODE": "bogus"}},
         ["zenoh.mode = 'bogus'", "environment OPENFUSION_ZENOH__MODE", "'peer', 'client' or 'router'"]),
        ({"environ": {"OPENFUSION_MAP_ID": "my lab"}},
         ["map_id = 'my lab'", "environment OPENFUSION_MAP_ID", "whitespace"]),
        ({"environ": {"OPENFUSION_ZENOH__CONECT": "tcp/1.2.3.4:5"}},
         ["zenoh.conect", "environment OPENFUSION_ZENOH__CONECT", "Extra inputs are not permitted"]),
        ({"environ": {"OPENFUSION_HEALTH_PERIOD_S": "-1"}}, ["health_period_s = '-1'", "greater than 0"]),
        ({"environ": {"OPENFUSION_ZENOH__CONNECT": "localhost:7447"}}, ["PROTOCOL/ADDRESS"]),
        ({"overrides": ["zenoh.listen=[broken"]}, ["zenoh.listen", "not a valid JSON list"]),
        ({"overrides": ["nosuchfield=1"]}, ["nosuchfield = '1'", "--set nosuchfield", "Extra inputs"]),
        ({"overrides": ["map_id"]}, ["expected KEY=VALUE"]),
        ({"cli": {"log_level": "loud"}}, ["log_level = 'loud'", "command line", "not one of DEBUG"]),
    ],
    ids=["bad-mode", "bad-map", "typo", "negative", "endpoint", "bad-json", "unknown-set", "set-syntax", "log-level"],
)
def test_validation_errors_name_field_value_and_source(kwargs: dict, expected: list[str]) -> None:
    """Each invalid value raises ConfigError whose message names the field, value and source."""
    kwargs.setdefault("environ", {})
    with pytest.raises(ConfigError) as info:
        load_config(**kwargs)
    for text in expected:
        assert text in str(info.value)


def test_file_errors_name_the_file(tmp_path: Path) -> None:
    """Missing, unparsable, wrongly shaped and unknown-key files are refused naming the file."""
    cases = {
        "missing.toml": None,
        "bad.toml": "map_id = ",
        "bad.json": "{",
        "list.json": "[1, 2]",
        "c.ini": "map_id=x",
        "unknown.toml": "mapid = 'typo'\n",
    }
    for name, text in cases.items():
        path = tmp_path / name
        if text is not None:
            path.write_text(text)
        with pytest.raises(ConfigError) as info:
            load_config(config_file=path, environ={})
        assert str(path) in str(info.value), name


def test_zenoh_config_applies_only_what_is_set(tmp_path: Path) -> None:
    """Mode, endpoints and multicast go into zenoh.Config; unset ones keep the Zenoh file's values."""
    cfg = _parse(["--mode", "client", "--connect", "tcp/127.0.0.1:7447", "--no-multicast", "--listen", "tcp/127.0.0.1:0"])
    conf = zenoh_config(cfg)
    assert json.loads(conf.get_json("mode")) == "client"
    assert json.loads(conf.get_json("connect/endpoints")) == ["tcp/127.0.0.1:7447"]
    assert json.loads(conf.get_json("listen/endpoints")) == ["tcp/127.0.0.1:0"]
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    zfile = tmp_path / "zenoh.json5"
    zfile.write_text('{ mode: "router", scouting: { multicast: { enabled: false } } }')
    conf = zenoh_config(_parse(["--zenoh-config", str(zfile), "--connect", "tcp/127.0.0.1:9"]))
    assert json.loads(conf.get_json("mode")) == "router"  # from the file: not overridden
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    with pytest.raises(ConfigError, match="zenoh config file"):
        zenoh_config(_parse(["--zenoh-config", str(tmp_path / "nope.json5")]))


def test_shared_memory_switch_reaches_the_zenoh_config() -> None:
    """`zenoh.shared_memory` (flag --set zenoh.shared_memory=false, file, env) sets Zenoh's
    transport/shared_memory/enabled; unset keeps Zenoh's own default (on in 1.x)."""
    import json

    from openfusion.config import ServiceConfig, zenoh_config

    default = json.loads(zenoh_config(ServiceConfig()).get_json("transport/shared_memory/enabled"))
    off = ServiceConfig.model_validate({"zenoh": {"shared_memory": False}})
    assert default is True
    assert json.loads(zenoh_config(off).get_json("transport/shared_memory/enabled")) is False
