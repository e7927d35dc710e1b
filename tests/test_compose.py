"""docker-compose.yml is secure by default: the router takes TLS + mutual TLS + access control
from the certificates a one-shot service makes, and every service connects with its identity.
`docker compose up` works on a fresh checkout: a one-shot `prepare` service generates the demo
room into a named volume when there is no dataset and makes the outputs writable for the
services' user; one image per variant is built once; the router and the Python package run the
same zenoh; the live viewer's ports are published on loopback.
No Docker engine here: the file is checked as data, and the one-shot services' commands
(certificates, deploy/prepare.sh) are run locally (tests/test_services.py runs
`docker-compose config -q` where installed)."""
from __future__ import annotations

import importlib.util
import json
import os
import re
import shlex
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
IDENTITY = {"mapper": "mapper", "mapper-gpu": "mapper", "tracker": "tracker", "tracker-gpu": "tracker",
            "io-record": "io", "io-view": "io", "io-play": "io"}


@pytest.fixture(scope="module")
def compose() -> dict:
    return yaml.safe_load((ROOT / "docker-compose.yml").read_text())


def test_router_is_tls_with_access_control_and_bound_to_loopback(compose):
    z = compose["services"]["zenoh"]
    assert z["command"] == ["-c", "/certs/zenoh/router.json5"]
    assert z["ports"] == ["127.0.0.1:7447:7447"]  # the host's loopback only
    assert z["depends_on"]["certs"]["condition"] == "service_completed_successfully"
    import zenoh

    conf = zenoh.Config.from_file(str(ROOT / "deploy" / "zenoh" / "router.json5"))
    assert json.loads(conf.get_json("transport/link/protocols")) == ["tls"]
    assert json.loads(conf.get_json("transport/link/tls/enable_mtls")) is True
    assert json.loads(conf.get_json("access_control/enabled")) is True
    assert json.loads(conf.get_json("access_control/default_permission")) == "deny"


def test_every_service_connects_over_tls_with_its_own_identity(compose):
    for name, identity in IDENTITY.items():
        svc = compose["services"][name]
        argv = shlex.split(svc["command"])
        assert argv[argv.index("--zenoh-config") + 1] == f"/certs/zenoh/client-{identity}.json5", name
        assert argv[argv.index("--connect") + 1] == "tls/zenoh:7447" and "--mode" in argv, name
        assert "certs:/certs:ro" in svc["volumes"], name
        assert svc["depends_on"]["certs"]["condition"] == "service_completed_successfully", name
        assert "ports" not in svc or name == "io-view", name  # only the viewer's, see below
    assert not re.search(r"tcp/", (ROOT / "docker-compose.yml").read_text())


