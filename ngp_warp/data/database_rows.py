"""Rows of a COLMAP database that pycolmap is writing, counted from a child process (the
progress of ``process``'s feature and matching stages).

pycolmap keeps its database in SQLite's WAL mode, whose index file (``database.db-shm``) every
reader maps into memory. A second SQLite library inside pycolmap's own process shares that
process's POSIX locks, so when its connection closes it can take itself for the last one and
reset the index under pycolmap's mapping: the process dies of SIGBUS. A child process holds
locks of its own and reads beside pycolmap as SQLite intends.
"""

from __future__ import annotations

import subprocess
import sys
import threading
from pathlib import Path

POLL_SECONDS = 0.25

_CHILD = f"""
import contextlib, sqlite3, sys, time
uri, table = "file:" + sys.argv[1] + "?mode=ro", sys.argv[2]
while True:
    try:
        with contextlib.closing(sqlite3.connect(uri, uri=True, timeout=0.05)) as db:
            print(db.execute("SELECT COUNT(*) FROM " + table).fetchone()[0], flush=True)
    except sqlite3.Error:
        pass
    time.sleep({POLL_SECONDS})
"""


class DatabaseRows:
    """``rows()``: the latest count of ``table``'s rows in ``database`` (None until one is read),
    polled by a child process every :data:`POLL_SECONDS`; a context manager that ends the child."""

    def __init__(self, database: Path, table: str):
        self._latest: int | None = None
        self._child = subprocess.Popen([sys.executable, "-c", _CHILD, str(database), table],
                                       stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                       stderr=subprocess.DEVNULL, text=True)
        threading.Thread(target=self._read, name=f"rows of {table}", daemon=True).start()

    def _read(self) -> None:
        for line in self._child.stdout:
            self._latest = int(line)

    def rows(self) -> int | None:
        return self._latest

    def __enter__(self) -> DatabaseRows:
        return self

    def __exit__(self, *exc) -> None:
        self._child.kill()
        self._child.wait()
        self._child.stdout.close()
