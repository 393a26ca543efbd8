"""The deployment's zenoh security (deploy/zenoh/*.json5, docs/security.md), on loopback.

The router runs the example configuration itself; only addresses, file paths and passwords are
replaced, with certificates made here by the ``openssl`` command (a throw-away CA). Checked:
authorised puts arrive; unauthorised puts to protected keys never reach a subscriber; a wrong
password or an unknown user cannot connect; TLS works with the CA and is refused without it,
with another CA, or when the certificate names another host.

Non-delivery is shown without waiting for a time: after its puts, each publisher puts a probe
(a test-only key every test user may publish) on the same session, and the probe is awaited.
One session's puts of one priority travel in order through the router, so when the probe
arrives, every earlier put of that session has been delivered or dropped.
"""
from __future__ import annotations

import json
import shutil
import subprocess
import threading
import time
from contextlib import ExitStack, contextmanager
from pathlib import Path

import pytest
import zenoh
from support import free_port

ROOT = Path(__file__).resolve().parents[3]
DEPLOY = ROOT / "deploy" / "zenoh"
ROBOT = "paper_robot"
PASSWORDS = {"gateway": "gw-secret", "controller": "ctl-secret", "observer": "obs-secret", "intruder": "in-secret"}
WAIT_S = 15.0      # a missing probe becomes a failure after this; nothing waits for a fixed time

needs_openssl = pytest.mark.skipif(shutil.which("openssl") is None, reason="needs the openssl command")


# --- certificates and credentials --------------------------------------------------------------

def _openssl(*args: str, cwd: Path) -> None:
    subprocess.run(["openssl", *args], cwd=cwd, check=True, capture_output=True)


def _ca(d: Path, name: str) -> None:
    _openssl("req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes",
             "-keyout", f"{name}.key", "-out", f"{name}.crt", "-days", "2", "-subj", f"/CN=bsc test {name}",
             "-addext", "basicConstraints=critical,CA:TRUE", "-addext", "keyUsage=critical,keyCertSign,cRLSign", cwd=d)


def _leaf(d: Path, name: str, ca: str, san: str) -> None:
    (d / f"{name}.ext").write_text("basicConstraints=critical,CA:FALSE\nkeyUsage=critical,digitalSignature\n"
                                   f"extendedKeyUsage=serverAuth,clientAuth\nsubjectAltName={san}\n")
    _openssl("req", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes", "-keyout", f"{name}.key",
             "-out", f"{name}.csr", "-subj", f"/CN={name}", cwd=d)
    _openssl("x509", "-req", "-in", f"{name}.csr", "-CA", f"{ca}.crt", "-CAkey", f"{ca}.key", "-CAcreateserial",
             "-out", f"{name}.crt", "-days", "2", "-extfile", f"{name}.ext", cwd=d)


@pytest.fixture(scope="module")
def pki(tmp_path_factory) -> Path:
    if shutil.which("openssl") is None:
        pytest.skip("needs the openssl command")
    d = tmp_path_factory.mktemp("pki")
    _ca(d, "ca")
    _ca(d, "other-ca")
    _leaf(d, "router", "ca", "IP:127.0.0.1,DNS:localhost")
    _leaf(d, "elsewhere", "ca", "DNS:elsewhere.invalid")          # right CA, wrong host name
    (d / "credentials.txt").write_text("".join(f"bsc-{u}:{p}\n" for u, p in PASSWORDS.items()))
    (d / "credentials.txt").chmod(0o600)
    return d


# --- configurations: the deployment files, re-pointed ------------------------------------------

def router_config(pki: Path, endpoint: str, cert: str = "router") -> zenoh.Config:
    conf = zenoh.Config.from_file(str(DEPLOY / "router.json5"))
    conf.insert_json5("listen/endpoints", json.dumps([endpoint]))
    conf.insert_json5("transport/link/tls/listen_certificate", json.dumps(str(pki / f"{cert}.crt")))
    conf.insert_json5("transport/link/tls/listen_private_key", json.dumps(str(pki / f"{cert}.key")))
    conf.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(str(pki / "ca.crt")))
    conf.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(pki / "credentials.txt")))
    # test only: every test user may publish probes (see the module docstring)
    acl = json.loads(conf.get_json("access_control"))
    acl["rules"].append({"id": "test-probe", "permission": "allow", "flows": ["ingress"], "messages": ["put"],
                         "key_exprs": [f"bsc/{ROBOT}/probe/**"]})
    acl["subjects"].append({"id": "test-users", "usernames": [f"bsc-{u}" for u in PASSWORDS]})
    acl["policies"].append({"id": "test-probes", "rules": ["test-probe"], "subjects": ["test-users"]})
    conf.insert_json5("access_control", json.dumps(acl))
    return conf


