"""``python -m emr_client save | watch | keys``: the Python counterparts of ``emr-station save``,
``emr-station watch`` and ``emr-station keys``."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from . import keys, ply
from .messages import MessageError, status_name


def main(argv=None) -> int:
    """Runs one command; returns the exit status (errors are one line on stderr, status 1)."""
    args = _parser().parse_args(argv)
    try:
        return args.run(args)
    except (MessageError, ValueError, RuntimeError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130
    except Exception as e:
        # zenoh's own errors (an endpoint it cannot parse, a configuration file it refuses).
        if type(e).__module__.startswith("zenoh"):
            print(f"error: zenoh: {e}", file=sys.stderr)
            return 1
        raise


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m emr_client", description=__doc__.split("\n")[0])
    commands = parser.add_subparsers(required=True, metavar="COMMAND")

    save = commands.add_parser("save", help="fetch the fleet's latest global map and write it as binary PLY")
    _network(save)
    save.add_argument("--fleet", required=True, help="fleet name")
    save.add_argument("--out", required=True, type=Path, help="the .ply file to write")
    save.add_argument("--transforms", type=Path, help="also write the placements as JSON, as emr-station save does")
    save.add_argument("--timeout-s", type=float, default=10.0, help="how long to wait for the station (default 10)")
    save.set_defaults(run=_save)

    watch = commands.add_parser("watch", help="print every message on the fleet's keys, decoded, one line each")
    _network(watch)
    watch.add_argument("--fleet", required=True, help="fleet name")
    watch.add_argument("--count", type=int, help="stop after this many messages")
    watch.add_argument("--duration-s", type=float, help="stop after this many seconds")
    watch.add_argument("--json", action="store_true", help="one JSON object per line")
    watch.set_defaults(run=_watch)

    table = commands.add_parser("keys", help="print the key expressions of a fleet")
    table.add_argument("--fleet", default="demo", help="fleet name (default demo)")
    table.add_argument("--robot", type=int, default=1, help="robot id in the per-robot keys (default 1)")
    table.set_defaults(run=_keys)
    return parser


def _network(parser: argparse.ArgumentParser) -> None:
    """The session options of the Rust tools: loopback endpoints, or a zenoh configuration file."""
    group = parser.add_mutually_exclusive_group()
    group.add_argument(
        "--connect",
        action="append",
        metavar="ENDPOINT",
        help="endpoint to connect to, e.g. tcp/127.0.0.1:7447 (repeatable; the default)",
    )
    group.add_argument("--zenoh", metavar="FILE", help="zenoh JSON5 configuration (client mode, a router, mTLS)")


def _client(args):
    from .client import DEFAULT_ENDPOINT, Client

    return Client(args.fleet, connect=args.connect or [DEFAULT_ENDPOINT], config_file=args.zenoh)


def _save(args) -> int:
    if args.out.suffix.lower() != ".ply":
        raise ValueError(f"--out {args.out}: only .ply is written (emr-station save also writes .pcd and .bin)")
    with _client(args) as fleet:
        found = fleet.latest_global_map(timeout=args.timeout_s)
    ply.write(args.out, found.cloud)
    m = found.message
    print(f"global map revision {m.revision} of fleet {args.fleet}: {len(found.cloud)} points in {args.out}")
    if args.transforms:
        args.transforms.write_text(json.dumps(placements_json(m), indent=2) + "\n")
    return 0


def placements_json(global_map) -> dict:
    """The placements as ``emr-station save --transforms`` writes them: the map's fields but its
    cloud and stamp, each robot's and edge's fields, poses as 4x4 row-major matrices and statuses
    by short name. Built from the message's descriptor, so that fields added to the .proto appear
    here as they do on the Rust side."""
    skip = {"cloud", "stamp"}
    return {f.name: _json_value(global_map, f) for f in global_map.DESCRIPTOR.fields if f.name not in skip}


_SHORT_STATUS = {"MERGE_STATUS_MERGED": "merged", "MERGE_STATUS_UNMERGED": "unmerged"}


def _json_value(message, field):
    """One field as JSON: nested messages as objects, poses as matrices, the status by name."""
    from .messages import pose_matrix

    value = getattr(message, field.name)
    if field.message_type is not None and field.message_type.name == "Pose":
        try:
            return pose_matrix(value).tolist()
        except MessageError:
            return None  # as emr-station writes a pose that is no rotation
    if field.enum_type is not None and field.enum_type.name == "MergeStatus":
        return _SHORT_STATUS.get(status_name(value), "unspecified")
    # ``is_repeated`` in protobuf 5.29 and later, ``label`` before (removed in 7).
    repeated = field.is_repeated if hasattr(field, "is_repeated") else field.label == field.LABEL_REPEATED
    if repeated:
        if field.message_type is not None:
            return [{f.name: _json_value(item, f) for f in item.DESCRIPTOR.fields} for item in value]
        return list(value)
    return value


def _watch(args) -> int:
    with _client(args) as fleet:
        for found in fleet.subscribe(duration=args.duration_s, count=args.count):
            fields = summary(found)
            print(json.dumps(fields) if args.json else " ".join(f"{k}={v}" for k, v in fields.items()), flush=True)
    return 0


def summary(found) -> dict:
    """A few fields of a decoded message, for one line of ``watch``."""
    if isinstance(found, MessageError):
        return {"malformed": str(found)}
    out = {"key": found.key, "type": found.topic.kind}
    m = found.message
    if found.topic.kind == "alive":
        out["alive"] = m
    elif found.topic.kind == "keyframe":
        out |= {"robot": m.robot, "seq": m.seq, "points": len(found.cloud)}
    elif found.topic.kind == "posegraph":
        out |= {"robot": m.robot, "revision": m.revision, "poses": len(m.poses), "loops": len(m.loops)}
    elif found.topic.kind == "globalmap":
        robots = [f"{r.robot}:{status_name(r.status)}:{r.confidence:.3f}" for r in m.robots]
        out |= {"revision": m.revision, "robots": robots, "points": len(found.cloud), "settled": m.settled}
    elif found.topic.kind == "status":
        out |= {"robots": list(m.robots), "keyframes": m.keyframes, "revision": m.global_map_revision}
    return out


def _keys(args) -> int:
    fleet, robot = args.fleet, args.robot
    for kind, (pattern, payload, publisher) in keys.TABLE.items():
        key = pattern.format(fleet=keys.check_fleet(fleet), robot=robot)
        print(f"{key:<40} {payload:<42} {publisher}")
    return 0

