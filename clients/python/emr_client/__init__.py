"""Python client of the EMR-FLOAM fleet: the key table, every message of proto/emr/v1/messages.proto
decoded, compressed clouds included, to numpy arrays, over Zenoh.

    from emr_client import Client
    with Client("demo", connect=["tcp/127.0.0.1:7447"]) as fleet:
        xyz = fleet.latest_global_map().cloud.xyz      # (n, 3) float32, global frame
"""

from . import keys
from .codec import Cloud, CodecError, decode_cloud, decode_quantised
from .messages import Message, MessageError, decode, placements, pose_matrix, trajectory

__version__ = "0.1.0"


def __getattr__(name):
    # The network part needs eclipse-zenoh; the decoder alone does not.
    if name in ("Client", "NoAnswer"):
        from . import client

        return getattr(client, name)
    raise AttributeError(f"module 'emr_client' has no attribute {name!r}")


__all__ = [
    "Client",
    "Cloud",
    "CodecError",
    "Message",
    "MessageError",
    "NoAnswer",
    "decode",
    "decode_cloud",
    "decode_quantised",
    "keys",
    "placements",
    "pose_matrix",
    "trajectory",
]
