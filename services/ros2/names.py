"""How ROS 2 topics, nodes and publishers look on Zenoh, in the two ways ROS 2 meets it (docs/ros2.md).

**rmw_zenoh** (ros2/rmw_zenoh, docs/design.md and rmw_zenoh_cpp/src/detail/liveliness_utils.cpp):

- a topic's samples travel on ``<domain>/<fully qualified name without the leading />/<DDS type>/<type hash>``,
  e.g. ``0/robot1/map/nav_msgs::msg::dds_::OccupancyGrid_/RIHS01_8d34...``;
- every node, publisher and subscription declares a liveliness token, ``@ros2_lv/<domain>/<session id>/<node id>/
  <entity id>/<kind NN|MP|MS>/<enclave>/<namespace>/<node name>`` and, for a publisher or subscription,
  ``/<topic>/<DDS type>/<type hash>/<QoS>``, where names have each ``/`` replaced by ``%`` ("mangled") and QoS is
  rmw_zenoh's compact form (:func:`rmw_qos`);
- every sample carries an attachment: the publisher's sequence number and source timestamp (ns since the Unix
  epoch), each an int64, and its 16-byte GID, in Zenoh's serialisation format (:func:`encode_attachment`).

**zenoh-bridge-ros2dds** (eclipse-zenoh/zenoh-plugin-ros2dds, zenoh-plugin-ros2dds/src/ros2_utils.rs and
liveliness_mgt.rs): samples travel on the topic's name without the leading ``/`` (``robot1/map``), with no
attachment; a route is announced by the token ``@/<session id>/@ros2_lv/<MP|MS>/<key with / as §>/<ROS type with
/ as §>/<DDS QoS>`` (:func:`dds_qos`), which makes a remote bridge create the matching DDS reader or writer.
"""

from __future__ import annotations

import hashlib
import re
from dataclasses import dataclass

#: the two ways of meeting ROS 2 on Zenoh
RMW, BRIDGE = "rmw_zenoh", "bridge"
MODES = (RMW, BRIDGE)

ADMIN_SPACE = "@ros2_lv"
NODE, PUBLISHER, SUBSCRIPTION = "NN", "MP", "MS"

#: rmw_zenoh's default depth (rmw_zenoh_cpp/src/detail/qos.cpp), left out of its QoS strings
RMW_DEFAULT_DEPTH = 42

#: one token of a ROS 2 name (design.ros2.org, "Topic and Service name mapping"): letters, digits and underscores,
#: not starting with a digit
_TOKEN = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


class RosNameError(ValueError):
    """A ROS 2 name, namespace or domain that is not valid."""


@dataclass(frozen=True)
class QoS:
    """The QoS posegrid declares for one endpoint: reliable or best effort, transient local or volatile, and the
    history depth (keep last)."""

    reliable: bool = True
    transient_local: bool = False
    depth: int = 10


#: QoS of the bridge's endpoints (docs/ros2.md): the map is latched (TRANSIENT_LOCAL, depth 1), as map_server's is;
#: sensors are read best effort (rclcpp's SensorDataQoS), the static transforms transient local
MAP_QOS = QoS(transient_local=True, depth=1)
STREAM_QOS = QoS(depth=10)
SENSOR_QOS = QoS(reliable=False, depth=5)
TF_QOS = QoS(depth=100)
TF_STATIC_QOS = QoS(transient_local=True, depth=1)


def check_name(name: str, what: str) -> None:
    """Raise :class:`RosNameError` unless ``name`` is a ROS 2 topic name or namespace (tokens of letters, digits and
    ``_`` not starting with a digit, separated by single ``/``; relative or absolute; no ``~`` or substitutions)."""
    body = name[1:] if name.startswith("/") else name
    if name == "/":
        return
    if not body or not all(_TOKEN.fullmatch(token) for token in body.split("/")):
        raise RosNameError(
            f"{what} {name!r} is not a ROS 2 name: tokens of letters, digits and '_' (not starting with a digit) "
            "separated by single '/'"
        )


def normalize_namespace(namespace: str) -> str:
    """``namespace`` as ROS 2 writes it: absolute, no trailing ``/`` (``robot1`` -> ``/robot1``, ``''`` -> ``/``)."""
    namespace = "/" + namespace.strip("/") if namespace.strip("/") else "/"
    check_name(namespace, "namespace")
    return namespace


