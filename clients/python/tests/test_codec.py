"""The decoder against the format: round trips through the reference encoder, both predictors,
wrapping arithmetic, and malformed input, which must raise CodecError and nothing else."""

import random
import struct
import unittest

import numpy as np
import zstandard

import reference
from emr_client import predict
from emr_client.codec import CodecError, decode_cloud, decode_quantised


def ring_scan(n, rng):
    """Quantised points of a spinning sensor in firing order (1 mm units): the scan predictor's case."""
    points = []
    for i in range(n):
        azimuth = i * 0.004
        r = 15000 + 4000 * abs(np.sin(3 * azimuth)) + rng.randint(-20, 20)
        points.append([int(r * np.cos(azimuth)), int(r * np.sin(azimuth)), -1700 + (i % 16) * 150])
    return points


class RoundTrip(unittest.TestCase):
    def setUp(self):
        self.rng = random.Random(0x5EED)

    def check(self, points, predictor, **channels):
        data = reference.encode(points, predictor, **channels)
        header, q = decode_quantised(data)
        np.testing.assert_array_equal(q["xyz"], np.array(points, dtype=np.int64).reshape(-1, 3))
        cloud = decode_cloud(data)
        expected = (np.array(points, dtype=np.float64).reshape(-1, 3) * header.step).astype(np.float32)
        np.testing.assert_array_equal(cloud.xyz, expected)
        self.assertEqual(cloud.predictor, ("delta", "scan")[predictor])
        for name, values in channels.items():
            if name in ("intensity", "ring", "time"):
                np.testing.assert_array_equal(q[name], values)
        return cloud

    def test_both_predictors_on_a_scan_with_every_channel(self):
        points = ring_scan(3000, self.rng)
        n = len(points)
        channels = dict(
            intensity=[self.rng.randint(0, 255000) for _ in range(n)],
            ring=[i % 16 for i in range(n)],
            time=[i * 3 for i in range(n)],
        )
        for predictor in (0, 1):
            cloud = self.check(points, predictor, **channels)
            self.assertEqual(cloud.ring.dtype, np.uint16)
            np.testing.assert_array_equal(cloud.time, (np.array(channels["time"]) * 1e-6).astype(np.float32))

    def test_values_that_wrap(self):
        edge = [-(2**31), 2**31 - 1, 0, -1, 1, 1 << 20, -(1 << 30)]
        points = [[x, y, z] for x in edge for y in edge for z in edge]
        for predictor in (0, 1):
            self.check(points, predictor, intensity=[2**31 - 1, -(2**31)] * (len(points) // 2) + [0])

    def test_empty_and_tiny(self):
        for n in (0, 1, 2, 3):
            for predictor in (0, 1):
                cloud = self.check([[7 * i, -3 * i, i] for i in range(n)], predictor)
                self.assertEqual(cloud.xyz.shape, (n, 3))

    def test_random_points_both_predictors(self):
        points = [[self.rng.randint(-200000, 200000) for _ in range(3)] for _ in range(2000)]
        for predictor in (0, 1):
            self.check(points, predictor)


class ScanSolver(unittest.TestCase):
    """The fast scan loop against the wrapping point-by-point reference, on residual streams no
    encoder would write (every value wraps) and on tame ones."""

    def test_fast_loop_matches_the_reference(self):
        rng = np.random.default_rng(7)
        for trial in range(12):
            n = 700
            if trial % 3 == 0:
                codes = rng.integers(0, 2**32, size=(3, n), dtype=np.uint64).astype(np.uint32)
            elif trial % 3 == 1:
                codes = rng.integers(0, 64, size=(3, n)).astype(np.uint32)
            else:
                codes = rng.integers(0, 2**20, size=(3, n)).astype(np.uint32)
            residuals = predict.unzigzag(codes)
            expected = np.zeros((n, 3), dtype=np.int64)
            predict.scan_sequential(residuals, expected, 0)
            np.testing.assert_array_equal(predict.reconstruct_scan(residuals), expected, err_msg=f"trial {trial}")

    def test_batches_join_exactly(self):
        rng = np.random.default_rng(8)
        n = predict.SCAN_BATCH + 5
        # Small residuals stay on the fast path; the second stream starts wrapping in the second batch.
        tame = rng.integers(0, 16, size=(3, n)).astype(np.uint32)
        wild = tame.copy()
        wild[:, predict.SCAN_BATCH + 2 :] = 0xFFFFFFF0
        for codes in (tame, wild):
            residuals = predict.unzigzag(codes)
            expected = np.zeros((n, 3), dtype=np.int64)
            for start in (0, predict.SCAN_BATCH // 2):
                predict.scan_sequential(residuals, expected, 0)
                partial = expected.copy()
                predict.scan_sequential(residuals, partial, start)
                np.testing.assert_array_equal(partial, expected)
            np.testing.assert_array_equal(predict.reconstruct_scan(residuals), expected)

    def test_unzigzag(self):
        codes = np.array([0, 1, 2, 3, 0xFFFFFFFE, 0xFFFFFFFF], dtype=np.uint32)
        self.assertEqual(predict.unzigzag(codes).tolist(), [0, -1, 1, -2, 2**31 - 1, -(2**31)])


def valid(n=50, predictor=0, **channels):
    rng = random.Random(n)
    return reference.encode([[rng.randint(-999, 999) for _ in range(3)] for _ in range(n)], predictor, **channels)


class MalformedInput(unittest.TestCase):
    def refuses(self, data, words, **kwargs):
        with self.assertRaises(CodecError) as caught:
            decode_cloud(data, **kwargs)
        self.assertIn(words, str(caught.exception))

    def test_header_fields(self):
        data = bytearray(valid())
        self.refuses(b"", "truncated")
        self.refuses(b"PLY\n" + bytes(data[4:]), "magic")
        for at, value, words in [(4, 2, "version 2"), (5, 0x10, "flags"), (7, 1, "reserved"), (6, 2, "predictor 2")]:
            bad = bytearray(data)
            bad[at] = value
            self.refuses(bytes(bad), words)
        for at, name in [(8, "step"), (16, "intensity_step"), (24, "time_step")]:
            for value in (0.0, -1e-3, float("nan"), float("inf"), 1e30):
                bad = bytearray(data)
                bad[at : at + 8] = struct.pack("<d", value)
                self.refuses(bytes(bad), f"invalid {name}")

    def test_point_count_limits(self):
        data = bytearray(valid())
        self.refuses(bytes(data), "limit is 10", max_points=10)
        data[32:40] = struct.pack("<Q", 2**64 - 1)
        self.refuses(bytes(data), "limit")

    def test_every_truncation(self):
        data = valid(30, 1, intensity=list(range(30)), ring=[1] * 30)
        for cut in range(len(data)):
            with self.assertRaises(CodecError, msg=f"cut at {cut}"):
                decode_cloud(data[:cut])

    def test_sections(self):
        data = valid()
        self.refuses(data + b"\0", "1 unexpected bytes")
        # The first plane of stream 0: its length at 40, its frame at 44.
        bad = bytearray(data)
        bad[44:48] = b"\0\0\0\0"
        self.refuses(bytes(bad), "not a zstd frame")
        other = zstandard.ZstdCompressor(write_checksum=True).compress(bytes(49))
        (length,) = struct.unpack_from("<I", data, 40)
        swapped = data[:40] + struct.pack("<I", len(other)) + other + data[44 + length :]
        self.refuses(swapped, "differs from the point count")
        no_size = zstandard.ZstdCompressor(write_content_size=False).compress(bytes(range(50)))
        unsized = data[:40] + struct.pack("<I", len(no_size)) + no_size + data[44 + length :]
        self.refuses(unsized, "does not declare its size")
        flipped = bytearray(data)
        flipped[44 + length - 1] ^= 0xFF
        self.refuses(bytes(flipped), "zstd failed")

    def test_rings_out_of_range(self):
        data = valid(3, ring=[70000, 0, 0])
        self.refuses(data, "ring of point 0 out of range")
        data = valid(3, ring=[5, 0, -1])
        self.refuses(data, "ring of point 2 out of range")

    def test_random_damage_raises_only_codec_errors(self):
        rng = random.Random(0xDA3A6E)
        sources = [valid(200, p, intensity=list(range(200)), ring=[3] * 200, time=list(range(200))) for p in (0, 1)]
        for trial in range(3000):
            data = bytearray(sources[trial % 2])
            for _ in range(rng.randint(1, 4)):
                data[rng.randrange(len(data))] = rng.randrange(256)
            if trial % 7 == 0:
                data = data[: rng.randrange(len(data))]
            try:
                decode_cloud(bytes(data))
            except CodecError:
                pass


if __name__ == "__main__":
    unittest.main()
