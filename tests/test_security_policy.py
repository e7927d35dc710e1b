"""The project's deserialisation policy, checked on the source (docs/security.md).

No pickle / marshal / shelve / dill, no eval / exec, ``torch.load`` only with
``weights_only=True``, YAML only through ``safe_load``, ``numpy.load`` never with
``allow_pickle=True``, no ``shell=True`` subprocesses, and every ``msgpack.unpackb`` with
explicit size limits. Tests are exempt (they craft hostile payloads on purpose).
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SCANNED = ("fmapping", "services", "scripts", "bench", "examples")
BANNED_MODULES = {"pickle", "cPickle", "_pickle", "dill", "cloudpickle", "marshal", "shelve", "joblib"}
BANNED_BUILTINS = {"eval", "exec", "__import__"}
MSGPACK_LIMITS = {"max_bin_len", "max_str_len", "max_array_len", "max_map_len"}


def _dotted(node: ast.AST) -> str:
    parts = []
    while isinstance(node, ast.Attribute):
        parts.append(node.attr)
        node = node.value
    if isinstance(node, ast.Name):
        parts.append(node.id)
    return ".".join(reversed(parts))


def _kw(call: ast.Call, name: str):
    for k in call.keywords:
        if k.arg == name:
            return k.value
    return None


def _is_true(node) -> bool:
    return isinstance(node, ast.Constant) and node.value is True


def violations(source: str, filename: str = "<src>") -> list[str]:
    """Every policy violation in one Python source, as 'file:line: what'."""
    out = []
    tree = ast.parse(source, filename=filename)
    for node in ast.walk(tree):
        where = f"{filename}:{getattr(node, 'lineno', 0)}"
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name.split(".")[0] in BANNED_MODULES:
                    out.append(f"{where}: import {a.name}")
        elif isinstance(node, ast.ImportFrom):
            if (node.module or "").split(".")[0] in BANNED_MODULES:
                out.append(f"{where}: from {node.module} import ...")
        elif isinstance(node, ast.Call):
            name = _dotted(node.func)
            if isinstance(node.func, ast.Name) and name in BANNED_BUILTINS:
                out.append(f"{where}: {name}()")
            elif name == "torch.load":
                if not _is_true(_kw(node, "weights_only")):
                    out.append(f"{where}: torch.load without weights_only=True")
            elif name in ("yaml.load", "yaml.unsafe_load", "yaml.full_load", "yaml.load_all",
                          "yaml.unsafe_load_all", "yaml.full_load_all"):
                out.append(f"{where}: {name} (use yaml.safe_load)")
            elif name in ("np.load", "numpy.load") and _is_true(_kw(node, "allow_pickle")):
                out.append(f"{where}: {name}(allow_pickle=True)")
            elif name in ("msgpack.unpackb", "msgpack.Unpacker", "msgpack.unpack", "msgpack.loads"):
                missing = MSGPACK_LIMITS - {k.arg for k in node.keywords}
                if missing:
                    out.append(f"{where}: {name} without {sorted(missing)}")
            if _is_true(_kw(node, "shell")):
                out.append(f"{where}: {name}(shell=True)")
    return out


def _sources():
    for d in SCANNED:
        yield from sorted((REPO / d).rglob("*.py"))


def test_policy_checker_catches_violations():
    bad = """
import pickle
from marshal import loads
import torch, yaml, numpy as np, msgpack, subprocess
eval("1")
exec("x = 1")
torch.load("f.pt")
torch.load("f.pt", weights_only=False)
yaml.load(open("c.yaml"))
np.load("a.npy", allow_pickle=True)
msgpack.unpackb(b"")
subprocess.run("ls", shell=True)
"""
    found = violations(bad)
    assert len(found) == 10, found
    good = """
import torch, yaml, numpy as np, msgpack
model.eval()
torch.load("f.pt", map_location="cpu", weights_only=True)
yaml.safe_load("a: 1")
np.load("a.npy")
msgpack.unpackb(b"", max_bin_len=1, max_str_len=1, max_array_len=1, max_map_len=1)
"""
    assert violations(good) == []


def test_sources_follow_the_policy():
    files = list(_sources())
    assert any(f.name == "protocol.py" for f in files)
    found = []
    for f in files:
        try:
            found += violations(f.read_text(), str(f.relative_to(REPO)))
        except SyntaxError as e:  # a file being edited right now: report, do not hide
            pytest.fail(f"{f}: cannot parse: {e}")
    assert found == [], "\n".join(found)
