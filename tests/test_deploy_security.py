"""Production Zenoh security from deploy/zenoh/prod/: TLS, user/password and access control.

Real Zenoh sessions on loopback. One Python session in router mode runs the COMMITTED production
router config (deploy/zenoh/prod/router.json5) with only its listen endpoint and file paths
rewritten: a free tls/127.0.0.1 port, certificates from scripts/gen_dev_certs.sh and a credentials
file from deploy/zenoh/prod/gen_credentials.sh, generated into a temporary folder. Clients load
the committed per-identity configs (client-<identity>.json5) with the endpoint, CA path and the
generated password rewritten. So these tests exercise the committed rules, not copies of them.

"Denied" is asserted against a positive control in the same test: the denied message is sent
first (``session.put`` always sends, so only the router can stop it), then an allowed one; once
the allowed one has arrived plus a short settle time, the denied one must not have.
"""

from __future__ import annotations

import json
import shutil
import socket
import stat
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import pytest

zenoh = pytest.importorskip("zenoh")

ROOT = next(p for p in Path(__file__).resolve().parents if (p / "pyproject.toml").is_file())
PROD = ROOT / "deploy" / "zenoh" / "prod"
GEN_CERTS = ROOT / "scripts" / "gen_dev_certs.sh"
GEN_CREDENTIALS = PROD / "gen_credentials.sh"
IDENTITIES = ("robot-sensor", "geometry", "gpu-semantic", "query-service", "query-client", "admin")
MAP = "lab"
SETTLE_S = 0.3
WAIT_S = 5.0

pytestmark = [
    pytest.mark.timeout(120),
    pytest.mark.skipif(
        shutil.which("openssl") is None, reason="openssl is needed to generate test certificates"
    ),
]


@dataclass(frozen=True)
class Bundle:
    """Generated development certificates and credentials (in a temporary folder)."""

    certs: Path
    secrets: Path
    passwords: dict[str, str]


@dataclass(frozen=True)
class Router:
    """A running production-config router on loopback."""

    port: int
    bundle: Bundle

    @property
    def endpoint(self) -> str:
        return f"tls/127.0.0.1:{self.port}"


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def _run(*args: str | Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(a) for a in args], capture_output=True, text=True, timeout=60, check=False)


def _wait_until(predicate: Callable[[], bool], timeout_s: float = WAIT_S) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.02)
    return predicate()


def _read_passwords(credentials: Path) -> dict[str, str]:
    passwords = {}
    for line in credentials.read_text().splitlines():
        user, _, password = line.partition(":")
        passwords[user] = password
    return passwords


@pytest.fixture(scope="module")
def bundle(tmp_path_factory: pytest.TempPathFactory) -> Bundle:
    base = tmp_path_factory.mktemp("prod")
    certs, secrets = base / "certs", base / "secrets"
    done = _run(GEN_CERTS, certs)
    assert done.returncode == 0, done.stderr
    done = _run(GEN_CREDENTIALS, secrets)
    assert done.returncode == 0, done.stderr
    return Bundle(certs=certs, secrets=secrets, passwords=_read_passwords(secrets / "credentials.txt"))


def _router_config(bundle: Bundle, endpoint: str) -> zenoh.Config:
    config = zenoh.Config.from_file(PROD / "router.json5")
    config.insert_json5("listen/endpoints", json.dumps([endpoint]))
    config.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(str(bundle.certs / "ca.pem")))
    config.insert_json5("transport/link/tls/listen_certificate", json.dumps(str(bundle.certs / "router.pem")))
    config.insert_json5(
        "transport/link/tls/listen_private_key", json.dumps(str(bundle.certs / "router-key.pem"))
    )
    config.insert_json5(
        "transport/auth/usrpwd/dictionary_file", json.dumps(str(bundle.secrets / "credentials.txt"))
    )
    return config


def _client_config(
    identity: str,
    router: Router,
    *,
    password: str | None = None,
    endpoint: str | None = None,
    ca_path: Path | None = None,
) -> zenoh.Config:
    config = zenoh.Config.from_file(PROD / f"client-{identity}.json5")
    config.insert_json5("connect/endpoints", json.dumps([endpoint or router.endpoint]))
    config.insert_json5("connect/timeout_ms", "0")  # fail at once instead of retrying 10 s
    config.insert_json5(
        "transport/link/tls/root_ca_certificate", json.dumps(str(ca_path or router.bundle.certs / "ca.pem"))
    )
    config.insert_json5(
        "transport/auth/usrpwd/password",
        json.dumps(password if password is not None else router.bundle.passwords[identity]),
    )
    return config


