"""Reads an MCAP file with the reference Python readers (`mcap`, `protobuf`) and prints, as JSON,
per topic: message count, encodings, schema name, and a summary of its last message decoded from
the schema the file carries (no Foxglove package needed). Used by tests/tests/live_recording.rs."""

import json
import struct
import sys

from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from mcap.reader import make_reader


def message_class(schema):
    files = descriptor_pb2.FileDescriptorSet.FromString(schema.data)
    pool = descriptor_pool.DescriptorPool()
    for f in files.file:
        pool.Add(f)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(schema.name))


def point_cloud(msg):
    offsets = {f.name: f.offset for f in msg.fields}
    n = len(msg.data) // msg.point_stride if msg.point_stride else 0
    out = {"frame_id": msg.frame_id, "points": n, "fields": sorted(offsets)}
    if "robot" in offsets:
        counts = {}
        for i in range(n):
            (robot,) = struct.unpack_from("<I", msg.data, i * msg.point_stride + offsets["robot"])
            counts[robot] = counts.get(robot, 0) + 1
        out["robots"] = {str(k): v for k, v in sorted(counts.items())}
    return out


def summarize(name, msg):
    if name == "foxglove.PointCloud":
        return point_cloud(msg)
    if name == "foxglove.FrameTransforms":
        return {"frames": [[t.parent_frame_id, t.child_frame_id] for t in msg.transforms]}
    if name == "foxglove.PosesInFrame":
        return {"frame_id": msg.frame_id, "poses": len(msg.poses)}
    if name == "foxglove.SceneUpdate":
        return {"entities": [{"id": e.id, "frame_id": e.frame_id, "points": sum(len(l.points) for l in e.lines)}
                             for e in msg.entities]}
    return {}


def main(path):
    topics, last = {}, {}
    with open(path, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages():
            t = topics.setdefault(channel.topic, {
                "count": 0,
                "message_encoding": channel.message_encoding,
                "schema": schema.name if schema else None,
                "schema_encoding": schema.encoding if schema else None,
            })
            t["count"] += 1
            last[channel.topic] = (schema, message.data)
    for topic, (schema, data) in last.items():
        if topics[topic]["message_encoding"] == "json":
            topics[topic]["last"] = json.loads(data)
        elif schema is not None and schema.encoding == "protobuf":
            msg = message_class(schema)()
            msg.ParseFromString(data)
            topics[topic]["last"] = summarize(schema.name, msg)
    print(json.dumps(topics))


if __name__ == "__main__":
    main(sys.argv[1])
