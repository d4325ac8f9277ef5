"""Binary little-endian PLY, laid out as the cloud crate writes it (``emr-station save``): x, y, z
as float, then each channel present: intensity float, ring ushort, time float."""

from __future__ import annotations

import numpy as np

from .codec import Cloud


def encode(cloud: Cloud) -> bytes:
    """The PLY file's bytes."""
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    columns = [cloud.xyz[:, 0], cloud.xyz[:, 1], cloud.xyz[:, 2]]
    for name, dtype in (("intensity", "<f4"), ("ring", "<u2"), ("time", "<f4")):
        values = getattr(cloud, name)
        if values is not None:
            fields.append((name, dtype))
            columns.append(values)
    records = np.empty(len(cloud), dtype=np.dtype(fields))
    for (name, _), values in zip(fields, columns):
        records[name] = values
    header = ["ply", "format binary_little_endian 1.0", "comment written by emr_client", f"element vertex {len(cloud)}"]
    header += [f"property {'ushort' if dtype == '<u2' else 'float'} {name}" for name, dtype in fields]
    header.append("end_header\n")
    return "\n".join(header).encode("ascii") + records.tobytes()


def write(path, cloud: Cloud) -> None:
    """Writes ``cloud`` to ``path`` as binary PLY."""
    with open(path, "wb") as f:
        f.write(encode(cloud))