def test_the_one_shot_certificate_service_makes_what_the_others_read(compose, tmp_path):
    """Run the certs service's generator command locally (its paths moved under tmp_path): the
    router and every identity the services use get a certificate, the configs point into /certs,
    and the CA key is deleted afterwards."""
    pytest.importorskip("cryptography")
    script = compose["services"]["certs"]["command"][-1]
    assert "rm -f /certs/ca-key.pem" in script and "--hosts localhost 127.0.0.1 zenoh" in script
    gen = " ".join(line.strip().rstrip("\\") for line in script.splitlines() if "make_test_certs.py" in line
                   or line.strip().startswith("--configs"))
    argv = shlex.split(gen)[2:]  # after `python /src/scripts/make_test_certs.py`
    argv[0] = str(tmp_path)
    spec = importlib.util.spec_from_file_location("make_test_certs", ROOT / "scripts" / "make_test_certs.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("make_test_certs", mod)
    spec.loader.exec_module(mod)
    assert mod.main(argv) == 0
    for identity in ("router", *set(IDENTITY.values())):
        assert (tmp_path / f"{identity}.pem").is_file() and (tmp_path / f"{identity}-key.pem").is_file()
    for identity in set(IDENTITY.values()):
        text = (tmp_path / "zenoh" / f"client-{identity}.json5").read_text()
        assert f'"/certs/{identity}.pem"' in text and '"/certs/ca.pem"' in text
    assert '"/certs/router-key.pem"' in (tmp_path / "zenoh" / "router.json5").read_text()


FMAPPING_SERVICES = list(IDENTITY)
DEFAULT = re.compile(r"^\$\{(\w+):-([^}]*)\}$")  # ${VAR:-default}


def _default(text: str) -> tuple[str, str]:
    m = DEFAULT.match(text)
    assert m, f"{text!r} is not ${{VAR:-default}}"
    return m.group(1), m.group(2)


def test_fresh_checkout_data_is_a_named_volume_that_prepare_fills_before_the_services(compose):
    """No FMAPPING_DATA: a named volume (not a ./data that Docker would create empty); every
    service waits for `prepare`, which generates the demo room into it when it holds no dataset."""
    text = (ROOT / "docker-compose.yml").read_text()
    assert "./data" not in text
    assert "demo-data" in compose["volumes"]
    prep = compose["services"]["prepare"]
    assert prep["user"] == "0:0" and prep["command"] == ["sh", "/prepare.sh"]
    assert "./deploy/prepare.sh:/prepare.sh:ro" in prep["volumes"]
    assert "${FMAPPING_DATA:-demo-data}:/data" in prep["volumes"] and "${FMAPPING_OUT:-./out}:/out" in prep["volumes"]
    for name in FMAPPING_SERVICES:
        svc = compose["services"][name]
        assert "${FMAPPING_DATA:-demo-data}:/data:ro" in svc["volumes"], name
        assert svc["depends_on"]["prepare"]["condition"] == "service_completed_successfully", name
    play = shlex.split(compose["services"]["io-play"]["command"])
    assert play[play.index("--data") + 1] == "/data"  # where prepare put the dataset


def test_services_run_as_the_configurable_user_that_owns_the_outputs_and_certificates(compose):
    dockerfile = (ROOT / "Dockerfile").read_text()
    image_uid = re.search(r"useradd .*--uid (\d+)", dockerfile).group(1)
    assert "chown fmapping:fmapping /data /out" in dockerfile  # fresh named volumes start with that owner
    for name in FMAPPING_SERVICES:
        uid, gid = re.fullmatch(r"(\$\{[^}]*\}):(\$\{[^}]*\})", compose["services"][name]["user"]).groups()
        assert _default(uid) == ("FMAPPING_UID", image_uid) and _default(gid) == ("FMAPPING_GID", image_uid), name
        assert compose["services"][name]["environment"]["HOME"] == "/tmp", name
    for one_shot in ("certs", "prepare"):  # they hand the files to the same user
        env = compose["services"][one_shot]["environment"]
        assert env["FMAPPING_UID"] == "${FMAPPING_UID:-1000}" and env["FMAPPING_GID"] == "${FMAPPING_GID:-1000}"
    assert 'chown -R "$$FMAPPING_UID:$$FMAPPING_GID" /certs' in compose["services"]["certs"]["command"][-1]


def test_each_image_is_built_by_one_service_and_reused(compose):
    """One build per image tag: `prepare` builds fmapping:cpu, mapper-gpu fmapping:gpu (CUDA torch);
    tracker-gpu no longer inherits the CPU build while tagging fmapping:gpu."""
    builders: dict[str, list[str]] = {}
    for name, svc in compose["services"].items():
        if "build" in svc:
            builders.setdefault(svc["image"], []).append(name)
    assert builders == {"fmapping:cpu": ["prepare"], "fmapping:gpu": ["mapper-gpu"]}
    for name in ("mapper", "tracker", "io-record", "io-view", "io-play"):
        assert compose["services"][name]["image"] == "fmapping:cpu", name
    gpu = compose["services"]["mapper-gpu"]
    assert "cu" in gpu["build"]["args"]["TORCH_INDEX"]
    assert compose["services"]["tracker-gpu"]["image"] == "fmapping:gpu"
    for name in ("mapper-gpu", "tracker-gpu"):
        svc = compose["services"][name]
        assert svc["profiles"] == ["gpu"] and svc["deploy"]["resources"]["reservations"]["devices"], name
    assert "--device cuda" in gpu["command"]


def test_router_image_and_python_package_run_the_same_zenoh(compose):
    from packaging.specifiers import SpecifierSet

    var, router = _default(compose["services"]["zenoh"]["image"].split(":", 1)[1])
    assert var == "ZENOH_VERSION" and re.fullmatch(r"1\.10\.\d+", router)
    for name in ("prepare", "mapper-gpu"):  # every image build pins eclipse-zenoh to it
        assert _default(compose["services"][name]["build"]["args"]["ZENOH_VERSION"]) == (var, router), name
    dockerfile = (ROOT / "Dockerfile").read_text()
    assert f"ARG ZENOH_VERSION={router}" in dockerfile and '"eclipse-zenoh==${ZENOH_VERSION}"' in dockerfile
    pyproject = (ROOT / "pyproject.toml").read_text()
    spec = re.search(r'"eclipse-zenoh([^"]*)"', pyproject).group(1)
    assert router in SpecifierSet(spec)  # the pin is one the package allows


def test_viewer_serves_live_on_loopback_ports_and_saves(compose):
    from services.io import view
    from services.process import service_parser

    svc = compose["services"]["io-view"]
    argv = shlex.split(svc["command"])[4:]  # after `python -m services.io view`
    args = view.add_args(service_parser("view", "")).parse_args(argv)
    assert view.serving(args) and args.serve and args.bind == "0.0.0.0"  # reachable through the published ports
    assert args.save == "/out/run.rrd" and args.final_outputs == "/out"
    assert svc["ports"] == [f"127.0.0.1:{args.web_port}:{args.web_port}",
                            f"127.0.0.1:{args.grpc_port}:{args.grpc_port}"]
    assert (args.web_port, args.grpc_port) == (9090, 9876)
    for name, other in compose["services"].items():  # every published port is on the host's loopback only
        for port in other.get("ports", []):
            assert port.startswith("127.0.0.1:"), (name, port)


def _prepare(tmp_path, data, out, **env):
    fmapping = Path(sys.executable).with_name("fmapping")
    if not fmapping.is_file():
        pytest.skip("the fmapping command is not installed next to this python")
    env = {**os.environ, "FMAPPING_DATA_DIR": str(data), "FMAPPING_OUT_DIR": str(out), "FMAPPING_BIN": str(fmapping),
           "FMAPPING_PYTHON": sys.executable, "FMAPPING_UID": str(os.getuid()), "FMAPPING_GID": str(os.getgid()),
           **env}
    return subprocess.run(["sh", str(ROOT / "deploy" / "prepare.sh")], env=env, capture_output=True, text=True,
                          timeout=300)


def test_prepare_generates_the_demo_room_once_into_an_empty_data_folder(tmp_path):
    from fmapping.datasets import open_dataset

    data, out = tmp_path / "data", tmp_path / "out"
    data.mkdir()
    out.mkdir()
    r = _prepare(tmp_path, data, out, FMAPPING_DEMO_FRAMES="3")
    assert r.returncode == 0, r.stderr
    assert "generating the synthetic demo room (3 frames)" in r.stdout
    assert len(open_dataset(data)) == 3 and not list(out.iterdir())  # the write probe left nothing
    stamp = (data / "rgb.txt").stat().st_mtime_ns
    r = _prepare(tmp_path, data, out)
    assert r.returncode == 0 and "dataset found" in r.stdout and (data / "rgb.txt").stat().st_mtime_ns == stamp


def test_prepare_refuses_a_folder_without_a_dataset_and_an_unwritable_output(tmp_path):
    data, out = tmp_path / "data", tmp_path / "out"
    data.mkdir()
    out.mkdir()
    (data / "notes.txt").write_text("not a dataset\n")
    r = _prepare(tmp_path, data, out)
    assert r.returncode == 2 and "holds no dataset fmapping reads" in r.stderr
    assert "notes.txt" in {p.name for p in data.iterdir()} and len(list(data.iterdir())) == 1  # untouched
    if os.getuid() != 0:
        return  # the rest needs root: chown, and writing as another user
    (out / "keep").write_text("")  # not empty: not Docker's fresh folder, so never chowned
    r = _prepare(tmp_path, data, out, FMAPPING_UID="65534", FMAPPING_GID="65534")
    assert r.returncode == 2 and "not writable by uid 65534" in r.stderr and "FMAPPING_UID=$(id -u)" in r.stderr
    assert out.stat().st_uid == 0
    with tempfile.TemporaryDirectory() as top:  # pytest's tmp_path is root's only: nobody could enter it
        os.chmod(top, 0o755)
        fresh = Path(top) / "out"  # as Docker creates a missing ./out: root's and empty
        fresh.mkdir()
        r = _prepare(tmp_path, data, fresh, FMAPPING_UID="65534", FMAPPING_GID="65534")
        assert fresh.stat().st_uid == 65534 and r.returncode == 2 and "holds no dataset" in r.stderr, r.stderr


def test_crashed_mapper_and_tracker_are_restarted_and_resume_within_the_run(compose, tmp_path):
    """As under `fmapping up`: a crashed mapper / tracker comes back (bounded), the mapper from its
    checkpoint in /out, the tracker re-localising against the keyframes it keeps in /out, and play
    sends them the frames they missed; a new `docker compose up` starts over (prepare removes an
    earlier run's checkpoint and tracker state, and runs once per up, not on those restarts)."""
    svc = compose["services"]
    for name in ("mapper", "tracker", "mapper-gpu", "tracker-gpu"):
        policy = svc[name]["restart"]
        assert policy.startswith("on-failure:") and 1 <= int(policy.split(":")[1]) <= 5, (name, policy)
        argv = shlex.split(svc[name]["command"])
        # the data's camera: a first frame of another camera is refused (a peer gone wrong cannot fix the stream's)
        assert argv[argv.index("--stream-camera-of") + 1] == "/data"
        if name.startswith("tracker"):
            assert argv[argv.index("--state") + 1].startswith("/out/")
        else:
            assert argv[argv.index("--out") + 1] == "/out" and "--resent-frames" in argv
    play = shlex.split(svc["io-play"]["command"])
    assert set(play[play.index("--resend-to") + 1].split(",")) == {"mapper", "tracker"}
    assert svc["prepare"]["restart"] == "no"
    data, out = tmp_path / "data", tmp_path / "out"
    data.mkdir()
    (out / "tracker").mkdir(parents=True)
    (out / "checkpoint.pt").write_bytes(b"old")
    (out / "tracker" / "state.npz").write_bytes(b"old")
    (out / "map.ply").write_bytes(b"an earlier run's output")
    r = _prepare(tmp_path, data, out, FMAPPING_DEMO_FRAMES="3")
    assert r.returncode == 0, r.stderr
    assert not (out / "checkpoint.pt").exists() and not (out / "tracker" / "state.npz").exists()
    assert (out / "map.ply").read_bytes() == b"an earlier run's output"
    assert r.stdout.count("starting over") == 2
