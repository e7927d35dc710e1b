"""TLS, mutual TLS and access control over zenoh loopback, with the shipped configs.

Certificates come from scripts/make_test_certs.py (into tmp folders); the router and
client configs are the files in deploy/zenoh/ rendered with absolute certificate paths
and only their endpoints replaced. Nothing sleeps to synchronise: deliveries are awaited
on queues with timeouts, and "never arrives" is proven either by an allowed message sent
*after* the forbidden one on the same link arriving first (one link delivers in order),
or, where no such sentinel exists, by a bounded wait.
"""
from __future__ import annotations

import contextlib
import datetime as dt
import importlib.util
import json
import os
import queue
import stat
import sys
import threading
import time
from pathlib import Path

import pytest

zenoh = pytest.importorskip("zenoh")
pytest.importorskip("cryptography")
from cryptography import x509  # noqa: E402
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID  # noqa: E402

from services.zenoh_session import free_port  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
DEPLOY = REPO / "deploy" / "zenoh"
NS = "fmapping/tlstest"
NEVER = 1.5  # seconds to wait for something that must not arrive (no sentinel possible)


def _load_script():
    spec = importlib.util.spec_from_file_location("make_test_certs", REPO / "scripts" / "make_test_certs.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("make_test_certs", mod)
    spec.loader.exec_module(mod)
    return mod


mtc = _load_script()


def conf_from(path: Path, **inserts) -> "zenoh.Config":
    """A config file with some keys replaced (key paths use '/', values are JSON)."""
    c = zenoh.Config.from_file(str(path))
    for k, v in inserts.items():
        c.insert_json5(k.replace("__", "/"), json.dumps(v))
    return c


def plain_conf(mode: str, listen=(), connect=(), tls=None, extra=None) -> "zenoh.Config":
    c = zenoh.Config()
    c.insert_json5("mode", json.dumps(mode))
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("transport/shared_memory/enabled", "false")
    c.insert_json5("listen/endpoints", json.dumps(list(listen)))
    c.insert_json5("connect/endpoints", json.dumps(list(connect)))
    if tls is not None:
        c.insert_json5("transport/link/tls", json.dumps({k: str(v) if isinstance(v, Path) else v
                                                         for k, v in tls.items()}))
    for k, v in (extra or {}).items():
        c.insert_json5(k, json.dumps(v))
    return c


def server_tls(certs, name="router", mtls=True):
    return {"root_ca_certificate": certs.ca, "listen_certificate": certs.leaf[name].cert,
            "listen_private_key": certs.leaf[name].key, "enable_mtls": mtls}


def client_tls(ca, kp=None, verify=True):
    t = {"root_ca_certificate": ca, "enable_mtls": kp is not None, "verify_name_on_connect": verify}
    if kp is not None:
        t.update(connect_certificate=kp.cert, connect_private_key=kp.key)
    return t


def mtls_listener(certs, stack, extra=None) -> tuple["zenoh.Session", int]:
    """A peer listening with mutual TLS (the router's certificate) on a free loopback port: (session, port)."""
    port = free_port()
    return stack(zenoh.open(plain_conf("peer", listen=[f"tls/127.0.0.1:{port}"], tls=server_tls(certs),
                                       extra=extra))), port


def mtls_dialler(certs, stack, port: int, kp) -> "zenoh.Session":
    """A peer dialling ``port`` (name verified) with client key pair ``kp`` (None: no certificate)."""
    return stack(zenoh.open(plain_conf("peer", connect=[f"tls/localhost:{port}"], tls=client_tls(certs.ca, kp))))


def deliver(sender, key: str, q: "queue.Queue", payload: bytes = b"x", timeout: float = 5.0):
    """Put until the first sample arrives on ``q`` (declarations take a moment to propagate)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        sender.put(key, payload)
        try:
            return q.get(timeout=0.05)
        except queue.Empty:
            pass
    return None


def drain(q: "queue.Queue") -> list:
    out = []
    while True:
        try:
            out.append(q.get_nowait())
        except queue.Empty:
            return out


def until(q: "queue.Queue", payload: bytes, timeout: float = 5.0) -> list:
    """Everything received before the sample carrying ``payload`` (which must arrive).

    A link delivers in order, so after a sender's marker has arrived, nothing that sender
    put before the marker can still be on the way (warm-up repeats of :func:`deliver`
    included)."""
    seen, deadline = [], time.monotonic() + timeout
    while True:
        left = deadline - time.monotonic()
        assert left > 0, f"{payload!r} never arrived; got {seen}"
        try:
            item = q.get(timeout=left)
        except queue.Empty:
            continue
        if item[2] == payload:
            return seen
        seen.append(item)


def forged(items: list) -> list:
    return [i for i in items if b"FORGED" in i[2]]


def collector(session, key: str, q: "queue.Queue", tag: str = ""):
    return session.declare_subscriber(key, lambda s: q.put((tag, str(s.key_expr), s.payload.to_bytes())))


@pytest.fixture(scope="module")
def certs(tmp_path_factory):
    root = tmp_path_factory.mktemp("certs")
    paths = mtc.make_test_certs(root, names=("io", "tracker", "mapper", "poses", "intruder"))
    mtc.render_configs(root)
    return paths


@pytest.fixture(scope="module")
def other_certs(tmp_path_factory):
    """Same names, different CA: must be refused everywhere."""
    return mtc.make_test_certs(tmp_path_factory.mktemp("other"), names=("io",))


@pytest.fixture
def stack():
    with contextlib.ExitStack() as st:
        def push(obj):  # sessions close, subscribers / queryables undeclare
            st.callback(obj.close if hasattr(obj, "close") else obj.undeclare)
            return obj
        yield push


# ------------------------------------------------------------------- certificate generation
def _cert(path: Path) -> x509.Certificate:
    return x509.load_pem_x509_certificate(path.read_bytes())


def test_make_test_certs_chain(certs, other_certs):
    ca = _cert(certs.ca)
    assert ca.extensions.get_extension_for_class(x509.BasicConstraints).value.ca is True
    ca.verify_directly_issued_by(ca)
    assert set(certs.leaf) == {"router", "io", "tracker", "mapper", "poses", "intruder"}
    for name, kp in certs.leaf.items():
        c = _cert(kp.cert)
        c.verify_directly_issued_by(ca)  # raises if the signature does not check
        assert c.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value == name
        assert c.extensions.get_extension_for_class(x509.BasicConstraints).value.ca is False
        eku = c.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value
        assert {ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH} <= set(eku)
        san = c.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
        assert san.get_values_for_type(x509.DNSName) == ["localhost"]
        assert [str(ip) for ip in san.get_values_for_type(x509.IPAddress)] == ["127.0.0.1"]
        now = dt.datetime.now(dt.timezone.utc)
        assert c.not_valid_before_utc <= now <= c.not_valid_after_utc
        assert stat.S_IMODE(os.stat(kp.key).st_mode) == 0o600
        assert b"PRIVATE KEY" in kp.key.read_bytes()
    assert stat.S_IMODE(os.stat(certs.ca_key).st_mode) == 0o600
    # a second CA does not vouch for the first one's certificates
    with pytest.raises(Exception):
        _cert(certs.leaf["io"].cert).verify_directly_issued_by(_cert(other_certs.ca))


def test_make_test_certs_rejects_bad_input(tmp_path):
    with pytest.raises(ValueError, match="certificate name"):
        mtc.make_test_certs(tmp_path, names=("bad name",))
    with pytest.raises(ValueError, match="days"):
        mtc.make_test_certs(tmp_path, days=0)
    assert mtc.main([str(tmp_path / "x"), "--names", "a/b"]) == 2


def test_make_test_certs_cli(tmp_path, capsys):
    assert mtc.main([str(tmp_path), "--names", "io", "--hosts", "router.local", "10.0.0.7", "--configs"]) == 0
    san = _cert(tmp_path / "io.pem").extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert san.get_values_for_type(x509.DNSName) == ["router.local"]
    assert [str(a) for a in san.get_values_for_type(x509.IPAddress)] == ["10.0.0.7"]
    rendered = {p.name for p in (tmp_path / "zenoh").glob("*.json5")}
    assert rendered == {p.name for p in DEPLOY.glob("*.json5")}
    # container layout: the folder will be mounted at /certs
    assert mtc.main([str(tmp_path), "--names", "io", "--configs", "--config-prefix", "/certs/"]) == 0
    d = json.loads(str(zenoh.Config.from_file(str(tmp_path / "zenoh" / "client-io.json5"))))
    assert d["transport"]["link"]["tls"]["connect_certificate"] == "/certs/io.pem"
    assert d["transport"]["link"]["tls"]["root_ca_certificate"] == "/certs/ca.pem"
    with pytest.raises(ValueError, match="prefix"):
        mtc.render_configs(tmp_path, prefix='a"b')


# --------------------------------------------------------------------------- shipped configs
def test_deploy_configs(certs):
    files = sorted(DEPLOY.glob("*.json5"))
    assert {p.name for p in files} >= {"router.json5", "client-io.json5", "client-tracker.json5",
                                       "client-mapper.json5", "client-poses.json5"}
    router = json.loads(str(zenoh.Config.from_file(str(DEPLOY / "router.json5"))))
    acl = router["access_control"]
    assert router["mode"] == "router" and acl["enabled"] and acl["default_permission"] == "deny"
    tls = router["transport"]["link"]["tls"]
    assert tls["enable_mtls"] is True and router["transport"]["link"]["protocols"] == ["tls"]
    assert all(e.startswith("tls/") for e in router["listen"]["endpoints"])
    cns = {cn for s in acl["subjects"] for cn in s.get("cert_common_names", [])}
    rule_ids = {r["id"] for r in acl["rules"]}
    assert all(set(p["rules"]) <= rule_ids for p in acl["policies"])
    for f in files:
        d = json.loads(str(zenoh.Config.from_file(str(f))))
        link = d["transport"]["link"]
        assert link["protocols"] == ["tls"] and link["tls"]["enable_mtls"] is True, f.name
        assert d["transport"]["shared_memory"]["enabled"] is False, f.name
        assert d["scouting"]["multicast"]["enabled"] is False, f.name
        assert link["rx"]["max_message_size"] >= 160 * 1024 * 1024, f.name
        if f.name.startswith("client-"):
            name = f.name[len("client-"):-len(".json5")]
            assert name in cns, f"{f.name}: no access-control subject for CN {name!r}"
            assert d["mode"] == "client" and link["tls"]["verify_name_on_connect"] is True
            assert link["tls"]["connect_certificate"] == f"certs/{name}.pem"
            assert link["tls"]["connect_private_key"] == f"certs/{name}-key.pem"
        # the rendered copy points at files that exist
        r = json.loads(str(zenoh.Config.from_file(str(certs.folder / "zenoh" / f.name))))
        for k, v in r["transport"]["link"]["tls"].items():
            if k.endswith(("certificate", "private_key")) and v is not None:
                assert Path(v).is_file(), (f.name, k, v)


# ------------------------------------------------------------------------------ mutual TLS
def test_mtls_peer_pair(certs, stack):
    a, port = mtls_listener(certs, stack)
    q = queue.Queue()
    stack(collector(a, f"{NS}/**", q))
    b = mtls_dialler(certs, stack, port, certs.leaf["io"])
    assert deliver(b, f"{NS}/frames", q, b"hello") == ("", f"{NS}/frames", b"hello")
    assert len(list(a.info.peers_zid())) == 1


def test_shipped_client_configs_as_peers(certs, stack):
    """client-<svc>.json5 with --mode peer semantics: one listens, the other dials it."""
    port = free_port()
    z = certs.folder / "zenoh"
    a = stack(zenoh.open(conf_from(z / "client-mapper.json5", mode="peer",
                                   listen__endpoints=[f"tls/127.0.0.1:{port}"], connect__endpoints=[])))
    q = queue.Queue()
    stack(collector(a, f"{NS}/frames", q))
    b = stack(zenoh.open(conf_from(z / "client-io.json5", mode="peer",
                                   connect__endpoints=[f"tls/127.0.0.1:{port}"])))
    assert deliver(b, f"{NS}/frames", q, b"p2p") == ("", f"{NS}/frames", b"p2p")


@pytest.mark.parametrize("who", ["no-certificate", "other-ca-certificate", "plain-tcp"])
def test_client_without_valid_certificate_cannot_open(who, certs, other_certs, stack):
    """Against an mTLS listener, a client-mode session fails to open (zenoh.ZError)."""
    _, port = mtls_listener(certs, stack)
    if who == "plain-tcp":
        conf = plain_conf("client", connect=[f"tcp/127.0.0.1:{port}"])
    else:
        kp = None if who == "no-certificate" else other_certs.leaf["io"]
        conf = plain_conf("client", connect=[f"tls/localhost:{port}"], tls=client_tls(certs.ca, kp))
    t0 = time.monotonic()
    with pytest.raises(zenoh.ZError, match="Unable to connect"):
        zenoh.open(conf)
    assert time.monotonic() - t0 < 10


def test_peer_without_certificate_gets_nothing_through(certs, stack):
    """A peer-mode session opens anyway (peers retry in the background) but never joins."""
    a, port = mtls_listener(certs, stack)
    q = queue.Queue()
    stack(collector(a, f"{NS}/**", q))
    b = mtls_dialler(certs, stack, port, None)
    b.put(f"{NS}/frames", b"intruder")
    with pytest.raises(queue.Empty):
        q.get(timeout=NEVER)
    assert list(a.info.peers_zid()) == [] and list(b.info.peers_zid()) == []


def test_client_refuses_server_from_another_ca(certs, other_certs, stack):
    """Server authentication: a client that trusts only its own CA will not talk to an impostor."""
    port = free_port()
    stack(zenoh.open(plain_conf("peer", listen=[f"tls/127.0.0.1:{port}"],
                                tls=server_tls(other_certs, "router", mtls=False))))
    with pytest.raises(zenoh.ZError):
        zenoh.open(plain_conf("client", connect=[f"tls/localhost:{port}"],
                              tls=client_tls(certs.ca, certs.leaf["io"])))


def test_verify_name_on_connect(tmp_path, stack):
    """A certificate naming another host is refused when names are verified, accepted otherwise."""
    wrong = mtc.make_test_certs(tmp_path, names=("io",), hosts=("elsewhere.invalid",))
    port = free_port()
    stack(zenoh.open(plain_conf("peer", listen=[f"tls/127.0.0.1:{port}"], tls=server_tls(wrong))))
    with pytest.raises(zenoh.ZError):
        zenoh.open(plain_conf("client", connect=[f"tls/127.0.0.1:{port}"],
                              tls=client_tls(wrong.ca, wrong.leaf["io"], verify=True)))
    stack(zenoh.open(plain_conf("client", connect=[f"tls/127.0.0.1:{port}"],
                                tls=client_tls(wrong.ca, wrong.leaf["io"], verify=False))))


def test_max_message_size_drops_larger_messages(certs, stack):
    """transport/link/rx/max_message_size (set in every shipped file) drops oversized messages
    at the receiver; the session still delivers afterwards (the sentinel is repeated: under
    load, the receiver may reset the link on the oversized message and the peers reconnect)."""
    a, port = mtls_listener(certs, stack, extra={"transport/link/rx/max_message_size": 200_000})
    q = queue.Queue()
    stack(collector(a, f"{NS}/frames", q))
    b = mtls_dialler(certs, stack, port, certs.leaf["io"])
    assert deliver(b, f"{NS}/frames", q, b"warm-up") is not None
    b.put(f"{NS}/frames", b"x" * 150_000)  # fragmented (> 64 KiB batch), under the limit
    b.put(f"{NS}/frames", b"FORGED" + b"x" * 1_000_000)  # over the limit
    done = threading.Event()

    def repeat_sentinel():
        while not done.wait(0.1):
            b.put(f"{NS}/frames", b"sentinel")

    b.put(f"{NS}/frames", b"sentinel")
    threading.Thread(target=repeat_sentinel, daemon=True).start()
    try:
        sizes = [len(i[2]) for i in until(q, b"sentinel", timeout=30.0) if i[2] != b"warm-up"]
    finally:
        done.set()
    assert sizes == [150_000]


# --------------------------------------------------------------------------- access control
@pytest.fixture
def routed(certs, stack):
    """The shipped router.json5 on a free port and a factory of clients from client-<svc>.json5."""
    port = free_port()
    z = certs.folder / "zenoh"
    stack(zenoh.open(conf_from(z / "router.json5", listen__endpoints=[f"tls/127.0.0.1:{port}"])))

    def client(svc: str, cert: str | None = None):
        inserts = {"connect__endpoints": [f"tls/localhost:{port}"]}
        if cert is not None:  # same config, another identity
            inserts["transport__link__tls__connect_certificate"] = str(certs.leaf[cert].cert)
            inserts["transport__link__tls__connect_private_key"] = str(certs.leaf[cert].key)
        return stack(zenoh.open(conf_from(z / f"client-{svc}.json5", **inserts)))

    return client


def test_router_acl_allows_each_role_its_keys(routed, stack):
    io, tracker, mapper = routed("io"), routed("tracker"), routed("mapper")
    # one queue per observing session: a session's own subscribers get its puts locally,
    # without the router, so only other sessions show what the router lets through
    qt, qm = queue.Queue(), queue.Queue()
    for key in ("frames", "map/field", "poses/*"):
        stack(collector(tracker, f"{NS}/{key}", qt, "tracker"))
    stack(collector(mapper, f"{NS}/poses/*", qm, "mapper"))
    assert deliver(io, f"{NS}/frames", qt, b"frame") == ("tracker", f"{NS}/frames", b"frame")
    assert deliver(mapper, f"{NS}/map/field", qt, b"field")[1:] == (f"{NS}/map/field", b"field")
    assert deliver(io, f"{NS}/poses/gt", qm, b"gt")[1:] == (f"{NS}/poses/gt", b"gt")

    # io may not publish map snapshots or tracker poses: denied at the router, while the
    # allowed sentinel sent next on the same link arrives
    io.put(f"{NS}/map/field", b"FORGED FIELD")
    io.put(f"{NS}/poses/tracker", b"FORGED POSE")
    io.put(f"{NS}/frames", b"sentinel")
    assert forged(until(qt, b"sentinel")) == []
    # the tracker may publish its poses, not ground truth
    tracker.put(f"{NS}/poses/gt", b"FORGED GT")
    tracker.put(f"{NS}/poses/tracker", b"tracker pose")
    assert forged(until(qm, b"tracker pose")) == []


def test_router_acl_blocks_subscriptions_outside_a_role(routed, stack):
    """The tracker may not subscribe to map/points; its declaration is dropped at the router."""
    tracker, mapper = routed("tracker"), routed("mapper")
    q = queue.Queue()
    stack(collector(tracker, f"{NS}/map/points", q, "points"))
    stack(collector(tracker, f"{NS}/map/field", q, "field"))
    assert deliver(mapper, f"{NS}/map/field", q, b"f")[0] == "field"  # both declarations had time
    mapper.put(f"{NS}/map/points", b"points")
    mapper.put(f"{NS}/map/field", b"sentinel")
    assert [i for i in until(q, b"sentinel") if i[0] == "points"] == []


def test_router_acl_queries(routed, stack):
    """Only the mapper may answer map/latest; the tracker may ask; an unknown CN gets nothing."""
    tracker, mapper, intruder = routed("tracker"), routed("mapper"), routed("io", cert="intruder")
    stack(mapper.declare_queryable(f"{NS}/map/latest", lambda query: query.reply(query.key_expr, b"snapshot")))
    got, deadline = None, time.monotonic() + 5
    while got is None and time.monotonic() < deadline:
        for reply in tracker.get(f"{NS}/map/latest", timeout=1.0):
            if reply.ok is not None:
                got = reply.ok.payload.to_bytes()
    assert got == b"snapshot"
    assert [r.ok for r in intruder.get(f"{NS}/map/latest", timeout=NEVER) if r.ok is not None] == []


@pytest.mark.parametrize("acl", [True, False])
def test_router_admin_space_closed_to_clients(acl, certs, stack):
    """With its admin space on (zenohd's default), the router answers @/<zid>/** queries
    only when access control is off: @/** is outside every allowed key expression."""
    port = free_port()
    z = certs.folder / "zenoh"
    router = stack(zenoh.open(conf_from(z / "router.json5", listen__endpoints=[f"tls/127.0.0.1:{port}"],
                                        adminspace__enabled=True, access_control__enabled=acl)))
    tracker = stack(zenoh.open(conf_from(z / "client-tracker.json5",
                                         connect__endpoints=[f"tls/localhost:{port}"])))
    keys = [str(r.ok.key_expr) for r in tracker.get(f"@/{router.info.zid()}/**", timeout=NEVER)
            if r.ok is not None]
    assert (keys == []) == acl, keys


def test_router_acl_refuses_unknown_common_name(routed, stack):
    """A certificate from the right CA but with a CN no policy names: connected, yet mute."""
    io, tracker = routed("io"), routed("tracker")
    intruder = routed("io", cert="intruder")  # client-io.json5 with the intruder's certificate
    q, q2 = queue.Queue(), queue.Queue()
    stack(collector(intruder, f"{NS}/frames", q2))  # declared first: it has had the most time
    stack(collector(tracker, f"{NS}/frames", q))
    assert deliver(io, f"{NS}/frames", q, b"ok") is not None  # the tracker's subscription is live
    io.put(f"{NS}/frames", b"sync")
    until(q, b"sync")  # io's warm-up repeats are all in
    intruder.put(f"{NS}/frames", b"FORGED FRAME")
    with pytest.raises(queue.Empty):
        q.get(timeout=NEVER)  # its publication never reaches the tracker ...
    # ... and nothing io published reached it (its own put it gets locally, not via the router)
    assert [i[2] for i in drain(q2)] in ([], [b"FORGED FRAME"])


def test_peer_acl_by_common_name(certs, stack):
    """Access control also works between two peers (no router), on the dialling side's CN."""
    acl = {"enabled": True, "default_permission": "deny",
           "rules": [{"id": "frames", "permission": "allow", "messages": ["put", "declare_subscriber"],
                      "key_exprs": [f"{NS}/frames"]}],
           "subjects": [{"id": "io", "cert_common_names": ["io"]}],
           "policies": [{"rules": ["frames"], "subjects": ["io"]}]}
    q = queue.Queue()
    for dialler, expect in (("io", True), ("mapper", False)):
        a, port = mtls_listener(certs, stack, extra={"access_control": acl})
        stack(collector(a, f"{NS}/frames", q, dialler))
        b = mtls_dialler(certs, stack, port, certs.leaf[dialler])
        got = deliver(b, f"{NS}/frames", q, dialler.encode(), timeout=5 if expect else NEVER)
        assert (got is not None) == expect, dialler
