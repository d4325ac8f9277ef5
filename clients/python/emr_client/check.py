"""``python -m emr_client.check DIR``: decodes every ``*.emp`` file in DIR (an encoded cloud, as
the Rust encoder wrote it) and writes what came out beside it, for the Rust test that compares.

For ``NAME.emp`` it writes ``NAME.decoded``: the decoded values, little-endian, xyz as f32 (x y z
per point), then each channel present: intensity f32, ring u16, time f32. Input the decoder refuses
gives ``NAME.error`` with the message instead. One JSON line per file goes to stdout: name, points,
predictor, channels, best decode time in milliseconds over ``--repeat`` runs (or the error).
Anything but a ``CodecError`` is a bug and ends the run with a traceback.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from .codec import Cloud, CodecError, decode_cloud


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m emr_client.check", description=__doc__.split("\n")[0])
    parser.add_argument("dir", type=Path, help="directory of .emp files")
    parser.add_argument("--repeat", type=int, default=1, help="decode each file this many times, report the best")
    args = parser.parse_args(argv)
    files = sorted(args.dir.glob("*.emp"))
    if not files:
        print(f"error: no .emp file in {args.dir}", file=sys.stderr)
        return 1
    for path in files:
        print(json.dumps(check(path, max(1, args.repeat))), flush=True)
    return 0


def check(path: Path, repeat: int) -> dict:
    """Decodes one file, writes its result beside it, returns its JSON line."""
    data = path.read_bytes()
    best = float("inf")
    try:
        for _ in range(repeat):
            start = time.perf_counter()
            cloud = decode_cloud(data)
            best = min(best, time.perf_counter() - start)
    except CodecError as e:
        path.with_suffix(".error").write_text(str(e))
        return {"file": path.name, "error": str(e)}
    path.with_suffix(".decoded").write_bytes(raw(cloud))
    channels = [c for c in ("intensity", "ring", "time") if getattr(cloud, c) is not None]
    return {"file": path.name, "points": len(cloud), "predictor": cloud.predictor, "channels": channels, "ms": best * 1e3}


def raw(cloud: Cloud) -> bytes:
    """The decoded values in the layout the module doc describes."""
    parts = [cloud.xyz.astype("<f4").tobytes()]
    for name, dtype in (("intensity", "<f4"), ("ring", "<u2"), ("time", "<f4")):
        values = getattr(cloud, name)
        if values is not None:
            parts.append(np.asarray(values).astype(dtype).tobytes())
    return b"".join(parts)


if __name__ == "__main__":
    sys.exit(main())
