"""A Zenoh session on a fleet's keys: subscribe to everything, fetch the latest global map, ask a
robot for keyframes.

Without a configuration file the session is what the Rust tools open (bus crate): a peer that
connects to the given ``tcp/127.0.0.1:PORT`` endpoints, listens on nothing and never scouts, so
nothing leaves the machine. A zenoh JSON5 file (client mode, a router, mutual TLS) replaces all of
that, as ``--zenoh FILE`` does for the Rust binaries.
"""

from __future__ import annotations

import json
import queue
import time
from typing import Iterator, Optional, Sequence

from . import keys, messages_pb2 as pb
from .messages import Message, MessageError, decode

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"


class NoAnswer(RuntimeError):
    """Nobody answered a query in time, or the station has nothing to answer with yet."""


def zenoh_config(connect: Sequence[str] = (DEFAULT_ENDPOINT,), config_file: Optional[str] = None):
    """The session's configuration: ``config_file`` as given, else a loopback peer connecting to
    ``connect`` with scouting off."""
    import zenoh

    if config_file is not None:
        return zenoh.Config.from_file(str(config_file))
    config = zenoh.Config()
    config.insert_json5("mode", '"peer"')
    config.insert_json5("connect/endpoints", json.dumps(list(connect)))
    config.insert_json5("listen/endpoints", "[]")
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("scouting/gossip/enabled", "false")
    return config


class Client:
    """One fleet seen over one zenoh session; close it (or use ``with``) when done."""

    def __init__(self, fleet: str, connect: Sequence[str] = (DEFAULT_ENDPOINT,), config_file: Optional[str] = None):
        import zenoh

        self.fleet = keys.check_fleet(fleet)
        self.session = zenoh.open(zenoh_config(connect, config_file))

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Closes the session."""
        self.session.close()

    def latest_global_map(self, timeout: float = 10.0, clouds: bool = True) -> Message:
        """The station's latest ``GlobalMap`` from its queryable, cloud decoded."""
        key = keys.global_map(self.fleet)
        refused = False
        for reply in self.session.get(key, timeout=timeout):
            if reply.ok is None:
                refused = True
                continue
            return decode(str(reply.ok.key_expr), reply.ok.payload.to_bytes(), clouds=clouds)
        if refused:
            raise NoAnswer(f"the station on {key} has no global map yet")
        raise NoAnswer(f"no station answered on {key} within {timeout} s")

    def keyframes(
        self,
        robot: int,
        seqs: Sequence[int] = (),
        from_seq: Optional[int] = None,
        limit: Optional[int] = None,
        timeout: float = 10.0,
    ) -> list:
        """Asks a robot's keyframe store (the backfill queryable) for keyframes; returns the
        decoded replies, lowest sequence number first."""
        request = pb.KeyframeRequest(seqs=list(seqs))
        if from_seq is not None:
            request.from_seq = from_seq
        if limit is not None:
            request.limit = limit
        import zenoh

        key = keys.keyframe_store(self.fleet, robot)
        # Every reply is a distinct keyframe on the same key: zenoh's default consolidation would
        # keep only one of them.
        replies = self.session.get(
            key,
            payload=request.SerializeToString(),
            consolidation=zenoh.ConsolidationMode.NONE,
            timeout=timeout,
        )
        found = [decode(key, r.ok.payload.to_bytes()) for r in replies if r.ok is not None]
        return sorted(found, key=lambda m: m.message.seq)

    def alive(self, timeout: float = 2.0) -> list:
        """Ids of the robots whose liveliness token is up."""
        replies = self.session.liveliness().get(keys.all_alive(self.fleet), timeout=timeout)
        topics = [keys.parse(str(r.ok.key_expr)) for r in replies if r.ok is not None]
        return sorted({t.robot for t in topics if t is not None})

    def subscribe(
        self, duration: Optional[float] = None, count: Optional[int] = None, clouds: bool = True
    ) -> Iterator[Message]:
        """Every sample on the fleet's keys, decoded, as it arrives: keyframes, pose graphs, global
        maps, station status, and robots' liveliness (a ``Message`` whose ``message`` is True when
        the robot appears and False when it goes). Stops after ``duration`` seconds or ``count``
        messages, if given. A payload that does not decode is yielded as a ``MessageError`` rather
        than raised, so that one bad sender does not end the stream."""
        inbox: queue.Queue = queue.Queue()
        put = lambda sample: inbox.put(sample)  # noqa: E731
        subscribers = [
            self.session.declare_subscriber(keys.everything(self.fleet), put),
            self.session.liveliness().declare_subscriber(keys.all_alive(self.fleet), put, history=True),
        ]
        deadline = None if duration is None else time.monotonic() + duration
        seen = 0
        try:
            while count is None or seen < count:
                wait = None if deadline is None else deadline - time.monotonic()
                if wait is not None and wait <= 0:
                    return
                try:
                    sample = inbox.get(timeout=wait)
                except queue.Empty:
                    return
                yield self._decoded(sample, clouds)
                seen += 1
        finally:
            for subscriber in subscribers:
                subscriber.undeclare()

    @staticmethod
    def _decoded(sample, clouds: bool):
        """A received sample decoded by its key; liveliness samples become True / False."""
        import zenoh

        key = str(sample.key_expr)
        topic = keys.parse(key)
        if topic is not None and topic.kind == "alive":
            return Message(key=key, topic=topic, message=sample.kind == zenoh.SampleKind.PUT)
        try:
            return decode(key, sample.payload.to_bytes(), clouds=clouds)
        except MessageError as e:
            return e
