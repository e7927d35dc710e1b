"""docker-compose.yml is secure by default: the router takes TLS + mutual TLS + access control
from the certificates a one-shot service makes, and every service connects with its identity.
No Docker engine here: the file is checked as data, and the one-shot service's certificate
command is run locally (tests/test_services.py runs `docker-compose config -q` where installed)."""
from __future__ import annotations

import importlib.util
import json
import re
import shlex
import sys
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
        assert "ports" not in svc, name
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
