"""Suite-wide guard: no test writes into the user's home. `rgbdnav batch` (and
``rgbdnav.cache.recording_for``) renders a world file into a cache, by default
``~/.cache/rgbdnav/recordings``; for the whole session ``RGBDNAV_CACHE`` points into pytest's
temporary directory, and the CLIs that tests start as child processes inherit it."""

from __future__ import annotations

import functools
import os
import re
from collections.abc import Iterator
from pathlib import Path

import pytest


@pytest.fixture(scope="session", autouse=True)
def _render_cache_in_a_temporary_dir(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("RGBDNAV_CACHE", str(tmp_path_factory.mktemp("rgbdnav-cache")))
        yield


@pytest.fixture(scope="session")
def passes_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A folder both passes of `make test` see (RGBDNAV_TEST_PASSES_DIR: the Makefile makes
    and removes it): a module whose tests run in both passes builds its inputs there once,
    keyed by their parameters. Elsewhere, this session's own temporary folder."""
    env = os.environ.get("RGBDNAV_TEST_PASSES_DIR")
    return Path(env) if env else tmp_path_factory.mktemp("passes")


# `make test` runs the suite in two parts: `pytest -n 2 --dist loadfile -m "not realtime"` on two
# pytest-xdist workers, then `pytest -m realtime` alone (live runs against the wall clock get the
# machine to themselves). The unit xdist hands to a worker is a module, so a module-scoped
# fixture is built once; the modules that name one of the session fixtures below form one unit,
# so that run is made once, not once per worker. Units holding a `slow` test go first, so no long
# module is left for the end. (xdist's own `--dist loadgroup` renames node ids, which pytest 9.2
# no longer allows: the grouping is done here instead.)
SHARED_SESSION_FIXTURES = ("house_recording", "orebro_map", "live_recorded_run")


@functools.cache
def _units(root: Path) -> dict[str, str]:
    """Test module (node id) -> its unit: the modules naming a shared fixture, joined."""
    parent: dict[str, str] = {}

    def find(key: str) -> str:
        while parent.setdefault(key, key) != key:
            key = parent[key]
        return key

    pattern = re.compile(r"\b(" + "|".join(SHARED_SESSION_FIXTURES) + r")\b")
    for path in sorted((root / "tests").rglob("test_*.py")):
        module = path.relative_to(root).as_posix()
        for name in set(pattern.findall(path.read_text())):
            parent[find(module)] = find(name)
    units: dict[str, list[str]] = {}
    for module in parent:
        if module.endswith(".py"):
            units.setdefault(find(module), []).append(module)
    return {m: "+".join(sorted(ms)) for ms in units.values() for m in ms}


def _unit(config: pytest.Config, nodeid: str) -> str:
    module = nodeid.split("::", 1)[0]
    return _units(config.rootpath).get(module, module)


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config: pytest.Config, log: object) -> object:
    if config.getvalue("dist") != "loadfile":
        return None
    from xdist.scheduler import LoadFileScheduling

    class SharedFixtureScheduling(LoadFileScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return _unit(config, nodeid)

    return SharedFixtureScheduling(config, log)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if not hasattr(config, "workerinput"):  # not an xdist worker: the order is left alone
        return
    slow = {_unit(config, item.nodeid) for item in items if item.get_closest_marker("slow")}
    # Stable: the order inside a unit stays. Every worker computes the same order.
    items.sort(key=lambda item: _unit(config, item.nodeid) not in slow)
