"""Recover a cut-off MCAP recording: copy the records written before the cut.

A recorder that is killed, a full disk or an interrupted copy leaves an MCAP file
without its end (summary, footer, closing magic), and readers (rosbags among them)
refuse it; :mod:`bag` names ``neurncd recover`` in its error. :func:`recover_mcap`
streams the file's whole records into a new one that readers scan. Pure Python, the
MCAP format at https://mcap.dev/spec; chunks are decompressed by rosbags' own helper.
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path
from typing import Any

from .bag import BagError, recording_file

_MCAP_MAGIC = b"\x89MCAP0\r\n"


def recover_mcap(src: str | Path, out: str | Path) -> dict[str, int]:
    """Copy the part of a cut-off MCAP recording that was written, so it can be read.

    A recorder that is killed, a full disk or an interrupted copy leaves an MCAP file
    without its end (summary, footer, closing magic), which readers refuse. MCAP writes
    records one after another, each with its length, and a chunk record whole when the
    chunk closes: every complete record before the cut is intact. They are copied
    byte for byte (the offsets stay as written), a chunk whose data does not decompress
    to its stated size (or checksum) ends the copy, and a data-end record and a footer
    without a summary close the file; readers then scan it. A file cut in its summary
    (after the data-end record) keeps all its data. What the MCAP CLI's ``mcap
    recover`` does, without a Go binary. The file is streamed (one chunk in memory at a
    time): a recording cut off by a full disk can be larger than memory. ``src``: the
    .mcap file, or a bag folder holding one. Returns the counts: ``records``,
    ``messages`` (outside chunks) and ``chunks`` kept, ``bytes`` kept of ``size``.
    Raises :class:`BagError` for a file that is no MCAP, is not cut off (nothing to
    recover), or whose cut leaves nothing to read.
    """
    out = Path(out)
    src = recording_file(Path(src), out, ".mcap")
    size = src.stat().st_size
    with src.open("rb") as f:
        head = f.read(17)
        if head[:8] != _MCAP_MAGIC or size < 17 or head[8] != 0x01:
            raise BagError(f"{src}: not an MCAP file (no MCAP magic and header record)")
        # A closed file ends with a footer record (opcode 0x02, length 20), then the
        # magic; a cut may end in the magic's bytes alone (a message carrying them).
        f.seek(max(0, size - 37))
        tail = f.read(37)
        if (size >= 8 + 9 + 37 and tail[-8:] == _MCAP_MAGIC
                and tail[:9] == b"\x02" + struct.pack("<Q", 20)
                and struct.unpack_from("<Q", tail, 9)[0] <= size - 37):
            raise BagError(f"{src}: the recording is complete (it ends with its footer and "
                           "closing MCAP magic): nothing to recover")
        counts = {"records": 0, "messages": 0, "chunks": 0, "size": size}
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = out.with_name(out.name + ".part")
        try:
            _copy_records(f, tmp, size, counts)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
    tmp.replace(out)
    return counts


# The records an MCAP data section holds (schema, channel, message, chunk, message
# index, attachment, metadata); 0x80-0xFF are private records, allowed anywhere.
_MCAP_DATA_OPS = (0x03, 0x04, 0x05, 0x06, 0x07, 0x09, 0x0C)


def _copy_records(f: Any, tmp: Path, size: int, counts: dict[str, int]) -> None:
    """:func:`recover_mcap`'s copy of the whole records of MCAP file ``f`` (``size``
    bytes, its header record checked) into ``tmp``, closed with a data-end record and a
    footer; ``counts`` filled. The copy ends at the first record cut off, of no
    data-section kind (the data-end record; zeros a crash left), or a chunk that is not
    whole."""
    with tmp.open("wb") as dst:
        dst.write(_MCAP_MAGIC)
        pos = 8  # the header record is the first one
        f.seek(pos)
        while pos + 9 <= size:
            rec = f.read(9)
            op, length = rec[0], struct.unpack_from("<Q", rec, 1)[0]
            end = pos + 9 + length
            if end > size or not (op in _MCAP_DATA_OPS or op >= 0x80 or pos == 8):
                break
            if op == 0x06:  # a chunk: its data must decompress to what it states
                body = f.read(length)
                if not _whole_chunk(memoryview(body)):
                    break
                dst.write(rec)
                dst.write(body)
                del body  # before the next chunk is read: one in memory
                counts["chunks"] += 1
            else:
                dst.write(rec)
                _copy_exactly(f, dst, length)
            counts["messages"] += op == 0x05
            counts["records"] += 1
            pos = end
        if not counts["chunks"] and not counts["messages"]:
            raise BagError(f"{f.name}: cut off before its first complete message or chunk "
                           f"({pos} of {size} bytes): nothing to recover")
        counts["bytes"] = pos
        dst.write(b"\x0f" + struct.pack("<QI", 4, 0))           # data end, no checksum
        dst.write(b"\x02" + struct.pack("<QQQI", 20, 0, 0, 0))  # footer: no summary
        dst.write(_MCAP_MAGIC)


def _whole_chunk(body: memoryview) -> bool:
    """Whether an MCAP chunk record's body (start and end times u64, uncompressed size
    u64, checksum u32, compression string, records u64-sized)
    decompresses to its stated size and checksum, into records (schema, channel,
    message, private) that fill it exactly. The last test catches what the others
    cannot in an uncompressed chunk without a checksum (rosbags writes them): zeros a
    crash left in place of its end."""
    from rosbags.rosbag2.storage_mcap import decompress

    try:
        raw_size, crc = struct.unpack_from("<QI", body, 16)
        n = struct.unpack_from("<I", body, 28)[0]
        compression = bytes(body[32: 32 + n]).decode("utf-8")
        clen = struct.unpack_from("<Q", body, 32 + n)[0]
        if 40 + n + clen > len(body):
            return False
        raw = body[40 + n: 40 + n + clen]
        if compression:
            raw = memoryview(decompress(bytes(raw), compression, raw_size, crc))
        elif len(raw) != raw_size or (crc and zlib.crc32(raw) != crc):
            return False  # uncompressed: checked in place, no copy of the chunk
        pos = 0
        while pos + 9 <= len(raw):
            if raw[pos] not in (0x03, 0x04, 0x05) and raw[pos] < 0x80:
                return False
            pos += 9 + struct.unpack_from("<Q", raw, pos + 1)[0]
        return pos == len(raw)
    except Exception:  # a field past the body's end, an unknown compression
        return False


def _copy_exactly(f: Any, dst: Any, n: int) -> None:
    """Copy the next ``n`` bytes of file ``f`` to ``dst`` in blocks (an attachment may be
    larger than memory)."""
    while n > 0:
        block = f.read(min(n, 1 << 20))
        dst.write(block)
        n -= len(block)
