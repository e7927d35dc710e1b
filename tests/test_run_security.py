"""Secure-by-default ``fmapping up``: per-run credentials and access control (services.credentials).

In-process: a router opened from the run's generated router config, the services' roles as
client sessions opened from their generated configs. "Never arrives" is shown with a sentinel:
an allowed message sent after the forbidden one on the same link arrives, the forbidden one
does not (one link delivers in order); queries wait a bounded time.
"""
from __future__ import annotations

import json
import os
import queue
import stat
import time

import pytest

zenoh = pytest.importorskip("zenoh")

from fmapping import protocol as P  # noqa: E402
from services.zenoh_session import free_port  # noqa: E402
from services.credentials import ROLES, acl_policy, make_run_credentials  # noqa: E402

NS = "sectest"
KEYS = P.Keys(NS)


@pytest.fixture
def run(tmp_path):
    """(credentials, router session, open(role) -> client session); everything closed at the end."""
    creds = make_run_credentials(tmp_path / "secrets", f"tcp/127.0.0.1:{free_port()}", NS)
    sessions = [zenoh.open(zenoh.Config.from_file(str(creds.router_config)))]

    def open_role(role: str):
        s = zenoh.open(zenoh.Config.from_file(str(creds.config(role))))
        sessions.append(s)
        return s

    yield creds, open_role
    for s in reversed(sessions):
        s.close()


def intruder_conf(endpoint: str, mode: str = "client", user=None, password=None) -> "zenoh.Config":
    c = zenoh.Config()
    c.insert_json5("mode", json.dumps(mode))
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("connect/endpoints", json.dumps([endpoint]))
    c.insert_json5("connect/timeout_ms", "1000")  # a refused client retries until then (a real one links in ms)
    if user is not None:
        c.insert_json5("transport/auth/usrpwd", json.dumps({"user": user, "password": password}))
    return c


def subscribe(session, key: str) -> "queue.Queue":
    q: queue.Queue = queue.Queue()
    session.declare_subscriber(key, lambda s: q.put((str(s.key_expr), s.payload.to_bytes())))
    return q


