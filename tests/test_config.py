from dataclasses import dataclass, field

import pytest

from fmapping.config import ConfigError, load_config


@dataclass
class Inner:
    lr: float = 0.02
    kind: str = "cp"


@dataclass
class Outer:
    inner: Inner = field(default_factory=Inner)
    iters: int = 20
    flag: bool = False


def test_yaml_overrides_nested(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("iters: 5\ninner:\n  lr: 1\n")
    cfg = load_config(Outer(), p, {"flag": True})
    assert cfg == Outer(Inner(lr=1.0, kind="cp"), iters=5, flag=True)
    assert isinstance(cfg.inner.lr, float)


@pytest.mark.parametrize("text,match", [
    ("itters: 5\n", "unknown key 'itters'"),
    ("inner:\n  lr: fast\n", "inner.lr: expected float"),
    ("flag: 3\n", "flag: expected true/false"),
    ("iters: [1\n", "invalid YAML"),
])
def test_bad_config_is_named(tmp_path, text, match):
    p = tmp_path / "c.yaml"
    p.write_text(text)
    with pytest.raises(ConfigError, match=match):
        load_config(Outer(), p)


def test_missing_config_file(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_config(Outer(), tmp_path / "nope.yaml")


@dataclass
class WithTuples:
    rounds: tuple = ((0, 32), (3, 64))
    scales: tuple[float, ...] = (1.0,)
    names: list = field(default_factory=lambda: ["a"])


def test_yaml_lists_become_tuples_for_tuple_fields_and_dump_round_trips(tmp_path):
    from fmapping.config import to_yaml

    p = tmp_path / "c.yaml"
    p.write_text("rounds: [[1, 2], [3, 4]]\nscales: [2]\nnames: [b, c]\n")
    cfg = load_config(WithTuples(), p)
    assert cfg.rounds == ((1, 2), (3, 4)) and cfg.scales == (2,) and cfg.names == ["b", "c"]
    p.write_text(to_yaml(cfg))
    assert "rounds: [[1, 2], [3, 4]]" in p.read_text()
    assert load_config(WithTuples(), p) == cfg
    p.write_text(to_yaml(Outer()))
    assert load_config(Outer(), p) == Outer()
