"""Deployment files: docker-compose*.yml, the two-host example, Dockerfiles, .dockerignore and the
plain Zenoh configs in deploy/zenoh/.

No Docker engine runs here, so compose files are checked as data (PyYAML) against what the
services need: explicit router endpoints, no multicast, health checks that require the service,
the map volume on geometry, GPU only in the override. The plain Zenoh configs are opened as real
sessions on loopback. test_compose_commands_parse_with_cli parses every command with the real
`openfusion` argument parser.
"""

from __future__ import annotations

import importlib
import json
import re
import shlex
from pathlib import Path
from typing import Any

import pytest
import zenoh
from compose_support import load_compose

#: The repository root (deploy files, docs, the README's commands).
ROOT = next(p for p in Path(__file__).resolve().parents if (p / "pyproject.toml").is_file())

ZENOH_DIR = ROOT / "deploy" / "zenoh"
TWO_HOST = ROOT / "deploy" / "two-host"
IMAGE_ROOT = "/opt/openfusion"  # WORKDIR of both Dockerfiles: the repository root in the image
SERVICES = ("bridge", "geometry", "semantic", "query")
ROUTER_ENDPOINT = "tcp/router:7447"

pytestmark = pytest.mark.timeout(60)


# --------------------------------------------------------------------------- helpers

def option(argv: list[str], name: str) -> str:
    """The value after ``name`` in ``argv``; fails the test when missing."""
    assert name in argv, f"{name} missing from {shlex.join(argv)}"
    index = argv.index(name)
    assert index + 1 < len(argv), f"{name} has no value in {shlex.join(argv)}"
    return argv[index + 1]


def health_argv(service: dict[str, Any]) -> list[str]:
    test = service["healthcheck"]["test"]
    assert isinstance(test, list) and test[0] == "CMD", f"health check must be an exec-form list: {test}"
    return test[1:]


def repo_path_of_image_path(image_path: str) -> Path:
    assert image_path.startswith(IMAGE_ROOT + "/"), f"{image_path} is not under {IMAGE_ROOT}"
    return ROOT / image_path[len(IMAGE_ROOT) + 1 :]


# --------------------------------------------------------------------------- docker-compose.yml


@pytest.fixture(scope="module")
def compose() -> dict[str, Any]:
    return load_compose(ROOT / "docker-compose.yml")


def test_compose_has_router_and_four_services_built_from_the_project_image(compose: dict[str, Any]) -> None:
    """Bad input guarded: a missing service, a service without image/build, a Dockerfile path
    that does not exist, a service not restarted after a crash."""
    services = compose["services"]
    assert set(services) == {"router", *SERVICES}
    for name, service in services.items():
        assert service["image"] == "openfusion-z:cpu", name
        assert (ROOT / service["build"]["context"] / service["build"]["dockerfile"]).is_file(), name
        assert service["restart"] == "unless-stopped", name
        assert isinstance(service["command"], list) and service["command"][0] == "openfusion", name


def test_compose_router_listens_on_the_published_port(compose: dict[str, Any]) -> None:
    """Bad input guarded: a router listening elsewhere than the endpoint the services connect
    to, a config path that does not exist in the image, no health check."""
    router = compose["services"]["router"]
    argv = router["command"]
    assert argv[:2] == ["openfusion", "router"]
    assert option(argv, "--listen") == "tcp/0.0.0.0:7447"
    config = repo_path_of_image_path(option(argv, "--zenoh-config"))
    assert config.is_file()
    assert json.loads(zenoh.Config.from_file(config).get_json("mode")) == "router"
    assert "7447:7447" in router["ports"]
    assert "7447" in " ".join(router["healthcheck"]["test"])


@pytest.mark.parametrize("name", SERVICES)
def test_compose_service_connects_explicitly_and_checks_its_own_health(
    compose: dict[str, Any], name: str
) -> None:
    """Bad input guarded: a service relying on multicast discovery across the Docker network,
    peer mode, a health check requiring another service or another map, no start ordering."""
    service = compose["services"][name]
    argv = service["command"]
    assert argv[:3] == ["openfusion", "service", name]
    assert option(argv, "--mode") == "client"
    assert option(argv, "--connect") == ROUTER_ENDPOINT
    assert "--no-multicast" in argv and "--multicast" not in argv
    map_id = option(argv, "--map")
    assert map_id == "demo"  # the ${OPENFUSION_MAP:-demo} default

    check = health_argv(service)
    assert check[:2] == ["openfusion", "health"]
    assert option(check, "--require") == name
    assert option(check, "--map") == map_id
    assert option(check, "--connect") == ROUTER_ENDPOINT
    assert option(check, "--mode") == "client"
    assert "--no-multicast" in check
    assert service["depends_on"]["router"]["condition"] == "service_healthy"
    assert "network_mode" not in service