def client_config(pki: Path, endpoint: str, user: str, password: str | None = None,
                  ca: str | None = "ca") -> zenoh.Config:
    role = user if (DEPLOY / f"{user}.json5").exists() else "observer"
    conf = zenoh.Config.from_file(str(DEPLOY / f"{role}.json5"))
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    conf.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(str(pki / f"{ca}.crt") if ca else None))
    conf.insert_json5("transport/auth/usrpwd/user", json.dumps(f"bsc-{user}"))
    conf.insert_json5("transport/auth/usrpwd/password", json.dumps(PASSWORDS.get(user, "x") if password is None
                                                                   else password))
    return conf


@contextmanager
def running_router(pki: Path, cert: str = "router"):
    ep = f"tls/127.0.0.1:{free_port()}"
    with zenoh.open(router_config(pki, ep, cert)):
        yield ep


class Inbox:
    """The observer's subscriber callback: every (key, payload), and a condition to wait on."""

    def __init__(self):
        self.got: list[tuple[str, bytes]] = []
        self.cond = threading.Condition()

    def __call__(self, sample):
        with self.cond:
            self.got.append((str(sample.key_expr), sample.payload.to_bytes()))
            self.cond.notify_all()

    def wait_for_key(self, key: str, timeout: float = WAIT_S) -> bool:
        with self.cond:
            return self.cond.wait_for(lambda: any(k == key for k, _ in self.got), timeout)

    def data(self) -> set[tuple[str, bytes]]:
        with self.cond:
            return {(k, p) for k, p in self.got if "/probe/" not in k}


def probe_key(who: str, what: str) -> str:
    return f"bsc/{ROBOT}/probe/{who}/{what}"


def warm_up(session, who: str, inbox: Inbox) -> None:
    """Until the observer's subscription is known along this publisher's path, puts may be
    dropped for want of a subscriber: repeat a probe until one arrives."""
    for i in range(int(WAIT_S / 0.1)):
        session.put(probe_key(who, f"warm-{i}"), b"")
        if inbox.wait_for_key(probe_key(who, f"warm-{i}"), timeout=0.1):
            return
    pytest.fail(f"{who}: no probe ever reached the observer")


# --- the tests ---------------------------------------------------------------------------------

K = {
    "wrench": f"bsc/{ROBOT}/sensors/wrench/arm0",
    "imu": f"bsc/{ROBOT}/sensors/imu",
    "bus_health": f"bsc/{ROBOT}/health/bus/arm0",
    "device_health": f"bsc/{ROBOT}/health/device/imu",
    "joint_efforts": f"bsc/{ROBOT}/efforts/joints/arm0",
    "thruster_effort": f"bsc/{ROBOT}/efforts/thrusters",
    "valve_wrenches": f"bsc/{ROBOT}/efforts/valves",
    "alerts": f"bsc/{ROBOT}/alerts",
    "observed_torque_cmd": f"bsc/{ROBOT}/sensors/commands/torque/arm0/j1",
    "torque_cmd": f"bsc/{ROBOT}/commands/torque/arm0/j1",
    "thruster_cmd": f"bsc/{ROBOT}/commands/thrusters",          # bsc control's valve commands
    "drive_cmd": f"bsc/{ROBOT}/commands/drives/arm0",
    "control_status": f"bsc/{ROBOT}/commands/status",
}
# who -> the keys it may publish (every other key of K is refused); "intruder" has valid
# credentials but no role in the access rules.
ALLOWED = {
    "gateway": set(K) - {"torque_cmd", "thruster_cmd", "drive_cmd", "control_status"},   # observes commands only
    "controller": {"torque_cmd", "thruster_cmd", "drive_cmd", "control_status"},
    "observer": set(),
    "intruder": set(),
}


@needs_openssl
def test_only_authorised_roles_publish_protected_keys(pki):
    with running_router(pki) as ep, ExitStack() as stack:
        observer = stack.enter_context(zenoh.open(client_config(pki, ep, "observer")))
        inbox = Inbox()
        stack.callback(observer.declare_subscriber(f"bsc/{ROBOT}/**", inbox).undeclare)
        expected = set()
        for who, allowed in ALLOWED.items():
            # a session of its own even for the observer: a session's own subscribers get its puts
            # locally, without the router (no security question: it only tells itself)
            s = stack.enter_context(zenoh.open(client_config(pki, ep, who)))
            warm_up(s, who, inbox)
            for name, key in K.items():
                payload = f"{who}:{name}".encode()
                s.put(key, payload)
                if name in allowed:
                    expected.add((key, payload))
            s.put(probe_key(who, "done"), b"")
            assert inbox.wait_for_key(probe_key(who, "done")), f"{who}: the probe after the puts never came"
        got = inbox.data()
        assert got - expected == set(), "refused puts were delivered"
        assert expected - got == set(), "authorised puts were lost"
        assert len(expected) == len(K)


