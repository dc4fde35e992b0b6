"""A lean chunked MCAP writer for uwbd's logs: the ``mcap`` library's records, with the
per-message path in one call.

``mcap.writer.Writer`` builds a dataclass and makes a dozen calls for every message. Here a
message is one packed header and its bytes appended to the open chunk (:class:`PyChunk`, or
its C twin ``_chunk.c`` where built); everything else — schemas, channels, metadata, chunks,
message and chunk indexes, statistics, the summary and its offsets, the footer — is written
with the library's own record classes, in the same layout as its writer (the reader tests
and ``uwbd.logs.reading.read_log`` check the files with the library's reader).
"""

from __future__ import annotations

import struct
import zlib
from collections import defaultdict
from typing import IO, Any

import zstandard
from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    McapRecord,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)

from uwbd.fusion.core import native
from uwbd.logs import records

# the file's first and last bytes (mcap.writer's MCAP0_MAGIC: that module is not imported,
# it reads its package's version from the installed metadata at import, ~15 ms)
MCAP0_MAGIC = b"\x89MCAP0\r\n"
# the records' heads (records.py, which _chunk.c is generated from): then the data, or the
# index's pairs
_MESSAGE = struct.Struct(records.struct_format(records.MESSAGE_HEAD))
_MESSAGE_FIXED = _MESSAGE.size - 9  # the record's content before its data
_MESSAGE_INDEX = struct.Struct(records.struct_format(records.MESSAGE_INDEX_HEAD))
if (records.OP_MESSAGE, records.OP_MESSAGE_INDEX) != (Opcode.MESSAGE, Opcode.MESSAGE_INDEX):
    raise ImportError("uwbd/logs/records.py: its opcodes are not the mcap package's")
# zstd level 1: the same ratio as the default 3 on these logs (JSON and device bytes, ~6x)
# at three quarters of the time (measured on 64 kB chunks)
ZSTD_LEVEL = 1
# what PyChunk.take gives: data, ((channel, messages, Message Index record), ...), start,
# end, messages
Taken = tuple[bytes, tuple[tuple[int, int, bytes], ...], int, int, int]