def first(sender, key: str, q: "queue.Queue", payload: bytes, timeout: float = 10.0):
    """Put ``payload`` until something arrives on ``q`` (declarations take a moment to reach the router)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        sender.put(key, payload)
        try:
            return q.get(timeout=0.05)
        except queue.Empty:
            pass
    return None


def ask(session, key: str, timeout: float = 2.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        for r in session.get(key, timeout=0.3):
            if r.ok is not None:
                return r.ok.payload.to_bytes()
    return None


def test_credential_files_are_private_and_random(tmp_path):
    a = make_run_credentials(tmp_path / "a", "tcp/127.0.0.1:1", NS)
    b = make_run_credentials(tmp_path / "b", "tcp/127.0.0.1:1", NS)
    assert stat.S_IMODE(os.stat(a.folder).st_mode) == 0o700
    for p in [a.dictionary, a.router_config, *a.configs.values()]:
        assert stat.S_IMODE(os.stat(p).st_mode) == 0o600, p
    assert set(a.configs) == set(ROLES)
    users = dict(line.split(":", 1) for line in a.dictionary.read_text().split())
    other = dict(line.split(":", 1) for line in b.dictionary.read_text().split())
    assert set(users) == set(ROLES) and len(set(users.values())) == len(ROLES)
    assert all(len(pw) >= 40 and pw != other[u] for u, pw in users.items())  # per run, per role
    conf = json.loads(a.config("tracker").read_text())
    assert conf["mode"] == "client" and conf["listen"]["endpoints"] == []
    assert conf["transport"]["auth"]["usrpwd"] == {"user": "tracker", "password": users["tracker"]}
    a.remove()
    assert not a.folder.exists()


def test_acl_policy_is_deny_by_default_and_pinned_to_the_namespace():
    acl = acl_policy(NS)
    assert acl["enabled"] and acl["default_permission"] == "deny"
    keys = [k for r in acl["rules"] for k in r["key_exprs"]]
    assert all(k.startswith(f"fmapping/{NS}/") for k in keys)
    rules = {r["id"]: r for r in acl["rules"]}
    puts = {p["subjects"][0]: [k for rid in p["rules"] if "put" in rules[rid]["messages"]
                               for k in rules[rid]["key_exprs"]]
            for p in acl["policies"]}
    ctl = f"fmapping/{NS}/control"
    assert sorted(role for role, ks in puts.items() if ctl in ks) == ["launcher", "play"]
    assert [role for role, ks in puts.items() if f"fmapping/{NS}/poses/tracker" in ks] == ["tracker"]
    assert [role for role, ks in puts.items() if f"fmapping/{NS}/frames" in ks] == ["play"]


@pytest.mark.slow
def test_a_session_without_the_run_credentials_cannot_join(run):
    creds, open_role = run
    mapper = open_role("mapper")
    ctl = subscribe(mapper, KEYS.control)
    mapper.declare_queryable(KEYS.latest, lambda q: q.reply(KEYS.latest, b"MAP"))
    launcher = open_role("launcher")
    assert first(launcher, KEYS.control, ctl, b"real") == (KEYS.control, b"real")  # the set-up works
    # a client without credentials, or with a wrong password, is refused at once
    for user, pw in ((None, None), ("launcher", "guess"), ("intruder", "x")):
        with pytest.raises(zenoh.ZError):
            zenoh.open(intruder_conf(creds.endpoint, user=user, password=pw))
    # a peer opens (peers retry in the background) but gets no link: nothing it sends arrives
    peer = zenoh.open(intruder_conf(creds.endpoint, mode="peer"))
    try:
        stop = P.encode(P.Control("stop"))
        assert first(peer, KEYS.control, ctl, stop, timeout=1.5) is None
        assert ask(peer, KEYS.latest, timeout=1.0) is None
    finally:
        peer.close()


def test_roles_may_do_only_their_own_part(run):
    creds, open_role = run
    mapper = open_role("mapper")
    ctl = subscribe(mapper, KEYS.control)
    poses = subscribe(mapper, KEYS.poses())
    mapper.declare_queryable(KEYS.latest, lambda q: q.reply(KEYS.latest, b"MAP"))
    tracker = open_role("tracker")
    # the tracker's own key works ...
    assert first(tracker, KEYS.poses("tracker"), poses, b"t0") == (KEYS.poses("tracker"), b"t0")
    # ... its control and a forged ground-truth pose are dropped at the router: the allowed
    # message sent after them on the same link arrives first
    tracker.put(KEYS.control, P.encode(P.Control("reset")))
    tracker.put(KEYS.poses("gt"), b"forged")
    tracker.put(KEYS.poses("tracker"), b"t1")
    assert poses.get(timeout=5) == (KEYS.poses("tracker"), b"t1")
    assert ctl.empty() and poses.empty()
    assert ask(tracker, KEYS.latest) == b"MAP"  # the tracker may ask for the map
    record = open_role("record")
    assert ask(record, KEYS.latest, timeout=1.5) is None  # record may not
    # the player sends the end-of-sequence stop, the launcher commands: both reach the mapper
    for role in ("play", "launcher"):
        assert first(open_role(role), KEYS.control, ctl, role.encode()) == (KEYS.control, role.encode())
    # a client with a valid identity may not pretend to answer map/latest
    view = open_role("view")
    view.declare_queryable(KEYS.latest, lambda q: q.reply(KEYS.latest, b"FAKE"))
    answers = set()
    for _ in range(5):
        for r in tracker.get(KEYS.latest, timeout=0.5):
            if r.ok is not None:
                answers.add(r.ok.payload.to_bytes())
    assert answers == {b"MAP"}
    # the monitor (bench/system.py's observer) reads poses; it may send only its own status: a control
    # and a frame it sends are dropped at the router, the status sent after them arrives alone
    monitor = open_role("monitor")
    seen = subscribe(monitor, KEYS.poses())
    assert first(tracker, KEYS.poses("tracker"), seen, b"m0") == (KEYS.poses("tracker"), b"m0")
    everything = subscribe(view, f"{KEYS.root}/**")
    assert first(monitor, KEYS.status("monitor"), everything, b"s0") == (KEYS.status("monitor"), b"s0")
    time.sleep(0.3)
    while not everything.empty():
        everything.get()
    monitor.put(KEYS.control, P.encode(P.Control("reset")))
    monitor.put(KEYS.frames, b"forged")
    monitor.put(KEYS.status("monitor"), b"s1")
    assert everything.get(timeout=5) == (KEYS.status("monitor"), b"s1")
    time.sleep(0.3)
    assert everything.empty()
    assert ask(monitor, KEYS.latest, timeout=1.5) is None  # nor may it ask for the map


@pytest.mark.slow
def test_a_running_fmapping_up_ignores_outsiders_and_roles_overstepping(scene, tmp_path):
    """End to end: while `fmapping up` runs, a session without the run's credentials cannot join,
    and one holding the tracker's credentials floods `control` with stop / reset and forges GT
    poses: the ACL drops all of it, the run completes with every frame and its outputs."""
    import subprocess
    import sys
    import threading

    import numpy as np
    import yaml

    from fmapping.trajectory import read_tum_trajectory
    from service_helpers import ROOT, SMALL_MAPPER, subprocess_env

    cfg = tmp_path / "up.yaml"
    cfg.write_text(yaml.safe_dump({"mapper": SMALL_MAPPER, "launcher": {"timeout": 240, "threads": 1,
                                                                         "view": False}}))
    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-m", "services.cli", "up", "--data", str(scene), "--poses", "gt",
                             "--out", str(out), "--config", str(cfg)], cwd=ROOT, env=subprocess_env(),
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    stop = threading.Event()
    sent = {"n": 0}
    try:
        deadline = time.monotonic() + 120
        while not (out / "status" / "router.json").is_file():
            assert proc.poll() is None and time.monotonic() < deadline, "the router never came up"
            time.sleep(0.05)
        conf_path = out / "secrets" / "tracker.json5"
        tracker_conf = json.loads(conf_path.read_text())
        endpoint = tracker_conf["connect"]["endpoints"][0]
        assert endpoint.startswith("tcp/127.0.0.1:") and stat.S_IMODE(os.stat(conf_path).st_mode) == 0o600
        keys = P.Keys(f"up{proc.pid}")  # the launcher's namespace: up<its pid>
        with pytest.raises(zenoh.ZError):
            zenoh.open(intruder_conf(endpoint))
        tracker = zenoh.open(zenoh.Config.from_file(str(conf_path)))
        peer = zenoh.open(intruder_conf(endpoint, mode="peer"))
        forged = [P.encode(P.Control("stop")), P.encode(P.Control("reset")),
                  P.encode(P.Pose(seq=3, timestamp=0.0, c2w=np.eye(4), source="gt"))]

        def flood():
            while not stop.wait(0.01):
                for s in (tracker, peer):
                    s.put(keys.control, forged[sent["n"] % 2])
                    s.put(keys.poses("gt"), forged[2])
                sent["n"] += 1

        t = threading.Thread(target=flood, daemon=True)
        t.start()
        assert ask(peer, keys.latest, timeout=1.0) is None
        rc = proc.wait(timeout=280)
        stop.set()
        t.join(timeout=5)
        log = proc.stdout.read()
        tracker.close()
        peer.close()
    finally:
        stop.set()
        if proc.poll() is None:
            proc.kill()
    assert rc == 0, log[-3000:]
    assert sent["n"] > 10
    ts, c2w = read_tum_trajectory(out / "traj.txt")
    assert len(ts) == 14  # every frame mapped: no stop ended the run early, no reset wiped it
    stats = json.loads((out / "stats.json").read_text())
    assert stats["counters"].get("control_stop") == 1 and "control_reset" not in stats["counters"]
    assert not (out / "secrets").exists()  # the per-run passwords are gone with the run

