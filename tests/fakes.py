"""Stand-ins for a launcher child process (``FakeProc``, ``fake_up``) and for a zenoh session
(``FakeSession``), so that the launcher and the service shells run in-process without starting
a process or opening the network.

Importable as a plain module (``tests/`` is on ``sys.path`` under pytest).
"""
from __future__ import annotations

from typing import Optional


class FakeProc:
    """A ``launcher.Proc`` that starts no process: it keeps its command line, has an exit code the
    test sets (``rc``, None while "running") and counts its restarts."""

    def __init__(self, name: str, argv: Optional[list] = None, out=None, env=None, rc: Optional[int] = None):
        self.name, self.argv, self._rc, self.restarts = name, argv, rc, 0

    @property
    def rc(self):
        return self._rc

    def restart(self):
        self.restarts += 1
        self._rc = None

    def close(self):
        pass


def fake_up(monkeypatch) -> dict:
    """Make ``fmapping up`` start no process: returns {service name: command line} of what it would
    start; readiness, monitoring and stopping do nothing."""
    from services.launcher import up as launcher

    started: dict = {}

    def proc(name, argv, out, env):  # records what would run
        started[name] = argv
        return FakeProc(name, argv, out, env)

    monkeypatch.setattr(launcher, "Proc", proc)
    monkeypatch.setattr(launcher, "wait_ready", lambda procs, timeout: None)
    monkeypatch.setattr(launcher, "monitor", lambda procs, *a, **k: 0)
    monkeypatch.setattr(launcher, "stop_all", lambda *a, **k: None)
    return started


class FakeSession:
    """A zenoh session stand-in: remembers each subscription's callback (``deliver`` calls them) and
    what goes out on each publisher (``published`` by key, ``puts`` as (key, data) in order)."""

    class _Decl:
        def __init__(self, session=None, key=None):
            self.session, self.key = session, key

        def undeclare(self):
            pass

        def put(self, data):
            if self.session is not None:
                self.session.published[self.key].append(data)
                self.session.puts.append((self.key, data))

    class _Sample:
        def __init__(self, key: str, data: bytes):
            self.key_expr, self._data = key, data

        @property
        def payload(self):
            return self

        def to_bytes(self) -> bytes:
            return self._data

    def __init__(self):
        self.subs: dict[str, list] = {}
        self.published: dict[str, list] = {}
        self.puts: list[tuple] = []

    def declare_subscriber(self, key, cb):
        self.subs.setdefault(key, []).append(cb)
        return self._Decl()

    def declare_publisher(self, key, **kw):
        self.published.setdefault(key, [])
        return self._Decl(self, key)

    def declare_queryable(self, key, cb):
        return self._Decl()

    def get(self, key, timeout=None):  # nobody answers a query
        return []

    def deliver(self, key: str, data: bytes, sub_key: str = None) -> None:
        for cb in self.subs[sub_key or key]:
            cb(self._Sample(key, data))
