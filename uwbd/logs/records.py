"""The MCAP records the output log's open chunk writes per message, laid out once: the
Message record's head and the Message Index record's (MCAP's spec: little-endian fields,
the opcode first, then the record's length). ``chunked.PyChunk`` packs them with ``struct``
from these tables; ``_chunk.c`` is compiled from the header setup.py generates from them
(``_chunk_layout.h``). The standard library only: setup.py reads this file."""

OP_MESSAGE = 0x05
OP_MESSAGE_INDEX = 0x07
# (field, bytes) in order; a Message's data follows its head
MESSAGE_HEAD = (("opcode", 1), ("record_length", 8), ("channel_id", 2), ("sequence", 4),
                ("log_time", 8), ("publish_time", 8))
# a Message Index's (log time, offset) pairs, u64 each, follow its head
MESSAGE_INDEX_HEAD = (("opcode", 1), ("record_length", 8), ("channel_id", 2),
                      ("array_bytes", 4))
STRUCT_CODES = {1: "B", 2: "H", 4: "I", 8: "Q"}  # (little-endian, unsigned)


def struct_format(head: tuple[tuple[str, int], ...]) -> str:
    """The ``struct`` format of a record's head."""
    return "<" + "".join(STRUCT_CODES[size] for _, size in head)
