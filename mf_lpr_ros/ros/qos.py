"""QoS profiles and discovery waits: every topic's profile is chosen here, for nodes, the bag
replayer and the in-process graph alike."""

from __future__ import annotations

import time
from typing import Iterable

from rclpy.qos import QoSDurabilityPolicy, QoSHistoryPolicy, QoSProfile, QoSReliabilityPolicy

# Discovery is not symmetric: a subscriber may match a writer a moment after the writer has
# matched it, and a best-effort subscription drops what arrives before.
DISCOVERY_SETTLE_S = 0.5


def sensor_qos(depth: int, reliable: bool = False) -> QoSProfile:
    """Best effort by default: it matches sensor drivers (best effort) and recorders (reliable)
    alike, but drops messages under load. Reliable loses nothing from reliable publishers
    (bag replays, most drivers) and cannot connect to best-effort ones."""
    return QoSProfile(history=QoSHistoryPolicy.KEEP_LAST, depth=depth,
                      reliability=QoSReliabilityPolicy.RELIABLE if reliable
                      else QoSReliabilityPolicy.BEST_EFFORT)


def latched_qos() -> QoSProfile:
    """Reliable and transient local with depth 1: a late subscriber still gets the last message
    (as map servers publish a map, and as nav2 expects /initialpose to be reachable)."""
    return QoSProfile(history=QoSHistoryPolicy.KEEP_LAST, depth=1,
                      reliability=QoSReliabilityPolicy.RELIABLE,
                      durability=QoSDurabilityPolicy.TRANSIENT_LOCAL)


def wait_for_subscribers(publishers: Iterable, count: int, timeout_s: float) -> bool:
    """Wait until every publisher has count subscribers, then let discovery settle; False when
    timeout_s passes first."""
    publishers = list(publishers)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if all(publisher.get_subscription_count() >= count for publisher in publishers):
            time.sleep(DISCOVERY_SETTLE_S)
            return True
        time.sleep(0.02)
    return False
