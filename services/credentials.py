"""Per-run credentials and access control for ``fmapping up`` (zenoh-free: it only writes files).

Every run gets its own zenoh router on a loopback port and one identity per role (``play``,
``record``, ``view``, ``tracker``, ``mapper``, ``launcher``, ``external``, ``monitor``): a zenoh
user name and a random password made at start (:func:`make_run_credentials`). The router
admits only those users (``transport/auth/usrpwd`` with a dictionary file) and routes by an
access-control policy with ``default_permission: deny`` pinned to the run's namespace
(:func:`acl_policy`): each role may publish, subscribe, ask and answer exactly the keys of
:data:`ROLES`. The services are zenoh *clients* of that router, each with the config file of
its role.

Why a router rather than the peer mesh: zenoh's user/password authentication is one-way, the
listening side learns the user name of the side that dials, not the reverse (measured with
zenoh 1.10: a dialling peer sees the listener as an unknown subject). In a peer mesh half
of the links could not tell roles apart; with clients and one router every link is dialled
by a client, so the router knows who sent every message.

Files (``OUT/secrets/``, directory 0700, files 0600): ``users.txt`` (the router's dictionary,
``user:password`` per line), ``router.json5`` and ``<role>.json5``. The launcher deletes them
at the end of the run; the passwords are useless afterwards (the router is gone).
"""
from __future__ import annotations

import json
import os
import secrets
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

from fmapping.fileio import atomic_write_text

# What each role may do, as key expressions under fmapping/<ns>/. Every role may also publish
# its own status (status/<role>) and subscribe to control and status/* (COMMON_SUB).
#   put:   publish        sub: subscribe to        query: ask        serve: answer (queryable + reply)
ROLES: dict[str, dict[str, tuple[str, ...]]] = {
    # play also sends the end-of-sequence marker, a Control(stop, reason=end)
    "play": {"put": ("frames", "poses/gt", "control")},
    "record": {"sub": ("poses/*", "map/points")},
    "view": {"sub": ("**",), "query": ("map/latest",)},
    "tracker": {"put": ("poses/tracker",), "sub": ("frames", "map/field", "poses/*"), "query": ("map/latest",)},
    "mapper": {"put": ("map/field", "map/points", "poses/mapper"), "sub": ("frames", "poses/*"),
               "serve": ("map/latest",)},
    "launcher": {"put": ("control",)},
    "external": {"put": ("poses/external",), "sub": ("frames",)},  # an external pose producer
    # an observer of the run (bench/system.py's monitor, a dashboard): reads poses and the map points
    "monitor": {"sub": ("poses/*", "map/points")},
}
COMMON_SUB = ("control", "status/*")
PASSWORD_BYTES = 32  # secrets.token_urlsafe: 43 characters, 256 bits


@dataclass
class RunCredentials:
    """Where the files of one run are (see the module docstring)."""
    folder: Path
    endpoint: str  # the router's tcp/127.0.0.1:<port>
    router_config: Path
    dictionary: Path
    configs: dict  # role -> Path of its client config

    def config(self, role: str) -> Path:
        return self.configs[role]

    def remove(self) -> None:
        """Delete the files (end of the run)."""
        for p in [self.router_config, self.dictionary, *self.configs.values()]:
            try:
                p.unlink()
            except FileNotFoundError:
                pass
        try:
            self.folder.rmdir()
        except OSError:
            pass  # not empty: someone put something else there


