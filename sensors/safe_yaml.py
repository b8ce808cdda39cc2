"""Every YAML file rgbdnav reads goes through here: one place that refuses what would hang,
exhaust memory, crash the parser or be silently misread.

- **Size, encoding, kind of file**: a regular file of at most ``MAX_YAML_BYTES``, UTF-8.
- **Nesting and aliases**: the document is first walked as a stream of parser events (the
  parser keeps an explicit stack; the composer and constructor recurse), so nesting deeper than
  ``MAX_DEPTH`` and alias bombs (``MAX_EXPANDED_NODES`` nodes once every alias is expanded) are
  errors before anything is built or printed.
- **Duplicate keys** are an error naming the key and its line (PyYAML keeps the last silently).
  Keys merged in with ``<<: *anchor`` may still be overridden: that is what merges are for.
- **Numbers as users type them**: ``1e12`` and ``-3E-4`` are floats (YAML 1.2), not strings
  (PyYAML's YAML 1.1 resolver wants ``1.0e+12``).

Errors are the caller's :class:`RgbdNavError` subclass (a config file raises ConfigError, a map
MapError), with the file named.
"""

from __future__ import annotations

import os
import re
from typing import Any

import yaml

from sensors.bounded_read import read_bounded
from sensors.types import ConfigError, RgbdNavError

MAX_YAML_BYTES = 16 * 2**20  # [bytes] configs, scenes, worlds and map.yaml are kilobytes
MAX_DEPTH = 64  # [levels] of nested mappings/sequences
MAX_EXPANDED_NODES = 1_000_000  # [nodes] after alias expansion (a billion laughs has 10^9)
_QUOTE_LIMIT = 80  # [chars] of a key quoted in an error

# YAML 1.2 core-schema floats: an exponent without a dot (1e12) is a float too.
_FLOAT_12 = re.compile(
    r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
    |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
    |[-+]?\.[0-9_]+(?:[eE][-+]?[0-9]+)?
    |[-+]?[0-9][0-9_]*(?::[0-5]?[0-9])+\.[0-9_]*
    |[-+]?\.(?:inf|Inf|INF)
    |\.(?:nan|NaN|NAN))$""",
    re.X,
)


class _DuplicateKey(yaml.YAMLError):
    pass


class SafeYamlLoader(yaml.SafeLoader):
    """SafeLoader + duplicate keys rejected + YAML 1.2 floats."""

    def construct_mapping(self, node: yaml.Node, deep: bool = False) -> dict[Any, Any]:
        if isinstance(node, yaml.MappingNode):
            seen: set[Any] = set()
            for key_node, _ in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge" or not isinstance(
                    key_node, yaml.ScalarNode
                ):
                    continue
                key = self.construct_object(key_node)
                if key in seen:
                    line = key_node.start_mark.line + 1
                    raise _DuplicateKey(f"line {line}: duplicate key {_quote(key)}")
                seen.add(key)
        return super().construct_mapping(node, deep=deep)  # type: ignore[arg-type]


SafeYamlLoader.add_implicit_resolver("tag:yaml.org,2002:float", _FLOAT_12, list("-+0123456789."))


def _quote(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= _QUOTE_LIMIT else text[: _QUOTE_LIMIT - 3] + "..."


def _check_shape(text: str) -> str | None:
    """A problem with the document's nesting or alias expansion, or None; walks events only."""
    depth = 0
    sizes: list[int] = []  # nodes under each open collection
    anchored: list[str | None] = []  # the anchor of each open collection
    anchors: dict[str, int] = {}  # anchor -> expanded size of its node
    total = 0
    for event in yaml.parse(text, Loader=SafeYamlLoader):
        if isinstance(event, yaml.AliasEvent):
            n = anchors.get(event.anchor, 1)  # an undefined alias: the composer reports it
        elif isinstance(event, (yaml.MappingStartEvent, yaml.SequenceStartEvent)):
            depth += 1
            if depth > MAX_DEPTH:
                line = event.start_mark.line + 1 if event.start_mark else 0
                return f"line {line}: nested deeper than {MAX_DEPTH} levels"
            sizes.append(1)
            anchored.append(event.anchor)
            continue
        elif isinstance(event, (yaml.MappingEndEvent, yaml.SequenceEndEvent)):
            depth -= 1
            n = sizes.pop()
            anchor = anchored.pop()
            if anchor is not None:
                anchors[anchor] = n
        elif isinstance(event, yaml.ScalarEvent):
            n = 1
            if event.anchor is not None:
                anchors[event.anchor] = 1
        else:
            continue
        if sizes:
            sizes[-1] += n
            if sizes[-1] > MAX_EXPANDED_NODES:
                return f"expands to more than {MAX_EXPANDED_NODES} nodes (an alias bomb?)"
        else:
            total += n
            if total > MAX_EXPANDED_NODES:
                return f"expands to more than {MAX_EXPANDED_NODES} nodes (an alias bomb?)"
    return None


INVALID = "{source}: not valid YAML (line {line}: {problem})"  # the default message


def load_yaml(
    text: str, source: str, error: type[RgbdNavError] = ConfigError, invalid: str = INVALID
) -> Any:
    """Parse one YAML document from ``text``; problems raise ``error("<source>: ...")``.
    ``invalid`` words a syntax error (fields ``source``, ``line``, ``problem``)."""
    try:
        problem = _check_shape(text)
        if problem is not None:
            raise error(f"{source}: {problem}")
        return yaml.load(text, Loader=SafeYamlLoader)  # noqa: S506 (a SafeLoader subclass)
    except _DuplicateKey as err:
        raise error(f"{source}: {err}") from None
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        line = mark.line + 1 if mark is not None else "?"
        problem = getattr(err, "problem", None) or type(err).__name__
        raise error(invalid.format(source=source, line=line, problem=problem)) from None
    except RecursionError:  # pragma: no cover - _check_shape bounds the depth first
        raise error(f"{source}: nested too deeply to parse") from None


def read_yaml(
    path: str | os.PathLike[str],
    error: type[RgbdNavError] = ConfigError,
    what: str = "file",
    invalid: str = INVALID,
) -> Any:
    """:func:`load_yaml` of a file, which must be a regular UTF-8 file of sane size (a FIFO
    or ``/dev/zero`` would block or never end); ``what`` names it in errors ("config file")."""
    data = read_bounded(path, MAX_YAML_BYTES, error, what)
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as err:
        raise error(f"{path}: {what} is not UTF-8 text (byte {err.start})") from None
    return load_yaml(text, str(path), error, invalid)


__all__ = ["MAX_DEPTH", "MAX_EXPANDED_NODES", "SafeYamlLoader", "load_yaml", "read_yaml"]
