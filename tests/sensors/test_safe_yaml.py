"""The one YAML reader: what would hang, exhaust memory, crash or be misread is a clear error."""

from __future__ import annotations

from pathlib import Path

import pytest

from sensors.safe_yaml import MAX_DEPTH, load_yaml, read_yaml
from sensors.types import ConfigError, MapError


def test_keys_merged_from_an_anchor_may_be_overridden_but_not_repeated() -> None:
    doc = load_yaml("base: &b {x: 1, y: 2}\nother:\n  <<: *b\n  x: 3\n", "s")
    assert doc["other"] == {"x": 3, "y": 2}
    with pytest.raises(ConfigError, match=r"s: line 4: duplicate key 'x'"):
        load_yaml("other:\n  <<: {x: 1}\n  x: 3\n  x: 4\n", "s")


def test_keys_that_are_the_same_value_written_differently_are_duplicates() -> None:
    with pytest.raises(ConfigError, match="duplicate key 1"):
        load_yaml("{1: a, 0x1: b}", "s")


def test_nesting_is_bounded_before_anything_is_built() -> None:
    ok = "[" * MAX_DEPTH + "]" * MAX_DEPTH
    assert load_yaml(ok, "s") is not None
    with pytest.raises(ConfigError, match=f"nested deeper than {MAX_DEPTH}"):
        load_yaml("[" + ok + "]", "s")


def test_the_error_class_is_the_callers(tmp_path: Path) -> None:
    path = tmp_path / "map.yaml"
    path.write_text("a: [1,\n")
    with pytest.raises(MapError, match=r"map\.yaml: not valid YAML \(line 2:"):
        read_yaml(path, MapError)
    with pytest.raises(MapError, match=r"nothing\.yaml: cannot read file \(No such file"):
        read_yaml(tmp_path / "nothing.yaml", MapError)


def test_an_undefined_alias_is_a_syntax_error_not_a_crash() -> None:
    with pytest.raises(ConfigError, match="undefined alias"):
        load_yaml("a: *nowhere\n", "s")
