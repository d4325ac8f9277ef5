"""The key table as proto/src/keyexpr.rs has it: the same keys, the same keys refused."""

import unittest

from emr_client import keys
from emr_client.keys import Topic


class Keys(unittest.TestCase):
    def test_keys_follow_the_table(self):
        f = "warehouse-1"
        self.assertEqual(keys.keyframe(f, 3), "emr/warehouse-1/robot/3/keyframe")
        self.assertEqual(keys.posegraph(f, 3), "emr/warehouse-1/robot/3/posegraph")
        self.assertEqual(keys.keyframe_store(f, 3), "emr/warehouse-1/robot/3/keyframes")
        self.assertEqual(keys.alive(f, 3), "emr/warehouse-1/robot/3/alive")
        self.assertEqual(keys.global_map(f), "emr/warehouse-1/station/globalmap")
        self.assertEqual(keys.station_status(f), "emr/warehouse-1/station/status")
        self.assertEqual(keys.all_robots(f), "emr/warehouse-1/robot/*/*")
        self.assertEqual(keys.all_alive(f), "emr/warehouse-1/robot/*/alive")

    def test_every_topic_parses_back(self):
        f = "warehouse-1"
        for key, topic in [
            (keys.keyframe(f, 0), Topic("keyframe", f, 0)),
            (keys.posegraph(f, 7), Topic("posegraph", f, 7)),
            (keys.keyframe_store(f, 4_000_000_000), Topic("keyframes", f, 4_000_000_000)),
            (keys.alive(f, 1), Topic("alive", f, 1)),
            (keys.global_map(f), Topic("globalmap", f)),
            (keys.station_status(f), Topic("status", f)),
        ]:
            self.assertEqual(keys.parse(key), topic, key)

    def test_foreign_keys_do_not_parse(self):
        for key in [
            "",
            "emr",
            "emr/f/robot/1",
            "emr/f/robot/x/keyframe",
            "emr/f/robot/01/keyframe",
            "emr/f/robot/-1/keyframe",
            "emr/f/robot/+1/keyframe",
            "emr/f/robot/1/keyframe/extra",
            "emr/f/robot/1/other",
            "emr/f/station/other",
            "emr/*/station/status",
            "other/f/station/status",
            "emr/f/robot/99999999999/keyframe",
        ]:
            self.assertIsNone(keys.parse(key), key)

    def test_fleet_names_cannot_smuggle_wildcards(self):
        for bad in ["", "a/b", "*", "**", "a$b", "a?", "a#", "é", "x" * 65]:
            with self.assertRaises(ValueError, msg=bad):
                keys.global_map(bad)
        self.assertEqual(keys.check_fleet("Fleet_2-b"), "Fleet_2-b")
        for bad in (-1, 2**32, 1.5, True):
            with self.assertRaises(ValueError, msg=repr(bad)):
                keys.keyframe("f", bad)


if __name__ == "__main__":
    unittest.main()
