"""Payloads decoded by their keys, the PLY layout ``save`` writes, and the checked-in message classes
against what protoc generates from proto/emr/v1/messages.proto."""

import math
import shutil
import struct
import subprocess
import tempfile
import unittest
from pathlib import Path

import numpy as np
from google.protobuf import descriptor_pb2

import reference
from emr_client import messages_pb2 as pb
from emr_client import ply
from emr_client.codec import Cloud
from emr_client.messages import MessageError, decode, placements, pose_matrix, trajectory

CLIENT = Path(__file__).resolve().parent.parent
PROTO_ROOT = CLIENT.parent.parent / "proto"


class Decode(unittest.TestCase):
    def test_a_keyframe_with_its_cloud(self):
        points = [[1000, 2000, 3000], [1001, 2002, 2999], [-5, 0, 7]]
        k = pb.Keyframe(fleet="f", robot=3, seq=17)
        k.odom_pose.tx, k.odom_pose.qw = 1.5, 1.0
        k.cloud.data = reference.encode(points, 1, intensity=[1, 2, 3])
        k.cloud.points = 3
        found = decode("emr/f/robot/3/keyframe", k.SerializeToString())
        self.assertEqual((found.topic.kind, found.topic.robot, found.message.seq), ("keyframe", 3, 17))
        np.testing.assert_array_equal(found.cloud.xyz, (np.array(points) * 1e-3).astype(np.float32))
        np.testing.assert_array_equal(found.cloud.intensity, np.array([1e-3, 2e-3, 3e-3], dtype=np.float32))
        self.assertEqual(pose_matrix(found.message.odom_pose)[0, 3], 1.5)

    def test_a_global_map_and_its_placements(self):
        g = pb.GlobalMap(fleet="f", revision=4, reference_robot=1)
        r = g.robots.add(robot=2, confidence=0.5, status=pb.MERGE_STATUS_MERGED, keyframes=9)
        half = math.sqrt(0.5)
        r.transform.tx, r.transform.qz, r.transform.qw = 2.0, half, half
        found = decode("emr/f/station/globalmap", g.SerializeToString())
        self.assertEqual(len(found.cloud), 0)
        (placed,) = placements(found.message)
        self.assertEqual(placed["status"], "MERGE_STATUS_MERGED")
        np.testing.assert_allclose(placed["transform"] @ [1, 0, 0, 1], [2, 1, 0, 1], atol=1e-12)

    def test_a_pose_graph_as_arrays(self):
        u = pb.PoseGraphUpdate(fleet="f", robot=1, revision=2)
        for seq in range(3):
            u.poses.add(seq=seq).pose.qw = 1.0
        seqs, poses = trajectory(decode("emr/f/robot/1/posegraph", u.SerializeToString()).message)
        self.assertEqual(seqs.tolist(), [0, 1, 2])
        self.assertEqual(poses.shape, (3, 4, 4))

    def test_bad_payloads_name_their_key(self):
        with self.assertRaisesRegex(MessageError, "emr/f/robot/1/keyframe"):
            decode("emr/f/robot/1/keyframe", b"\xff\xff\xff")
        k = pb.Keyframe(fleet="f")
        k.cloud.data = b"EMPC garbage"
        with self.assertRaisesRegex(MessageError, "cloud does not decode"):
            decode("emr/f/robot/1/keyframe", k.SerializeToString())
        with self.assertRaisesRegex(MessageError, "not a key of the table"):
            decode("emr/f/robot/1/alive", b"")


class Ply(unittest.TestCase):
    def test_layout_is_the_cloud_crates(self):
        cloud = Cloud(
            xyz=np.array([[1, 2, 3], [4, 5, 6]], dtype=np.float32),
            intensity=np.array([0.5, 0.25], dtype=np.float32),
            ring=np.array([7, 65535], dtype=np.uint16),
        )
        data = ply.encode(cloud)
        header, body = data.split(b"end_header\n")
        self.assertEqual(
            header.decode().splitlines(),
            [
                "ply",
                "format binary_little_endian 1.0",
                "comment written by emr_client",
                "element vertex 2",
                "property float x",
                "property float y",
                "property float z",
                "property float intensity",
                "property ushort ring",
            ],
        )
        self.assertEqual(body, struct.pack("<ffffH", 1, 2, 3, 0.5, 7) + struct.pack("<ffffH", 4, 5, 6, 0.25, 65535))


def without_json_names(file: descriptor_pb2.FileDescriptorProto) -> descriptor_pb2.FileDescriptorProto:
    """The descriptor without the JSON field names, which protoc writes into descriptor sets and
    leaves out of generated Python."""
    stack = list(file.message_type)
    while stack:
        message = stack.pop()
        for field in message.field:
            field.ClearField("json_name")
        stack.extend(message.nested_type)
    return file


class GeneratedClasses(unittest.TestCase):
    """messages_pb2.py is checked in (installing needs no protoc); it must describe exactly the
    messages of proto/emr/v1/messages.proto. Run clients/python/regenerate.sh after changing it."""

    def setUp(self):
        if shutil.which("protoc") is None:
            self.skipTest("protoc is not installed (Debian: protobuf-compiler)")

    def protoc(self, out: Path, *args):
        subprocess.run(["protoc", "-I", str(PROTO_ROOT), *args, "emr/v1/messages.proto"], cwd=out, check=True)

    def test_checked_in_file_describes_the_proto(self):
        with tempfile.TemporaryDirectory() as out:
            self.protoc(Path(out), "--descriptor_set_out=set.pb")
            generated = descriptor_pb2.FileDescriptorSet.FromString((Path(out) / "set.pb").read_bytes()).file[0]
        checked_in = descriptor_pb2.FileDescriptorProto.FromString(pb.DESCRIPTOR.serialized_pb)
        self.assertEqual(without_json_names(checked_in), without_json_names(generated), "run clients/python/regenerate.sh")

    def test_regenerating_gives_the_same_file(self):
        with tempfile.TemporaryDirectory() as out:
            self.protoc(Path(out), f"--python_out={out}")
            fresh = (Path(out) / "emr/v1/messages_pb2.py").read_text()
        version = subprocess.run(["protoc", "--version"], capture_output=True, text=True).stdout.strip()
        if version != "libprotoc 3.21.12":
            self.skipTest(f"{version} lays the file out differently from the 3.21.12 that generated it")
        self.assertEqual((CLIENT / "emr_client/messages_pb2.py").read_text(), fresh, "run clients/python/regenerate.sh")



class PlacementsJson(unittest.TestCase):
    def test_every_field_but_the_cloud_and_stamp(self):
        from emr_client.cli import placements_json

        g = pb.GlobalMap(fleet="f", revision=3, reference_robot=1, settled=True)
        r = g.robots.add(robot=1, confidence=1.0, status=pb.MERGE_STATUS_UNMERGED, keyframes=5)
        r.transform.qw = 1.0
        g.edges.add(robot_a=1, robot_b=2, inliers=40)
        out = placements_json(g)
        self.assertEqual(set(out), {f.name for f in g.DESCRIPTOR.fields} - {"cloud", "stamp"})
        self.assertEqual(out["robots"][0]["status"], "unmerged")
        self.assertEqual(out["robots"][0]["transform"], np.eye(4).tolist())
        self.assertIsNone(out["edges"][0]["transform"], "a zero quaternion is no rotation")


if __name__ == "__main__":
    unittest.main()
