"""Write files and folders so that a failure never leaves anything half-written.

Temporary files and folders are named ``.<name>.<random>.partial[<suffix>]`` beside their
target; :func:`remove_stale_partials` clears those a killed process left behind. What is
published gets the permissions of a file or folder the user would create (0666 / 0777 less the
umask), not the 0600 / 0700 that :mod:`tempfile` gives.
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import tempfile
from pathlib import Path

# .<target name>.<mkstemp's 8 random characters>.partial, then any suffix (e.g. ".mp4")
_PARTIAL = re.compile(r"^\..+\.[A-Za-z0-9_]{8}\.partial(\.[A-Za-z0-9]+)?$")


def _umask() -> int:
    """The process's umask (read by setting it and putting it back)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _publish_mode(path: Path, base: int) -> None:
    os.chmod(path, base & ~_umask())


@contextlib.contextmanager
def atomic_file(path: Path, suffix: str = ""):
    """Yield a temporary path beside ``path`` (ending in ``.partial`` + ``suffix``, e.g. an
    extension a writer needs); rename it onto ``path``, readable as the umask allows, when the
    block succeeds."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".partial" + suffix, dir=path.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        _publish_mode(Path(tmp), 0o666)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def atomic_write_text(path: Path, text: str) -> None:
    with atomic_file(path) as tmp:
        tmp.write_text(text)


@contextlib.contextmanager
def atomic_dir(path: Path):
    """Yield a temporary folder beside ``path``; it replaces ``path`` (a folder, if there is
    one: NotADirectoryError for a file) when the block succeeds."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise NotADirectoryError(f"{path} is a file, not a folder")
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".partial", dir=path.parent))
    try:
        yield tmp
        _publish_mode(tmp, 0o777)
        if path.exists():
            shutil.rmtree(path)
        tmp.rename(path)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp)


def is_partial(name: str) -> bool:
    """Whether ``name`` is one of this module's temporary files or folders."""
    return _PARTIAL.match(name) is not None


def remove_stale_partials(folder: Path) -> list[Path]:
    """Delete the temporary files and folders of this module directly inside ``folder`` (left
    by a process killed mid-write; call it only where no other run writes at the same time).
    Returns what was removed."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    removed = []
    for entry in folder.iterdir():
        if not is_partial(entry.name):
            continue
        if entry.is_dir() and not entry.is_symlink():
            shutil.rmtree(entry, ignore_errors=True)
        else:
            entry.unlink(missing_ok=True)
        removed.append(entry)
    return removed