def test_compose_map_volume_and_service_options(compose: dict[str, Any]) -> None:
    """Bad input guarded: map checkpoints written inside the container (lost on rebuild), a
    bridge without a source, a semantic service without an encoder."""
    services = compose["services"]
    geometry = services["geometry"]
    assert "maps:/data/maps" in geometry["volumes"]
    assert "maps" in compose["volumes"]
    assert option(geometry["command"], "--map-dir") == "/data/maps"
    bridge = services["bridge"]["command"]
    assert option(bridge, "--source") == "synthetic:seed=0"
    assert float(option(bridge, "--rate-hz")) > 0
    assert "--loop" in bridge
    assert option(services["semantic"]["command"], "--encoder") == "gt"
    assert services["bridge"]["depends_on"]["geometry"]["condition"] == "service_healthy"
    for service in services.values():
        assert "deploy" not in service, "GPU reservations belong in docker-compose.gpu.yml"


def test_compose_variables_override_map_and_source() -> None:
    """Bad input guarded: a hard-coded map id or source that the documented variables do not reach."""
    compose = load_compose(
        ROOT / "docker-compose.yml",
        env={"OPENFUSION_MAP": "warehouse", "OPENFUSION_SOURCE": "scannet:/data/datasets/scene0000_00"},
    )
    for name in SERVICES:
        service = compose["services"][name]
        assert option(service["command"], "--map") == "warehouse"
        assert option(health_argv(service), "--map") == "warehouse"
    assert (
        option(compose["services"]["bridge"]["command"], "--source") == "scannet:/data/datasets/scene0000_00"
    )


def test_gpu_override_reserves_a_gpu_for_semantic_only() -> None:
    """Bad input guarded: a GPU reservation that is not in the override (so it cannot be switched
    off), a CUDA image for services that do not need it."""
    base = load_compose(ROOT / "docker-compose.yml")
    merged = load_compose(ROOT / "docker-compose.yml", ROOT / "docker-compose.gpu.yml")
    semantic = merged["services"]["semantic"]
    devices = semantic["deploy"]["resources"]["reservations"]["devices"]
    assert devices == [{"driver": "nvidia", "count": 1, "capabilities": ["gpu"]}]
    assert semantic["build"]["dockerfile"] == "docker/Dockerfile.cuda"
    assert semantic["image"] == "openfusion-z:cuda"
    assert semantic["command"] == base["services"]["semantic"]["command"]
    for name in ("router", "bridge", "geometry", "query"):
        assert "deploy" not in merged["services"][name]
        assert merged["services"][name]["image"] == "openfusion-z:cpu"


# --------------------------------------------------------------------------- two-host example


def test_robots_override_adds_a_bridge_per_robot_named_as_its_health_key() -> None:
    """docker-compose.robots.yml: a second bridge for robot1 whose health check requires the name the
    bridge reports under (bridge-robot1), and geometry told how robot1's frame joins the map's
    (bad input guarded: a robot_frames value geometry would refuse at start-up)."""
    from openfusion.mapping.robot_streams import parse_robot_frames
    from openfusion.services.bridge.service import bridge_name

    merged = load_compose(ROOT / "docker-compose.yml", ROOT / "docker-compose.robots.yml")
    second = merged["services"]["bridge-robot1"]
    robot = option(second["command"], "--robot")
    assert robot == "robot1" and bridge_name(robot) == "bridge-robot1"
    assert second["healthcheck"]["test"][-1] == bridge_name(robot)
    assert "--robot" not in merged["services"]["bridge"]["command"]  # robot0: health key "bridge"
    frames = merged["services"]["geometry"]["environment"]["OPENFUSION_GEOMETRY__ROBOT_FRAMES"]
    assert set(parse_robot_frames(frames)) == {"robot1"}


