"""Crash-safe file writes and checksums.

Every file of a session is written the same way: into a temporary file in the
*same* directory (so the final rename never crosses a file system), flushed and
fsync'ed, renamed over the target with :func:`os.replace` (atomic on POSIX),
and then the directory itself is fsync'ed so that the rename survives a power
cut. A reader therefore sees either the complete old file or the complete new
one, never a torn mix; an interrupted write leaves at most a stray temporary
file whose name starts with :data:`TEMP_PREFIX` (removed by
:func:`remove_stale_temps`).
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import secrets
from collections.abc import Iterator
from pathlib import Path

#: Temporary files are named ``.<target name>.tmp-<pid>-<random>`` next to the target.
TEMP_PREFIX = "."
TEMP_MARKER = ".tmp-"
_CHUNK = 1 << 20


def sha256_bytes(data: bytes) -> str:
    """Hex SHA-256 of ``data``."""
    return hashlib.sha256(data).hexdigest()


def sha256_file(path: str | os.PathLike[str]) -> str:
    """Hex SHA-256 of a file's content, read in 1 MiB chunks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(_CHUNK):
            h.update(chunk)
    return h.hexdigest()


def fsync_dir(path: str | os.PathLike[str]) -> None:
    """fsync a directory so that entries created or renamed in it are durable."""
    fd = os.open(os.fspath(path), os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _temp_path(target: Path) -> Path:
    return target.with_name(f"{TEMP_PREFIX}{target.name}{TEMP_MARKER}{os.getpid()}-{secrets.token_hex(4)}")


def is_temp_name(name: str) -> bool:
    """True for names made by this module's temporary files."""
    return name.startswith(TEMP_PREFIX) and TEMP_MARKER in name


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path to write ``path`` through, for writers that want a file name.

    On a normal exit of the ``with`` block the temporary file is fsync'ed,
    renamed over ``path`` and the directory fsync'ed. On any exception the
    temporary file is removed and ``path`` is left exactly as it was.

    Example::

        with atomic_path("hdr/a00_r.exr") as tmp:
            some_library.write(str(tmp))
    """
    target = Path(path)
    tmp = _temp_path(target)
    try:
        yield tmp
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    fsync_dir(target.parent)


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes) -> str:
    """Write ``data`` to ``path`` atomically; return its hex SHA-256."""
    with atomic_path(path) as tmp, open(tmp, "xb") as f:
        f.write(data)
        f.flush()
    return sha256_bytes(data)


def atomic_write_text(path: str | os.PathLike[str], text: str, encoding: str = "utf-8") -> str:
    """Write ``text`` to ``path`` atomically; return the hex SHA-256 of the encoded bytes."""
    return atomic_write_bytes(path, text.encode(encoding))


def remove_stale_temps(directory: str | os.PathLike[str]) -> list[Path]:
    """Delete temporary files left by interrupted atomic writes (recursively); return them."""
    removed: list[Path] = []
    for root, _dirs, files in os.walk(directory):
        for name in files:
            if is_temp_name(name):
                p = Path(root) / name
                with contextlib.suppress(FileNotFoundError):
                    p.unlink()
                    removed.append(p)
    return removed
