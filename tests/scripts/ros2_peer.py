#!/usr/bin/env python3
"""An independent ROS 2 peer speaking rmw_zenoh's wire format (Jazzy/Kilted), written only with
`zenoh`, `rosbags`, `numpy` and `xxhash`. Rust system tests use it to check that our programs are
understood by (and understand) a ROS 2 node.

Subcommands:
  listen   discover a publisher from liveliness tokens, receive samples, check them, write JSON
  publish  play KITTI velodyne scans as sensor_msgs/msg/PointCloud2 once a subscription appears

Exit codes: 0 success, 1 timeout or error, 2 samples received but some wire check failed (the
JSON file is still written; the failed checks are printed on stderr).
"""

import argparse
import json
import math
import queue
import struct
import sys
import time
from pathlib import Path

import numpy as np
import xxhash
import zenoh
import zenoh.ext
from rosbags.typesys import Stores, get_typestore

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
QOS_RELIABLE_VOLATILE_10 = "::,10:,:,:,,"
TRANSIENT_LOCAL = "1"
ATTACHMENT_LEN = 33
GID_LEN_MARKER = 16
POINT_FIELD_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
TOKEN_FIELDS = ("prefix", "domain", "zid", "node_id", "entity_id", "kind", "enclave",
                "namespace", "node", "topic", "dds_type", "type_hash", "qos")


class PeerError(Exception):
    """A failure reported on stderr with exit code 1."""


def open_session(endpoints):
    """Opens a zenoh peer session that only connects to `endpoints` (no listening, no scouting)."""
    config = zenoh.Config()
    config.insert_json5("mode", '"peer"')
    config.insert_json5("connect/endpoints", json.dumps(endpoints))
    config.insert_json5("listen/endpoints", "[]")
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("scouting/gossip/enabled", "false")
    return zenoh.open(config)


def mangle(name):
    """Writes a ROS name as one key-expression chunk (every `/` becomes `%`)."""
    return name.replace("/", "%")


def dds_type(ros_type):
    """`pkg/msg/Name` -> `pkg::msg::dds_::Name_`."""
    package, kind, name = ros_type.split("/")
    return f"{package}::{kind}::dds_::{name}_"


def parse_token(token):
    """Splits an entity liveliness token into named, unmangled fields (None for other tokens)."""
    parts = token.split("/")
    if len(parts) != len(TOKEN_FIELDS) or parts[0] != "@ros2_lv":
        return None
    fields = dict(zip(TOKEN_FIELDS, parts))
    for name in ("namespace", "topic"):
        fields[name] = fields[name].replace("%", "/")
    return fields


def data_key(domain, topic, dds, type_hash):
    """Key expression the samples of a topic are published on."""
    return f"{domain}/{topic.lstrip('/')}/{dds}/{type_hash}"


def gid_of(token):
    """Publisher GID: XXH3-128 of its liveliness token, low 64 bits then high 64 bits, both LE."""
    return xxhash.xxh3_128_intdigest(token.encode()).to_bytes(16, "little")


def make_attachment(sequence, gid):
    """33-byte attachment: sequence i64 LE, source time ns i64 LE, length byte 16, 16-byte GID."""
    return struct.pack("<qqB", sequence, time.time_ns(), GID_LEN_MARKER) + gid


def parse_attachment(raw):
    """Decodes an attachment; fields are None when it does not have the expected length."""
    out = {"attachment_len": len(raw), "sequence": None, "source_time_ns": None,
           "gid_len_marker": None, "gid": None}
    if len(raw) == ATTACHMENT_LEN:
        out["sequence"], out["source_time_ns"], out["gid_len_marker"] = struct.unpack_from("<qqB", raw)
        out["gid"] = raw[17:].hex()
    return out