def test_two_host_example_splits_services_and_uses_tls_identities() -> None:
    """Bad input guarded: semantic on both hosts or none, a plain-tcp link between hosts, a
    service using another identity's credentials, a GPU box started without ROBOT_HOST, a
    certificate or secret path that the router config does not read."""
    robot = load_compose(TWO_HOST / "robot.compose.yml")
    gpu = load_compose(TWO_HOST / "gpu.compose.yml", env={"ROBOT_HOST": "robot.local"})
    assert set(robot["services"]) == {"router", "bridge", "geometry", "query"}
    assert set(gpu["services"]) == {"semantic"}
    with pytest.raises(KeyError, match="ROBOT_HOST"):
        load_compose(TWO_HOST / "gpu.compose.yml")

    router = robot["services"]["router"]
    assert option(router["command"], "--listen") == "tls/0.0.0.0:7447"
    router_config = zenoh.Config.from_file(
        repo_path_of_image_path(option(router["command"], "--zenoh-config"))
    )
    mounted = {volume.split(":")[1] for volume in router["volumes"]}
    for key in (
        "transport/link/tls/root_ca_certificate",
        "transport/link/tls/listen_certificate",
        "transport/link/tls/listen_private_key",
        "transport/auth/usrpwd/dictionary_file",
    ):
        assert json.loads(router_config.get_json(key)) in mounted, key

    identities = {"bridge": "robot-sensor", "geometry": "geometry", "query": "query-service"}
    expected = {name: (robot["services"][name], "tls/router:7447") for name in identities}
    expected["semantic"] = (gpu["services"]["semantic"], "tls/robot.local:7447")
    identities["semantic"] = "gpu-semantic"
    for name, (service, endpoint) in expected.items():
        for argv in (service["command"], health_argv(service)):
            assert option(argv, "--connect") == endpoint, name
            assert option(argv, "--mode") == "client" and "--no-multicast" in argv, name
            config_path = option(argv, "--zenoh-config")
            assert config_path == f"/etc/openfusion/secrets/client-{identities[name]}.json5", name
            assert any(volume.endswith(f":{config_path}:ro") for volume in service["volumes"]), name
        assert option(health_argv(service), "--require") == name
        assert any(volume.endswith(":/etc/openfusion/certs/ca.pem:ro") for volume in service["volumes"]), name
    assert "maps:/data/maps" in robot["services"]["geometry"]["volumes"]
    devices = gpu["services"]["semantic"]["deploy"]["resources"]["reservations"]["devices"]
    assert devices[0]["driver"] == "nvidia"


# --------------------------------------------------------------------------- Dockerfiles


def _dockerfile(name: str) -> str:
    return (ROOT / "docker" / name).read_text()


def _instructions(text: str) -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) with continuation lines joined and comments dropped."""
    joined = re.sub(
        r"\\\n", " ", "\n".join(line for line in text.splitlines() if not line.lstrip().startswith("#"))
    )
    out = []
    for line in joined.splitlines():
        if line.strip():
            word, _, rest = line.strip().partition(" ")
            out.append((word.upper(), rest.strip()))
    return out


def _dockerignore_excludes(path: str) -> bool:
    """Docker's .dockerignore rule: the last pattern matching the path or a parent folder wins."""
    excluded = False
    for raw in (ROOT / ".dockerignore").read_text().splitlines():
        pattern = raw.strip()
        if not pattern or pattern.startswith("#"):
            continue
        negate = pattern.startswith("!")
        pattern = pattern.lstrip("!").strip("/")
        regex = "".join(
            "(.*/)?"
            if token == "**/"
            else ".*"
            if token == "**"
            else "[^/]*"
            if token == "*"
            else re.escape(token)
            for token in re.findall(r"\*\*/|\*\*|\*|[^*]+", pattern)
        )
        parts = path.split("/")
        candidates = ["/".join(parts[: i + 1]) for i in range(len(parts))]
        if any(re.fullmatch(regex, candidate) for candidate in candidates):
            excluded = not negate
    return excluded