def resolve(topic: str, namespace: str) -> str:
    """The fully qualified name of ``topic`` in ``namespace`` (absolute names stay as they are)."""
    check_name(topic, "topic")
    if topic.startswith("/"):
        return topic
    return f"{namespace.rstrip('/')}/{topic}"


def mangle(name: str) -> str:
    """A name as one key chunk of rmw_zenoh's tokens: every ``/`` becomes ``%`` (``/robot1/map`` -> ``%robot1%map``)."""
    return name.replace("/", "%")


def rmw_qos(qos: QoS) -> str:
    """rmw_zenoh's compact QoS chunk (``qos_to_keyexpr``): reliability, durability, history and depth, deadline,
    lifespan, liveliness; a value equal to rmw_zenoh's default (reliable, volatile, keep last 42, infinite
    durations, automatic liveliness) is left empty. Keep last 10, reliable, volatile: ``::,10:,:,:,,``."""
    reliability = "" if qos.reliable else "2"  # rmw_qos_reliability_policy_e: RELIABLE 1, BEST_EFFORT 2
    durability = "1" if qos.transient_local else ""  # rmw_qos_durability_policy_e: TRANSIENT_LOCAL 1, VOLATILE 2
    depth = "" if qos.depth == RMW_DEFAULT_DEPTH else str(qos.depth)
    return f"{reliability}:{durability}:,{depth}:,:,:,,"


def dds_qos(qos: QoS) -> str:
    """zenoh-bridge-ros2dds's QoS chunk (``qos_to_key_expr``): ``<keyless>:<reliability>:<durability>:<history>,
    <depth>`` with DDS's enum values (RELIABLE 1, BEST_EFFORT 0; TRANSIENT_LOCAL 1, VOLATILE 0; KEEP_LAST 0);
    posegrid's topics are keyless, so the first field is empty."""
    return f":{1 if qos.reliable else 0}:{1 if qos.transient_local else 0}:0,{qos.depth}"


def gid_of(token: str) -> bytes:
    """The 16-byte GID of the entity whose liveliness token is ``token``: a hash of the token, as rmw_zenoh derives
    its GIDs (it uses XXH3-128; posegrid uses BLAKE2b, a GID being opaque to every subscriber)."""
    return hashlib.blake2b(token.encode(), digest_size=16).digest()


#: bytes of a GID (RMW_GID_STORAGE_SIZE)
GID_SIZE = 16


@dataclass(frozen=True)
class Attachment:
    """What rmw_zenoh attaches to every sample: the publisher's sequence number (1, 2, ...), the source timestamp
    (ns since the Unix epoch) and the publisher's GID (16 bytes)."""

    sequence_number: int
    source_timestamp: int
    gid: bytes


def encode_attachment(attachment: Attachment) -> bytes:
    """rmw_zenoh's attachment (``AttachmentData::serialize_to_zbytes``) in Zenoh's serialisation format: the two
    int64 little endian, then the GID as a sequence (its length, 16, as one LEB128 byte, then the bytes): 33 bytes."""
    from zenoh.ext import Int64, z_serialize

    gid = bytes(attachment.gid)
    if len(gid) != GID_SIZE:
        raise ValueError(f"a GID has {GID_SIZE} bytes, got {len(gid)}")
    return z_serialize((Int64(attachment.sequence_number), Int64(attachment.source_timestamp), gid)).to_bytes()


def decode_attachment(data: bytes) -> Attachment | None:
    """The attachment ``data`` holds, or None when it is none: the current layout of :func:`encode_attachment`, or
    the earlier one of rmw_zenoh releases that named each field first (``"sequence_number"``, int64,
    ``"source_timestamp"``, int64, ``"source_gid"``, bytes; rmw_zenoh_cpp/src/detail/attachment_helpers.cpp before
    the names were dropped)."""
    from zenoh import ZBytes
    from zenoh.ext import Int64, ZDeserializeError, z_deserialize, z_serialize

    layouts = ((Int64, Int64, bytes), (str, Int64, str, Int64, str, bytes))
    for layout in layouts:
        try:
            fields = z_deserialize(tuple[layout], ZBytes(data))  # type: ignore[valid-type]
        except (ZDeserializeError, ValueError, TypeError):
            continue
        if z_serialize(fields).to_bytes() != data:  # trailing bytes: no attachment of this layout
            continue
        if len(layout) == 6:
            if fields[0::2] != ("sequence_number", "source_timestamp", "source_gid"):
                continue
            fields = fields[1::2]
        seq, stamp, gid = fields
        if len(gid) == GID_SIZE:
            return Attachment(int(seq), int(stamp), bytes(gid))
    return None


