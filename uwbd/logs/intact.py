"""What of a damaged MCAP file can be read: every record that reads whole, and where the rest
was lost (:class:`Damage`).

Three kinds of damage, each costing what it damaged and no more:

* a flipped bit in a chunk's contents: its CRC fails; reading goes on at the next record
  (its length field is intact), else at the next chunk that reads whole;
* a flipped bit in a chunk's record-length field: the chunk's own fields (its compression
  name and its records' length) say where it ends; the chunk is read by them, and reading
  goes on there;
* a zeroed tail (what a power loss leaves: the file's size was written, its last blocks were
  not): found by walking the records' headers, which is one bounded read a record, and by one
  bounded read of the file's end; the file is read up to it, never past it
  (:func:`intact_size`).
"""

from __future__ import annotations

import io
import os
import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zstandard
from mcap.exceptions import EndOfFile, McapError
from mcap.records import Chunk
from mcap.stream_reader import StreamReader, breakup_chunk

from uwbd.logs.chunked import MCAP0_MAGIC
from uwbd.logs.scan import HEAD

MAX_OPCODE = 0x10
OP_CHUNK, OP_FOOTER = 0x06, 0x02
ZEROS_CHECKED = 65536  # the bounded read that tells a zeroed tail from a zero byte or two
# what reading a damaged or torn file raises: mcap's own errors, a record cut off (EOFError,
# struct.error), a damaged compressed chunk (zstandard, lz4: a RuntimeError), a damaged
# length or size field, which has the reader ask for more than an index holds
# (OverflowError) or allocate exabytes for a chunk's records (MemoryError: found by the
# damaged-log property test)
DAMAGED = (McapError, EOFError, ValueError, struct.error, zstandard.ZstdError, RuntimeError,
           OverflowError, MemoryError)
_CHUNK_HEAD = struct.Struct("<BQQQQII")  # opcode, length, start, end, size, CRC, compression
_U64 = struct.Struct("<Q")


@dataclass
class Damage:
    """What :func:`intact_records` had to pass over: damaged stretches (from byte, to byte,
    why), whether the file ends mid-record (a crash), and a zeroed tail."""

    skipped: list[tuple[int, int, str]] = field(default_factory=list)
    torn_at: int | None = None  # where the last, unfinished record starts
    torn_why: str = ""
    zeroed: tuple[int, int] | None = None  # a zeroed tail: from byte, to the file's end

    def __bool__(self) -> bool:
        return bool(self.skipped) or self.torn_at is not None or self.zeroed is not None

    def said(self, path: Path) -> str:
        parts = []
        if self.skipped:
            lost = sum(end - start for start, end, _ in self.skipped)
            start, end, why = self.skipped[0]
            parts.append(f"{len(self.skipped)} damaged stretch(es) skipped ({lost} bytes; the "
                         f"first, bytes {start}-{end}: {why}), read on from the next intact "
                         "record")
        if self.torn_at is not None and self.torn_why:
            parts.append(f"it ends mid-record near byte {self.torn_at} ({self.torn_why})")
        elif self.torn_at is not None:
            parts.append(f"it ends at byte {self.torn_at} without a footer (the writer never "
                         "finished: a crash or a power loss)")
        if self.zeroed is not None:
            start, end = self.zeroed
            parts.append(f"bytes {start}-{end} are zeros ({end - start} bytes never written: "
                         "a power loss), read up to them")
        return f"{path}: " + "; ".join(parts)