def test_dockerignore_keeps_sources_and_drops_secrets_and_environments() -> None:
    """Bad input guarded: generated keys, credentials or the local virtualenv entering the build
    context (and so an image layer); the package sources left out."""
    for kept in (
        "pyproject.toml",
        "README.md",
        "shared/openfusion/__init__.py",
        "services/geometry/__init__.py",
        "deploy/zenoh/prod/router.json5",
        "deploy/zenoh/router.json5",
    ):
        assert not _dockerignore_excludes(kept), kept
    for dropped in (
        ".venv/bin/python",
        ".git/HEAD",
        "deploy/two-host/certs/router-key.pem",
        "deploy/two-host/secrets/credentials.txt",
        "deploy/zenoh/prod/secrets/credentials.txt",
        "deploy/zenoh/certs/ca-key.pem",
        "shared/openfusion/__pycache__/frame.cpython-311.pyc",
        "tests/test_deploy_files.py",
        "out/run/map.npz",
    ):
        assert _dockerignore_excludes(dropped), dropped


@pytest.mark.parametrize("name", ["Dockerfile.cpu", "Dockerfile.cuda"])
def test_dockerfile_copies_only_existing_unignored_sources(name: str) -> None:
    """Bad input guarded: a COPY of a file that does not exist or that .dockerignore drops (the
    build would fail), installing the project before torch (pulls the wrong torch build)."""
    instructions = _instructions(_dockerfile(name))
    copies = [args.split() for word, args in instructions if word == "COPY"]
    assert copies
    for args in copies:
        for source in args[:-1]:
            assert (ROOT / source).exists(), f"{name}: COPY {source} does not exist"
            probe = next((ROOT / source).rglob("*.py"), None) if (ROOT / source).is_dir() else ROOT / source
            if probe is not None:
                relative = probe.relative_to(ROOT).as_posix()
                assert not _dockerignore_excludes(relative), f"{name}: .dockerignore drops {relative}"
    runs = [args for word, args in instructions if word == "RUN"]
    torch_at = next(i for i, run in enumerate(runs) if "torch==${TORCH_VERSION}" in run)
    project_at = next(
        i for i, run in enumerate(runs) if re.search(r"pip install (\"\.\[gpu\]\"|\.)(\s|$)", run)
    )
    assert torch_at < project_at
    assert ("USER", "openfusion") in instructions
    assert instructions[-1] == ("CMD", '["openfusion", "run"]')


def test_dockerfile_cpu_pins_cpu_torch_on_python_slim() -> None:
    """Bad input guarded: a CUDA torch in the CPU image, a missing system library open3d needs."""
    instructions = _instructions(_dockerfile("Dockerfile.cpu"))
    assert instructions[0] == ("FROM", "python:3.11-slim")
    assert ("ARG", "TORCH_VERSION=2.13.0") in instructions
    runs = " ".join(args for word, args in instructions if word == "RUN")
    assert "--index-url https://download.pytorch.org/whl/cpu" in runs
    assert "libusb-1.0-0" in runs and "libgomp1" in runs
    assert "torch.cuda.is_available()" in runs  # the build fails if a CUDA torch slipped in


def test_dockerfile_cuda_uses_a_cuda_base_and_the_gpu_extra() -> None:
    """Bad input guarded: a CPU base image, a CPU torch index, the CPU onnxruntime shadowing
    onnxruntime-gpu, a `gpu` extra that pyproject does not define."""
    text = _dockerfile("Dockerfile.cuda")
    instructions = _instructions(text)
    base = dict(args.split("=", 1) for word, args in instructions if word == "ARG" and "=" in args)
    assert re.fullmatch(r"nvidia/cuda:[0-9.]+-cudnn-runtime-ubuntu[0-9.]+", base["CUDA_BASE"])
    assert ("FROM", "${CUDA_BASE}") in instructions
    assert base["TORCH_VERSION"] == "2.13.0"
    assert re.fullmatch(r"https://download\.pytorch\.org/whl/cu[0-9]+", base["TORCH_INDEX"])
    runs = " ".join(args for word, args in instructions if word == "RUN")
    assert "pip uninstall -y onnxruntime" in runs and "CUDAExecutionProvider" in runs
    pyproject = (ROOT / "pyproject.toml").read_text()
    assert re.search(r'^gpu\s*=\s*\[[^\]]*"onnxruntime-gpu', pyproject, re.MULTILINE), (
        "no `gpu` extra with onnxruntime-gpu"
    )


# --------------------------------------------------------------------------- plain Zenoh configs


