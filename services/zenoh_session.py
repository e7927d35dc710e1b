"""zenoh sessions: the network options every service accepts (``--listen``, ``--connect``,
``--zenoh-config``, ``--ns``, ...), the zenoh config they make, opening a session, and reading
payloads and the latest value of a queryable.

Network defaults are explicit and container friendly: peer mode, multicast scouting off,
loopback endpoints given on the command line (``--listen`` / ``--connect``), or a zenoh
JSON5 config file (``--zenoh-config``) for anything else (TLS, access control, routers).
This module imports zenoh only when a session or config is made.
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import socket
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterable, Optional

from fmapping import protocol as P
from fmapping.config import read_yaml_mapping
from services.process import LOG_LEVEL_HELP

if TYPE_CHECKING:
    import zenoh

log = logging.getLogger("fmapping.services")


def _split(values: Optional[Iterable[str]]) -> list[str]:
    out: list[str] = []
    for v in values or []:
        out += [x.strip() for x in str(v).split(",") if x.strip()]
    return out


def names(text: Optional[str]) -> list[str]:
    """Service names from a comma-separated option value ('' or None: none)."""
    return _split([text] if text else [])



def add_common_args(p: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """zenoh and service options every service accepts."""
    g = p.add_argument_group("zenoh")
    g.add_argument("--mode", choices=["peer", "client"], default=None, help="zenoh mode (default peer)")
    g.add_argument("--listen", action="append", default=None, metavar="ENDPOINT",
                   help="listen endpoint(s), e.g. tcp/127.0.0.1:7447 (repeat or comma-separate)")
    g.add_argument("--connect", action="append", default=None, metavar="ENDPOINT",
                   help="endpoint(s) to connect to, e.g. tcp/127.0.0.1:7447 or a router tcp/zenoh:7447")
    g.add_argument("--multicast", action="store_true", default=None,
                   help="enable multicast scouting (off by default: explicit endpoints work in containers and CI)")
    g.add_argument("--zenoh-config", default=None, metavar="FILE",
                   help="zenoh JSON5 config (native format, e.g. for TLS) or a YAML file with keys "
                        "mode, listen, connect, multicast, namespace, options {json5/key/path: value}; "
                        "command-line options override it")
    g.add_argument("--ns", "--namespace", dest="ns", default=None,
                   help="key-expression namespace: fmapping/<ns>/... (default $FMAPPING_NS or 'default')")
    g = p.add_argument_group("service")
    g.add_argument("--status-file", default=None, help="also write the status as JSON to this file (atomically)")
    g.add_argument("--status-interval", type=float, default=0.5, help="heartbeat period in seconds")
    g.add_argument("--exit-with-parent", action="store_true", help="stop when the parent process goes away")
    g.add_argument("--sched-idle", action="store_true",
                   help="once started (its first status out), run under the SCHED_IDLE policy: only on the CPU time "
                        "nothing else wants (fmapping up starts the mapper and the viewer so)")
    g.add_argument("--log-level", default=os.environ.get("FMAPPING_LOG", "INFO"), help=LOG_LEVEL_HELP)
    return p


def _insert(conf: zenoh.Config, key: str, value: Any) -> None:
    try:
        conf.insert_json5(key, json.dumps(value))
    except Exception as e:  # zenoh raises ZError with the offending key
        raise ValueError(f"zenoh config: cannot set {key} = {value!r}: {e}") from None


def zenoh_config(mode: Optional[str] = "peer", listen: Optional[list[str]] = None,
                 connect: Optional[list[str]] = None, multicast: Optional[bool] = False, options: Optional[dict] = None,
                 base: Optional[zenoh.Config] = None) -> zenoh.Config:
    """A zenoh config with explicit endpoints; ``options`` maps JSON5 key paths to values."""
    import zenoh

    conf = base if base is not None else zenoh.Config()
    # None keeps what ``base`` (a native JSON5 file) says
    if mode is not None:
        if mode not in ("peer", "client", "router"):
            raise ValueError(f"zenoh mode must be peer, client or router, got {mode!r}")
        _insert(conf, "mode", mode)
    if multicast is not None:
        _insert(conf, "scouting/multicast/enabled", bool(multicast))
    if listen is not None:
        _insert(conf, "listen/endpoints", list(listen))
    if connect is not None:
        _insert(conf, "connect/endpoints", list(connect))
    for k, v in (options or {}).items():
        _insert(conf, k, v)
    return conf


def resolve_network(args) -> dict:
    """Merge --zenoh-config (YAML) and command-line options into mode/listen/connect/multicast/ns/options."""
    net: dict[str, Any] = {"mode": "peer", "listen": None, "connect": None, "multicast": False,
                           "ns": os.environ.get("FMAPPING_NS", "default"), "options": {}, "native": None}
    path = getattr(args, "zenoh_config", None)
    if path:
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"zenoh config not found: {path}")
        if path.suffix in (".json5", ".json"):
            # a native file keeps its own mode and scouting unless the command line says otherwise
            net.update(native=str(path), mode=None, multicast=None)
        else:
            data = read_yaml_mapping(path)
            unknown = set(data) - {"mode", "listen", "connect", "multicast", "namespace", "options"}
            if unknown:
                raise ValueError(f"{path}: unknown keys {sorted(unknown)} "
                                 "(valid: mode, listen, connect, multicast, namespace, options)")
            for k in ("mode", "multicast", "options"):
                if k in data:
                    net[k] = data[k]
            for k in ("listen", "connect"):
                if k in data:
                    net[k] = _split(data[k] if isinstance(data[k], list) else [data[k]])
            if "namespace" in data:
                net["ns"] = str(data["namespace"])
    if getattr(args, "mode", None):
        net["mode"] = args.mode
    if getattr(args, "listen", None):
        net["listen"] = _split(args.listen)
    if getattr(args, "connect", None):
        net["connect"] = _split(args.connect)
    if getattr(args, "multicast", None):
        net["multicast"] = True
    if getattr(args, "ns", None):
        net["ns"] = args.ns
    if net["mode"] == "peer" and net["listen"] is None and net["native"] is None:
        net["listen"] = ["tcp/127.0.0.1:0"]  # loopback only, any free port, announced by gossip
    if net["mode"] == "client":
        net["listen"] = net["listen"] or []
        # wait (up to 2 min) for the router instead of failing at once: containers start in any order
        net["options"].setdefault("connect/timeout_ms", 120000)
        net["options"].setdefault("connect/exit_on_failure", False)
    return net


def open_session(args) -> tuple[zenoh.Session, P.Keys]:
    """Open the zenoh session described by the parsed arguments; returns (session, keys)."""
    import zenoh

    net = resolve_network(args)
    keys = P.Keys(net["ns"])
    base = zenoh.Config.from_file(net["native"]) if net["native"] else None
    conf = zenoh_config(net["mode"], net["listen"], net["connect"], net["multicast"], net["options"], base=base)
    log.debug("zenoh: mode=%s listen=%s connect=%s multicast=%s ns=%s",
              net["mode"], net["listen"], net["connect"], net["multicast"], net["ns"])
    return zenoh.open(conf), keys


def payload_bytes(sample) -> bytes:
    """The payload of a zenoh Sample (or Reply.ok) as bytes."""
    return sample.payload.to_bytes()


def query_latest(session: zenoh.Session, key: str, timeout: float = 5.0, retry: float = 0.05) -> Optional[bytes]:
    """Ask the queryable on ``key`` for its latest value; retry until ``timeout`` (a queryable
    declared by a peer that just connected takes a moment to propagate). None if nobody answers."""
    deadline = time.monotonic() + timeout
    while True:
        left = deadline - time.monotonic()
        if left <= 0:
            return None
        for reply in session.get(key, timeout=max(0.05, min(left, 2.0))):
            if reply.ok is not None:
                return payload_bytes(reply.ok)
        time.sleep(min(retry, max(0.0, deadline - time.monotonic())))


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port free right now on ``host`` (small race window until someone binds it)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return s.getsockname()[1]
