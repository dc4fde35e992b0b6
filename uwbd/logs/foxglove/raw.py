"""``/raw/<source>`` as protobuf ``uwbd.Raw``, encoded and decoded by hand
(:mod:`uwbd.logs.foxglove`)."""

from __future__ import annotations

RAW_SCHEMA_NAME = "uwbd.Raw"
RAW_MESSAGE_ENCODING = "protobuf"
LEGACY_RAW_ENCODING = "uwbd.raw"  # before: schemaless, the bytes as they are


def _varint(n: int) -> bytes:
    out = bytearray()
    while n > 0x7F:
        out.append((n & 0x7F) | 0x80)
        n >>= 7
    out.append(n)
    return bytes(out)


def _pb_bytes(field: int, payload: bytes) -> bytes:
    return _varint(field << 3 | 2) + _varint(len(payload)) + payload


def _pb_int(field: int, value: int) -> bytes:
    return _varint(field << 3) + _varint(value)


# FileDescriptorSet { file: FileDescriptorProto { name, package, message_type: DescriptorProto
# { name: "Raw", field: FieldDescriptorProto { name: "data", number: 1, LABEL_OPTIONAL,
# TYPE_BYTES, json_name: "data" } }, syntax: "proto3" } }
RAW_DESCRIPTOR = _pb_bytes(1, b"".join((
    _pb_bytes(1, b"uwbd/Raw.proto"),
    _pb_bytes(2, b"uwbd"),
    _pb_bytes(4, _pb_bytes(1, b"Raw") + _pb_bytes(2, b"".join((
        _pb_bytes(1, b"data"), _pb_int(3, 1), _pb_int(4, 1), _pb_int(5, 12),
        _pb_bytes(10, b"data"))))),
    _pb_bytes(12, b"proto3"))))


def encode_raw(data: bytes) -> bytes:
    """``uwbd.Raw {data}`` as protobuf: tag 0x0A, the length as a varint, the bytes."""
    n = len(data)
    if n < 0x80:
        return b"\n" + bytes((n,)) + data if n else b""
    return b"\n" + _varint(n) + data


def decode_raw(message: bytes) -> bytes:
    """The bytes of a ``uwbd.Raw`` message (any valid encoding of it: fields other than
    ``data`` are skipped, the last ``data`` wins, as protobuf says)."""
    data, k, end = b"", 0, len(message)
    while k < end:
        key, k = _read_varint(message, k)
        wire = key & 7
        if wire == 2:
            n, k = _read_varint(message, k)
            if key >> 3 == 1:
                data = message[k:k + n]
            k += n
        elif wire == 0:
            _, k = _read_varint(message, k)
        elif wire in (1, 5):
            k += 8 if wire == 1 else 4
        else:
            raise ValueError(f"uwbd.Raw: unsupported protobuf wire type {wire}")
    if k != end:
        raise ValueError("uwbd.Raw: message ends inside a field")
    return data


def _read_varint(buf: bytes, k: int) -> tuple[int, int]:
    value = shift = 0
    while True:
        if k >= len(buf):
            raise ValueError("uwbd.Raw: message ends inside a varint")
        b = buf[k]
        k += 1
        value |= (b & 0x7F) << shift
        if b < 0x80:
            return value, k
        shift += 7