@pytest.fixture(scope="module")
def router(bundle: Bundle) -> Iterator[Router]:
    port = _free_port()
    session = zenoh.open(_router_config(bundle, f"tls/127.0.0.1:{port}"))
    try:
        yield Router(port=port, bundle=bundle)
    finally:
        session.close()


@contextmanager
def _client(identity: str, router: Router, **overrides: object) -> Iterator[zenoh.Session]:
    session = zenoh.open(_client_config(identity, router, **overrides))  # type: ignore[arg-type]
    try:
        yield session
    finally:
        session.close()


class Inbox:
    """Thread-safe list of payloads received by a subscriber or a queryable."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._items: list[bytes] = []

    def add(self, payload: bytes) -> None:
        with self._lock:
            self._items.append(payload)

    @property
    def items(self) -> list[bytes]:
        with self._lock:
            return list(self._items)


def _subscribe(session: zenoh.Session, key: str) -> tuple[object, Inbox]:
    inbox = Inbox()
    subscriber = session.declare_subscriber(key, lambda sample: inbox.add(sample.payload.to_bytes()))
    return subscriber, inbox


def _serve(session: zenoh.Session, key: str, answer: bytes) -> tuple[object, Inbox]:
    """A queryable on ``key`` that records each query it receives and answers ``answer``."""
    inbox = Inbox()

    def on_query(query: zenoh.Query) -> None:
        inbox.add(str(query.key_expr).encode())
        query.reply(key, answer)  # on the declared (concrete) key, as services do

    return session.declare_queryable(key, on_query), inbox


def _ask(session: zenoh.Session, key: str, *, timeout_s: float = 2.0) -> list[bytes]:
    return [
        reply.ok.payload.to_bytes() for reply in session.get(key, timeout=timeout_s) if reply.ok is not None
    ]


def _key(*parts: str) -> str:
    return "/".join(("openfusion", MAP, *parts))


# --------------------------------------------------------------------------- configs and scripts


def test_prod_configs_parse_and_every_identity_has_a_policy() -> None:
    """Bad input guarded: a policy naming a rule or subject that does not exist, an identity
    without a client config or without a policy, a client allowed plain tcp or multicast."""
    router_cfg = zenoh.Config.from_file(PROD / "router.json5")
    acl = json.loads(router_cfg.get_json("access_control"))
    assert acl["enabled"] is True
    assert acl["default_permission"] == "deny"
    assert json.loads(router_cfg.get_json("transport/link/protocols")) == ["tls"]
    assert json.loads(router_cfg.get_json("scouting/multicast/enabled")) is False
    assert json.loads(router_cfg.get_json("listen/endpoints")) == ["tls/0.0.0.0:7447"]

    rule_ids = {rule["id"] for rule in acl["rules"]}
    subject_users = {subject["id"]: subject["usernames"] for subject in acl["subjects"]}
    used_rules: set[str] = set()
    covered: set[str] = set()
    for policy in acl["policies"]:
        assert set(policy["rules"]) <= rule_ids, f"policy {policy['id']} names unknown rules"
        assert set(policy["subjects"]) <= set(subject_users), f"policy {policy['id']} names unknown subjects"
        used_rules |= set(policy["rules"])
        for subject in policy["subjects"]:
            covered |= set(subject_users[subject])
    assert used_rules == rule_ids, f"rules no policy uses: {sorted(rule_ids - used_rules)}"
    assert covered == set(IDENTITIES)
    for rule in acl["rules"]:
        assert rule["permission"] == "allow"
        assert all(key.startswith("openfusion/") for key in rule["key_exprs"]), rule["id"]

    for identity in IDENTITIES:
        client_cfg = zenoh.Config.from_file(PROD / f"client-{identity}.json5")
        assert json.loads(client_cfg.get_json("mode")) == "client"
        assert json.loads(client_cfg.get_json("transport/auth/usrpwd/user")) == identity
        assert json.loads(client_cfg.get_json("transport/auth/usrpwd/password")) == "CHANGE-ME"
        assert json.loads(client_cfg.get_json("transport/link/protocols")) == ["tls"]
        assert json.loads(client_cfg.get_json("scouting/multicast/enabled")) is False
        assert all(ep.startswith("tls/") for ep in json.loads(client_cfg.get_json("connect/endpoints")))


def test_generated_client_configs_carry_the_router_passwords(bundle: Bundle) -> None:
    """Bad input guarded: a generated config still holding the placeholder, a password that does
    not match the router's dictionary, shared passwords, secrets readable by others."""
    assert set(bundle.passwords) == set(IDENTITIES)
    assert len(set(bundle.passwords.values())) == len(IDENTITIES)
    assert all(len(password) == 32 for password in bundle.passwords.values())
    for identity in IDENTITIES:
        path = bundle.secrets / f"client-{identity}.json5"
        config = zenoh.Config.from_file(path)
        assert json.loads(config.get_json("transport/auth/usrpwd/password")) == bundle.passwords[identity]
        assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert stat.S_IMODE((bundle.secrets / "credentials.txt").stat().st_mode) == 0o600
    assert (bundle.secrets / ".gitignore").read_text().strip() == "*"


