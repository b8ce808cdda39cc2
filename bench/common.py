"""Shared by the benchmark scripts: results go into docs/benchmarks.md, one marked section each."""

from __future__ import annotations

import re
from pathlib import Path


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
