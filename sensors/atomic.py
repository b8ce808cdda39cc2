"""Atomic writes: a reader sees the old file (or folder) or the new one, never half of either."""

from __future__ import annotations

import glob
import os
import shutil
import tempfile
from pathlib import Path


def current_umask() -> int:
    """The process's file-mode creation mask, read without changing it where Linux allows
    (``/proc/self/status``; setting and restoring it would race with other threads)."""
    try:
        with open("/proc/self/status", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes) -> None:
    """Write ``data`` to a temp file beside ``path``, fsync, then rename over ``path``.

    ``mkstemp`` creates the temp file 0600; it gets the mode ``open()`` would have given
    (0666 less the umask: 0644 by default) so a map or run folder is readable by other users
    and containers (a Nav2 map_server) as with any other tool."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        os.fchmod(fd, 0o666 & ~current_umask())
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_write_text(path: str | os.PathLike[str], text: str) -> None:
    atomic_write_bytes(path, text.encode("utf-8"))


STAGING_SUFFIX = ".partial"


def make_staging_dir(final: Path) -> Path:
    """A fresh hidden folder beside ``final`` (same file system, so the rename is atomic),
    named after the writing process (``.NAME.pidPID-XXXX.partial``) so that a later commit can
    tell a folder whose writer died (kill -9 mid-save) from one still being written.
    ``mkdtemp`` makes it 0700; it gets ``mkdir``'s mode (0777 less the umask: 0755 by default)
    since it becomes the final folder by a rename."""
    final.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(
        tempfile.mkdtemp(
            prefix=f".{final.name}.pid{os.getpid()}-", suffix=STAGING_SUFFIX, dir=final.parent
        )
    )
    staging.chmod(0o777 & ~current_umask())
    return staging


def _process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # exists, owned by someone else
        return True
    return True


def abandoned_staging_dirs(final: Path) -> list[Path]:
    """Staging folders of ``final`` whose writing process is gone (a save killed before its
    rename): never renamed into place, so nothing reads them."""
    out = []
    prefix = f".{final.name}.pid"
    for p in final.parent.glob(f"{glob.escape(prefix)}*-*{STAGING_SUFFIX}"):
        pid = p.name.removeprefix(prefix).split("-", 1)[0]
        if not (p.is_dir() and pid.isdigit()) or int(pid) == os.getpid():
            continue
        if not _process_alive(int(pid)):
            out.append(p)
    return out


def interrupted_replacement(final: Path) -> Path | None:
    """The previous ``final`` that :func:`commit_staging_dir` had moved aside when the process
    died between its two renames (``final`` is then missing; kill -9 during a checkpoint), or
    None. The newest such folder when there are several."""
    if final.exists():
        return None
    aside = [p for p in final.parent.glob(f".{final.name}.old-*") if p.is_dir()]
    return max(aside, key=lambda p: p.stat().st_mtime) if aside else None


def commit_staging_dir(staging: Path, final: Path) -> None:
    """Replace ``final`` by ``staging``. An existing ``final`` is moved aside first and removed
    only after the new folder is in place, so a crash leaves either the old or the new one (the
    old one under its moved-aside name: :func:`interrupted_replacement` finds it). Folders an
    earlier, interrupted commit left aside are removed once the new one is in place, and so
    are staging folders of writers that died before their commit."""
    for root, _dirs, files in os.walk(staging):
        for name in files:
            with open(os.path.join(root, name), "rb") as fh:
                os.fsync(fh.fileno())
    if final.exists():
        old = final.with_name(f".{final.name}.old-{os.getpid()}")
        if old.exists():
            shutil.rmtree(old)
        os.replace(final, old)
        os.replace(staging, final)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.replace(staging, final)
    for stale in [*final.parent.glob(f".{final.name}.old-*"), *abandoned_staging_dirs(final)]:
        shutil.rmtree(stale, ignore_errors=True)
