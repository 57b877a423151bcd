"""Single-file ROS 2 MCAP bags: an atomic, interrupt-safe writer and a stamp-ordered reader.

A ROS 2 bag is normally a folder (``metadata.yaml`` + ``*.mcap``). Our tools write **one file,
``OUT.mcap``**: ``rosbags.rosbag2.Writer`` (format version 9, storage ``mcap``, ``ros2msg``
schemas from the Jazzy type store, CDR messages) writes into a hidden temporary folder next to
the output, ``.OUT.mcap.partial-<pid>/OUT/OUT.mcap``, and only a complete file is renamed to
``OUT.mcap`` (the folder's ``metadata.yaml`` is dropped: the MCAP file carries the same
``rosbag2`` metadata record inside). ``ros2 bag play OUT.mcap``, ``ros2 bag info OUT.mcap``,
Foxglove, ``rosbags`` (``AnyReader`` / ``rosbag2.Reader``) and the plain ``mcap`` reader all open it.

On an error, Ctrl-C or SIGTERM the temporary folder is deleted; after a SIGKILL it stays behind
under its clearly temporary name and the next writer of the same output deletes it.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Iterable, Iterator
from contextlib import suppress
from pathlib import Path
from typing import Any

from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import Reader, StoragePlugin, Writer

from vlocnetpp_core.bag import messages
from vlocnetpp_core.errors import DataError, UserError
from vlocnetpp_core.outputs import refuse_existing, remove_stale_temps, temp_dir_for

ROSBAG2_VERSION = 9


_LATCHED_QOS = Qos(
    QosHistory.KEEP_LAST,
    1,
    QosReliability.RELIABLE,
    QosDurability.TRANSIENT_LOCAL,
    QosTime(0, 0),
    QosTime(0, 0),
    QosLiveliness.AUTOMATIC,
    QosTime(0, 0),
    False,
)


class BagWriter:
    """Context manager writing a single-file ROS 2 Jazzy MCAP bag at ``path`` (ends in ``.mcap``).

    ``path`` must not exist unless ``force``; it appears only when the block ends without an
    exception (then atomically replacing any old file). Use :meth:`add_topic` then :meth:`write`
    (a ``rosbags`` message) or :meth:`write_raw` (CDR bytes); times are integer nanoseconds.
    """

    def __init__(self, path: str | Path, force: bool = False):
        self.path = Path(path)
        if self.path.suffix != ".mcap":
            raise UserError(f"{self.path}: the output bag must be a file ending in .mcap")
        if self.path.is_dir():
            raise UserError(f"{self.path}: is a folder; give a file name ending in .mcap")
        refuse_existing(self.path, force)
        self.tmp = temp_dir_for(self.path)
        self._writer: Writer | None = None
        self._connections: dict[str, Any] = {}
        self.counts: dict[str, int] = {}

    def __enter__(self) -> BagWriter:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        remove_stale_temps(self.path)
        self.tmp.mkdir()
        try:
            self._writer = Writer(self.tmp / self.path.stem, version=ROSBAG2_VERSION, storage_plugin=StoragePlugin.MCAP)
            self._writer.open()
        except BaseException:
            shutil.rmtree(self.tmp, ignore_errors=True)
            raise
        return self

    def add_topic(
        self, topic: str, msgtype: str, msgdef: str | None = None, digest: str | None = None, latched: bool = False
    ) -> None:
        """Declare ``topic`` of ``msgtype`` (e.g. ``sensor_msgs/msg/Image``). Types outside the Jazzy
        store need their ``msgdef`` text and RIHS01 ``digest`` (as read from another bag). ``latched``:
        offered as reliable, transient-local, depth 1 (as tf2's static broadcaster does), so that
        ``ros2 bag play`` republishes it for late subscribers such as tf2's ``/tf_static`` listener."""
        assert self._writer is not None, "use BagWriter as a context manager"
        qos = [_LATCHED_QOS] if latched else []
        if msgtype in messages.TYPESTORE.types:
            conn = self._writer.add_connection(topic, msgtype, typestore=messages.TYPESTORE, offered_qos_profiles=qos)
        else:
            conn = self._writer.add_connection(topic, msgtype, msgdef=msgdef, rihs01=digest, offered_qos_profiles=qos)
        self._connections[topic] = conn
        self.counts[topic] = 0

    def has_topic(self, topic: str) -> bool:
        return topic in self._connections

    def write(self, topic: str, ns: int, msg: Any) -> None:
        """Serialise ``msg`` (a ``rosbags`` message) and write it on ``topic`` at log time ``ns``."""
        self.write_raw(topic, ns, messages.serialize(msg))

    def write_raw(self, topic: str, ns: int, data: bytes | memoryview) -> None:
        assert self._writer is not None, "use BagWriter as a context manager"
        self._writer.write(self._connections[topic], int(ns), data)
        self.counts[topic] += 1

    def __exit__(self, exc_type, exc, tb) -> None:
        writer, self._writer = self._writer, None
        try:
            if exc_type is None and writer is not None:
                writer.close()
                os.replace(self.tmp / self.path.stem / self.path.name, self.path)
            elif writer is not None:
                with suppress(Exception):
                    writer.abort()
        finally:
            shutil.rmtree(self.tmp, ignore_errors=True)


# --------------------------------------------------------------------------- reading


class BagReader:
    """Context manager reading a ROS 2 bag (a ``.mcap`` / ``.db3`` file or a rosbag2 folder) with ``rosbags``.

    ``topics`` maps each topic to its message type; :meth:`messages` yields ``(topic, log_ns,
    msg)`` in log-time order, deserialised with the Jazzy type store (or ``(topic, log_ns, bytes)``
    with ``raw=True``).
    """

    def __init__(self, path: str | Path):
        self.path = Path(path)
        if not self.path.exists():
            raise DataError(self.path, "bag not found")
        self._reader: Reader | None = None

    def __enter__(self) -> BagReader:
        try:
            self._reader = Reader(self.path)
            self._reader.open()
        except Exception as err:  # rosbags raises several types for a bad file
            raise DataError(self.path, f"cannot open as a ROS 2 bag ({err})") from err
        return self

    def __exit__(self, *exc) -> None:
        if self._reader is not None:
            self._reader.close()
            self._reader = None

    @property
    def connections(self) -> list[Any]:
        assert self._reader is not None, "use BagReader as a context manager"
        return list(self._reader.connections)

    @property
    def topics(self) -> dict[str, str]:
        return {c.topic: c.msgtype for c in self.connections}

    def count(self, topic: str) -> int:
        return sum(c.msgcount for c in self.connections if c.topic == topic)

    def messages(self, topics: Iterable[str] | None = None, raw: bool = False) -> Iterator[tuple[str, int, Any]]:
        assert self._reader is not None, "use BagReader as a context manager"
        wanted = None if topics is None else set(topics)
        conns = [c for c in self._reader.connections if wanted is None or c.topic in wanted]
        if not conns:
            return
        try:
            for conn, ns, data in self._reader.messages(connections=conns):
                yield conn.topic, ns, (data if raw else messages.deserialize(data, conn.msgtype))
        except (KeyError, ValueError, AssertionError) as err:
            raise DataError(self.path, f"cannot decode a message ({type(err).__name__}: {err})") from err