class PyChunk:
    """The open chunk's records (uncompressed) and its messages' (log time, offset) pairs by
    channel: the reference of ``_chunk.c``'s ChunkBuffer, which has the same methods."""

    def __init__(self) -> None:
        self._data = bytearray()
        self._index: dict[int, list[int]] = {}  # channel -> log time, offset, log time, …

    @property
    def size(self) -> int:
        return len(self._data)

    def add(self, channel_id: int, log_time: int, data: bytes, sequence: int) -> int:
        """A Message record (``publish_time = log_time``); the chunk's length after it."""
        chunk = self._data
        # packed first: a value out of range (struct.error) leaves the chunk as it was
        head = _MESSAGE.pack(Opcode.MESSAGE, _MESSAGE_FIXED + len(data), channel_id,
                             sequence, log_time, log_time)
        index = self._index.get(channel_id)
        if index is None:
            index = self._index[channel_id] = []
        index += (log_time, len(chunk))  # the chunk's times and counts follow from these
        chunk += head
        chunk += data
        return len(chunk)

    def append(self, record: bytes) -> None:
        self._data += record

    def take(self) -> Taken | None:
        """The chunk and its indexes (None while it holds no message); it starts anew."""
        if not self._index:
            return None  # schemas and channels wait for the chunk of their first message
        index = self._index
        taken = (bytes(self._data),
                 tuple((channel_id, len(entries) // 2, _message_index(channel_id, entries))
                       for channel_id, entries in index.items()),
                 min(min(entries[0::2]) for entries in index.values()),
                 max(max(entries[0::2]) for entries in index.values()),
                 sum(len(entries) // 2 for entries in index.values()))
        self._data, self._index = bytearray(), {}
        return taken


def new_chunk() -> Any:
    """A :class:`PyChunk`, or its C twin where built (and ``UWBD_PURE_PYTHON`` unset)."""
    if native.core is not None:
        try:
            from uwbd.logs import _chunk  # noqa: PLC0415
        except ImportError:
            pass
        else:
            return _chunk.ChunkBuffer()
    return PyChunk()


class ChunkedWriter:
    """Writes one MCAP file to ``stream`` in zstd chunks of about ``chunk_size`` bytes."""

    def __init__(self, stream: IO[bytes], chunk_size: int) -> None:
        self._out = stream
        self._chunk_size = chunk_size
        self._chunk = new_chunk()  # the open chunk and its message indexes
        self._zstd = zstandard.ZstdCompressor(level=ZSTD_LEVEL)
        self._schemas: list[Schema] = []
        self._channels: list[Channel] = []
        # the channels the open chunk defines: every chunk defines the channels of its
        # messages, so a damaged chunk cannot take their topics with it (schemas, kilobytes
        # of JSON each, are written once: in the chunk of their first message, and the summary)
        self._defined: set[int] = set()
        self._chunk_indexes: list[ChunkIndex] = []
        self._metadata_indexes: list[MetadataIndex] = []
        self._counts: defaultdict[int, int] = defaultdict(int)
        self._messages = 0
        self._start = self._end = 0
        self._metadata = 0

    def start(self, library: str) -> None:
        self._out.write(MCAP0_MAGIC)
        self._out.write(_record(Header(profile="", library=library)))

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """Written at once, between chunks (as the library's writer does)."""
        self._metadata += 1
        record = _record(Metadata(name=name, metadata=data))
        self._metadata_indexes.append(MetadataIndex(offset=self._out.tell(),
                                                    length=len(record), name=name))
        self._out.write(record)

    def register_schema(self, name: str, encoding: str, data: bytes) -> int:
        schema = Schema(id=len(self._schemas) + 1, name=name, encoding=encoding, data=data)
        self._schemas.append(schema)
        self._chunk.append(_record(schema))
        return schema.id

    def register_channel(self, topic: str, message_encoding: str, schema_id: int) -> int:
        channel = Channel(id=len(self._channels) + 1, topic=topic,
                          message_encoding=message_encoding, schema_id=schema_id, metadata={})
        self._channels.append(channel)
        self._define(channel)
        return channel.id

    def _define(self, channel: Channel) -> None:
        self._chunk.append(_record(channel))
        self._defined.add(channel.id)

    def add_message(self, channel_id: int, log_time: int, data: bytes, sequence: int) -> None:
        """A message with ``publish_time = log_time``; a value its field cannot hold raises
        (``struct.error`` or ``ValueError``) and leaves the chunk as it was."""
        if channel_id not in self._defined and 0 < channel_id <= len(self._channels):
            self._define(self._channels[channel_id - 1])
        if self._chunk.add(channel_id, log_time, data, sequence) > self._chunk_size:
            self.end_chunk()

    def flush(self) -> None:
        """The open chunk written out, the stream flushed (not fsynced)."""
        self.end_chunk()
        self._out.flush()

    def finish(self) -> None:
        """The last chunk, the data end, the summary (schemas, channels, statistics, chunk and
        metadata indexes, their offsets) and the footer. Does not close the stream."""
        self.end_chunk()
        self._out.write(_record(DataEnd(data_section_crc=0)))  # 0: not computed
        summary_start = self._out.tell()
        summary = bytearray()
        offsets: list[SummaryOffset] = []
        stats = Statistics(
            message_count=self._messages, schema_count=len(self._schemas),
            channel_count=len(self._channels), attachment_count=0,
            metadata_count=self._metadata, chunk_count=len(self._chunk_indexes),
            message_start_time=self._start, message_end_time=self._end,
            channel_message_counts=dict(self._counts))
        for opcode, group in ((Opcode.SCHEMA, self._schemas), (Opcode.CHANNEL, self._channels),
                              (Opcode.STATISTICS, [stats]),
                              (Opcode.CHUNK_INDEX, self._chunk_indexes),
                              (Opcode.ATTACHMENT_INDEX, []),
                              (Opcode.METADATA_INDEX, self._metadata_indexes)):
            begin = len(summary)
            for record in group:
                summary += _record(record)
            offsets.append(SummaryOffset(group_opcode=opcode,
                                         group_start=summary_start + begin,
                                         group_length=len(summary) - begin))
        offset_start = summary_start + len(summary)
        for offset in offsets:
            summary += _record(offset)
        crc = zlib.crc32(struct.pack("<BQQQ", Opcode.FOOTER, 20, summary_start, offset_start),
                         zlib.crc32(summary))
        self._out.write(summary)
        self._out.write(_record(Footer(summary_start=summary_start,
                                       summary_offset_start=offset_start, summary_crc=crc)))
        self._out.write(MCAP0_MAGIC)

    def end_chunk(self) -> None:
        """The open chunk compressed and written with its message indexes (nothing when it
        holds no message)."""
        taken = self._chunk.take()
        if taken is None:
            return  # schemas and channels wait for the chunk of their first message
        self._defined = set()
        data, message_indexes, start, end, messages = taken
        for channel_id, count, _ in message_indexes:
            self._counts[channel_id] += count
        compressed = self._zstd.compress(data)
        chunk = Chunk(message_start_time=start, message_end_time=end,
                      uncompressed_size=len(data), uncompressed_crc=zlib.crc32(data),
                      compression="zstd", data=compressed)
        chunk_offset = self._out.tell()
        record = _record(chunk)
        index_offset = chunk_offset + len(record)
        offsets: dict[int, int] = {}
        indexes = bytearray()
        for channel_id, _, index_record in message_indexes:
            offsets[channel_id] = index_offset + len(indexes)
            indexes += index_record
        self._out.write(record + indexes)  # made whole first, written in one go
        self._chunk_indexes.append(ChunkIndex(
            message_start_time=start, message_end_time=end,
            chunk_start_offset=chunk_offset, chunk_length=len(record),
            message_index_offsets=offsets, message_index_length=len(indexes),
            compression="zstd", compressed_size=len(compressed),
            uncompressed_size=len(data)))
        if self._messages == 0:
            self._start, self._end = start, end
        else:
            self._start = min(self._start, start)
            self._end = max(self._end, end)
        self._messages += messages


def _message_index(channel_id: int, flat: list[int]) -> bytes:
    """A Message Index record (opcode 0x07: channel id u16, then its (log time, offset) u64
    pairs as an array with a u32 byte length), packed at once: ``mcap``'s record class makes
    two calls a message (a third of the writer's time)."""
    size = 8 * len(flat)
    return _MESSAGE_INDEX.pack(Opcode.MESSAGE_INDEX, 2 + 4 + size, channel_id, size) \
        + struct.pack(f"<{len(flat)}Q", *flat)


def _record(record: McapRecord) -> bytes:
    builder = RecordBuilder()
    record.write(builder)
    return builder.end()  # type: ignore[no-any-return, no-untyped-call]
