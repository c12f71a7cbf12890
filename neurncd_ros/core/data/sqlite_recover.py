"""Recover a damaged rosbag2 SQLite recording: copy the messages that can still be read.

An interrupted copy or a full disk leaves a ``.db3`` file shorter than its header says,
and SQLite (rosbags with it) then refuses the whole file as malformed; a recorder killed
mid-write (rosbag2's default preset writes with ``synchronous=OFF``) can leave pages torn
in the middle. :func:`recover_sqlite` reads what is left into a new ``.db3`` file that
rosbags and ``neurncd`` read on its own (no ``metadata.yaml`` needed): the tables
rosbag2 writes (``schema``, ``topics``, ``message_definitions``, ``messages``) with their
own ``CREATE`` statements, and every message row that SQLite can still return, in id
order. What sqlite3's ``.recover`` does for any database, with the Python standard library
alone and for the tables a bag has.
"""

from __future__ import annotations

import os
import shutil
import sqlite3
import struct
import tempfile
from pathlib import Path

from .bag import BagError, _storage_files
from .mcap_recover import recording_file

_SQLITE_MAGIC = b"SQLite format 3\x00"
# The small tables copied whole; ``metadata`` (rosbag2's summary of the whole recording,
# written when it closes) is left out: it would count messages the copy no longer has.
_TABLES = ("schema", "topics", "message_definitions")
_BATCH = 256
_PROBE_LIMIT = 1 << 40  # ids probed at most this far past a damaged range


def is_sqlite(src: str | Path) -> bool:
    """Whether ``src`` (a file, or a bag folder) holds an SQLite recording: the file
    starts with SQLite's header, or the folder's storage files are .db3 ones."""
    src = Path(src)
    if src.is_dir():
        files = _storage_files(src)
        return bool(files) and all(f.endswith(".db3") for f in files)
    try:
        with src.open("rb") as f:
            head = f.read(16)
    except OSError:
        head = b""
    if head == _SQLITE_MAGIC or head.startswith(b"\x89MCAP"):
        return head == _SQLITE_MAGIC
    return src.suffix.lower() == ".db3"  # neither: the name says which it was meant to be


def _source(src: Path, out: Path) -> Path:
    """The .db3 file of ``src`` (the file, or a bag folder holding one), checked to be
    SQLite and not to be ``out`` (:func:`.mcap_recover.recording_file`)."""
    src = recording_file(src, out, ".db3")
    with src.open("rb") as f:
        if f.read(16) != _SQLITE_MAGIC:
            raise BagError(f"{src}: not an SQLite file (no SQLite header)")
    return src


def _page_size(header: bytes) -> int:
    """The page size a database header gives (1 stands for 65536)."""
    (size,) = struct.unpack(">H", header[16:18])
    return 65536 if size == 1 else size


def _intact(src: Path) -> bool:
    """Whether the file opens and SQLite's own quick check finds nothing wrong with it
    (then there is nothing to recover)."""
    try:
        con = sqlite3.connect(f"file:{src}?mode=ro", uri=True)
    except sqlite3.Error:
        return False
    try:
        return con.execute("PRAGMA quick_check").fetchone()[0] == "ok"
    except sqlite3.Error:
        return False
    finally:
        con.close()


def _stage_copy(src: Path, stage: Path) -> tuple[Path, int]:
    """Copy the file's whole pages (and any -wal or -journal beside it, which SQLite
    replays or rolls back when the copy opens) into ``stage``, with the header's page
    count set to the pages copied: SQLite refuses a file shorter than its header says
    even where the pages a query needs are all there. Returns the copy and its pages."""
    with src.open("rb") as f:
        header = f.read(100)
        if len(header) < 100:
            raise BagError(f"{src}: cut off within its SQLite header: nothing to recover")
        page = _page_size(header)
        pages = src.stat().st_size // page
        if pages < 2:
            raise BagError(f"{src}: cut off within its first page: nothing to recover")
        copy = stage / "recording.db3"
        with copy.open("wb") as out:
            f.seek(0)
            left = pages * page
            while left:
                block = f.read(min(left, 1 << 24))
                if not block:
                    break
                out.write(block)
                left -= len(block)
            out.seek(28)
            out.write(struct.pack(">I", pages))
    for side in ("-wal", "-journal"):
        beside = src.with_name(src.name + side)
        if beside.is_file():
            shutil.copyfile(beside, copy.with_name(copy.name + side))
    return copy, pages


