"""Rendered recordings of shipped worlds live in a cache outside git, keyed by their inputs."""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import yaml

from rgbdnav.config import Config, config_to_dict

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
