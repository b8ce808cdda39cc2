"""Shared by the benchmark scripts: results go into docs/benchmarks.md, one marked section each;
the rgbdnav they run is this tree's (``python -m rgbdnav.cli`` with the tree on the path)."""

from __future__ import annotations

import contextlib
import logging
import os
import re
import resource
import subprocess
import sys
import time
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path


@contextlib.contextmanager
def quiet_logger(name: str, level: int) -> Iterator[None]:
    """Raise logger ``name`` to ``level`` inside the block and put its level back after: a bench
    function a test calls in its own process must not change what later tests log."""
    logger = logging.getLogger(name)
    before = logger.level
    logger.setLevel(level)
    try:
        yield
    finally:
        logger.setLevel(before)


def write_section(out: Path, section: str, body: str) -> None:
    """Replace (or append) the block between ``<!-- section:start -->`` and ``:end -->``."""
    text = out.read_text() if out.exists() else "# rgbdnav benchmarks\n"
    start, end = f"<!-- {section}:start -->", f"<!-- {section}:end -->"
    block = f"{start}\n{body.rstrip()}\n{end}"
    if start in text:
        text = re.sub(re.escape(start) + ".*?" + re.escape(end), lambda _: block, text, flags=re.S)
    else:
        text = text.rstrip() + "\n\n" + block + "\n"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text)


def machine(*libraries: str) -> str:
    """CPU model, cores, Python and the versions of ``libraries`` (module names), for the report."""
    import importlib
    import os
    import platform

    cpu = "unknown CPU"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    parts = [cpu, f"{os.cpu_count()} cores", f"Python {platform.python_version()}"]
    for name in libraries:
        module = importlib.import_module(name)
        version = getattr(module, "__version__", None) or getattr(module, "VERSION", "?")
        parts.append(f"{name} {version}")
    return ", ".join(parts)


def publish(body: str, out: Path | None, section: str) -> None:
    """Print a benchmark's markdown and, with ``--out``, put it into that file's section."""
    print(body)
    if out:
        write_section(out, section, body)
        print(f"updated {out}")


REPO = Path(__file__).resolve().parents[1]
TREE_CLI = [sys.executable, "-m", "rgbdnav.cli"]  # this tree's rgbdnav, not an installed script


def tree_env() -> dict[str, str]:
    """The environment for a child running :data:`TREE_CLI`: this tree first on the path."""
    return {**os.environ, "PYTHONPATH": str(REPO)}


def run_cli(*args: str) -> tuple[float, float]:
    """Run ``rgbdnav ARGS -q`` from this tree in a child process (its output discarded); (wall
    [s], CPU user + system [s] of the child and its own children, the renderer's process too)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run([*TREE_CLI, *args, "-q"], check=True, env=tree_env(), stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def folder_mb(folder: Path) -> float:
    """The size of the files below ``folder`` [MiB]."""
    return sum(f.stat().st_size for f in folder.rglob("*") if f.is_file()) / 2**20


def figure_section(
    title: str,
    preamble: Sequence[str],
    rows: Iterable[tuple[str, str]],
    header: tuple[str, str] = ("figure", "value"),
) -> str:
    """A benchmark's markdown section: ``## title``, the preamble lines (date, machine, load,
    command), then a two-column table of (figure, value) rows."""
    table = [
        f"| {header[0]} | {header[1]} |",
        "| --- | --- |",
        *(f"| {k} | {v} |" for k, v in rows),
    ]
    return "\n".join([f"## {title}", "", *preamble, "", *table])
