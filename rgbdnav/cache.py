"""Rendered recordings of shipped worlds live in a cache outside git, keyed by their inputs."""

from __future__ import annotations

import hashlib
import logging
import os
from collections.abc import Callable
from contextlib import AbstractContextManager, nullcontext
from pathlib import Path

import yaml

from rgbdnav.config import Config, config_to_dict
from sensors.source import Source
from sensors.types import RgbdNavError

log = logging.getLogger(__name__)
ProgressBar = Callable[[str], AbstractContextManager[Callable[[int, int], None] | None]]

SIM_VERSION = "2"  # bump when the simulator's output changes for the same inputs


def cache_root() -> Path:
    env = os.environ.get("RGBDNAV_CACHE")
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "rgbdnav"


def recording_key(world_path: Path, cfg: Config, seed: int) -> str:
    """Hash of everything that determines a rendered recording."""
    parts = {
        "sim_version": SIM_VERSION,
        "world": world_path.read_text(),
        "seed": seed,
        "config": {k: v for k, v in config_to_dict(cfg).items() if k in ("robot", "camera", "sim")},
    }
    digest = hashlib.sha256(yaml.safe_dump(parts, sort_keys=True).encode()).hexdigest()
    return f"{world_path.stem}-seed{seed}-{digest[:12]}"


def cached_recording_path(world_path: Path, cfg: Config, seed: int) -> Path:
    return cache_root() / "recordings" / recording_key(world_path, cfg, seed)


def is_world(path: Path) -> bool:
    return path.is_file() and path.suffix in (".yaml", ".yml")


def recording_for(
    source: Path, cfg: Config, seed: int, progress_bar: ProgressBar | None = None
) -> Path:
    """A recording folder or log as given, or the cached rendering of a world file (made if
    missing); ``progress_bar(description)`` gives the rendering's progress callback."""
    from sensors.recording import Recording
    from sensors.sim.simulator import simulate
    from sensors.source import is_device_uri

    if not source.exists() and not is_device_uri(source):
        raise RgbdNavError(f"{source}: no such file or folder")
    if not is_world(source):
        return source
    cached = cached_recording_path(source, cfg, seed)
    if cached.exists():
        try:
            Recording.open(cached)
            log.info("using cached rendering %s", cached)
            return cached
        except RgbdNavError as err:
            log.warning("cached rendering is unreadable (%s); rendering again", err)
    log.info("rendering %s (seed %d) into %s", source, seed, cached)
    bar = progress_bar or (lambda _: nullcontext(None))
    with bar(f"rendering {source.stem}") as progress:
        simulate(source, cached, cfg.robot, cfg.camera, cfg.sim, seed=seed, progress=progress)
    return cached


def open_world_or_source(source: Path, cfg: Config, seed: int, render_ahead: bool = True) -> Source:
    """A world file as a source rendered on demand (no cache; see
    :mod:`sensors.sim.world_source`; its renderer process starting at once unless
    ``render_ahead`` is False: a caller that reads no frames starts none), any other path as
    :func:`sensors.source.open_source` opens it with ``cfg``'s options."""
    from rgbdnav.config import source_options
    from sensors.sim.world_source import open_world
    from sensors.source import open_source

    if is_world(source):
        return open_world(source, cfg.robot, cfg.camera, cfg.sim, seed, render_ahead=render_ahead)
    return open_source(source, source_options(cfg))