def test_gen_credentials_refuses_to_overwrite(bundle: Bundle) -> None:
    """Bad input guarded: running the generator twice silently rotating every password."""
    before = (bundle.secrets / "credentials.txt").read_text()
    done = _run(GEN_CREDENTIALS, bundle.secrets)
    assert done.returncode != 0
    assert "--force" in done.stderr
    assert (bundle.secrets / "credentials.txt").read_text() == before


def test_gen_dev_certs_chain_names_and_key_modes(bundle: Bundle, tmp_path: Path) -> None:
    """Bad input guarded: a router certificate that does not chain to the CA or lacks the names
    clients connect to, world-readable keys, silent overwrite, a malformed --san."""
    certs = bundle.certs
    for leaf in ("router.pem", "client-admin.pem", "client-robot-sensor.pem"):
        done = _run("openssl", "verify", "-CAfile", certs / "ca.pem", certs / leaf)
        assert done.returncode == 0, done.stdout + done.stderr
    text = _run("openssl", "x509", "-in", certs / "router.pem", "-noout", "-ext", "subjectAltName").stdout
    for name in ("DNS:localhost", "IP Address:127.0.0.1", "DNS:router"):
        assert name in text
    client_cn = _run("openssl", "x509", "-in", certs / "client-gpu-semantic.pem", "-noout", "-subject").stdout
    assert "CN=gpu-semantic" in client_cn.replace(" = ", "=")
    for key in certs.glob("*-key.pem"):
        assert stat.S_IMODE(key.stat().st_mode) == 0o600, key.name
    assert (certs / ".gitignore").read_text().strip() == "*"

    before = (certs / "router.pem").read_bytes()
    again = _run(GEN_CERTS, certs)
    assert again.returncode != 0 and "--force" in again.stderr
    assert (certs / "router.pem").read_bytes() == before

    bad = _run(GEN_CERTS, tmp_path / "bad", "--san", "not a host")
    assert bad.returncode != 0 and "--san" in bad.stderr
    assert not (tmp_path / "bad").exists()

    extra = _run(
        GEN_CERTS, tmp_path / "extra", "--san", "gpu-box.local", "--san", "10.1.2.3", "--client", "ops"
    )
    assert extra.returncode == 0, extra.stderr
    text = _run(
        "openssl", "x509", "-in", tmp_path / "extra" / "router.pem", "-noout", "-ext", "subjectAltName"
    ).stdout
    assert "DNS:gpu-box.local" in text and "IP Address:10.1.2.3" in text
    assert sorted(p.name for p in (tmp_path / "extra").glob("client-*")) == [
        "client-ops-key.pem",
        "client-ops.pem",
    ]


# --------------------------------------------------------------------------- authentication


