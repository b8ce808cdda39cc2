"""Suite-wide guard: no test writes into the user's home. `rgbdnav batch` (and
``rgbdnav.cache.recording_for``) renders a world file into a cache, by default
``~/.cache/rgbdnav/recordings``; for the whole session ``RGBDNAV_CACHE`` points into pytest's
temporary directory, and the CLIs that tests start as child processes inherit it."""

from __future__ import annotations

from collections.abc import Iterator

import pytest


@pytest.fixture(scope="session", autouse=True)
def _render_cache_in_a_temporary_dir(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("RGBDNAV_CACHE", str(tmp_path_factory.mktemp("rgbdnav-cache")))
        yield
