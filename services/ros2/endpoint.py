"""ROS 2 publishers and subscriptions on a Zenoh session, as rmw_zenoh or zenoh-bridge-ros2dds declare them
(docs/ros2.md; the names and formats are :mod:`services.ros2.names`').

A :class:`RosNode` is posegrid's node in the ROS 2 graph: with rmw_zenoh it declares the node's liveliness token and,
per publisher and subscription, the entity's token, so that ``ros2 node list`` and ``ros2 topic list`` show them.
Publishers are Zenoh advanced publishers, as rmw_zenoh's are: a TRANSIENT_LOCAL one keeps its last ``depth`` samples
in a cache that late subscribers query, announces itself for publisher detection and sends sporadic heartbeats for
sample-miss detection; every sample goes out reliably with congestion control BLOCK (a large OccupancyGrid would
otherwise be dropped in fragments) and, with rmw_zenoh, the attachment (sequence number, source timestamp, GID).
A TRANSIENT_LOCAL subscription is an advanced subscriber that asks publishers' caches for their history, late
joiners included.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import zenoh
import zenoh.ext

from services.ros2.names import (
    PUBLISHER,
    RMW,
    SUBSCRIPTION,
    Attachment,
    Graph,
    QoS,
    encode_attachment,
    gid_of,
    resolve,
)
from services.ros2.types import MessageType

#: s between sample-miss heartbeats of a reliable TRANSIENT_LOCAL publisher (rmw_zenoh's
#: SAMPLE_MISS_DETECTION_HEARTBEAT_PERIOD, 500 ms)
HEARTBEAT_PERIOD = 0.5


@dataclass(frozen=True)
class Received:
    """One sample on a subscribed ROS topic: the topic's fully qualified name, the sample's key, its payload and
    attachment (None when it has none), and the payload's size in bytes (the payload is left empty, not copied,
    when it is larger than the subscription takes)."""

    topic: str
    key: str
    payload: bytes
    attachment: bytes | None
    size: int


class RosPublisher:
    """A ROS 2 publisher of one topic and type; :meth:`put` publishes a rosbags message or CDR bytes."""

    def __init__(self, node: RosNode, fqn: str, message_type: MessageType, qos: QoS, entity_id: int):
        graph = node.graph
        self.fqn = fqn
        self.type = message_type
        self.key = graph.topic_key(fqn, message_type.name, message_type.type_hash)
        self.token_key = graph.entity_token(PUBLISHER, entity_id, fqn, message_type.name, message_type.type_hash, qos)
        self.gid = gid_of(self.token_key)
        self.attach = graph.mode == RMW
        self.sequence_number = 0
        options: dict[str, Any] = {}
        if qos.transient_local:
            options = {
                "cache": zenoh.ext.CacheConfig(qos.depth),
                "publisher_detection": True,
                "sample_miss_detection": zenoh.ext.MissDetectionConfig(
                    heartbeat=None, sporadic_heartbeat=HEARTBEAT_PERIOD
                ),
            }
        self._publisher = zenoh.ext.declare_advanced_publisher(
            node.session,
            self.key,
            congestion_control=zenoh.CongestionControl.BLOCK,
            reliability=zenoh.Reliability.RELIABLE,
            **options,
        )
        self._token = node.session.liveliness().declare_token(self.token_key)

    def put(self, message: Any) -> int:
        """Publish a rosbags message of this publisher's type; the CDR bytes sent."""
        return self.put_cdr(self.type.encode(message))

    def put_cdr(self, data: bytes) -> int:
        """Publish CDR bytes (encapsulation header included); their count."""
        self.sequence_number += 1
        attachment = None
        if self.attach:
            attachment = encode_attachment(Attachment(self.sequence_number, time.time_ns(), self.gid))
        self._publisher.put(data, attachment=attachment)
        return len(data)

    def undeclare(self) -> None:
        self._token.undeclare()
        self._publisher.undeclare()