def wait_for_token(session, domain, kind, matches, timeout):
    """Watches `@ros2_lv/DOMAIN/**` (with history) until an entity token of `kind` satisfies
    `matches(fields)`; returns (token, fields) or raises PeerError listing the tokens seen."""
    tokens = queue.Queue()
    watcher = session.liveliness().declare_subscriber(
        f"@ros2_lv/{domain}/**", lambda s: tokens.put((s.kind, str(s.key_expr))), history=True)
    seen = []
    deadline = time.monotonic() + timeout
    try:
        while (left := deadline - time.monotonic()) > 0:
            try:
                sample_kind, token = tokens.get(timeout=left)
            except queue.Empty:
                break
            if sample_kind != zenoh.SampleKind.PUT:
                continue
            seen.append(token)
            fields = parse_token(token)
            if fields and fields["kind"] == kind and matches(fields):
                return token, fields
    finally:
        watcher.undeclare()
    raise PeerError(f"no {kind} token found within {timeout} s; tokens seen:\n  "
                    + "\n  ".join(seen or ["(none)"]))


def field_names(message):
    """Names of a rosbags message's fields (its dataclass also holds constants and `__msgtype__`)."""
    return [name for name, _ in TYPESTORE.fielddefs[message.__msgtype__][1]]


def to_json(value):
    """Converts a rosbags value to JSON values: dicts, lists, None for non-finite floats."""
    if hasattr(value, "__msgtype__"):
        return {name: to_json(getattr(value, name)) for name in field_names(value)}
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if isinstance(value, (list, tuple)):
        return [to_json(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def point_columns(cloud):
    """Decodes PointCloud2 data into {field name: ndarray} with a numpy structured dtype."""
    order = ">" if cloud.is_bigendian else "<"
    dtype = np.dtype({
        "names": [f.name for f in cloud.fields],
        "formats": [order + POINT_FIELD_TYPES[f.datatype] if f.count == 1
                    else (order + POINT_FIELD_TYPES[f.datatype], (f.count,)) for f in cloud.fields],
        "offsets": [f.offset for f in cloud.fields],
        "itemsize": cloud.point_step,
    })
    row_bytes = cloud.width * cloud.point_step
    rows = np.frombuffer(cloud.data, np.uint8)[:cloud.height * cloud.row_step]
    packed = rows.reshape(cloud.height, cloud.row_step)[:, :row_bytes].tobytes()
    points = np.frombuffer(packed, dtype)
    return {name: points[name] for name in dtype.names}


def message_json(message, ros_type):
    """JSON of a message; a PointCloud2 gets decoded `columns` instead of raw `data` bytes."""
    if ros_type != POINTCLOUD2:
        return to_json(message)
    out = {name: to_json(getattr(message, name)) for name in field_names(message) if name != "data"}
    out["columns"] = {name: to_json(column) for name, column in point_columns(message).items()}
    return out


def declare_entity(session, domain, node, kind, topic, ros_type, qos):
    """Declares the liveliness tokens of node `/node` (node id 0) and of its entity 1, a publisher
    (`MP`) or subscription (`MS`); returns the entity token string and the token handles (dropping
    a handle undeclares its token)."""
    prefix = f"@ros2_lv/{domain}/{session.zid()}/0"
    token = (f"{prefix}/1/{kind}/%/%/{node}/{mangle(topic)}/{dds_type(ros_type)}/"
             f"{TYPESTORE.hash_rihs01(ros_type)}/{qos}")
    liveliness = session.liveliness()
    return token, [liveliness.declare_token(f"{prefix}/0/NN/%/%/{node}"),
                   liveliness.declare_token(token)]


def subscribe(session, key, transient_local, on_sample):
    """A plain subscriber, or for a transient-local publisher an AdvancedSubscriber that also
    fetches the publisher's cache (late joiner)."""
    if not transient_local:
        return session.declare_subscriber(key, on_sample)
    return zenoh.ext.declare_advanced_subscriber(
        session, key, on_sample, history=zenoh.ext.HistoryConfig(detect_late_publishers=True),
        recovery=zenoh.ext.RecoveryConfig(heartbeat=True), subscriber_detection=True)


def collect(received, args, key, expected_gid):
    """Takes (payload, attachment) pairs from `received` until `--count` samples are kept;
    returns (samples as JSON, number skipped below --min-points)."""
    samples, skipped = [], 0
    deadline = time.monotonic() + args.timeout
    while len(samples) < args.count:
        try:
            payload, attachment = received.get(timeout=max(0.0, deadline - time.monotonic()))
        except queue.Empty:
            raise PeerError(f"timeout: {len(samples)}/{args.count} samples on {key} "
                            f"({skipped} skipped below --min-points)") from None
        message = TYPESTORE.deserialize_cdr(payload, args.type)
        if args.type == POINTCLOUD2 and message.width * message.height < args.min_points:
            skipped += 1
            continue
        entry = parse_attachment(attachment)
        entry["gid_matches_token"] = entry["gid"] == expected_gid
        entry["message"] = message_json(message, args.type)
        samples.append(entry)
    return samples, skipped


def failed_checks(result, expected_hash):
    """Descriptions of the wire checks that `result` fails."""
    failures = [] if result["type_hash_ok"] else [f"token type hash is not {expected_hash}"]
    for s in result["samples"]:
        if s["attachment_len"] != ATTACHMENT_LEN or s["gid_len_marker"] != GID_LEN_MARKER:
            failures.append(f"bad attachment (len {s['attachment_len']}, marker {s['gid_len_marker']})")
        elif not s["gid_matches_token"]:
            failures.append(f"sample gid {s['gid']} is not the one derived from the token")
    return failures


def listen(args):
    """`listen` subcommand: discover, subscribe, check and dump samples; returns the exit code."""
    dds = dds_type(args.type)
    received = queue.Queue()

    def on_sample(sample):
        attachment = sample.attachment.to_bytes() if sample.attachment is not None else b""
        received.put((sample.payload.to_bytes(), attachment))

    with open_session(args.connect) as session:
        token, fields = wait_for_token(
            session, args.domain, "MP",
            lambda f: f["dds_type"] == dds and (f["topic"] == args.topic
                                                 or f["topic"].endswith("/" + args.topic)),
            args.timeout)
        print(f"found publisher token {token}", file=sys.stderr)
        key = data_key(args.domain, fields["topic"], fields["dds_type"], fields["type_hash"])
        transient_local = fields["qos"].split(":")[1] == TRANSIENT_LOCAL
        alive = [subscribe(session, key, transient_local, on_sample)]
        if args.declare_subscription:
            sub_token, tokens = declare_entity(session, args.domain, "peer_listener", "MS",
                                               fields["topic"], args.type, fields["qos"])
            alive += tokens
            print(f"declared subscription token {sub_token}", file=sys.stderr)
        samples, skipped = collect(received, args, key, gid_of(token).hex())

    expected_hash = TYPESTORE.hash_rihs01(args.type)
    result = {"key": key, "token": token, "qos": fields["qos"], "transient_local": transient_local,
              "type_hash_ok": fields["type_hash"] == expected_hash, "skipped": skipped,
              "samples": samples}
    Path(args.out).write_text(json.dumps(result))
    failures = failed_checks(result, expected_hash)
    for failure in failures:
        print(f"FAIL: {failure}", file=sys.stderr)
    print(f"received {len(samples)} samples on {key} -> {args.out}", file=sys.stderr)
    return 2 if failures else 0


def kitti_scans(directory):
    """Sorted KITTI velodyne scan files of `directory` (or of its `velodyne/` subfolder)."""
    root = Path(directory)
    scans = sorted((root / "velodyne").glob("*.bin")) or sorted(root.glob("*.bin"))
    if not scans:
        raise PeerError(f"no *.bin scans in {root} or {root / 'velodyne'}")
    return scans


def kitti_stamps(directory, count):
    """The scans' times in seconds: KITTI's `times.txt` beside the scans, else 0.1 s apart."""
    times = Path(directory) / "times.txt"
    if times.is_file():
        return [float(line) for line in times.read_text().split()[:count]]
    return [index * 0.1 for index in range(count)]


def kitti_cloud(path, stamp):
    """PointCloud2 of one KITTI scan (x, y, z, intensity float32), stamped `stamp` seconds."""
    data = np.fromfile(path, dtype=np.uint8)
    types = TYPESTORE.types
    sec = int(stamp)
    return types[POINTCLOUD2](
        header=types["std_msgs/msg/Header"](
            stamp=types["builtin_interfaces/msg/Time"](sec=sec, nanosec=round((stamp - sec) * 1e9)),
            frame_id="velodyne"),
        height=1, width=len(data) // 16,
        fields=[types["sensor_msgs/msg/PointField"](name=name, offset=4 * i, datatype=7, count=1)
                for i, name in enumerate(("x", "y", "z", "intensity"))],
        is_bigendian=False, point_step=16, row_step=len(data), data=data, is_dense=True)


def publish(args):
    """`publish` subcommand: announce a publisher, wait for a subscription, send KITTI scans."""
    scans = kitti_scans(args.kitti)[:args.frames]
    topic = "/" + args.topic.lstrip("/")
    key = data_key(args.domain, topic, dds_type(POINTCLOUD2), TYPESTORE.hash_rihs01(POINTCLOUD2))
    with open_session(args.connect) as session:
        pub_token, alive = declare_entity(session, args.domain, "kitti_player", "MP", topic,
                                          POINTCLOUD2, QOS_RELIABLE_VOLATILE_10)
        publisher = session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK,
                                              reliability=zenoh.Reliability.RELIABLE)
        print(f"declared publisher token {pub_token}", file=sys.stderr)
        sub_token, _ = wait_for_token(
            session, args.domain, "MS",
            lambda f: f["topic"] == topic and f["dds_type"] == dds_type(POINTCLOUD2),
            args.wait_subscriber_timeout)
        print(f"found subscription token {sub_token}", file=sys.stderr)
        gid = gid_of(pub_token)
        stamps = kitti_stamps(args.kitti, len(scans))
        start = time.monotonic()
        for index, path in enumerate(scans):
            time.sleep(max(0.0, start + index / args.rate - time.monotonic()))
            payload = TYPESTORE.serialize_cdr(kitti_cloud(path, stamps[index]), POINTCLOUD2)
            publisher.put(bytes(payload), attachment=make_attachment(index + 1, gid))
        time.sleep(1.0)
    print(f"sent {len(scans)} PointCloud2 scans on {key}")
    return 0


def parse_args():
    """Command line of both subcommands."""
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = parser.add_subparsers(dest="command", required=True)
    for name in ("listen", "publish"):
        sub = commands.add_parser(name)
        sub.add_argument("--connect", action="append", required=True,
                         help="zenoh endpoint to connect to, e.g. tcp/127.0.0.1:7447 (repeatable)")
        sub.add_argument("--domain", type=int, default=0, help="ROS domain id")
    listen_cmd = commands.choices["listen"]
    listen_cmd.add_argument("--type", required=True, help="ROS type, e.g. sensor_msgs/msg/PointCloud2")
    listen_cmd.add_argument("--topic", required=True, help="full topic or a suffix after a '/'")
    listen_cmd.add_argument("--count", type=int, default=1, help="samples to collect")
    listen_cmd.add_argument("--timeout", type=float, default=60, help="seconds for discovery, then for the samples")
    listen_cmd.add_argument("--out", required=True, help="JSON file to write")
    listen_cmd.add_argument("--min-points", type=int, default=0,
                            help="PointCloud2: skip samples with fewer points")
    listen_cmd.add_argument("--declare-subscription", action="store_true",
                            help="declare an MS liveliness token (node /peer_listener) for the topic")
    publish_cmd = commands.choices["publish"]
    publish_cmd.add_argument("--topic", default="/points", help="topic name (made absolute)")
    publish_cmd.add_argument("--kitti", required=True, help="KITTI sequence or velodyne directory")
    publish_cmd.add_argument("--frames", type=int, default=None, help="number of scans to send")
    publish_cmd.add_argument("--rate", type=float, default=2.0, help="scans per second")
    publish_cmd.add_argument("--wait-subscriber-timeout", type=float, default=60,
                             help="seconds to wait for a subscription token")
    return parser.parse_args()


def main():
    """Runs the chosen subcommand and maps PeerError to exit code 1."""
    args = parse_args()
    try:
        return listen(args) if args.command == "listen" else publish(args)
    except PeerError as error:
        print(f"error: {error}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