def test_plain_configs_parse_with_the_documented_modes() -> None:
    """Bad input guarded: multicast scouting left on, dev endpoints leaving loopback, a router
    not on 7447, a client that retries forever."""
    dev = zenoh.Config.from_file(ZENOH_DIR / "dev.json5")
    assert json.loads(dev.get_json("mode")) == "peer"
    endpoints = json.loads(dev.get_json("listen/endpoints")) + json.loads(dev.get_json("connect/endpoints"))
    assert endpoints and all(ep.startswith("tcp/127.0.0.1:") for ep in endpoints)
    router = zenoh.Config.from_file(ZENOH_DIR / "router.json5")
    assert json.loads(router.get_json("mode")) == "router"
    assert json.loads(router.get_json("listen/endpoints")) == ["tcp/0.0.0.0:7447"]
    client = zenoh.Config.from_file(ZENOH_DIR / "client.json5")
    assert json.loads(client.get_json("mode")) == "client"
    assert json.loads(client.get_json("connect/endpoints")) == [ROUTER_ENDPOINT]
    assert json.loads(client.get_json("connect/timeout_ms")) > 0
    for config in (dev, router, client):
        assert json.loads(config.get_json("scouting/multicast/enabled")) is False


# --------------------------------------------------------------------------- the real CLI


def _cli_parser_for(argv: list[str]) -> Any:
    """The `openfusion` argparse parser ready to parse ``argv`` (openfusion.app.cli.build_parser
    loads only the arguments of the sub-command named in argv, and returns (parser, loaded))."""
    try:
        cli = importlib.import_module("openfusion.app.cli")
    except ImportError as error:
        pytest.fail(f"openfusion.app.cli cannot be imported: {error}")
    builder = getattr(cli, "build_parser", None)
    if not callable(builder):
        pytest.fail("openfusion.app.cli exposes no build_parser(argv)")
    built = builder(argv)
    return built[0] if isinstance(built, tuple) else built


def test_compose_commands_parse_with_cli(capsys: pytest.CaptureFixture[str]) -> None:
    """Every command and health check in the compose files is a real `openfusion` invocation.

    Bad input guarded: an option the CLI does not have, a misspelt sub-command, a missing
    required value. Until `openfusion service` exists in openfusion.app.cli this test fails, listing
    the service commands the CLI rejects.
    """
    argvs: list[tuple[str, list[str]]] = []
    files = [
        (ROOT / "docker-compose.yml", {}),
        (ROOT / "docker-compose.gpu.yml", {}),
        (ROOT / "docker-compose.robots.yml", {}),
        (TWO_HOST / "robot.compose.yml", {}),
        (TWO_HOST / "gpu.compose.yml", {"ROBOT_HOST": "robot.local"}),
        (ROOT / "deploy" / "pool" / "gpu-workers.compose.yml", {"ROUTER_HOST": "robot.local"}),
    ]
    for path, env in files:
        for name, service in load_compose(path, env=env).get("services", {}).items():
            if "command" in service:
                argvs.append((f"{path.name}:{name}", service["command"]))
            test = service.get("healthcheck", {}).get("test", [])
            if test[1:2] == ["openfusion"]:
                argvs.append((f"{path.name}:{name} healthcheck", test[1:]))
    assert len(argvs) >= 14
    rejected = []
    for where, argv in argvs:
        assert argv[0] == "openfusion"
        try:
            _cli_parser_for(argv[1:]).parse_args(argv[1:])
        except SystemExit as error:
            rejected.append(
                f"{where}: `{shlex.join(argv)}` (exit {error.code}): {capsys.readouterr().err.strip()}"
            )
    assert not rejected, "the openfusion CLI rejects:\n" + "\n".join(rejected)


# --------------------------------------------------------------------------- prod access control

#: The identity (deploy/zenoh/prod) each service runs as.
PROD_IDENTITY = {"bridge": "robot-sensor", "geometry": "geometry", "semantic": "gpu-semantic", "query": "query-service"}


def _prod_rules_of(identity: str) -> list[dict[str, Any]]:
    acl = json.loads(zenoh.Config.from_file(ZENOH_DIR / "prod" / "router.json5").get_json("access_control"))
    rules = {rule["id"]: rule for rule in acl["rules"]}
    subjects = {s["id"] for s in acl["subjects"] if identity in s["usernames"]}
    names = [name for p in acl["policies"] if subjects & set(p["subjects"]) for name in p["rules"]]
    return [rules[name] for name in names]


