"""The ``[ros2]`` section: which ROS 2 domain, node and topic names the daemon's live topics
and ``uwbd export --ros2``'s bag use. Read without the ``ros2`` extra (check-config and the
daemon's start say what is missing before anything else starts).

Names follow ROS 2's rules (design.ros2.org, "Topic and Service name mapping"): a topic name
starting with ``/`` is absolute, ``~/x`` is private to the node (``<namespace>/<node>/x``),
anything else is relative to the namespace. An empty topic name turns that topic off. The
frame ids are the ``[robot]`` section's, as in the logs and Foxglove.
"""

from __future__ import annotations

import importlib.util
import os
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

# ROS 2 distributions whose rmw_zenoh this speaks; Humble's puts no type hash in its keys
DISTROS = ("humble", "jazzy", "kilted", "rolling")
NO_TYPE_HASH = frozenset({"humble"})
# the topics, by role: the config key of each and its default name
TOPIC_KEYS = {"pose": "pose_topic", "odom": "odom_topic", "imu": "imu_topic", "tf": "tf_topic",
              "tf_static": "tf_static_topic", "diagnostics": "diagnostics_topic"}
# the live topics a config must name to have (a bag of a log holds them by their default name):
# the IMU's, 200 messages a second, costs most of the publishers' CPU
LIVE_ONLY_WHEN_NAMED = frozenset({"imu"})
DEFAULT_TOPICS = {"pose": "uwbd/pose", "odom": "uwbd/odom", "imu": "uwbd/imu", "tf": "/tf",
                  "tf_static": "/tf_static", "diagnostics": "/diagnostics"}
MAX_DOMAIN_ID = 232  # DDS's limit, kept so a domain means the same under every middleware
TOKEN = r"[A-Za-z_][A-Za-z0-9_]*"
NODE_NAME = re.compile(TOKEN)
NAMESPACE = re.compile(rf"/?(?:{TOKEN}(?:/{TOKEN})*)?")
TOPIC_NAME = re.compile(rf"(?:~/|/)?{TOKEN}(?:/{TOKEN})*")
# what the section needs installed: the module and what it is for
EXTRA_MODULES = {"rosbags": "CDR and the type hashes", "xxhash": "rmw_zenoh's publisher ids"}
EXTRA_HINT = "pip install 'uwbd[ros2]' (from a checkout: pip install '.[ros2]')"


@dataclass(frozen=True)
class Ros2Settings:
    enabled: bool = False
    domain_id: int = 0
    namespace: str = "/"  # absolute, no trailing slash ("/" for none)
    node_name: str = "uwbd"
    distro: str = "jazzy"
    topics: dict[str, str] = field(default_factory=lambda: dict(DEFAULT_TOPICS))
    # roles off live because the config does not name them (LIVE_ONLY_WHEN_NAMED)
    unnamed: frozenset[str] = LIVE_ONLY_WHEN_NAMED
    domain_from: str = "default"  # "[ros2] domain_id", "ROS_DOMAIN_ID" or "default"

    def resolve(self, name: str) -> str:
        """The fully qualified name of a topic name."""
        if name.startswith("/"):
            return name
        if name.startswith("~/"):
            return f"{self.node_path}/{name[2:]}"
        return f"{self.namespace.rstrip('/')}/{name}"

    @property
    def node_path(self) -> str:
        """The node's fully qualified name (``/uwbd``, ``/robot1/uwbd``)."""
        return f"{self.namespace.rstrip('/')}/{self.node_name}"

    @property
    def published(self) -> dict[str, str]:
        """Role → fully qualified name, of the live topics that are on."""
        return {role: self.resolve(name) for role, name in self.topics.items()
                if name and role not in self.unnamed}

    @property
    def recorded(self) -> dict[str, str]:
        """Role → fully qualified name, of the topics a bag holds: every one not turned off
        (``""``), those off live only for want of a name included."""
        return {role: self.resolve(name) for role, name in self.topics.items() if name}


def normal_namespace(ns: str) -> str:
    return "/" + ns.strip("/")


def settings_of(section: Mapping[str, Any], env: Mapping[str, str] | None = None) -> Ros2Settings:
    """The settings a checked ``[ros2]`` table (:mod:`uwbd.config.schema`) says; the domain,
    when the table gives none, from ``ROS_DOMAIN_ID`` as a ROS 2 node takes it."""
    env = os.environ if env is None else env
    domain, domain_from = 0, "default"
    if "domain_id" in section:
        domain, domain_from = int(section["domain_id"]), "[ros2] domain_id"
    elif env.get("ROS_DOMAIN_ID", "").strip().isdigit():
        value = int(env["ROS_DOMAIN_ID"])
        if value <= MAX_DOMAIN_ID:
            domain, domain_from = value, "ROS_DOMAIN_ID"
    topics = {role: str(section.get(key, DEFAULT_TOPICS[role]))
              for role, key in TOPIC_KEYS.items()}
    return Ros2Settings(
        enabled=bool(section.get("enabled", False)), domain_id=domain,
        namespace=normal_namespace(str(section.get("namespace", "/"))),
        node_name=str(section.get("node_name", "uwbd")),
        distro=str(section.get("distro", "jazzy")), topics=topics, domain_from=domain_from,
        unnamed=frozenset(r for r in LIVE_ONLY_WHEN_NAMED if TOPIC_KEYS[r] not in section))


def missing_extra() -> str | None:
    """The first module the ``ros2`` extra brings that is not installed, or ``None``."""
    for name in EXTRA_MODULES:
        try:
            if importlib.util.find_spec(name) is None:
                return name
        except (ImportError, ValueError):
            return name
    return None
