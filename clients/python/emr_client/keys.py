"""The Zenoh key-expression scheme (README: key expressions; proto/src/keyexpr.rs), in Python.

Every topic of a fleet lives under ``emr/{fleet}/``. ``parse`` accepts exactly the keys the Rust
side accepts, so a subscriber here and there agree on what belongs to the scheme.
"""

from __future__ import annotations

import dataclasses
import re
from typing import Optional

_FLEET = re.compile(r"[A-Za-z0-9_-]{1,64}")

# kind -> (key pattern, payload message, who publishes); ``{fleet}`` and ``{robot}`` filled in.
TABLE = {
    "keyframe": ("emr/{fleet}/robot/{robot}/keyframe", "Keyframe", "edge, one per keyframe"),
    "posegraph": ("emr/{fleet}/robot/{robot}/posegraph", "PoseGraphUpdate", "edge, after each optimisation"),
    "keyframes": ("emr/{fleet}/robot/{robot}/keyframes", "queryable: KeyframeRequest -> Keyframe", "edge"),
    "alive": ("emr/{fleet}/robot/{robot}/alive", "liveliness token", "edge"),
    "globalmap": ("emr/{fleet}/station/globalmap", "GlobalMap (also a queryable)", "station"),
    "status": ("emr/{fleet}/station/status", "StationStatus", "station, periodically"),
}


def check_fleet(fleet: str) -> str:
    """The fleet name, if it is one plain key chunk: 1-64 ASCII letters, digits, '-' and '_'."""
    if not isinstance(fleet, str) or not _FLEET.fullmatch(fleet):
        raise ValueError(f"invalid fleet name {fleet!r}: 1-64 ASCII letters, digits, '-' and '_' only")
    return fleet


def check_robot(robot: int) -> int:
    """The robot id, if it is a u32."""
    if isinstance(robot, bool) or not isinstance(robot, int) or not 0 <= robot < 2**32:
        raise ValueError(f"invalid robot id {robot!r}: an integer in 0..2^32")
    return robot


def keyframe(fleet: str, robot: int) -> str:
    """One robot's keyframes."""
    return f"emr/{check_fleet(fleet)}/robot/{check_robot(robot)}/keyframe"


def posegraph(fleet: str, robot: int) -> str:
    """One robot's pose-graph updates."""
    return f"emr/{check_fleet(fleet)}/robot/{check_robot(robot)}/posegraph"


def keyframe_store(fleet: str, robot: int) -> str:
    """One robot's keyframe queryable (backfill)."""
    return f"emr/{check_fleet(fleet)}/robot/{check_robot(robot)}/keyframes"


def alive(fleet: str, robot: int) -> str:
    """One robot's liveliness token."""
    return f"emr/{check_fleet(fleet)}/robot/{check_robot(robot)}/alive"


def global_map(fleet: str) -> str:
    """The fleet's global map: publications and the queryable for the latest."""
    return f"emr/{check_fleet(fleet)}/station/globalmap"


def station_status(fleet: str) -> str:
    """The station's periodic status."""
    return f"emr/{check_fleet(fleet)}/station/status"


def all_robots(fleet: str) -> str:
    """Every robot topic of the fleet (keyframes and pose graphs of all robots)."""
    return f"emr/{check_fleet(fleet)}/robot/*/*"


def all_alive(fleet: str) -> str:
    """Every robot's liveliness token."""
    return f"emr/{check_fleet(fleet)}/robot/*/alive"


def everything(fleet: str) -> str:
    """Every key of the fleet: what ``Client.subscribe`` listens to."""
    return f"emr/{check_fleet(fleet)}/**"


@dataclasses.dataclass(frozen=True)
class Topic:
    """A parsed key: its ``kind`` (a key of ``TABLE``), fleet, and robot id (None for station keys)."""

    kind: str
    fleet: str
    robot: Optional[int] = None


def parse(key: str) -> Optional[Topic]:
    """The topic of a concrete key, or None for anything outside the scheme (robot ids must be
    canonical decimal u32: no sign, no leading zero, so that one robot has one key)."""
    parts = str(key).split("/")
    if len(parts) < 4 or parts[0] != "emr" or not _FLEET.fullmatch(parts[1]):
        return None
    fleet = parts[1]
    if len(parts) == 5 and parts[2] == "robot" and parts[4] in ("keyframe", "posegraph", "keyframes", "alive"):
        robot = _robot_id(parts[3])
        return None if robot is None else Topic(parts[4], fleet, robot)
    if len(parts) == 4 and parts[2] == "station" and parts[3] in ("globalmap", "status"):
        return Topic(parts[3], fleet)
    return None


def _robot_id(text: str) -> Optional[int]:
    """A canonical decimal u32, or None."""
    if not text.isascii() or not text.isdigit() or str(int(text)) != text:
        return None
    value = int(text)
    return value if value < 2**32 else None