def intact_size(f: Any, damage: Damage) -> int:
    """How much of the open MCAP file ``f`` to read: all of it, or up to a zeroed tail (then
    said in ``damage``). The records' headers are walked from the start, one 9-byte read a
    record, until one is zeros: the tail starts there when ``ZEROS_CHECKED`` bytes from it,
    and the file's last as many, are zeros. A file whose last bytes are zeros but whose
    headers stop short of them (a damaged record) is searched from its end instead."""
    size = os.fstat(f.fileno()).st_size
    if size < len(MCAP0_MAGIC) + ZEROS_CHECKED or not _zeros(f, size - ZEROS_CHECKED, size):
        return size
    pos = len(MCAP0_MAGIC)
    while pos + HEAD.size <= size:
        op, length = HEAD.unpack(os.pread(f.fileno(), HEAD.size, pos))
        if op == OP_FOOTER or not 0 < op <= MAX_OPCODE or pos + HEAD.size + length > size:
            break
        pos += HEAD.size + length
    if pos < size and _zeros(f, pos, size):
        damage.zeroed = (pos, size)
        return pos
    return _last_data(f, size, damage)


def _zeros(f: Any, start: int, size: int) -> bool:
    data = os.pread(f.fileno(), min(ZEROS_CHECKED, size - start), start)
    return not data.strip(b"\0")


def _last_data(f: Any, size: int, damage: Damage) -> int:
    """Where the zeros end a file whose headers could not be walked to them (a damaged record
    before the tail): found from the end backwards, a bounded read at a time."""
    end = size
    while end > len(MCAP0_MAGIC):
        start = max(len(MCAP0_MAGIC), end - ZEROS_CHECKED * 16)
        data = os.pread(f.fileno(), end - start, start).rstrip(b"\0")
        if data:
            tail_at = start + len(data)
            if size - tail_at >= ZEROS_CHECKED:
                damage.zeroed = (tail_at, size)
                return tail_at
            return size
        end = start
    return size


def intact_records(buf: bytes, damage: Damage) -> Iterator[Any]:
    """Every record of the MCAP file ``buf`` that reads whole and passes its CRC, in file
    order. Where one does not (a flipped bit, a torn write), reading goes on at the next
    record that reads whole; a chunk whose length field is damaged is read by its own fields
    (module doc). What was passed over goes in ``damage``."""
    pos = len(MCAP0_MAGIC)
    while True:
        stream = io.BytesIO(buf)
        stream.seek(pos)
        good_end = pos
        resume = None
        try:
            reader = StreamReader(stream, skip_magic=True, validate_crcs=True, emit_chunks=True)
            for record in reader.records:
                if not isinstance(record, Chunk):
                    yield record
                    good_end = stream.tell()
                    continue
                inner = breakup_chunk(record, validate_crc=True)  # (all of it, or it raises)
                yield from inner
                # a length field off passes the reader: the chunk's own fields say more
                own = _chunk_end(buf, good_end)
                said = good_end + HEAD.size + HEAD.unpack_from(buf, good_end)[1]
                if own is not None and own != said and _starts_record(buf, own):
                    damage.skipped.append((good_end, good_end, _LENGTH_SAID))
                    if own != stream.tell():  # the reader went elsewhere: on from its end
                        resume = own
                        break
                good_end = stream.tell()
            else:
                return
        except DAMAGED as err:
            why = f"{type(err).__name__}: {err}"
            mended = _mended_chunk(buf, good_end)
            if mended is not None:  # only its length field was wrong: read it by its own
                record_bytes, resume = mended
                reader = StreamReader(io.BytesIO(record_bytes), skip_magic=True, emit_chunks=True)
                chunk = next(iter(reader.records))
                assert isinstance(chunk, Chunk)  # (_mended_chunk read it as one)
                yield from breakup_chunk(chunk, validate_crc=True)
                damage.skipped.append((good_end, good_end, _LENGTH_SAID))
            else:
                resume = _after_record(buf, good_end)
                if resume is None:
                    resume = _next_chunk(buf, good_end + 1)
                if resume is None:
                    if isinstance(err, (EndOfFile, EOFError, struct.error)):
                        damage.torn_at = good_end  # (at the end: whole records, no footer)
                        damage.torn_why = why if good_end < len(buf) else ""
                    else:  # damaged, and nothing intact after it
                        damage.skipped.append((good_end, len(buf), why))
                    return
                damage.skipped.append((good_end, resume, why))
        pos = resume