def test_wrong_or_missing_password_is_refused(router: Router) -> None:
    """Bad input: a wrong password, an unknown user, no credentials at all. Observed behaviour:
    a client's zenoh.open raises ZError at once (the router closes the handshake); a peer with a
    wrong password opens (peer connect failures are not fatal) but is never connected to the
    router, so nothing it puts reaches a subscriber behind the router."""
    with _client("geometry", router) as geometry:
        _sub, inbox = _subscribe(geometry, _key("sensor", "rgbd"))
        time.sleep(SETTLE_S)

        with pytest.raises(zenoh.ZError):
            zenoh.open(_client_config("robot-sensor", router, password="not-the-password"))
        unknown = _client_config("robot-sensor", router)
        unknown.insert_json5("transport/auth/usrpwd/user", json.dumps("intruder"))
        with pytest.raises(zenoh.ZError):
            zenoh.open(unknown)
        anonymous = _client_config("robot-sensor", router)
        anonymous.insert_json5("transport/auth/usrpwd", json.dumps({"user": None, "password": None}))
        with pytest.raises(zenoh.ZError):
            zenoh.open(anonymous)

        peer_cfg = _client_config("robot-sensor", router, password="not-the-password")
        peer_cfg.insert_json5("mode", json.dumps("peer"))
        peer_cfg.insert_json5("listen/endpoints", "[]")
        peer_cfg.insert_json5("connect/exit_on_failure", "false")
        peer = zenoh.open(peer_cfg)
        try:
            assert list(peer.info.routers_zid()) == []
            peer.put(_key("sensor", "rgbd"), b"from-wrong-password-peer")
        finally:
            peer.close()

        with _client("robot-sensor", router) as sensor:  # positive control
            assert len(list(sensor.info.routers_zid())) == 1
            sensor.put(_key("sensor", "rgbd"), b"from-robot")
            assert _wait_until(lambda: b"from-robot" in inbox.items)
        time.sleep(SETTLE_S)
        assert inbox.items == [b"from-robot"]


def test_tls_with_test_ca_connects_plain_tcp_and_foreign_ca_fail(router: Router, tmp_path: Path) -> None:
    """Bad input: a plain tcp client on the TLS port, a client that trusts another CA, a client
    that trusts no CA (web PKI roots only). A client with the test CA connecting by name
    (tls/localhost) is accepted and its frames arrive."""
    with _client("geometry", router) as geometry:
        _sub, inbox = _subscribe(geometry, _key("sensor", "rgbd"))
        time.sleep(SETTLE_S)
        with _client("robot-sensor", router, endpoint=f"tls/localhost:{router.port}") as sensor:
            sensor.put(_key("sensor", "rgbd"), b"over-tls")
            assert _wait_until(lambda: b"over-tls" in inbox.items)

    plain = zenoh.Config.from_file(ROOT / "deploy" / "zenoh" / "client.json5")
    plain.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{router.port}"]))
    plain.insert_json5("connect/timeout_ms", "0")
    plain.insert_json5(
        "transport/auth/usrpwd", json.dumps({"user": "admin", "password": router.bundle.passwords["admin"]})
    )
    with pytest.raises(zenoh.ZError):
        zenoh.open(plain)

    other = tmp_path / "other-ca"
    done = _run(GEN_CERTS, other, "--client", "x")
    assert done.returncode == 0, done.stderr
    with pytest.raises(zenoh.ZError):
        zenoh.open(_client_config("admin", router, ca_path=other / "ca.pem"))

    no_ca = _client_config("admin", router)
    no_ca.insert_json5("transport/link/tls/root_ca_certificate", "null")
    with pytest.raises(zenoh.ZError):
        zenoh.open(no_ca)


# --------------------------------------------------------------------------- access control


def test_only_sensor_identities_put_frames(router: Router) -> None:
    """Bad input: frames put by identities that must not publish them (query client, query
    service); robot-sensor's and admin's frames arrive."""
    with (
        _client("geometry", router) as geometry,
        _client("robot-sensor", router) as sensor,
        _client("query-client", router) as asker,
        _client("query-service", router) as query_service,
        _client("admin", router) as admin,
    ):
        _sub, inbox = _subscribe(geometry, _key("sensor", "rgbd"))
        time.sleep(SETTLE_S)
        asker.put(_key("sensor", "rgbd"), b"query-client")
        query_service.put(_key("sensor", "rgbd"), b"query-service")
        denied_publisher = asker.declare_publisher(_key("sensor", "rgbd"))
        publisher = sensor.declare_publisher(_key("sensor", "rgbd"))
        assert _wait_until(lambda: publisher.matching_status.matching)
        publisher.put(b"robot-sensor")
        admin.put(_key("sensor", "rgbd"), b"admin")
        assert _wait_until(lambda: {b"robot-sensor", b"admin"} <= set(inbox.items))
        time.sleep(SETTLE_S)
        # The query client is not even told that a subscriber exists.
        assert denied_publisher.matching_status.matching is False
        assert sorted(inbox.items) == [b"admin", b"robot-sensor"]


