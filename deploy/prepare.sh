#!/bin/sh
# One-shot set-up that docker-compose.yml runs (service `prepare`, as root, in the fmapping image)
# before any fmapping service starts, so that `docker compose up` works on a fresh checkout:
#
# 1. Outputs: the services run as FMAPPING_UID:FMAPPING_GID (default 1000:1000, the image's user).
#    A folder that Docker has just created for a missing FMAPPING_OUT (./out) belongs to root and
#    is empty: it is handed to that user. A folder of the user's own is never chowned; when that
#    user cannot write in it, this stops with a message (set FMAPPING_UID/GID to its owner).
# 2. Data: when /data holds a dataset fmapping reads, nothing to do. When it is empty (the named
#    volume of the default set-up, or an empty host folder), the synthetic demo room is generated
#    into it (`fmapping synth`, FMAPPING_DEMO_FRAMES frames). Anything else is an error naming the
#    folder, before the services start (not a play service exiting while the others wait).
# 3. A new run starts over: an earlier run's mapper checkpoint and tracker keyframes in the output
#    folder are removed (a mapper / tracker that compose restarts after a crash in this run resumes
#    from them; prepare runs once per `docker compose up`, not on those restarts).
#
# Exit codes: 0 ready, 2 bad data / output folder. The paths are variables for the tests only.
set -eu
DATA=${FMAPPING_DATA_DIR:-/data}
OUT=${FMAPPING_OUT_DIR:-/out}
RUN_UID=${FMAPPING_UID:-1000}
RUN_GID=${FMAPPING_GID:-1000}
FMAPPING=${FMAPPING_BIN:-fmapping}
PYTHON=${FMAPPING_PYTHON:-python}

if [ "$(stat -c %u "$OUT")" = 0 ] && [ -z "$(ls -A "$OUT")" ] && [ "$(id -u)" = 0 ]; then
    chown "$RUN_UID:$RUN_GID" "$OUT"
fi
# a real write as the services' user: permission bits alone say nothing about ACLs or read-only mounts
if ! "$PYTHON" - "$RUN_UID" "$RUN_GID" "$OUT" <<'EOF'
import os, sys
uid, gid, out = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
if os.getuid() == 0:  # drop root's groups too: a root-group-writable folder is not writable for the services
    os.setgroups([])
    os.setgid(gid)
    os.setuid(uid)
probe = os.path.join(out, ".fmapping-write-test")
try:
    open(probe, "w").close()
    os.remove(probe)
except OSError as e:
    sys.exit(f"{e.strerror}")
EOF
then
    echo "prepare: error: the output folder (FMAPPING_OUT, $OUT in the containers) is not writable by uid" \
         "$RUN_UID gid $RUN_GID, the services' user: run with FMAPPING_UID=\$(id -u) FMAPPING_GID=\$(id -g)" \
         "for a folder of yours, or give another FMAPPING_OUT" >&2
    exit 2
fi

for stale in "$OUT/checkpoint.pt" "$OUT/tracker/state.npz"; do
    if [ -e "$stale" ]; then
        rm -f "$stale"
        echo "prepare: starting over: removed $stale of an earlier run"
    fi
done

if "$FMAPPING" info --data "$DATA" >/dev/null 2>&1; then
    echo "prepare: dataset found in $DATA"
    exit 0
fi
if [ -n "$(ls -A "$DATA")" ]; then
    echo "prepare: error: FMAPPING_DATA ($DATA in the containers) holds no dataset fmapping reads:" >&2
    "$FMAPPING" info --data "$DATA" >/dev/null || true  # its one-line reason
    exit 2
fi
echo "prepare: $DATA is empty: generating the synthetic demo room (${FMAPPING_DEMO_FRAMES:-200} frames)"
"$FMAPPING" synth --out "$DATA" --frames "${FMAPPING_DEMO_FRAMES:-200}" --seed 0 >/dev/null
echo "prepare: demo dataset ready in $DATA"