_LENGTH_SAID = "a chunk's length field is damaged: read by its own fields"


def _chunk_end(buf: bytes, at: int) -> int | None:
    """Where the chunk record at ``at`` ends by its own fields (its compression name's and its
    records' lengths), whatever its length field says; None if that does not fit the file."""
    if at + _CHUNK_HEAD.size > len(buf):
        return None
    op, _, _, _, _, _, name_len = _CHUNK_HEAD.unpack_from(buf, at)
    records_at = at + _CHUNK_HEAD.size + name_len
    if op != OP_CHUNK or name_len > 16 or records_at + _U64.size > len(buf):
        return None
    end = records_at + _U64.size + _U64.unpack_from(buf, records_at)[0]
    return end if end <= len(buf) else None


def _starts_record(buf: bytes, at: int) -> bool:
    """A record's header fits at ``at`` (or the file ends there)."""
    if at == len(buf):
        return True
    if at + HEAD.size > len(buf):
        return False
    op, length = HEAD.unpack_from(buf, at)
    return bool(0 < op <= MAX_OPCODE and at + HEAD.size + length <= len(buf))


def _mended_chunk(buf: bytes, at: int) -> tuple[bytes, int] | None:
    """The chunk record at ``at`` with its length field set by its own fields, and where it
    ends, when its length field was all that was wrong (it then reads whole, CRC and all)."""
    end = _chunk_end(buf, at)
    if end is None or not _starts_record(buf, end):
        return None
    (said,) = _U64.unpack_from(buf, at + 1)
    if said == end - at - HEAD.size:
        return None  # the length is right: the damage is elsewhere
    record = bytearray(buf[at:end])
    _U64.pack_into(record, 1, end - at - HEAD.size)
    return (bytes(record), end) if _whole_chunk(bytes(record)) else None


def _after_record(buf: bytes, at: int) -> int | None:
    """Where the record at ``at`` ends by its own length field, if that lands on the start
    of another record that fits the file (a bit flipped in a chunk's contents leaves its
    length intact: skipping just that record loses nothing else); None otherwise."""
    if at + HEAD.size > len(buf):
        return None
    opcode, length = HEAD.unpack_from(buf, at)
    end = int(at + HEAD.size + length)
    if not 0 < opcode <= MAX_OPCODE or end + HEAD.size > len(buf):
        return None
    next_opcode, next_length = HEAD.unpack_from(buf, end)
    if not 0 < next_opcode <= MAX_OPCODE or end + HEAD.size + next_length > len(buf):
        return None
    if next_opcode == OP_CHUNK and not _whole_chunk(buf[end:end + HEAD.size + next_length]):
        return None
    return end


def _whole_chunk(record: bytes) -> bool:
    """``record`` is one chunk record that decompresses, passes its CRC and holds whole
    records (the reader then finds the end of the bytes, as it would a file cut there)."""
    stream = io.BytesIO(record)
    inner = 0
    try:
        for _ in StreamReader(stream, skip_magic=True, validate_crcs=True).records:
            inner += 1
    except (EndOfFile, EOFError, struct.error):
        return inner > 0 and stream.tell() == len(record)
    except DAMAGED:
        return False
    return inner > 0


def _next_chunk(buf: bytes, start: int) -> int | None:
    """The offset of the first chunk record at or after ``start`` that reads whole, with
    its CRC right (None: none)."""
    i = buf.find(b"\x06", start)
    while i != -1:
        if i + _CHUNK_HEAD.size <= len(buf):
            _, length, *_, compression_len = _CHUNK_HEAD.unpack_from(buf, i)
            if (compression_len <= 16 and 32 <= length <= len(buf) - i - 9
                    and _whole_chunk(buf[i:i + 9 + length])):
                return i
        i = buf.find(b"\x06", i + 1)
    return None