def test_sensor_identity_cannot_write_outside_sensor_keys(router: Router) -> None:
    """Bad input: robot-sensor putting semantic updates, dictionary deltas, another map's control
    keys; gpu-semantic's update and delta (positive controls) arrive."""
    with (
        _client("geometry", router) as geometry,
        _client("query-service", router) as query_service,
        _client("robot-sensor", router) as sensor,
        _client("gpu-semantic", router) as semantic,
    ):
        _sub_u, updates = _subscribe(geometry, _key("semantic", "update"))
        _sub_d, deltas = _subscribe(query_service, _key("semantic", "dictionary", "delta"))
        time.sleep(SETTLE_S)
        sensor.put(_key("semantic", "update"), b"robot-sensor")
        sensor.put(_key("semantic", "dictionary", "delta"), b"robot-sensor")
        semantic.put(_key("semantic", "update"), b"gpu-semantic")
        semantic.put(_key("semantic", "dictionary", "delta"), b"gpu-semantic")
        assert _wait_until(lambda: updates.items and deltas.items)
        time.sleep(SETTLE_S)
        assert updates.items == [b"gpu-semantic"]
        assert deltas.items == [b"gpu-semantic"]


def test_sensor_identity_reads_geometry_progress_and_nothing_else_of_geometry(router: Router) -> None:
    """The bridge's flow control: robot-sensor receives geometry's acknowledgements on
    geometry/progress. Bad input: robot-sensor subscribing to other geometry keys (render, points)
    and putting a forged acknowledgement; the query client subscribing to progress."""
    with (
        _client("geometry", router) as geometry,
        _client("robot-sensor", router) as sensor,
        _client("query-client", router) as asker,
    ):
        _sub_p, progress = _subscribe(sensor, _key("geometry", "progress"))
        _sub_r, render = _subscribe(sensor, _key("geometry", "render"))
        _sub_q, asked = _subscribe(asker, _key("geometry", "progress"))
        _sub_g, forged = _subscribe(geometry, _key("geometry", "progress"))
        time.sleep(SETTLE_S)
        sensor.put(_key("geometry", "progress"), b"forged-by-robot-sensor")
        geometry.put(_key("geometry", "render"), b"geometry-render")
        geometry.put(_key("geometry", "progress"), b"geometry-ack")
        assert _wait_until(lambda: progress.items)
        time.sleep(SETTLE_S)
        # A session's own subscribers see its own puts (Zenoh delivers them without the router):
        # the forged acknowledgement reaches only robot-sensor itself, never geometry.
        assert progress.items == [b"forged-by-robot-sensor", b"geometry-ack"]
        assert forged.items == [b"geometry-ack"]
        assert render.items == [] and asked.items == []


def test_control_queries_need_the_admin_identity(router: Router) -> None:
    """Bad input: control/save asked by the query client, the robot sensor, the semantic service
    (which may answer control but not ask it). Only the admin's query reaches the queryable."""
    with (
        _client("geometry", router) as geometry,
        _client("query-client", router) as asker,
        _client("robot-sensor", router) as sensor,
        _client("gpu-semantic", router) as semantic,
        _client("admin", router) as admin,
    ):
        _qbl, received = _serve(geometry, _key("control", "save"), b"saved")
        time.sleep(SETTLE_S)
        for session in (asker, sensor, semantic):
            assert _ask(session, _key("control", "save"), timeout_s=1.0) == []
        assert received.items == []
        assert _ask(admin, _key("control", "save")) == [b"saved"]
        assert received.items == [_key("control", "save").encode()]


