"""rmw_zenoh's wire conventions, as pure functions: the key expression a topic's samples go
on, the liveliness tokens that put a node and its publishers in the ROS graph, a
publisher's id (GID) and the attachment every sample carries.

Read from ros2/rmw_zenoh's ``docs/design.md`` and the sources it names (rolling, 2025); each
function says the section. The tests hold these to the design document's worked examples
byte for byte, and the attachment to zenoh-ext's own serializer. Not checked here: a real
ROS 2 peer (there is none on this machine).

The floor: rmw_zenoh **Humble 0.1.2, Jazzy 0.2.4, Rolling 0.6.0** (every Kilted). Releases
before them wrote a string-keyed attachment and throw on the serialized one these samples
carry.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import xxhash

# design.md, "Graph Cache": a hermetic namespace, so `*`/`**` never match it
ADMIN_SPACE = "@ros2_lv"
NODE, PUBLISHER = "NN", "MP"  # "Graph Cache": <entity_kind>
SLASH_REPLACEMENT = "%"  # "Graph Cache": a mangled name has each '/' replaced by '%'
NO_TYPE_HASH = "TypeHashNotSupported"  # Humble's rmw_zenoh, which predates REP-2016's hashes
# rmw's QoS policy enums (rmw/types.h), as the token writes them
RELIABLE, BEST_EFFORT = 1, 2
TRANSIENT_LOCAL, VOLATILE = 1, 2
KEEP_LAST, KEEP_ALL = 1, 2
# "Publishers": <q sequence number, <q source timestamp (ns, Unix epoch), a length byte, GID
ATTACHMENT = struct.Struct("<qqB16s")
GID_SIZE = 16


@dataclass(frozen=True)
class Qos:
    """A publisher's QoS; rmw_zenoh's defaults (``qos.cpp``): reliable, volatile, keep last
    42, every duration infinite and liveliness automatic."""

    reliability: int = RELIABLE
    durability: int = VOLATILE
    history: int = KEEP_LAST
    depth: int = 42

    def keyexpr(self) -> str:
        """``qos_to_keyexpr`` (``liveliness_utils.cpp``): each policy's number, empty where
        it is rmw_zenoh's default: ``<rel>:<dur>:<hist>,<depth>:<deadline s>,<ns>:<lifespan
        s>,<ns>:<liveliness>,<lease s>,<ns>``; uwbd's durations are all the default."""
        d = Qos()

        def part(value: int, default: int) -> str:
            return "" if value == default else str(value)
        return (f"{part(self.reliability, d.reliability)}:{part(self.durability, d.durability)}:"
                f"{part(self.history, d.history)},{part(self.depth, d.depth)}:,:,:,,")


def dds_type_name(msgtype: str) -> str:
    """``geometry_msgs/msg/Pose`` → ``geometry_msgs::msg::dds_::Pose_`` ("Topic and Service
    name mapping": the type name as declared in DDS)."""
    package, kind, name = msgtype.split("/")
    return f"{package}::{kind}::dds_::{name}_"


def mangle(name: str) -> str:
    return name.replace("/", SLASH_REPLACEMENT)


def topic_key(domain_id: int, fq_name: str, dds_type: str, type_hash: str) -> str:
    """``<domain_id>/<fully_qualified_name>/<type_name>/<type_hash>``, the name without its
    leading slash ("Topic and Service name mapping to Zenoh key expressions")."""
    return f"{domain_id}/{fq_name.strip('/')}/{dds_type}/{type_hash}"


def node_token(domain_id: int, zid: str, node_id: int, namespace: str, node_name: str,
               enclave: str = "/") -> str:
    """A node's liveliness token ("Graph Cache"): ``@ros2_lv/<domain_id>/<session_id>/
    <node_id>/<node_id>/NN/<mangled_enclave>/<mangled_namespace>/<node_name>``."""
    return (f"{ADMIN_SPACE}/{domain_id}/{zid}/{node_id}/{node_id}/{NODE}/{mangle(enclave)}/"
            f"{mangle(namespace)}/{mangle(node_name)}")


def publisher_token(domain_id: int, zid: str, node_id: int, entity_id: int, namespace: str,
                    node_name: str, fq_name: str, dds_type: str, type_hash: str, qos: Qos,
                    enclave: str = "/") -> str:
    """A publisher's liveliness token ("Graph Cache"): the node's parts with the entity's id
    and ``MP``, then ``<mangled_qualified_name>/<type_name>/<type_hash>/<qos>``."""
    return (f"{ADMIN_SPACE}/{domain_id}/{zid}/{node_id}/{entity_id}/{PUBLISHER}/"
            f"{mangle(enclave)}/{mangle(namespace)}/{mangle(node_name)}/{mangle(fq_name)}/"
            f"{dds_type}/{type_hash}/{qos.keyexpr()}")


def gid(token: str) -> bytes:
    """An entity's 16-byte GID as rmw_zenoh makes it (``Entity::Entity`` in
    ``liveliness_utils.cpp``): XXH3-128 of the liveliness token, its low 64 bits then its
    high 64 bits, each little-endian."""
    return xxhash.xxh3_128_intdigest(token.encode()).to_bytes(GID_SIZE, "little")


def attachment(sequence_number: int, source_t_ns: int, publisher_gid: bytes) -> bytes:
    """The 33 bytes each sample carries ("Publishers"); sequence numbers start at 1."""
    return ATTACHMENT.pack(sequence_number, source_t_ns, GID_SIZE, publisher_gid)


def read_attachment(data: bytes) -> tuple[int, int, bytes]:
    """(sequence number, source timestamp ns, GID) of an attachment; ``ValueError`` if it is
    not one."""
    if len(data) != ATTACHMENT.size:
        raise ValueError(f"an rmw_zenoh attachment is {ATTACHMENT.size} bytes, got {len(data)}")
    seq, t_ns, size, publisher_gid = ATTACHMENT.unpack(data)
    if size != GID_SIZE:
        raise ValueError(f"an rmw_zenoh attachment's GID is {GID_SIZE} bytes, it says {size}")
    return seq, t_ns, publisher_gid
