"""Transport benchmark: 640x480 RGB-D frames and field snapshots over zenoh on loopback.

Two OS processes (this one publishes, a child subscribes), zenoh peers over
``tcp/127.0.0.1:<free port>``, multicast off. Measured per payload kind:

* encode / decode time of the protocol message (msgpack + validation), in this process;
* one-way latency, send -> subscriber callback, of the encoded bytes (the send time
  travels in the zenoh attachment; both processes read the same monotonic clock),
  paced so that messages do not queue; and the same plus encode and decode
  ("end to end": a service publishing a fresh message and a service decoding it);
* throughput: messages sent back to back (congestion control BLOCK), messages/s and MB/s
  at the subscriber.

Writes bench/results/transport.json. Timings on a shared CPU are noisy: the JSON records
the machine and the load average at the start.

    python bench/transport.py [--frames 300] [--snapshots 300] [--throughput 200]
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from fmapping import protocol as P  # noqa: E402
from services.zenoh_session import free_port  # noqa: E402

KEY = "fmapping/bench/{kind}"


def _conf(listen=None, connect=None):
    import zenoh

    c = zenoh.Config()
    c.insert_json5("mode", '"peer"')
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("listen/endpoints", json.dumps(listen or []))
    c.insert_json5("connect/endpoints", json.dumps(connect or []))
    return c


def make_frame(seq: int = 0) -> P.Frame:
    rng = np.random.default_rng(seq)
    return P.Frame(seq=seq, timestamp=seq / 30.0, rgb=rng.integers(0, 256, (480, 640, 3), dtype=np.uint8),
                   camera={"fx": 525.0, "fy": 525.0, "cx": 319.5, "cy": 239.5, "width": 640, "height": 480},
                   depth=rng.uniform(0.3, 5.0, (480, 640)).astype(np.float32))


def make_snapshot(version: int = 1) -> P.FieldSnapshot:
    """A FieldSnapshot of the default CP field (the tensors the tracker renders from)."""
    import dataclasses

    from fmapping.field import FieldConfig, build_field

    cfg = FieldConfig()
    aabb = np.array([[-3.0, -3.0, -1.0], [3.0, 3.0, 3.0]])
    arrays = build_field(cfg, aabb).snapshot()
    return P.FieldSnapshot(version=version, kind=cfg.kind, config={"field": dataclasses.asdict(cfg)}, aabb=aabb,
                           arrays=arrays, frame_seq=version)


def stats_ms(xs) -> dict:
    a = np.asarray(xs, np.float64) * 1e3
    return {"median": round(float(np.median(a)), 4), "p95": round(float(np.percentile(a, 95)), 4),
            "min": round(float(a.min()), 4), "max": round(float(a.max()), 4), "n": int(len(a))}


def time_codec(msg, n: int) -> tuple[dict, dict, int]:
    enc, dec = [], []
    data = P.encode(msg)
    for _ in range(n):
        t0 = time.perf_counter()
        data = P.encode(msg)
        t1 = time.perf_counter()
        P.decode(data)
        t2 = time.perf_counter()
        enc.append(t1 - t0)
        dec.append(t2 - t1)
    return stats_ms(enc), stats_ms(dec), len(data)


# ---------------------------------------------------------------------------- subscriber (child process)
def run_subscriber(port: int, kinds: list[str], counts: dict) -> None:
    import zenoh

    s = zenoh.open(_conf(listen=[f"tcp/127.0.0.1:{port}"]))
    results = {k: {"lat": [], "dec": [], "recv": []} for k in kinds}
    done = threading.Event()
    lock = threading.Lock()

    def handler(kind):
        def on(sample):
            t = time.perf_counter_ns()
            sent, phase = struct.unpack("<qb", sample.attachment.to_bytes())
            data = sample.payload.to_bytes()
            r = results[kind]
            if phase == 1:  # latency phase: decode too
                t0 = time.perf_counter()
                P.decode(data)
                r["dec"].append(time.perf_counter() - t0)
                r["lat"].append((t - sent) / 1e9)
            elif phase == 2:  # throughput phase
                r["recv"].append((t, len(data)))
            with lock:
                if all(len(results[k]["lat"]) >= counts[k]["lat"] and len(results[k]["recv"]) >= counts[k]["tp"]
                       for k in kinds):
                    done.set()
        return on

    subs = [s.declare_subscriber(KEY.format(kind=k), handler(k)) for k in kinds]
    print("ready", flush=True)
    done.wait(timeout=600)
    out = {}
    for k in kinds:
        r = results[k]
        tp = {}
        if len(r["recv"]) > 1:
            t0, t1 = r["recv"][0][0], r["recv"][-1][0]
            nbytes = sum(b for _, b in r["recv"][1:])
            secs = (t1 - t0) / 1e9
            tp = {"messages": len(r["recv"]), "msgs_per_s": round((len(r["recv"]) - 1) / secs, 1),
                  "MB_per_s": round(nbytes / secs / 1e6, 1)}
        out[k] = {"lat": r["lat"], "dec": r["dec"], "throughput": tp}
    for sub in subs:
        sub.undeclare()
    s.close()
    print(json.dumps(out), flush=True)


# ---------------------------------------------------------------------------- publisher (this process)
def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=300, help="paced frames for latency")
    ap.add_argument("--snapshots", type=int, default=300, help="paced snapshots for latency")
    ap.add_argument("--throughput", type=int, default=200, help="back-to-back messages per kind for throughput")
    ap.add_argument("--period", type=float, default=0.02, help="seconds between paced messages")
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "transport.json"))
    ap.add_argument("--role", default="pub", help=argparse.SUPPRESS)
    ap.add_argument("--port", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--counts", default="{}", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    kinds = ["frame_rgbd_640x480", "field_snapshot"]
    if a.role == "sub":
        run_subscriber(a.port, kinds, json.loads(a.counts))
        return 0

    import zenoh

    msgs = {"frame_rgbd_640x480": make_frame, "field_snapshot": make_snapshot}
    n_lat = {"frame_rgbd_640x480": a.frames, "field_snapshot": a.snapshots}
    warm = 20
    counts = {k: {"lat": n_lat[k], "tp": a.throughput} for k in kinds}
    load = os.getloadavg()
    report = {
        "machine": {"platform": platform.platform(), "python": platform.python_version(), "cpus": os.cpu_count(),
                    "processor": platform.processor() or platform.machine(),
                    "loadavg_at_start": [round(x, 2) for x in load]},
        "zenoh": getattr(zenoh, "__version__", None) or _pkg_version("eclipse-zenoh"),
        "msgpack": _pkg_version("msgpack"),
        "setup": "two processes, zenoh peers on tcp/127.0.0.1, multicast off; latency paced every "
                 f"{a.period * 1e3:.0f} ms; throughput back to back with congestion control BLOCK",
        "goal": "median one-way latency <= 2 ms per 640x480 RGB-D frame",
        "results": {},
    }
    # codec timings first (no network)
    for k in kinds:
        enc, dec, size = time_codec(msgs[k](1), 50)
        report["results"][k] = {"bytes": size, "encode_ms": enc, "decode_ms": dec}

    port = free_port()
    child = subprocess.Popen([sys.executable, __file__, "--role", "sub", "--port", str(port), "--counts",
                              json.dumps(counts)], stdout=subprocess.PIPE, text=True, cwd=ROOT)
    assert child.stdout.readline().strip() == "ready"
    s = zenoh.open(_conf(connect=[f"tcp/127.0.0.1:{port}"]))
    try:
        pubs = {k: s.declare_publisher(KEY.format(kind=k), congestion_control=zenoh.CongestionControl.BLOCK)
                for k in kinds}
        for k in kinds:
            end = time.monotonic() + 30
            while not pubs[k].matching_status.matching:
                if time.monotonic() > end:
                    raise RuntimeError("subscriber not matched")
                time.sleep(0.01)
        for k in kinds:
            objs = [msgs[k](i) for i in range(4)]  # built once: encoding is what is timed
            pre = [P.encode(m) for m in objs]
            e2e_enc = []
            for i in range(warm + n_lat[k]):
                t0 = time.perf_counter()
                data = P.encode(objs[i % 4])
                t1 = time.perf_counter()
                phase = 1 if i >= warm else 0
                pubs[k].put(data, attachment=struct.pack("<qb", time.perf_counter_ns(), phase))
                if phase:
                    e2e_enc.append(t1 - t0)
                time.sleep(a.period)
            report["results"][k]["_enc_in_loop"] = e2e_enc
            for i in range(a.throughput):
                pubs[k].put(pre[i % 4], attachment=struct.pack("<qb", time.perf_counter_ns(), 2))
        line = child.stdout.readline()
        child.wait(timeout=120)
    finally:
        s.close()
        if child.poll() is None:
            child.kill()
    sub = json.loads(line)
    for k in kinds:
        r = report["results"][k]
        enc_loop = r.pop("_enc_in_loop")
        lat, dec = np.asarray(sub[k]["lat"]), np.asarray(sub[k]["dec"])
        r["latency_ms"] = stats_ms(lat)
        n = min(len(lat), len(enc_loop), len(dec))
        r["latency_with_codec_ms"] = stats_ms(lat[:n] + np.asarray(enc_loop[:n]) + dec[:n])
        r["encode_in_loop_ms"] = stats_ms(enc_loop)  # encode right after an idle period (cold caches)
        r["decode_in_subscriber_ms"] = stats_ms(dec)
        r["throughput"] = sub[k]["throughput"]
    r = report["results"]["frame_rgbd_640x480"]
    report["goal_met"] = bool(r["latency_ms"]["median"] <= 2.0)
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(report, indent=1))
    for k, r in report["results"].items():
        print(f"{k:20s} {r['bytes'] / 1e6:7.3f} MB  encode {r['encode_ms']['median']:.3f} ms  "
              f"decode {r['decode_ms']['median']:.3f} ms  one-way {r['latency_ms']['median']:.3f} ms "
              f"(p95 {r['latency_ms']['p95']:.3f})  with codec {r['latency_with_codec_ms']['median']:.3f} ms  "
              f"throughput {r['throughput'].get('msgs_per_s', '?')} msg/s {r['throughput'].get('MB_per_s', '?')} MB/s")
    print(f"wrote {a.out}")
    return 0


def _pkg_version(name: str):
    try:
        from importlib.metadata import version

        return version(name)
    except Exception:
        return None


if __name__ == "__main__":
    sys.exit(main())
