"""The command line's user-facing basics: packaging (matplotlib only for benches), ``--version``,
``config dump``, help text on every flag, one-line errors for a bad ``--out``."""
from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_library_and_services_import_without_matplotlib():
    # matplotlib is the [bench] extra: a plain `pip install fmapping` must import every module
    code = textwrap.dedent("""
        import importlib, pkgutil, sys
        sys.modules["matplotlib"] = None  # any `import matplotlib` now raises ImportError
        import fmapping, services
        names = []
        for pkg in (fmapping, services):
            for m in pkgutil.walk_packages(pkg.__path__, pkg.__name__ + "."):
                if not m.name.endswith("__main__"):
                    importlib.import_module(m.name)
                    names.append(m.name)
        print(len(names))
    """)
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert int(r.stdout.split()[-1]) > 20
