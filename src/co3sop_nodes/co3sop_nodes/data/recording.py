"""MCAP recordings of raw ROS 2 messages: written chunk by chunk, recovered after a crash (ROS-free).

A recording is one .mcap file in the ros2 profile (CDR messages, `ros2msg`
schemas embedded), so rosbags, `ros2 bag` and Foxglove read it without this
package. The writer flushes every finished chunk (and the open one on
`flush()`), so a crash loses at most the chunk in progress; `recover` copies
every complete record of a damaged file into a new, fully indexed one.
"""

from __future__ import annotations

import os
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from co3sop_nodes.common.errors import DatasetError
from co3sop_nodes.data.bags import typestore

LIBRARY = "co3sop_nodes recorder"
# chunk compressions a recording may use (every MCAP reader, rosbags and Foxglove included, reads all three): zstd
# makes the smallest files; lz4 compresses in about half zstd's time at about 2.5 times the bytes (a graph recording
# at its sensors' rate on a small machine); none writes the messages as they came
COMPRESSIONS = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}


class McapRecorder:
    """Raw CDR messages -> `path` (ros2 profile), chunks compressed by `compression` (COMPRESSIONS); use as a context
    manager or call close()."""

    def __init__(self, path: Path, chunk_size: int = 256 * 1024, compression: str = "zstd"):
        if compression not in COMPRESSIONS:
            raise DatasetError(f"compression {compression!r}: one of {', '.join(COMPRESSIONS)}")
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(self.path, "wb")
        self._writer = Writer(self._file, chunk_size=chunk_size, compression=COMPRESSIONS[compression])
        self._writer.start(profile="ros2", library=LIBRARY)
        self._store = None  # the type store, loaded on the first schema that needs it
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self.counts: Counter[str] = Counter()
        self._closed = False

    def __enter__(self) -> McapRecorder:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _schema(self, msgtype: str, definition: bytes | None) -> int:
        if msgtype not in self._schemas:
            if definition is None:
                self._store = self._store or typestore()
                definition = self._store.generate_msgdef(msgtype, ros_version=2)[0].encode()
            self._schemas[msgtype] = self._writer.register_schema(msgtype, "ros2msg", definition)
        return self._schemas[msgtype]

    def write(
        self,
        topic: str,
        msgtype: str,
        data: bytes,
        log_time_ns: int,
        publish_time_ns: int | None = None,
        definition: bytes | None = None,
    ) -> None:
        """One serialized message of type 'pkg/msg/Type' (its definition comes from the installed types unless given)."""
        if topic not in self._channels:
            self._channels[topic] = self._writer.register_channel(topic, "cdr", self._schema(msgtype, definition))
        self._writer.add_message(
            self._channels[topic],
            log_time=log_time_ns,
            data=bytes(data),
            publish_time=log_time_ns if publish_time_ns is None else publish_time_ns,
        )
        self.counts[topic] += 1

    def flush(self) -> None:
        """Ends the chunk in progress and hands everything to the OS (survives a killed process)."""
        self._writer.flush()

    def close(self) -> None:
        """Writes the summary (indexes, statistics) and closes; the file is then complete."""
        if self._closed:
            return
        self._closed = True
        self._writer.finish()
        self._file.flush()
        os.fsync(self._file.fileno())
        self._file.close()


@dataclass(frozen=True)
class Recovered:
    messages: int
    topics: dict[str, int]
    complete: bool  # the source already ended with a valid footer
    problem: str  # what stopped the scan, or "" when the source was complete


def recover(source: Path, target: Path | None = None) -> Recovered:
    """Copies every complete message of `source` into a complete MCAP at `target` (default: `source`, replaced atomically)."""
    source = Path(source)
    target = source if target is None else Path(target)
    if not source.is_file():
        raise DatasetError(f"{source}: no such file")
    tmp = target.with_name(f".{target.name}.recovering")
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    problem, complete = "", False
    try:
        with open(source, "rb") as stream, McapRecorder(tmp) as out:
            try:
                for record in StreamReader(stream, validate_crcs=True).records:
                    if isinstance(record, Schema):
                        schemas[record.id] = record
                    elif isinstance(record, Channel):
                        channels[record.id] = record
                    elif isinstance(record, Message) and record.channel_id in channels:
                        channel = channels[record.channel_id]
                        schema = schemas[channel.schema_id]
                        out.write(
                            channel.topic, schema.name, record.data, record.log_time, record.publish_time, schema.data
                        )
                complete = True
            except Exception as exc:  # a damaged record fails in many ways; the scan stops at the first
                problem = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
            if not out.counts and not schemas:
                raise DatasetError(f"{source}: not an MCAP file or nothing recoverable ({problem})")
            counts = dict(out.counts)
    except BaseException:
        tmp.unlink(missing_ok=True)  # a failed recovery leaves nothing behind and the source untouched
        raise
    os.replace(tmp, target)
    return Recovered(sum(counts.values()), counts, complete, problem)
