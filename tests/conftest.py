"""Fixtures shared by the test modules (helpers they build on: service_helpers.py).

* ``one_thread``: torch on one thread for the test (opt in, e.g. ``pytestmark =
  pytest.mark.usefixtures("one_thread")``): results do not depend on the core count and
  tests do not fight over the two cores of CI.
* ``scene`` (session) / ``dataset`` (module): a tiny synthetic RGB-D scene with GT poses,
  14 frames of 64x48, read only by the tests.
* ``room320`` (session): a 40-frame 320x240 synthetic room, large enough for the RGB-only
  front end to bootstrap and track.
* ``zpair``: two zenoh peers in this process over a free loopback port (no router).
"""
from __future__ import annotations

import pytest


@pytest.fixture
def one_thread():
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="session")
def scene(tmp_path_factory):
    from fmapping.synthetic import generate_scene

    out = tmp_path_factory.mktemp("scene") / "s"
    generate_scene(out, seed=2, frames=14, size=(64, 48), max_cloud_points=2000, mesh_spacing=0.2)
    return out


@pytest.fixture(scope="session")
def room320(tmp_path_factory):
    from fmapping.synthetic import generate_scene

    root = tmp_path_factory.mktemp("room320") / "syn"
    generate_scene(root, seed=0, frames=40, size=(320, 240), supersample=1, max_cloud_points=20000,
                   mesh_spacing=0.2)
    return root


@pytest.fixture(scope="module")
def dataset(scene):
    from fmapping.datasets import open_dataset

    return open_dataset(scene)


@pytest.fixture
def zpair():
    """(a, b, endpoint): ``a`` listens on a free loopback port, ``b`` connects to it."""
    zenoh = pytest.importorskip("zenoh")
    from service_helpers import loopback_endpoint, peer_conf

    ep = loopback_endpoint()
    a = zenoh.open(peer_conf(listen=[ep]))
    b = zenoh.open(peer_conf(connect=[ep]))
    yield a, b, ep
    b.close()
    a.close()