def _allows(identity: str, flow: str, message: str, key: str) -> bool:
    return any(flow in r["flows"] and message in r["messages"]
               and any(zenoh.KeyExpr(expr).includes(zenoh.KeyExpr(key)) for expr in r["key_exprs"])
               for r in _prod_rules_of(identity))


def test_prod_acl_lets_every_service_serve_and_publish_its_own_keys() -> None:
    """Every queryable and topic of openfusion.wire.endpoints (semantic/merge included) can be
    declared by the identity of the service that owns it; the encoder pool's keys (outside any
    map) by the semantic box's identity. A key added without its ACL rule fails here, not on a
    TLS deployment."""
    from openfusion.wire.endpoints import ENDPOINTS, TOPICS
    from openfusion.wire.keys import KeySpace, PoolKeys

    keys = KeySpace("openfusion", "lab-1")
    for endpoint in ENDPOINTS:
        identity = PROD_IDENTITY[endpoint.owner]
        assert _allows(identity, "ingress", "declare_queryable", endpoint.key(keys)), (identity, endpoint.path)
        assert _allows(identity, "ingress", "reply", endpoint.key(keys)), (identity, endpoint.path)
    for topic in TOPICS:
        assert _allows(PROD_IDENTITY[topic.publisher], "ingress", "put", topic.key(keys)), topic.path
    # Geometry asks the semantic service for a merge pass before it saves.
    assert _allows("geometry", "ingress", "query", "openfusion/lab-1/semantic/merge")
    assert _allows("gpu-semantic", "egress", "query", "openfusion/lab-1/semantic/merge")
    pool = PoolKeys("openfusion")
    for message in ("declare_queryable", "reply", "query"):
        assert _allows("gpu-semantic", "ingress", message, pool.encode("w1")), message
        assert _allows("gpu-semantic", "egress", message, pool.info("w1")), message
    assert _allows("gpu-semantic", "ingress", "liveliness_token", pool.worker("w1"))
    assert _allows("gpu-semantic", "ingress", "liveliness_query", pool.workers)
    assert not _allows("query-client", "ingress", "query", "openfusion/lab-1/semantic/merge")
    # A geometry replica with no checkpoint asks its peer (also geometry) for one, and gets the replies.
    from openfusion.wire.endpoints import GEOMETRY_CHECKPOINT_CHUNK
    from openfusion.wire.keys import ShardId

    peer_key = GEOMETRY_CHECKPOINT_CHUNK.peer_key(keys, ShardId(0, 2))
    assert _allows("geometry", "ingress", "query", peer_key) and _allows("geometry", "egress", "query", peer_key)
    assert _allows("geometry", "ingress", "reply", peer_key) and _allows("geometry", "egress", "reply", peer_key)


def test_two_host_shards_split_the_map_and_name_each_shard_as_its_health_key() -> None:
    """deploy/two-host/*.shards.compose.yml: shard 0/2 on the robot, 1/2 on the second host, each
    health check requiring the name the shard reports under, the bridge waiting for both (bad input
    guarded: a shard spec geometry would refuse, a health name that is not the shard's, a bridge
    whose shard count differs from the shards')."""
    from openfusion.services.geometry.service import GeometrySection

    robot = load_compose(TWO_HOST / "robot.compose.yml", TWO_HOST / "robot.shards.compose.yml")
    gpu = load_compose(TWO_HOST / "gpu.compose.yml", TWO_HOST / "gpu.shards.compose.yml", env={"ROBOT_HOST": "robot.local"})
    shards = [robot["services"]["geometry"], gpu["services"]["geometry-1of2"]]
    specs = [GeometrySection(shard=option(s["command"], "--shard")).shard_id for s in shards]
    assert [str(s) for s in specs] == ["0/2", "1/2"]
    for service, spec in zip(shards, specs, strict=True):
        assert option(health_argv(service), "--require") == spec.service
        assert option(service["command"], "--zenoh-config") == "/etc/openfusion/secrets/client-geometry.json5"
        assert "--map-dir" in service["command"]
    assert option(gpu["services"]["geometry-1of2"]["command"], "--connect") == "tls/robot.local:7447"
    assert option(robot["services"]["bridge"]["command"], "--geometry-shards") == "2"
