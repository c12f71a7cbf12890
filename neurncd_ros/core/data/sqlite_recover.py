"""Recover a damaged rosbag2 SQLite recording: copy the messages that can still be read.

An interrupted copy or a full disk leaves a ``.db3`` file shorter than its header says,
and SQLite (rosbags with it) then refuses the whole file as malformed; a recorder killed
mid-write (rosbag2's default preset writes with ``synchronous=OFF``) can leave pages torn
in the middle. :func:`recover_sqlite` reads what is left into a new ``.db3`` file that
rosbags and ``neurncd`` read on its own (no ``metadata.yaml`` needed): the tables
rosbag2 writes (``schema``, ``topics``, ``message_definitions``, ``messages``, and
``metadata`` kept empty) with their own ``CREATE`` statements, the small ones copied
through SQLite, and the messages by reading
every page of the file for message rows (:func:`_message_rows`), as sqlite3's
``.recover`` does: a lost or torn page costs the rows on it, not the rows the B-tree
reaches through it. The SQLite file format: https://www.sqlite.org/fileformat2.html.
"""

from __future__ import annotations

import os
import shutil
import sqlite3
import struct
import tempfile
from pathlib import Path

from .bag import BagError, _storage_files, recording_file

_SQLITE_MAGIC = b"SQLite format 3\x00"
# The small tables copied whole. ``metadata`` (rosbag2's summary of the whole recording,
# written when it closes) is made but left empty: rosbag2 (schema 3 on) queries the table
# when it opens a file, and takes the files of the bag from its row (the recording's
# names, several for a split bag) when there is no metadata.yaml; with no row it takes
# the copy's own path (it counts the messages, start and duration itself either way).
_TABLES = ("schema", "topics", "message_definitions")
_EMPTY_TABLES = ("metadata",)
_BATCH_BYTES = 32 << 20  # message rows held at most before they are written
_TABLE_LEAF = 0x0D


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
    SQLite and not to be ``out`` (:func:`.bag.recording_file`)."""
    src = recording_file(src, out, ".db3")
    with src.open("rb") as f:
        if f.read(16) != _SQLITE_MAGIC:
            raise BagError(f"{src}: not an SQLite file (no SQLite header)")
    return src


def _page_size(src: Path, header: bytes) -> int:
    """The page size a database header gives (1 stands for 65536): a power of two from
    512 to 65536, or the header is damaged."""
    (size,) = struct.unpack(">H", header[16:18])
    size = 65536 if size == 1 else size
    if size < 512 or size & (size - 1):
        raise BagError(f"{src}: its SQLite header is damaged (page size {size}): nothing "
                       "to recover")
    return size


def _intact(src: Path) -> bool:
    """Whether the file opens and SQLite's own quick check finds nothing wrong with it
    (then there is nothing to recover). A ``-wal`` or ``-journal`` beside it means the
    writer never closed it: not intact, and not opened (a read-only open of a WAL file
    would create its ``-shm`` beside the recording)."""
    if any(src.with_name(src.name + side).exists() for side in ("-wal", "-journal")):
        return False
    try:
        con = sqlite3.connect(src.resolve().as_uri() + "?mode=ro&immutable=1", uri=True)
    except sqlite3.Error:
        return False
    try:
        return con.execute("PRAGMA quick_check").fetchone()[0] == "ok"
    except sqlite3.Error:
        return False
    finally:
        con.close()


def _stage_copy(src: Path, stage: Path) -> tuple[Path, int, int, int]:
    """Copy the file's whole pages into ``stage``, with the committed frames of a -wal
    beside it written in (:func:`_apply_wal`; the copy then ends where the log's last
    commit says the database does) and a -journal beside it copied (SQLite rolls it back
    when the copy opens), and the header's page count set to the pages there: SQLite
    refuses a file shorter than its header says even where the pages a query needs are
    all there. Returns the copy, its page size, the usable bytes of a page (less the
    reserved bytes the header names) and its pages."""
    with src.open("rb") as f:
        header = f.read(100)
        if len(header) < 100:
            raise BagError(f"{src}: cut off within its SQLite header: nothing to recover")
        page = _page_size(src, header)
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
    journal = src.with_name(src.name + "-journal")
    if journal.is_file():  # SQLite rolls a hot journal back when the copy opens
        shutil.copyfile(journal, copy.with_name(copy.name + "-journal"))
    wal = src.with_name(src.name + "-wal")
    size = _apply_wal(wal, copy, page) if wal.is_file() else 0
    with copy.open("r+b") as out:
        if size and size * page < out.seek(0, os.SEEK_END):
            out.truncate(size * page)  # pages past the log's end: freed, not data
        pages = out.seek(0, os.SEEK_END) // page
        out.seek(28)  # after the log, whose page 1 may say otherwise
        out.write(struct.pack(">I", pages))
    return copy, page, page - header[20], pages


def _wal_checksum(data: bytes, s0: int, s1: int, big: bool) -> tuple[int, int]:
    """The write-ahead log's running checksum over ``data`` (pairs of 32-bit words, in
    the byte order its magic names), continued from (s0, s1)."""
    words = struct.unpack(f"{'>' if big else '<'}{len(data) // 4}I", data)
    for i in range(0, len(words), 2):
        s0 = (s0 + words[i] + s1) & 0xFFFFFFFF
        s1 = (s1 + words[i + 1] + s0) & 0xFFFFFFFF
    return s0, s1


def _apply_wal(wal: Path, copy: Path, page: int) -> int:
    """Write the committed transactions of a write-ahead log into the staged copy, as a
    checkpoint would (SQLite itself refuses to checkpoint into a damaged file): frames
    whose salts and running checksum hold, up to the last commit frame; a torn or
    uncommitted tail is left out. Returns the database's size in pages after the last
    commit (0: no commit in the log)."""
    with wal.open("rb") as f:
        head = f.read(32)
        if len(head) < 32:
            return 0
        magic, _, wal_page, _, salt1, salt2, c0, c1 = struct.unpack(">8I", head)
        big = magic == 0x377F0683
        if magic not in (0x377F0682, 0x377F0683) or wal_page not in (page, page % 65536):
            return 0
        sums = _wal_checksum(head[:24], 0, 0, big)
        if sums != (c0, c1):
            return 0
        pending: list[tuple[int, bytes]] = []
        size = 0
        with copy.open("r+b") as out:
            while True:
                frame = f.read(24 + page)
                if len(frame) < 24 + page:
                    break
                number, commit, s1_, s2_, f0, f1 = struct.unpack(">6I", frame[:24])
                if (s1_, s2_) != (salt1, salt2):
                    break
                sums = _wal_checksum(frame[:8] + frame[24:], *sums, big)
                if sums != (f0, f1):
                    break
                pending.append((number, frame[24:]))
                if commit:  # a transaction's last frame: it is in
                    for n, data in pending:
                        out.seek((n - 1) * page)
                        out.write(data)
                    size, pending = commit, []
    return size


def _varint(buf: bytes, pos: int) -> tuple[int, int]:
    """SQLite's variable-length integer at ``pos``: its value and the position after it."""
    value = 0
    for k in range(8):
        b = buf[pos + k]
        value = (value << 7) | (b & 0x7F)
        if b < 0x80:
            return value, pos + k + 1
    return (value << 8) | buf[pos + 8], pos + 9


