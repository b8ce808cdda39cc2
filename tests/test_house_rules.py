"""House rules that hold for the whole tree: one-way imports and short module docstrings.

ARCHITECTURE.md: `sensors` <- `slam` <- `nav` <- `rgbdnav` (sensors import nothing of ours; nav
may import slam), and inside `rgbdnav/` a command never imports another command (what two verbs
share lives in `rgbdnav/runners/` or below). STYLE.md: a module docstring says what and why in
at most 25 lines; measurements and history live in `docs/`.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
MAX_DOCSTRING_LINES = 25


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path, source: str | None = None) -> Iterator[str]:
    """Every module `path` (or `source` read as that file) imports, lazy imports included."""
    package = _module_name(path).split(".")
    if path.name != "__init__.py":
        package = package[:-1]
    text = path.read_text() if source is None else source
    for node in ast.walk(ast.parse(text, filename=str(path))):
        if isinstance(node, ast.Import):
            yield from (alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = package[: len(package) - node.level + 1] if node.level else []
            module = ".".join([*base, *([node.module] if node.module else [])])
            yield module
            yield from (f"{module}.{alias.name}" for alias in node.names)


def _modules(*folders: str) -> list[Path]:
    return sorted(p for folder in folders for p in (ROOT / folder).rglob("*.py"))


def _is_in(module: str, package: str) -> bool:
    return module == package or module.startswith(package + ".")


def _verb_of(module: str) -> str | None:
    """The command a module belongs to: one module of `rgbdnav.commands`, or the `live` package."""
    if _is_in(module, "rgbdnav.live"):
        return "rgbdnav.live"
    parts = module.split(".")
    if parts[:2] == ["rgbdnav", "commands"] and len(parts) > 2:
        return ".".join(parts[:3])
    return None


def test_a_command_never_imports_another_command() -> None:
    bad = []
    for path in _modules("rgbdnav/commands", "rgbdnav/live"):
        own = _verb_of(_module_name(path))
        for module in _imports(path):
            other = _verb_of(module)
            if other is not None and other != own:
                bad.append(f"{path.relative_to(ROOT)} imports {module}")
    assert bad == []


def test_every_module_in_commands_is_a_verb() -> None:
    """A module in `rgbdnav/commands/` is there because `cli.py` runs it as a verb; work that
    no verb runs (a benchmark's scenario, a helper) belongs in `bench/`, `runners/` or below."""
    verbs = {_verb_of(m) for m in _imports(ROOT / "rgbdnav" / "cli.py")} - {None}
    commands = {
        _module_name(path) for path in _modules("rgbdnav/commands") if path.name != "__init__.py"
    }
    assert commands - verbs == set()


def test_a_run_imports_no_command_and_no_other_run() -> None:
    bad = []
    for path in _modules("rgbdnav/runners"):
        own = _module_name(path)
        for module in _imports(path):
            other_run = _is_in(module, "rgbdnav.runners") and module.split(".")[:3] != own.split(
                "."
            )
            if _verb_of(module) is not None or (other_run and module != "rgbdnav.runners"):
                bad.append(f"{path.relative_to(ROOT)} imports {module}")
    assert bad == []


def test_shared_pieces_of_rgbdnav_import_no_command_or_run() -> None:
    shared = [p for p in (ROOT / "rgbdnav").glob("*.py") if p.name not in ("cli.py", "__init__.py")]
    bad = [
        f"{path.relative_to(ROOT)} imports {module}"
        for path in shared
        for module in _imports(path)
        if _verb_of(module) is not None or _is_in(module, "rgbdnav.runners")
    ]
    assert bad == []


@pytest.mark.parametrize(
    ("folder", "forbidden"),
    [("sensors", ("rgbdnav", "slam", "nav")), ("slam", ("rgbdnav", "nav")), ("nav", ("rgbdnav",))],
)
def test_the_algorithm_layers_never_import_the_layers_above(
    folder: str, forbidden: tuple[str, ...]
) -> None:
    bad = [
        f"{path.relative_to(ROOT)} imports {module}"
        for path in _modules(folder)
        for module in _imports(path)
        if any(_is_in(module, top) for top in forbidden)
    ]
    assert bad == []


def test_the_import_walk_sees_lazy_and_relative_imports() -> None:
    """So the rules above can fail: a command importing a sibling inside a function is caught."""
    probe = ROOT / "rgbdnav" / "commands" / "probe.py"  # need not exist: the source is given
    source = "def f():\n    from rgbdnav.runners import map\n    from . import batch\n"
    found = set(_imports(probe, source))
    assert {"rgbdnav.runners.map", "rgbdnav.commands.batch"} <= found
    assert _verb_of("rgbdnav.commands.batch") != _verb_of(_module_name(probe))


def _docstring_lines(path: Path) -> int:
    doc = ast.get_docstring(ast.parse(path.read_text(), filename=str(path)), clean=False)
    return 0 if doc is None else len(doc.strip("\n").splitlines())


def test_module_docstrings_say_what_and_why_in_at_most_25_lines() -> None:
    long = {
        str(path.relative_to(ROOT)): n
        for path in _modules("sensors", "slam", "nav", "rgbdnav", "bench")
        if (n := _docstring_lines(path)) > MAX_DOCSTRING_LINES
    }
    assert long == {}
