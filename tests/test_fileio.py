import json
import os
import stat
from pathlib import Path

import numpy as np
import pytest

from fmapping.fileio import atomic_open, atomic_write_text, json_default, plain_tree, temp_path, write_json


def test_a_failed_write_leaves_the_old_file_and_its_temp_file(tmp_path):
    path = tmp_path / "a.bin"
    path.write_bytes(b"old")
    with pytest.raises(RuntimeError):
        with atomic_open(path, fsync=True, fsync_folder=True) as fh:
            fh.write(b"half")
            raise RuntimeError("dies mid-write")
    assert path.read_bytes() == b"old" and temp_path(path).read_bytes() == b"half"
    with atomic_open(path, fsync=True, fsync_folder=True) as fh:
        np.savez(fh, x=np.arange(3))
    assert np.load(path)["x"].tolist() == [0, 1, 2] and not temp_path(path).exists()


def test_mode_applies_from_creation_also_over_an_existing_temp_file(tmp_path):
    path = tmp_path / "secret.txt"
    temp_path(path).write_text("left by a crash")
    os.chmod(temp_path(path), 0o644)
    assert atomic_write_text(path, "pw\n", mode=0o600) == path
    assert path.read_text() == "pw\n" and stat.S_IMODE(path.stat().st_mode) == 0o600


def test_write_json_and_json_default(tmp_path):
    obj = {"b": np.float32(0.5), "a": np.int64(3), "arr": np.arange(2), "p": Path("x/y"), "o": object}
    path = write_json(tmp_path / "s.json", obj, sort_keys=True)
    assert json.loads(path.read_text()) == {"a": 3, "arr": [0, 1], "b": 0.5, "o": str(object), "p": "x/y"}
    assert path.read_text() == json.dumps(obj, indent=1, sort_keys=True, default=json_default)
    assert json.loads(write_json(path, {"n": np.int64(3)}, default=str).read_text()) == {"n": "3"}


def test_plain_tree_turns_tuples_into_lists_at_every_depth():
    tree = {"rounds": ((0, 32), (3, 64)), "field": {"size": (1, 2)}, "name": "x", "n": 3}
    assert plain_tree(tree) == {"rounds": [[0, 32], [3, 64]], "field": {"size": [1, 2]}, "name": "x", "n": 3}