_INT_BYTES = {1: 1, 2: 2, 3: 3, 4: 4, 5: 6, 6: 8}


def _message_types(payload: bytes) -> tuple[list[int], int] | None:
    """The serial types of a record whose shape is a ``messages`` row (id as the rowid,
    so NULL; topic_id and timestamp integers; data a blob) and where its body starts;
    None for another shape (another table's row, or garbage). The header is at the
    record's start, so the part of a payload on its leaf page is enough."""
    size, pos = _varint(payload, 0)
    types = []
    while pos < size and len(types) < 5:
        t, pos = _varint(payload, pos)
        types.append(t)
    if len(types) != 4 or types[0] != 0 or types[3] < 12 or types[3] % 2 or \
            not all(t in _INT_BYTES or t in (8, 9) for t in types[1:3]):
        return None
    return types, size


def _message(payload: bytes) -> tuple[int, int, bytes] | None:
    """A ``messages`` record as (topic_id, timestamp, data); None for another shape."""
    shape = _message_types(payload)
    if shape is None:
        return None
    types, at = shape
    values = []
    for t in types[1:3]:
        if t in (8, 9):
            values.append(t - 8)
        elif t in _INT_BYTES:
            n = _INT_BYTES[t]
            values.append(int.from_bytes(payload[at:at + n], "big", signed=True))
            at += n
    blob = payload[at:at + (types[3] - 12) // 2]
    if len(blob) != (types[3] - 12) // 2 or at + len(blob) != len(payload):
        return None
    return values[0], values[1], blob


def _freelist(path: Path, page: int, pages: int) -> set[int]:
    """The pages on the database's freelist (header offset 32: the first trunk page; each
    trunk names the next trunk, then its leaf pages), as far as it can be read."""
    free: set[int] = set()
    with path.open("rb") as f:
        f.seek(32)
        trunk = int.from_bytes(f.read(4), "big")
        while 1 < trunk <= pages and trunk not in free:
            free.add(trunk)
            f.seek((trunk - 1) * page)
            data = f.read(page)
            count = int.from_bytes(data[4:8], "big")
            if count > (page - 8) // 4:
                break  # a damaged trunk
            free.update(int.from_bytes(data[8 + 4 * i:12 + 4 * i], "big")
                        for i in range(count))
            trunk = int.from_bytes(data[:4], "big")
    return free


def _message_rows(path: Path, page: int, usable: int, counts: dict[str, int]):
    """(id, topic_id, timestamp, data) of every ``messages`` row on the file's table-leaf
    pages, in page order. Each leaf page is read on its own: a page lost or torn costs
    its rows (counted in ``counts["unreadable"]`` where a row's overflow chain is
    broken), not the rows after it. A payload too long for its page continues on a
    chain of overflow pages, each naming the next. Pages on the freelist are skipped
    (:func:`_freelist`): they can hold rows deleted or rewritten since (rosbag2 does
    neither, but a file may have been edited); a copy of a row left on a live page by a
    rebalance has the same id and bytes, and the caller keeps one."""
    pages = path.stat().st_size // page
    largest = pages * usable  # no payload is longer than the file
    free = _freelist(path, page, pages)
    max_local = usable - 35
    min_local = (usable - 12) * 32 // 255 - 23
    with path.open("rb") as f:
        def read_page(n: int) -> bytes:
            f.seek((n - 1) * page)
            return f.read(page)

        for number in range(1, pages + 1):
            if number in free:  # freed pages keep rows deleted or since rewritten
                continue
            data = read_page(number)
            base = 100 if number == 1 else 0
            if len(data) < page or data[base] != _TABLE_LEAF:
                continue
            cells = int.from_bytes(data[base + 3:base + 5], "big")
            if base + 8 + 2 * cells > page:
                continue
            for c in range(cells):
                off = int.from_bytes(data[base + 8 + 2 * c:base + 10 + 2 * c], "big")
                try:
                    size, pos = _varint(data, off)
                    rowid, pos = _varint(data, pos)
                    if size > largest:  # garbage where a cell should be
                        continue
                    if size <= max_local:
                        local, overflow = size, 0
                    else:
                        k = min_local + (size - min_local) % (usable - 4)
                        local = k if k <= max_local else min_local
                        overflow = int.from_bytes(data[pos + local:pos + local + 4], "big")
                    payload = bytearray(data[pos:pos + local])
                    if len(payload) != local:
                        continue
                    seen = 0
                    while len(payload) < size:  # the chain of overflow pages
                        if not 1 < overflow <= pages or seen > pages:
                            break
                        more = read_page(overflow)
                        overflow = int.from_bytes(more[:4], "big")
                        payload += more[4:usable][: size - len(payload)]
                        seen += 1
                    if len(payload) != size:
                        if _message_types(bytes(payload)) is not None:
                            counts["unreadable"] += 1  # a message whose data is lost
                        continue
                    row = _message(bytes(payload))
                except IndexError:  # a torn cell runs off its page
                    continue
                if row is not None:
                    yield (rowid - (1 << 64) if rowid >= 1 << 63 else rowid, *row)


def _read_tables(copy: Path, src: Path) -> tuple[list, dict[str, list]]:
    """The staged copy's table list and its small tables' rows (``_TABLES``), read through
    SQLite (which rolls back a hot journal first)."""
    con = sqlite3.connect(copy)
    try:
        try:
            master = con.execute("SELECT type, name, tbl_name, sql FROM sqlite_master"
                                 ).fetchall()
        except sqlite3.DatabaseError as err:
            raise BagError(f"{src}: its table list cannot be read ({err}): nothing to "
                           "recover") from None
        names = {name for kind, name, _, _ in master if kind == "table"}
        if not {"messages", "topics"} <= names:
            raise BagError(f"{src}: no rosbag2 tables (messages, topics) in it")
        rows: dict[str, list] = {}
        for name in (t for t in _TABLES if t in names):
            try:
                rows[name] = con.execute(f"SELECT * FROM {name}").fetchall()  # noqa: S608
            except sqlite3.DatabaseError as err:
                if name == "topics":
                    raise BagError(f"{src}: its topics cannot be read ({err}): nothing to "
                                   "recover") from None
                # schema / definitions: left out, made empty (_write)
        return master, rows
    finally:
        con.close()


def recover_sqlite(src: str | Path, out: str | Path) -> dict[str, int]:
    """Copy the messages of a damaged rosbag2 ``.db3`` recording that can still be read
    into a new ``.db3`` file ``out``, which reads on its own (rosbags, ``neurncd info``).

    The recording is not touched: its whole pages are copied into a staging folder beside
    ``out`` with the header's page count set to what is there, so SQLite opens the part
    that was written; a ``-journal`` beside it is copied too (SQLite rolls it back), and
    the committed frames of a ``-wal`` are written into the copy (:func:`_apply_wal`).
    The bag's tables are made anew from their own ``CREATE`` statements; ``schema``,
    ``topics`` and ``message_definitions`` are copied whole through SQLite (the
    definitions made empty when their rows are lost), ``metadata`` is left empty
    (rosbag2 then names the copy's own file, not the recording's), and the
    messages are read off every table-leaf page of the copy (:func:`_message_rows`), so
    a lost or torn page costs only its own rows. Messages of a topic no longer listed
    are dropped. The staging copy needs as much free space as the recording, next to
    the output; message rows are written out every 32 MB. ``src``:
    the .db3 file, or a bag folder holding one. Returns the counts: ``messages`` kept,
    ``first_id`` and ``last_id`` of them, ``missing`` (ids between those two not kept:
    rosbag2 numbers its messages one by one), ``dropped`` (no topic), ``unreadable``
    (rows whose overflow pages are lost), ``pages`` copied. Raises :class:`BagError` for
    a file that is no SQLite, is intact (nothing to recover), keeps no topic or no
    message, or cannot be written (disk full).
    """
    out = Path(out)
    src = _source(Path(src), out)
    if out.suffix.lower() != ".db3":
        raise BagError(f"{out}: the recovered copy of an SQLite recording is a .db3 file: "
                       f"name it {out.stem}.db3")
    if out.is_dir():
        raise BagError(f"{out}: is a folder; the recovered copy is one .db3 file (name "
                       "another, or remove the folder)")
    if _intact(src):
        raise BagError(f"{src}: SQLite finds nothing wrong with it: nothing to recover "
                       "(neurncd info reads it as it is)")
    made = [p for p in (out.parent, *out.parent.parents) if not p.exists()]
    counts = {"messages": 0, "first_id": 0, "last_id": 0, "missing": 0, "dropped": 0,
              "unreadable": 0, "pages": 0}
    stage = None
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        stage = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
        copy, page, usable, counts["pages"] = _stage_copy(src, stage)
        master, small = _read_tables(copy, src)
        _write(stage / out.name, master, small, _message_rows(copy, page, usable, counts),
               counts, src)
        os.replace(stage / out.name, out)
    except BaseException as err:
        if stage is not None:
            shutil.rmtree(stage, ignore_errors=True)
        for p in made:  # the folders this call made for the output, now empty
            try:
                p.rmdir()
            except OSError:
                break
        if isinstance(err, (OSError, sqlite3.Error)):  # a full disk, say
            raise BagError(f"{out}: cannot write the recovered copy ({err})") from None
        raise
    shutil.rmtree(stage, ignore_errors=True)
    return counts


def _write(fresh: Path, master: list, small: dict[str, list], messages, counts: dict,
           src: Path) -> None:
    """The new database: the small tables' rows, every message row of a listed topic
    (one of each id), the indexes after the rows (faster), and the counts filled in."""
    sql = {name: text for kind, name, _, text in master if kind == "table" and text}
    # message_definitions made empty when its rows are lost: rosbags and rosbag2 query it
    # on every schema-4 file (an unreadable schema table stays out: both readers then take
    # the file for an old one, where an empty one would break rosbag2)
    empty = [name for name in (*_EMPTY_TABLES, "message_definitions")
             if name in sql and name not in small]
    new = sqlite3.connect(fresh)
    try:
        for name in (*small, *empty, "messages"):
            new.execute(sql[name])
        for name, rows in small.items():
            if rows:
                marks = ", ".join("?" * len(rows[0]))
                new.executemany(f"INSERT INTO {name} VALUES ({marks})", rows)  # noqa: S608
        topics = {r[0] for r in small.get("topics", [])}
        insert = "INSERT OR IGNORE INTO messages (id, topic_id, timestamp, data) " \
                 "VALUES (?, ?, ?, ?)"
        batch, held = [], 0
        for row in messages:
            if row[1] not in topics:
                counts["dropped"] += 1
                continue
            batch.append(row)
            held += len(row[3])
            if held >= _BATCH_BYTES:
                new.executemany(insert, batch)
                batch, held = [], 0
        new.executemany(insert, batch)
        n, first, last = new.execute("SELECT count(*), min(id), max(id) FROM messages"
                                     ).fetchone()
        if not n:
            raise BagError(f"{src}: no message could be read: nothing to recover")
        counts.update(messages=n, first_id=first, last_id=last,
                      missing=last - first + 1 - n)
        kept = {*small, *empty, "messages"}
        for kind, _, table, text in master:
            if kind == "index" and text and table in kept:
                new.execute(text)
        new.commit()
    finally:
        new.close()
