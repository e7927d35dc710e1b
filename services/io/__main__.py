"""``python -m services.io {play,view,record} [options]`` (``--help`` on each)."""
from __future__ import annotations

import sys

USAGE = """usage: python -m services.io {play,view,record} [options]

  play    publish a dataset as frames (+ GT poses), paced by --fps or by consumer acknowledgements
  view    log frames, poses, trajectories and map points to rerun (live viewer or --save out.rrd)
  record  write traj.txt (TUM) and the latest map points to disk at the end

'python -m services.io <command> --help' for the options of each."""


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(USAGE)
        return 0 if argv else 2
    cmd, rest = argv[0], argv[1:]
    if cmd == "play":
        from services.io.play import main as run
    elif cmd == "view":
        from services.io.view import main as run
    elif cmd == "record":
        from services.io.record import main as run
    else:
        print(f"unknown command {cmd!r}\n\n{USAGE}", file=sys.stderr)
        return 2
    try:
        return run(rest)
    except (FileNotFoundError, ValueError) as e:
        print(f"services.io {cmd}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    from services.process import exit_process

    exit_process(main())  # outputs are written: skip the slow interpreter teardown