@needs_openssl
@pytest.mark.parametrize("user,password", [("observer", "not-the-password"), ("observer", ""),
                                           ("nobody", "x"), ("gateway", PASSWORDS["controller"])],
                         ids=["wrong-password", "empty-password", "unknown-user", "another-users-password"])
def test_bad_credentials_cannot_connect(pki, user, password):
    with running_router(pki) as ep:
        with zenoh.open(client_config(pki, ep, "observer")):      # the router does accept good ones
            pass
        with pytest.raises(zenoh.ZError, match="Unable to connect"):
            zenoh.open(client_config(pki, ep, user, password)).close()


@needs_openssl
def test_tls_with_the_ca_carries_data(pki):
    with running_router(pki) as ep, zenoh.open(client_config(pki, ep, "observer")) as obs, \
            zenoh.open(client_config(pki, ep, "gateway")) as gw:
        inbox = Inbox()
        sub = obs.declare_subscriber(f"bsc/{ROBOT}/**", inbox)
        try:
            warm_up(gw, "gateway", inbox)
            gw.put(K["alerts"], b"over tls")
            gw.put(probe_key("gateway", "done"), b"")
            assert inbox.wait_for_key(probe_key("gateway", "done"))
            assert inbox.data() == {(K["alerts"], b"over tls")}
        finally:
            sub.undeclare()


@needs_openssl
@pytest.mark.parametrize("ca,cert", [(None, "router"), ("other-ca", "router"), ("ca", "elsewhere")],
                         ids=["no-ca-configured", "another-ca", "certificate-for-another-host"])
def test_tls_refused_without_the_right_ca_or_name(pki, ca, cert):
    with running_router(pki, cert) as ep:
        with pytest.raises(zenoh.ZError, match="Unable to connect"):
            zenoh.open(client_config(pki, ep, "observer", ca=ca)).close()


def test_deployment_files_are_strict():
    """The example files themselves: TLS only, deny by default, no multicast, clients never listen."""
    def load(name):
        conf = zenoh.Config.from_file(str(DEPLOY / name))
        return {k: json.loads(conf.get_json(k)) for k in ("mode", "listen", "connect", "scouting", "transport",
                                                            "access_control")}

    router = load("router.json5")
    assert router["mode"] == "router"
    assert router["access_control"]["enabled"] and router["access_control"]["default_permission"] == "deny"
    assert router["transport"]["link"]["protocols"] == ["tls"]
    assert all(e.startswith("tls/") for e in router["listen"]["endpoints"])
    assert router["transport"]["auth"]["usrpwd"]["dictionary_file"]
    for role in ("gateway", "controller", "observer"):
        c = load(f"{role}.json5")
        assert c["mode"] == "client" and c["listen"]["endpoints"] == []
        assert not c["scouting"]["multicast"]["enabled"]
        assert c["transport"]["link"]["tls"]["root_ca_certificate"]
        assert all(e.startswith("tls/") for e in c["connect"]["endpoints"])
        assert c["transport"]["auth"]["usrpwd"]["user"] == f"bsc-{role}"
    users = {line.split(":", 1)[0] for line in (DEPLOY / "credentials.example.txt").read_text().split()}
    assert users == {"bsc-gateway", "bsc-controller", "bsc-observer"}


@needs_openssl
def test_schemas_are_served_by_the_gateway_only(pki):
    """Through the secured router every role reads the payload schemas the gateway serves; a role
    that is not the gateway cannot answer on the schema keys (its queryable is refused)."""
    from gateway import codec

    with running_router(pki) as ep, ExitStack() as stack:
        gw = stack.enter_context(zenoh.open(client_config(pki, ep, "gateway")))
        stack.callback(codec.serve_schemas(gw, ROBOT).undeclare)
        for who in ("observer", "controller"):
            s = stack.enter_context(zenoh.open(client_config(pki, ep, who)))
            deadline = time.monotonic() + WAIT_S
            got = {}
            while set(got) != set(codec.TYPES) and time.monotonic() < deadline:
                got = codec.fetch_schemas(s, ROBOT, timeout_s=1.0)   # the declaration may still be on its way
            assert set(got) == set(codec.TYPES), who
        fake = stack.enter_context(zenoh.open(client_config(pki, ep, "observer")))
        stack.callback(fake.declare_queryable(f"bsc/{ROBOT}/schemas/Forged",
                                              lambda q: q.reply(f"bsc/{ROBOT}/schemas/Forged", b"{}")).undeclare)
        asker = stack.enter_context(zenoh.open(client_config(pki, ep, "controller")))
        names = {str(r.ok.key_expr).rsplit("/", 1)[1] for r in asker.get(f"bsc/{ROBOT}/schemas/**", timeout=2.0)
                 if getattr(r, "ok", None) is not None}
        assert names == set(codec.TYPES)              # the real ones, never the forged one