@dataclass(frozen=True)
class Graph:
    """Where one node of posegrid sits in the ROS 2 graph: ``mode`` (RMW or BRIDGE), ``domain`` (ROS_DOMAIN_ID),
    ``namespace`` (absolute), ``node`` (its name), ``zid`` (its Zenoh session id) and ``enclave`` (SROS; "/")."""

    mode: str
    domain: int
    namespace: str
    node: str
    zid: str
    enclave: str = "/"

    def topic_key(self, fqn: str, type_name: str, type_hash: str) -> str:
        """The key expression samples of topic ``fqn`` (fully qualified) of ROS type ``type_name`` travel on."""
        if self.mode == BRIDGE:
            return fqn.lstrip("/")
        return f"{self.domain}/{fqn.lstrip('/')}/{dds_type_name(type_name)}/{type_hash}"

    def node_token(self, node_id: int = 0) -> str | None:
        """The node's liveliness token (rmw_zenoh: ``@ros2_lv/0/<zid>/0/0/NN/%/%/posegrid``); None with BRIDGE,
        whose tokens name routes, not nodes."""
        if self.mode == BRIDGE:
            return None
        return (
            f"{ADMIN_SPACE}/{self.domain}/{self.zid}/{node_id}/{node_id}/{NODE}/{mangle(self.enclave)}/"
            f"{mangle(self.namespace)}/{self.node}"
        )

    def entity_token(
        self, kind: str, entity_id: int, fqn: str, type_name: str, type_hash: str, qos: QoS, node_id: int = 0
    ) -> str:
        """The liveliness token of a publisher (``kind`` MP) or subscription (MS) of topic ``fqn``."""
        if self.mode == BRIDGE:
            key = fqn.lstrip("/").replace("/", "§")
            return f"@/{self.zid}/{ADMIN_SPACE}/{kind}/{key}/{type_name.replace('/', '§')}/{dds_qos(qos)}"
        return (
            f"{ADMIN_SPACE}/{self.domain}/{self.zid}/{node_id}/{entity_id}/{kind}/{mangle(self.enclave)}/"
            f"{mangle(self.namespace)}/{self.node}/{mangle(fqn)}/{dds_type_name(type_name)}/{type_hash}/"
            f"{rmw_qos(qos)}"
        )


def dds_type_name(type_name: str) -> str:
    """``pkg/msg/Name`` -> ``pkg::msg::dds_::Name_``."""
    package, kind, base = type_name.split("/")
    return f"{package}::{kind}::dds_::{base}_"


def check_domain(domain: int) -> None:
    """Raise :class:`RosNameError` unless ``domain`` is a ROS_DOMAIN_ID (0 .. 232, what DDS's port mapping allows)."""
    if not 0 <= domain <= 232:
        raise RosNameError(f"the ROS domain id must be 0 .. 232, got {domain}")


def parse_topic_key(key: str, graph: Graph, fqn: str) -> tuple[str, str] | None:
    """(DDS type, type hash) of a concrete rmw_zenoh sample key on topic ``fqn`` (``("", "")`` with BRIDGE, whose keys
    name neither); None when ``key`` is no key of that topic (a wildcard, another depth or topic)."""
    if graph.mode == BRIDGE:
        return ("", "") if key == fqn.lstrip("/") else None
    prefix = f"{graph.domain}/{fqn.lstrip('/')}/"
    if not key.startswith(prefix):
        return None
    rest = key[len(prefix) :].split("/")
    if len(rest) != 2 or any(not part or "*" in part or part.startswith("$") for part in rest):
        return None
    return rest[0], rest[1]
