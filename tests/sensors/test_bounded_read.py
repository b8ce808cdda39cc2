"""read_bounded reads what stat() saw, and still notices a file that grew past the limit."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from sensors.bounded_read import read_bounded
from sensors.types import RgbdNavError


class _Err(RgbdNavError):
    pass


def test_a_file_up_to_the_limit_is_read_whole_and_a_larger_one_is_refused(tmp_path: Path) -> None:
    f = tmp_path / "f.bin"
    f.write_bytes(bytes(range(256)) * 4)
    assert read_bounded(f, 1024, _Err) == bytes(range(256)) * 4
    with pytest.raises(_Err, match=r"f.bin: cannot read file \(1024 bytes, more than the 1023"):
        read_bounded(f, 1023, _Err)


def test_a_file_that_grew_after_stat_is_read_on_up_to_the_limit(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    f = tmp_path / "f.bin"
    f.write_bytes(b"x" * 1000)
    real_stat = Path.stat

    def stale_stat(self: Path, **kw: object) -> os.stat_result:  # as before 900 bytes were added
        st = real_stat(self, **kw)  # type: ignore[arg-type]
        if self == f:
            return os.stat_result((st.st_mode, *st[1:6], 100, *st[7:]))
        return st

    monkeypatch.setattr(Path, "stat", stale_stat)
    assert read_bounded(f, 1000, _Err) == b"x" * 1000  # all of it, not the 101 bytes first read
    with pytest.raises(_Err, match=r"more than 999 bytes"):
        read_bounded(f, 999, _Err)
