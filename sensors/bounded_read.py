"""Reading a whole file that a user named, safely: only a regular file, and only up to a size.

``image: /dev/zero`` in a map.yaml, a FIFO or a multi-gigabyte file read with ``read_bytes()``
would block or exhaust memory; here each is one error of the caller's class.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

from sensors.types import RgbdNavError


def read_bounded(
    path: str | os.PathLike[str], max_bytes: int, error: type[RgbdNavError], what: str = "file"
) -> bytes:
    """The bytes of regular file ``path`` (at most ``max_bytes``); anything else, a missing
    file included, raises ``error("<path>: cannot read <what> (<why>)")``."""
    path = Path(path)
    try:
        st = path.stat()  # before open(): opening a FIFO blocks until a writer comes
        if not stat.S_ISREG(st.st_mode):
            raise error(f"{path}: cannot read {what} (not a regular file)")
        if st.st_size > max_bytes:
            raise error(
                f"{path}: cannot read {what} ({st.st_size} bytes, more than the "
                f"{max_bytes} allowed)"
            )
        with open(path, "rb") as f:
            # The size stat() saw, plus one byte to notice growth: read(max_bytes + 1) would
            # allocate max_bytes at once (0.55 instead of 0.1 ms for a 0.6 MB PNG). A file
            # that grew since is read on, up to the limit, as before.
            data = f.read(min(st.st_size, max_bytes) + 1)
            if len(data) > st.st_size:
                data += f.read(max_bytes + 1 - len(data))
    except OSError as err:
        raise error(f"{path}: cannot read {what} ({err.strerror or err})") from None
    if len(data) > max_bytes:  # it grew while we read it
        raise error(f"{path}: cannot read {what} (more than {max_bytes} bytes)")
    return data


__all__ = ["read_bounded"]