class RosSubscription:
    """A ROS 2 subscription of one topic: every sample on the topic's keys goes to ``callback`` as a
    :class:`Received`. With rmw_zenoh it listens on ``<domain>/<topic>/*/*``, any type, so that a sample of another
    type or type hash can be told apart (and counted) rather than missed."""

    def __init__(
        self,
        node: RosNode,
        fqn: str,
        message_type: MessageType,
        qos: QoS,
        entity_id: int,
        callback: Callable[[Received], None],
        max_bytes: int | None = None,
    ):
        graph = node.graph
        self.fqn = fqn
        self.type = message_type
        self.key = graph.topic_key(fqn, message_type.name, message_type.type_hash)
        listen = self.key if graph.mode != RMW else f"{graph.domain}/{fqn.lstrip('/')}/*/*"
        self.token_key = graph.entity_token(
            SUBSCRIPTION, entity_id, fqn, message_type.name, message_type.type_hash, qos
        )

        def on_sample(sample: zenoh.Sample) -> None:
            attachment, size = sample.attachment, len(sample.payload)
            payload = b"" if max_bytes is not None and size > max_bytes else sample.payload.to_bytes()
            callback(
                Received(
                    fqn, str(sample.key_expr), payload, None if attachment is None else attachment.to_bytes(), size
                )
            )

        self._subscriber: Any
        if qos.transient_local:
            self._subscriber = zenoh.ext.declare_advanced_subscriber(
                node.session,
                listen,
                on_sample,
                history=zenoh.ext.HistoryConfig(detect_late_publishers=True, max_samples=qos.depth),
                subscriber_detection=True,
            )
        else:
            self._subscriber = node.session.declare_subscriber(listen, on_sample)
        self._token = node.session.liveliness().declare_token(self.token_key)

    def undeclare(self) -> None:
        self._token.undeclare()
        self._subscriber.undeclare()


class RosNode:
    """posegrid's node ``name`` in namespace ``namespace`` of ROS domain ``domain`` on ``session``, meeting ROS 2 in
    ``mode`` (names.RMW or names.BRIDGE). Topic names given to :meth:`publisher` and :meth:`subscription` resolve in
    the namespace (relative) or stand as they are (absolute)."""

    def __init__(self, session: zenoh.Session, mode: str, domain: int, namespace: str, name: str = "posegrid"):
        self.session = session
        self.graph = Graph(mode, domain, namespace, name, str(session.info.zid()))
        token = self.graph.node_token()
        self._node_token = None if token is None else session.liveliness().declare_token(token)
        self._next_id = 1  # entity ids within the node (rmw_zenoh counts them per context; any unique id will do)
        self.entities: list[RosPublisher | RosSubscription] = []

    def _entity_id(self) -> int:
        self._next_id += 1
        return self._next_id - 1

    def resolve(self, topic: str) -> str:
        return resolve(topic, self.graph.namespace)

    def publisher(self, topic: str, message_type: MessageType, qos: QoS) -> RosPublisher:
        publisher = RosPublisher(self, self.resolve(topic), message_type, qos, self._entity_id())
        self.entities.append(publisher)
        return publisher

    def subscription(
        self,
        topic: str,
        message_type: MessageType,
        qos: QoS,
        callback: Callable[[Received], None],
        max_bytes: int | None = None,
    ) -> RosSubscription:
        """A subscription of ``topic``; samples larger than ``max_bytes`` reach ``callback`` without their payload."""
        subscription = RosSubscription(
            self, self.resolve(topic), message_type, qos, self._entity_id(), callback, max_bytes
        )
        self.entities.append(subscription)
        return subscription

    def close(self) -> None:
        """Undeclare every entity, then the node's token."""
        for entity in reversed(self.entities):
            entity.undeclare()
        self.entities.clear()
        if self._node_token is not None:
            self._node_token.undeclare()
            self._node_token = None
