"""The QoS profiles of ROS 2 that the node and the player use, and what makes two of them match.

The profiles are ROS 2's own (rmw's ``qos_profile_sensor_data`` and default profile, tf2_ros's
broadcasters, a map server's latched topic):

| profile | reliability | durability | history |
|---|---|---|---|
| :data:`SENSOR_DATA` | best effort | volatile | keep last 5 |
| :data:`DEFAULT` | reliable | volatile | keep last 10 |
| :data:`TF` | reliable | volatile | keep last 100 |
| :data:`TF_STATIC` | reliable | transient local | keep last 1 |
| :data:`LATCHED` | reliable | transient local | keep last 1 |
| :data:`LISTENER` | best effort | volatile | keep last 100 |

DDS matches a writer and a reader when what the writer offers is at least what the reader asks:
a best-effort writer does not match a reliable reader, nor a volatile one a transient-local reader
(:func:`compatible`). The node's readers therefore ask little (best effort, except ``/tf_static``,
whose last message only a transient-local reader gets), and its writers offer much (reliable).
"""

from __future__ import annotations

from dataclasses import dataclass, replace


@dataclass(frozen=True)
class QosProfile:
    """A ROS 2 QoS profile: reliability, durability and the history's depth (keep last)."""

    name: str
    reliable: bool
    transient_local: bool
    depth: int

    def with_depth(self, depth: int) -> QosProfile:
        """The same profile, its history ``depth`` deep (a reader's own buffer: no part of matching)."""
        return replace(self, depth=int(depth))

    def describe(self) -> str:
        return f"{'reliable' if self.reliable else 'best effort'}, {'transient local' if self.transient_local else 'volatile'}, keep last {self.depth}"


SENSOR_DATA = QosProfile("sensor data", reliable=False, transient_local=False, depth=5)
DEFAULT = QosProfile("default", reliable=True, transient_local=False, depth=10)
TF = QosProfile("tf", reliable=True, transient_local=False, depth=100)
TF_STATIC = QosProfile("tf_static", reliable=True, transient_local=True, depth=1)
LATCHED = QosProfile("latched", reliable=True, transient_local=True, depth=1)
LISTENER = QosProfile("listener", reliable=False, transient_local=False, depth=100)
"""A reader that matches any writer (best effort, volatile): the node's subscriptions but ``/tf_static``'s."""

# DDS's QoS policy ids (the DDS specification's table; Cyclone's dds_qos_policy_id_t), for reports
POLICY_NAMES = {
    1: "user data", 2: "durability", 3: "presentation", 4: "deadline", 5: "latency budget", 6: "ownership", 7: "ownership strength",
    8: "liveliness", 9: "time-based filter", 10: "partition", 11: "reliability", 12: "destination order", 13: "history",
    14: "resource limits", 15: "entity factory", 16: "writer data lifecycle", 17: "reader data lifecycle", 18: "topic data",
    19: "group data", 20: "transport priority", 21: "lifespan", 22: "durability service", 23: "property",
    24: "type consistency enforcement", 25: "data representation",
}


def compatible(offered: QosProfile, requested: QosProfile) -> str | None:
    """Why a writer offering ``offered`` does not match a reader requesting ``requested`` (the policy), None when they match."""
    if requested.reliable and not offered.reliable:
        return "reliability"
    if requested.transient_local and not offered.transient_local:
        return "durability"
    return None


__all__ = ["DEFAULT", "LATCHED", "LISTENER", "POLICY_NAMES", "SENSOR_DATA", "TF", "TF_STATIC", "QosProfile", "compatible"]