def test_query_client_may_only_ask_queries(router: Router) -> None:
    """Bad input: the query client asking geometry points, the dictionary, subscribing to frames.
    Its text query is answered."""
    with (
        _client("geometry", router) as geometry,
        _client("gpu-semantic", router) as semantic,
        _client("query-service", router) as query_service,
        _client("robot-sensor", router) as sensor,
        _client("query-client", router) as asker,
    ):
        _q1, text_queries = _serve(query_service, _key("query", "text"), b"regions")
        _q2, point_queries = _serve(geometry, _key("geometry", "points"), b"points")
        _q3, dict_queries = _serve(semantic, _key("semantic", "dictionary"), b"dictionary")
        _s1, asker_frames = _subscribe(asker, _key("sensor", "rgbd"))
        _s2, geometry_frames = _subscribe(geometry, _key("sensor", "rgbd"))
        time.sleep(SETTLE_S)

        assert _ask(asker, _key("query", "text")) == [b"regions"]
        assert _ask(asker, _key("geometry", "points"), timeout_s=1.0) == []
        assert _ask(asker, _key("semantic", "dictionary"), timeout_s=1.0) == []
        assert point_queries.items == [] and dict_queries.items == []
        # The services that need them are answered (positive controls).
        assert _ask(query_service, _key("geometry", "points")) == [b"points"]
        assert _ask(query_service, _key("semantic", "dictionary")) == [b"dictionary"]

        sensor.put(_key("sensor", "rgbd"), b"frame")
        assert _wait_until(lambda: geometry_frames.items == [b"frame"])
        time.sleep(SETTLE_S)
        assert asker_frames.items == []
        assert len(text_queries.items) == 1


def test_dictionary_is_served_only_by_semantic_or_admin(router: Router) -> None:
    """Bad input: geometry and the query client declaring a queryable on the dictionary key
    (a forged dictionary). Only the semantic service's answer reaches the reader."""
    with (
        _client("gpu-semantic", router) as semantic,
        _client("geometry", router) as geometry,
        _client("query-client", router) as asker,
        _client("query-service", router) as query_service,
    ):
        _q1, forged_geometry = _serve(geometry, _key("semantic", "dictionary"), b"forged-by-geometry")
        _q2, forged_client = _serve(asker, _key("semantic", "dictionary"), b"forged-by-client")
        _q3, genuine = _serve(semantic, _key("semantic", "dictionary"), b"genuine")
        time.sleep(SETTLE_S)
        assert _ask(query_service, _key("semantic", "dictionary")) == [b"genuine"]
        assert forged_geometry.items == [] and forged_client.items == []
        assert len(genuine.items) == 1


def test_services_announce_only_themselves(router: Router) -> None:
    """Bad input: the robot-sensor identity declaring the geometry service's liveliness token
    on another map (impersonation); its own bridge token and geometry's own token are seen."""
    with (
        _client("robot-sensor", router) as sensor,
        _client("geometry", router) as geometry,
        _client("admin", router) as admin,
        _client("query-client", router) as asker,
    ):
        tokens = [
            sensor.liveliness().declare_token("openfusion/other/health/geometry"),
            sensor.liveliness().declare_token("openfusion/other/health/bridge"),
            geometry.liveliness().declare_token(_key("health", "geometry")),
        ]
        try:
            time.sleep(SETTLE_S)

            def alive(session: zenoh.Session, key: str) -> list[str]:
                replies = session.liveliness().get(key, timeout=1.0)
                return sorted(str(reply.ok.key_expr) for reply in replies if reply.ok is not None)

            assert alive(admin, "openfusion/other/health/*") == ["openfusion/other/health/bridge"]
            assert alive(admin, _key("health", "*")) == [_key("health", "geometry")]
            assert alive(sensor, _key("health", "*")) == [_key("health", "geometry")]  # health check
            assert alive(asker, _key("health", "*")) == []  # query clients see no health
        finally:
            for token in tokens:
                token.undeclare()


