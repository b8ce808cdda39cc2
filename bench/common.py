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
