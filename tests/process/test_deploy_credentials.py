"""Production Zenoh security from deploy/zenoh/prod/, part 1: the committed configs, the
credential and certificate generators, authentication (passwords, TLS) and the real
``openfusion router`` with the prod config. Setup and waiting: deploy_support.py."""

from __future__ import annotations

import json
import socket
import stat
import subprocess
import sys
import time
from pathlib import Path

import pytest
import zenoh
from deploy_support import (
    ABSENCE_WINDOW_S,
    GEN_CERTS,
    GEN_CREDENTIALS,
    IDENTITIES,
    MAP,
    MARKS,
    PROD,
    ROOT,
    Bundle,
    Router,
    client,
    client_config,
    key,
    openfusion_cli,
    rewrite_paths,
    run,
    subscribe,
    until_routed,
    wait_for,
)

from openfusion.bus import free_loopback_port

pytestmark = MARKS


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
    done = run(GEN_CREDENTIALS, bundle.secrets)
    assert done.returncode != 0
    assert "--force" in done.stderr
    assert (bundle.secrets / "credentials.txt").read_text() == before


def test_gen_dev_certs_chain_names_and_key_modes(bundle: Bundle, tmp_path: Path) -> None:
    """Bad input guarded: a router certificate that does not chain to the CA or lacks the names
    clients connect to, world-readable keys, silent overwrite, a malformed --san."""
    certs = bundle.certs
    for leaf in ("router.pem", "client-admin.pem", "client-robot-sensor.pem"):
        done = run("openssl", "verify", "-CAfile", certs / "ca.pem", certs / leaf)
        assert done.returncode == 0, done.stdout + done.stderr
    text = run("openssl", "x509", "-in", certs / "router.pem", "-noout", "-ext", "subjectAltName").stdout
    for name in ("DNS:localhost", "IP Address:127.0.0.1", "DNS:router"):
        assert name in text
    client_cn = run("openssl", "x509", "-in", certs / "client-gpu-semantic.pem", "-noout", "-subject").stdout
    assert "CN=gpu-semantic" in client_cn.replace(" = ", "=")
    for key_file in certs.glob("*-key.pem"):
        assert stat.S_IMODE(key_file.stat().st_mode) == 0o600, key_file.name
    assert (certs / ".gitignore").read_text().strip() == "*"

    before = (certs / "router.pem").read_bytes()
    again = run(GEN_CERTS, certs)
    assert again.returncode != 0 and "--force" in again.stderr
    assert (certs / "router.pem").read_bytes() == before

    bad = run(GEN_CERTS, tmp_path / "bad", "--san", "not a host")
    assert bad.returncode != 0 and "--san" in bad.stderr
    assert not (tmp_path / "bad").exists()

    extra = run(
        GEN_CERTS, tmp_path / "extra", "--san", "gpu-box.local", "--san", "10.1.2.3", "--client", "ops"
    )
    assert extra.returncode == 0, extra.stderr
    text = run(
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
    with client("geometry", router) as geometry:
        _sub, inbox = subscribe(geometry, key("sensor", "rgbd"))

        with pytest.raises(zenoh.ZError):
            zenoh.open(client_config("robot-sensor", router, password="not-the-password"))
        unknown = client_config("robot-sensor", router)
        unknown.insert_json5("transport/auth/usrpwd/user", json.dumps("intruder"))
        with pytest.raises(zenoh.ZError):
            zenoh.open(unknown)
        anonymous = client_config("robot-sensor", router)
        anonymous.insert_json5("transport/auth/usrpwd", json.dumps({"user": None, "password": None}))
        with pytest.raises(zenoh.ZError):
            zenoh.open(anonymous)

        peer_cfg = client_config("robot-sensor", router, password="not-the-password")
        peer_cfg.insert_json5("mode", json.dumps("peer"))
        peer_cfg.insert_json5("listen/endpoints", "[]")
        peer_cfg.insert_json5("connect/exit_on_failure", "false")
        peer = zenoh.open(peer_cfg)
        try:
            assert list(peer.info.routers_zid()) == []
            peer.put(key("sensor", "rgbd"), b"from-wrong-password-peer")
        finally:
            peer.close()

        with client("robot-sensor", router) as sensor:  # positive control
            assert len(list(sensor.info.routers_zid())) == 1
            until_routed(sensor, key("sensor", "rgbd"), inbox)
            sensor.put(key("sensor", "rgbd"), b"from-robot")
            assert wait_for(lambda: b"from-robot" in inbox.items)
        time.sleep(ABSENCE_WINDOW_S)  # the wrong-password peer's frame must still be missing
        assert inbox.items == [b"from-robot"]


def test_tls_with_test_ca_connects_plain_tcp_and_foreign_ca_fail(router: Router, tmp_path: Path) -> None:
    """Bad input: a plain tcp client on the TLS port, a client that trusts another CA, a client
    that trusts no CA (web PKI roots only). A client with the test CA connecting by name
    (tls/localhost) is accepted and its frames arrive."""
    with client("geometry", router) as geometry:
        _sub, inbox = subscribe(geometry, key("sensor", "rgbd"))
        with client("robot-sensor", router, endpoint=f"tls/localhost:{router.port}") as sensor:
            until_routed(sensor, key("sensor", "rgbd"), inbox)
            sensor.put(key("sensor", "rgbd"), b"over-tls")
            assert wait_for(lambda: b"over-tls" in inbox.items)

    plain = zenoh.Config.from_file(ROOT / "deploy" / "zenoh" / "client.json5")
    plain.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{router.port}"]))
    plain.insert_json5("connect/timeout_ms", "0")
    plain.insert_json5(
        "transport/auth/usrpwd", json.dumps({"user": "admin", "password": router.bundle.passwords["admin"]})
    )
    with pytest.raises(zenoh.ZError):
        zenoh.open(plain)

    other = tmp_path / "other-ca"
    done = run(GEN_CERTS, other, "--client", "x")
    assert done.returncode == 0, done.stderr
    with pytest.raises(zenoh.ZError):
        zenoh.open(client_config("admin", router, ca_path=other / "ca.pem"))

    no_ca = client_config("admin", router)
    no_ca.insert_json5("transport/link/tls/root_ca_certificate", "null")
    with pytest.raises(zenoh.ZError):
        zenoh.open(no_ca)


def test_openfusion_router_runs_the_prod_config_and_health_checks_pass_through_it(
    bundle: Bundle, tmp_path: Path
) -> None:
    """The real CLI, as in deploy/two-host/robot.compose.yml: `openfusion router --listen tls/…
    --zenoh-config prod/router.json5` and `openfusion health --zenoh-config client-<id>.json5
    --connect tls/… --mode client --no-multicast` (the compose health check). A service identity
    sees the live geometry service; a query client sees nothing (exit 1). Bad input guarded: a
    prod config the CLI cannot start a router from, a health check the ACL blocks."""
    port = free_loopback_port()
    endpoint = f"tls/127.0.0.1:{port}"
    router_file = rewrite_paths(PROD / "router.json5", tmp_path / "router.json5", bundle)
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

        assert wait_for(accepting, timeout_s=20.0)
        fake_router = Router(port=port, bundle=bundle)
        with client("geometry", fake_router) as geometry:
            token = geometry.liveliness().declare_token(key("health", "geometry"))
            try:
                results = {}
                for identity in ("robot-sensor", "query-client"):
                    config = rewrite_paths(
                        bundle.secrets / f"client-{identity}.json5",
                        tmp_path / f"client-{identity}.json5",
                        bundle,
                    )
                    results[identity] = openfusion_cli(
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