def _rows(con: sqlite3.Connection, counts: dict[str, int]):
    """Every message row SQLite still returns, in id order (ids from 1, as rosbag2
    numbers them). Rows are read in batches; a batch that meets a damaged page (lost or
    torn) is read again in halves down to single rows, so every row before the damage
    is kept; the damaged range is then skipped by probing ids past it, first one by
    one, then at doubling steps narrowed back by bisection to the first id that reads."""
    query = ("SELECT id, topic_id, timestamp, data FROM messages NOT INDEXED "
             "WHERE id > ? ORDER BY id LIMIT ?")
    one = "SELECT id, topic_id, timestamp, data FROM messages NOT INDEXED WHERE id = ?"

    def read(i: int):
        try:
            return con.execute(one, (i,)).fetchone(), True
        except sqlite3.DatabaseError:
            return None, False

    last, size = 0, _BATCH  # rosbag2 numbers its messages from 1
    while True:
        try:
            batch = con.execute(query, (last, size)).fetchall()
        except sqlite3.DatabaseError:
            batch = None
        if batch is not None:
            if not batch:
                return
            yield from batch
            last, size = batch[-1][0], _BATCH
            continue
        if size > 1:  # the damage lies within the batch: read up to it in smaller ones
            size //= 2
            continue
        # The row after ``last`` is on a damaged page: find the next id that reads.
        nxt = None
        for i in range(last + 1, last + 65):
            row, ok = read(i)
            if ok and row is not None:
                nxt = row
                break
        if nxt is None:
            lo, step = last + 64, 128
            while step <= _PROBE_LIMIT:
                row, ok = read(lo + step)
                if ok and row is not None:
                    hi = lo + step  # reads; bisect (lo, hi] for the first id that reads
                    while hi - lo > 1:
                        mid = (lo + hi) // 2
                        r, k = read(mid)
                        if k and r is not None:
                            hi, row = mid, r
                        else:
                            lo = mid
                    nxt = row
                    break
                step *= 2
        if nxt is None:  # nothing reads after it: the file was cut there
            counts["cut_after_id"] = last
            return
        counts["damaged_ranges"] += 1
        yield nxt
        last = nxt[0]


def recover_sqlite(src: str | Path, out: str | Path) -> dict[str, int]:
    """Copy the messages of a damaged rosbag2 ``.db3`` recording that can still be read
    into a new ``.db3`` file ``out``, which reads on its own (rosbags, ``neurncd info``).

    The recording is not touched: its whole pages (and any ``-wal`` or ``-journal``
    beside it) are copied into a staging folder beside ``out`` with the header's page
    count set to what is there, so SQLite opens the part that was written; the bag's
    tables are made anew from their own ``CREATE`` statements; ``schema``, ``topics`` and
    ``message_definitions`` are copied whole, and the messages row by row in id order,
    past any damaged range (:func:`_rows`); messages of a topic no longer listed are
    dropped. The staging copy needs as much free space as the recording, next to the
    output. ``src``: the .db3 file, or a bag folder holding one. Returns the counts:
    ``messages`` kept, ``dropped`` (no topic), ``damaged_ranges`` skipped (rows read
    after them), ``cut_after_id`` (the last id read before damage nothing reads past;
    0 when the scan reached the end), ``pages`` copied. Raises :class:`BagError` for a
    file that is no SQLite, is intact (nothing to recover), or keeps no topic or no
    message.
    """
    out = Path(out)
    src = _source(Path(src), out)
    if out.suffix.lower() != ".db3":
        raise BagError(f"{out}: the recovered copy of an SQLite recording is a .db3 file: "
                       f"name it {out.stem}.db3")
    if _intact(src):
        raise BagError(f"{src}: SQLite finds nothing wrong with it: nothing to recover "
                       "(neurncd info reads it as it is)")
    out.parent.mkdir(parents=True, exist_ok=True)
    counts = {"messages": 0, "dropped": 0, "damaged_ranges": 0, "cut_after_id": 0,
              "pages": 0}
    stage = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        copy, counts["pages"] = _stage_copy(src, stage)
        con = sqlite3.connect(copy)
        try:
            master = con.execute("SELECT type, name, tbl_name, sql FROM sqlite_master"
                                 ).fetchall()
        except sqlite3.DatabaseError as err:
            con.close()
            raise BagError(f"{src}: its table list cannot be read ({err}): nothing to "
                           "recover") from None
        sql = {name: text for kind, name, _, text in master if kind == "table" and text}
        if "messages" not in sql or "topics" not in sql:
            con.close()
            raise BagError(f"{src}: no rosbag2 tables (messages, topics) in it")
        fresh = stage / out.name
        new = sqlite3.connect(fresh)
        try:
            for name in (*(t for t in _TABLES if t in sql), "messages"):
                new.execute(sql[name])
            topics = set()
            for name in (t for t in _TABLES if t in sql):
                try:
                    rows = con.execute(f"SELECT * FROM {name}").fetchall()  # noqa: S608
                except sqlite3.DatabaseError as err:
                    if name == "topics":
                        raise BagError(f"{src}: its topics cannot be read ({err}): nothing "
                                       "to recover") from None
                    continue  # schema / definitions: rosbags reads a bag without them
                if rows:
                    marks = ", ".join("?" * len(rows[0]))
                    new.executemany(f"INSERT INTO {name} VALUES ({marks})", rows)  # noqa: S608
                if name == "topics":
                    topics = {r[0] for r in rows}
            batch = []
            for row in _rows(con, counts):
                if row[1] not in topics:
                    counts["dropped"] += 1
                    continue
                batch.append(row)
                if len(batch) >= _BATCH:
                    new.executemany("INSERT INTO messages (id, topic_id, timestamp, data) "
                                    "VALUES (?, ?, ?, ?)", batch)
                    counts["messages"] += len(batch)
                    batch = []
            if batch:
                new.executemany("INSERT INTO messages (id, topic_id, timestamp, data) "
                                "VALUES (?, ?, ?, ?)", batch)
                counts["messages"] += len(batch)
            if not counts["messages"]:
                raise BagError(f"{src}: no message could be read: nothing to recover")
            kept = {*(t for t in _TABLES if t in sql), "messages"}
            for kind, _, table, text in master:
                if kind == "index" and text and table in kept:  # after the rows: faster
                    new.execute(text)
            new.commit()
        finally:
            new.close()
            con.close()
        os.replace(fresh, out)
    finally:
        shutil.rmtree(stage, ignore_errors=True)
    return counts
