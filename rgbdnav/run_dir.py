"""The run-directory convention: every command that produces results writes here."""

from __future__ import annotations

import dataclasses
import json
import logging
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from rgbdnav.config import Config, write_config
from sensors.atomic import atomic_write_text

log = logging.getLogger(__name__)


def _jsonable(value: Any) -> Any:
    """Plain JSON data from summaries holding dataclasses, numpy values, paths and NaN."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        value = {f.name: getattr(value, f.name) for f in dataclasses.fields(value)}
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if hasattr(value, "item"):  # numpy scalar
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, Path):
        return str(value)
    return value


class RunDir:
    """``config.yaml`` (resolved config), ``summary.json``, ``trajectory.tum`` and pictures.

    ``summary.json`` is written last and marks a finished run. A run into a folder that holds
    an earlier one removes that summary first, so a re-run killed part-way leaves a folder
    without one (incomplete) rather than the old summary describing a mix of new and old files.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.path.mkdir(parents=True, exist_ok=True)
        stale = self.file("summary.json")
        if stale.is_file():
            log.info("%s: replacing the earlier run in this folder", self.path)
            stale.unlink()

    def file(self, name: str) -> Path:
        return self.path / name

    def write_config(self, cfg: Config) -> Path:
        write_config(cfg, self.file("config.yaml"))
        return self.file("config.yaml")

    def write_summary(self, summary: dict[str, Any]) -> Path:
        text = json.dumps(_jsonable(summary), indent=2) + "\n"
        atomic_write_text(self.file("summary.json"), text)
        return self.file("summary.json")
