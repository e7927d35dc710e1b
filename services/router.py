"""``python -m services.router --zenoh-config FILE``: a zenoh router process (the one ``fmapping up``
starts for a secure run, from the config :mod:`services.credentials` writes).

It opens the session (which binds the listen endpoint: if someone else holds that port, this
fails and the process exits with code 1, so no impostor router can take the run's place
silently), writes ``--status-file`` (JSON, state ``running``) and then only waits: for SIGINT /
SIGTERM, or for its parent to go away (``--exit-with-parent``).
"""
from __future__ import annotations

import argparse
import logging
import os
import time

from services.process import LOG_LEVEL_HELP, Shutdown, run_main, service_parser, setup_logging
from services.transport import write_json_atomic


def build_parser() -> argparse.ArgumentParser:
    p = service_parser("services.router", __doc__)
    p.add_argument("--zenoh-config", required=True, metavar="FILE", help="zenoh JSON5 config (mode router)")
    p.add_argument("--status-file", default=None, help="written once the router listens")
    p.add_argument("--exit-with-parent", action="store_true", help="stop when the parent process goes away")
    p.add_argument("--log-level", default=os.environ.get("FMAPPING_LOG", "INFO"), help=LOG_LEVEL_HELP)
    return p


def main(argv=None) -> int:
    import zenoh

    args = build_parser().parse_args(argv)
    setup_logging(args.log_level, "router")
    log = logging.getLogger("fmapping.router")
    if not os.path.isfile(args.zenoh_config):
        raise FileNotFoundError(f"zenoh config not found: {args.zenoh_config}")
    shutdown = Shutdown(install=True, watch_parent=args.exit_with_parent)
    try:
        session = zenoh.open(zenoh.Config.from_file(args.zenoh_config))
    except Exception as e:  # zenoh.ZError: the port is taken, a bad config
        log.error("cannot start the router: %s", e)
        return 1
    started = time.time()
    if args.status_file:
        write_json_atomic(args.status_file, {"service": "router", "state": "running", "pid": os.getpid(),
                                             "time": started, "counters": {}})
    log.info("router running (zid %s)", session.zid())
    while not shutdown.wait(0.5):
        pass
    log.info("%s: closing", shutdown.reason)
    if args.status_file:
        write_json_atomic(args.status_file, {"service": "router", "state": "done", "pid": os.getpid(),
                                             "time": time.time(), "counters": {"uptime": time.time() - started}})
    session.close()
    return 0


if __name__ == "__main__":
    run_main(main, "services.router")
