"""Rows of a database in WAL mode counted from a child process while this process writes."""

import contextlib
import sqlite3
import time

from ngp_warp.data.database_rows import DatabaseRows


def _wait_for(counter, value, seconds=20.0):
    end = time.monotonic() + seconds
    while counter.rows() != value and time.monotonic() < end:
        time.sleep(0.05)
    return counter.rows()


def test_counts_rows_written_while_it_runs_and_ends_its_child(tmp_path):
    database = tmp_path / "database.db"
    with contextlib.closing(sqlite3.connect(database)) as db:
        db.execute("PRAGMA journal_mode=WAL")
        db.execute("CREATE TABLE keypoints (image_id INTEGER)")
        db.commit()
        with DatabaseRows(database, "keypoints") as counter:
            assert _wait_for(counter, 0) == 0
            db.executemany("INSERT INTO keypoints VALUES (?)", [(i,) for i in range(7)])
            db.commit()
            assert _wait_for(counter, 7) == 7
            child = counter._child
        assert child.poll() is not None


def test_a_missing_database_counts_nothing(tmp_path):
    with DatabaseRows(tmp_path / "none.db", "keypoints") as counter:
        time.sleep(0.6)
        assert counter.rows() is None
    assert not (tmp_path / "none.db").exists()