def acl_policy(ns: str, roles: Optional[dict] = None) -> dict:
    """The ``access_control`` section: deny by default; per role, ingress rules (what arrives at the
    router from that client) for its keys; one egress rule delivering the namespace to the run's
    users. Keys are pinned to ``fmapping/<ns>``: nothing else is routed."""
    roles = ROLES if roles is None else roles
    root = f"fmapping/{ns}"
    rules = [{"id": "deliver", "permission": "allow", "flows": ["egress"],
              "messages": ["put", "declare_subscriber", "declare_queryable", "query", "reply"],
              "key_exprs": [f"{root}/**"]},
             {"id": "common-sub", "permission": "allow", "flows": ["ingress"], "messages": ["declare_subscriber"],
              "key_exprs": [f"{root}/{k}" for k in COMMON_SUB]}]
    policies = [{"rules": ["deliver", "common-sub"], "subjects": ["all"]}]
    subjects = [{"id": "all", "usernames": sorted(roles)}]
    for role, allowed in sorted(roles.items()):
        mine = []
        groups = (("put", ["put"], tuple(allowed.get("put", ())) + (f"status/{role}",)),
                  ("sub", ["declare_subscriber"], allowed.get("sub", ())),
                  ("query", ["query"], allowed.get("query", ())),
                  ("serve", ["declare_queryable", "reply"], allowed.get("serve", ())))
        for what, messages, keys in groups:
            if keys:
                rid = f"{role}-{what}"
                rules.append({"id": rid, "permission": "allow", "flows": ["ingress"], "messages": messages,
                              "key_exprs": [f"{root}/{k}" for k in keys]})
                mine.append(rid)
        subjects.append({"id": role, "usernames": [role]})
        policies.append({"rules": mine, "subjects": [role]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}


def _common_transport() -> dict:
    # shared memory off: payloads stay on the authenticated link; tcp only
    return {"shared_memory": {"enabled": False}, "link": {"protocols": ["tcp"]}}


def router_config(endpoint: str, dictionary: Path, ns: str, roles: Optional[dict] = None) -> dict:
    """The run's router: listens on ``endpoint`` only, admits the users of ``dictionary``, routes by
    :func:`acl_policy`; no discovery, no admin space."""
    transport = _common_transport()
    transport["auth"] = {"usrpwd": {"dictionary_file": str(dictionary)}}
    return {"mode": "router", "listen": {"endpoints": [endpoint]}, "connect": {"endpoints": []},
            "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
            "adminspace": {"enabled": False}, "transport": transport,
            "access_control": acl_policy(ns, roles)}


def client_config(endpoint: str, user: str, password: str, connect_timeout_ms: int = 30000) -> dict:
    """A service of the run: a client of the router (it listens nowhere), authenticated as ``user``.
    A router that is not there within ``connect_timeout_ms`` makes opening the session fail."""
    transport = _common_transport()
    transport["auth"] = {"usrpwd": {"user": user, "password": password}}
    return {"mode": "client", "listen": {"endpoints": []},
            "connect": {"endpoints": [endpoint], "timeout_ms": connect_timeout_ms, "exit_on_failure": True},
            "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
            "transport": transport}


def write_private(path: Path, text: str) -> Path:
    """Write ``text`` to ``path`` readable by the owner only (0600 from creation, then renamed)."""
    return atomic_write_text(path, text, mode=0o600)


def private_folder(folder: Path) -> Path:
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    os.chmod(folder, 0o700)
    return folder


def make_run_credentials(folder, endpoint: str, ns: str, roles: Optional[dict] = None) -> RunCredentials:
    """Fresh random passwords for every role of ``roles`` (default :data:`ROLES`) and the router's
    and each role's config files in ``folder`` (see the module docstring)."""
    roles = ROLES if roles is None else roles
    folder = private_folder(folder)
    passwords = {role: secrets.token_urlsafe(PASSWORD_BYTES) for role in sorted(roles)}
    dictionary = write_private(folder / "users.txt", "".join(f"{u}:{p}\n" for u, p in passwords.items()))
    router = write_private(folder / "router.json5",
                           json.dumps(router_config(endpoint, dictionary.resolve(), ns, roles), indent=1))
    configs = {role: write_private(folder / f"{role}.json5", json.dumps(client_config(endpoint, role, pw), indent=1))
               for role, pw in passwords.items()}
    return RunCredentials(folder=folder, endpoint=endpoint, router_config=router, dictionary=dictionary,
                          configs=configs)