def test_health_check_reads_tokens_and_stats_through_the_router(router: Router) -> None:
    """What `openfusion health` does, as each service identity (compose runs the health check
    inside the service's container with its credentials): a liveliness get and a stats get
    (target ALL) on the wildcard `…/health/*`, and a subscriber on it. Bad input guarded: rules
    written for concrete keys only, which Zenoh does not apply to a wider wildcard query."""
    with (
        _client("geometry", router) as geometry,
        _client("gpu-semantic", router) as semantic,
        _client("robot-sensor", router) as sensor,
    ):
        _qbl, stats_queries = _serve(geometry, _key("health", "geometry"), b"geometry-stats")
        token = geometry.liveliness().declare_token(_key("health", "geometry"))
        publisher = geometry.declare_publisher(_key("health", "geometry"))
        try:
            _sub, stats_seen = _subscribe(sensor, _key("health", "*"))
            assert _wait_until(lambda: publisher.matching_status.matching)
            publisher.put(b"geometry-periodic")
            assert _wait_until(lambda: stats_seen.items == [b"geometry-periodic"])
            for checker in (semantic, sensor):
                replies = checker.liveliness().get(_key("health", "*"), timeout=1.0)
                assert [str(r.ok.key_expr) for r in replies if r.ok is not None] == [
                    _key("health", "geometry")
                ]
                replies = checker.get(
                    _key("health", "*"),
                    timeout=2.0,
                    target=zenoh.QueryTarget.ALL,
                    consolidation=zenoh.QueryConsolidation(zenoh.ConsolidationMode.NONE),
                )
                assert [r.ok.payload.to_bytes() for r in replies if r.ok is not None] == [b"geometry-stats"]
            assert len(stats_queries.items) == 2
        finally:
            token.undeclare()


def _rewrite_paths(source: Path, target: Path, bundle: Bundle) -> Path:
    """Copy a committed/generated config with the container paths pointed at the test files."""
    text = source.read_text()
    assert "/etc/openfusion/certs/" in text
    text = text.replace("/etc/openfusion/certs/", f"{bundle.certs}/")
    text = text.replace("/etc/openfusion/secrets/", f"{bundle.secrets}/")
    target.write_text(text)
    return target


def _openfusion(*args: str, timeout_s: float = 30.0) -> subprocess.CompletedProcess[str]:
    code = "import sys; from openfusion.app.cli import main; sys.exit(main())"
    return subprocess.run(
        [sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=timeout_s, check=False
    )


def test_openfusion_router_runs_the_prod_config_and_health_checks_pass_through_it(
    bundle: Bundle, tmp_path: Path
) -> None:
    """The real CLI, as in deploy/two-host/robot.compose.yml: `openfusion router --listen tls/…
    --zenoh-config prod/router.json5` and `openfusion health --zenoh-config client-<id>.json5
    --connect tls/… --mode client --no-multicast` (the compose health check). A service identity
    sees the live geometry service; a query client sees nothing (exit 1). Bad input guarded: a
    prod config the CLI cannot start a router from, a health check the ACL blocks."""
    port = _free_port()
    endpoint = f"tls/127.0.0.1:{port}"
    router_file = _rewrite_paths(PROD / "router.json5", tmp_path / "router.json5", bundle)
    code = "import sys; from openfusion.app.cli import main; sys.exit(main())"
    router_process = subprocess.Popen(
        [sys.executable, "-c", code, "router", "--listen", endpoint, "--zenoh-config", str(router_file)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:

        def accepting() -> bool:
            assert router_process.poll() is None, "openfusion router exited early"
            with socket.socket() as probe:
                return probe.connect_ex(("127.0.0.1", port)) == 0

        assert _wait_until(accepting, timeout_s=20.0)
        fake_router = Router(port=port, bundle=bundle)
        with _client("geometry", fake_router) as geometry:
            token = geometry.liveliness().declare_token(_key("health", "geometry"))
            try:
                results = {}
                for identity in ("robot-sensor", "query-client"):
                    config = _rewrite_paths(
                        bundle.secrets / f"client-{identity}.json5",
                        tmp_path / f"client-{identity}.json5",
                        bundle,
                    )
                    results[identity] = _openfusion(
                        "health", "--map", MAP, "--zenoh-config", str(config), "--connect", endpoint,
                        "--mode", "client", "--no-multicast", "--timeout", "2",
                    )  # fmt: skip
            finally:
                token.undeclare()
        assert results["robot-sensor"].returncode == 0, results["robot-sensor"].stderr
        assert "geometry" in results["robot-sensor"].stdout
        assert results["query-client"].returncode == 1
        assert "no live services" in results["query-client"].stderr
    finally:
        router_process.terminate()
        try:
            _out, router_err = router_process.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            router_process.kill()
            _out, router_err = router_process.communicate(timeout=5)
    assert router_process.returncode == 0, router_err
