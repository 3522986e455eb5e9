"""MCAP recordings the way rosbag2 writes them, without rosbag2 (not on PyPI).

What ``ros2 bag record -s mcap`` produces and what we reproduce:

* MCAP profile ``ros2``; one schema per message type, named ``pkg/msg/Type``, encoding
  ``ros2msg``: the type's ``.msg`` text followed, for every type it depends on (depth first, each
  once), by a line of 80 ``=``, a line ``MSG: pkg/Type`` and that type's ``.msg`` text;
* one channel per topic, message encoding ``cdr``, metadata ``offered_qos_profiles`` (YAML list
  of the publishers' QoS, rosbag2's Jazzy spelling) and ``topic_type_hash`` (``RIHS01_…``);
* messages with ``log_time = publish_time =`` receive time (ns since the epoch), sequence 0;
* zstd-compressed chunks; a ``metadata.yaml`` (rosbag2 bag metadata, version 9) next to the
  ``.mcap`` when the file is closed, so the directory is a rosbag2 bag too.

This module needs no rclpy: payloads are CDR bytes; message definitions come from the installed
``share/<pkg>/msg/*.msg`` files (the ament index).
"""

from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import yaml
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from mlv_ros import __version__

ROS_DISTRO = "jazzy"
_PRIMITIVES = {
    "bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16", "int32",
    "uint32", "int64", "uint64", "string", "wstring",
}
_SEPARATOR = "=" * 80


# --------------------------------------------------------------------------- definitions
def _share_dirs() -> list[Path]:
    prefixes = [p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    import sys

    prefixes.append(sys.prefix)  # the venv is an ament prefix too
    return [Path(p) / "share" for p in dict.fromkeys(prefixes)]


def _msg_file(pkg: str, name: str, suffix: str = ".msg") -> Path:
    for share in _share_dirs():
        path = share / pkg / "msg" / (name + suffix)
        if path.is_file():
            return path
    raise FileNotFoundError(f"no {suffix} for {pkg}/msg/{name} under any AMENT_PREFIX_PATH share/")


def _split_type(type_name: str) -> tuple[str, str]:
    parts = type_name.split("/")
    if len(parts) == 3 and parts[1] == "msg":
        return parts[0], parts[2]
    if len(parts) == 2:
        return parts[0], parts[1]
    raise ValueError(f"not a message type name: {type_name!r} (want pkg/msg/Type)")


def _field_types(text: str, pkg: str) -> list[str]:
    """Complex field types ``pkg/Type`` referenced by a .msg text, in order."""
    out = []
    for line in text.splitlines():
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        ftype, _, rest = line.partition(" ")
        if re.match(r"^\s*\w+\s*=", rest):  # constant: TYPE NAME=value
            continue
        base = re.sub(r"\[.*\]$", "", ftype)
        base = re.sub(r"<=\d+$", "", base)
        if base in _PRIMITIVES:
            continue
        if base == "Header":
            base = "std_msgs/Header"
        if "/" not in base:
            base = f"{pkg}/{base}"
        out.append(base)
    return out


def message_definition(type_name: str) -> str:
    """rosbag2's ``ros2msg`` schema text for ``pkg/msg/Type`` (with every dependency appended)."""
    pkg, name = _split_type(type_name)
    root = _msg_file(pkg, name).read_text()
    parts, seen = [root], set()

    def visit(text: str, owner_pkg: str):
        for dep in _field_types(text, owner_pkg):
            if dep in seen:
                continue
            seen.add(dep)
            dpkg, dname = dep.split("/")
            dtext = _msg_file(dpkg, dname).read_text()
            parts.append(f"{_SEPARATOR}\nMSG: {dep}\n{dtext}")
            visit(dtext, dpkg)

    visit(root, pkg)
    return "\n".join(parts)


def type_hash(type_name: str) -> str:
    """``RIHS01_…`` type-description hash of ``pkg/msg/Type`` (from rosidl's generated .json)."""
    pkg, name = _split_type(type_name)
    data = json.loads(_msg_file(pkg, name, ".json").read_text())
    full = f"{pkg}/msg/{name}"
    for entry in data.get("type_hashes", []):
        if entry.get("type_name") == full:
            return entry["hash_string"]
    raise ValueError(f"no type hash for {full} in its .json")


def qos_yaml(profiles: list[dict]) -> str:
    """``offered_qos_profiles`` metadata: a YAML list, rosbag2 Jazzy spelling.

    Each profile is a dict with ``history`` (keep_last | keep_all), ``depth``, ``reliability``
    (reliable | best_effort), ``durability`` (volatile | transient_local); durations default to
    rosbag2's "infinite" (sec 9223372036, nsec 854775807) and liveliness to automatic.
    """
    infinite = {"sec": 9223372036, "nsec": 854775807}
    out = []
    for p in profiles:
        out.append({
            "history": p.get("history", "keep_last"), "depth": int(p.get("depth", 10)),
            "reliability": p.get("reliability", "reliable"), "durability": p.get("durability", "volatile"),
            "deadline": dict(infinite), "lifespan": dict(infinite), "liveliness": "automatic",
            "liveliness_lease_duration": dict(infinite), "avoid_ros_namespace_conventions": False,
        })
    return yaml.safe_dump(out, sort_keys=False)


# --------------------------------------------------------------------------- writing
@dataclass
class _Topic:
    name: str
    type_name: str
    channel_id: int
    qos: str
    type_hash: str
    count: int = 0


@dataclass
class BagWriter:
    """Write a rosbag2-compatible MCAP file.

    Parameters
    ----------
    path : path-like
        The ``.mcap`` file to create (its directory is created). Refuses to overwrite.
    chunk_size : int
        Bytes per chunk before it is compressed and written (a SIGKILL loses at most the chunk
        being filled; every completed chunk is on disk).
    compression : {"zstd", "lz4", "none"}
    """

    path: Path
    chunk_size: int = 1 << 20
    compression: str = "zstd"
    topics: dict = field(default_factory=dict)

    def __post_init__(self):
        self.path = Path(self.path)
        if self.path.exists():
            raise FileExistsError(f"refusing to overwrite existing recording {self.path}")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._fh = open(self.path, "wb")
        comp = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}
        if self.compression not in comp:
            raise ValueError(f"compression must be one of {sorted(comp)}, got {self.compression!r}")
        self._writer = Writer(self._fh, chunk_size=self.chunk_size, compression=comp[self.compression])
        self._writer.start(profile="ros2", library=f"mlv_ros {__version__}")
        self._schemas: dict[str, int] = {}
        self.start_ns: int | None = None
        self.end_ns = 0
        self.closed = False

    def add_topic(self, topic: str, type_name: str, qos_profiles: list[dict] | None = None) -> None:
        """Register a topic (idempotent). ``type_name`` is ``pkg/msg/Type``."""
        if topic in self.topics:
            return
        if type_name not in self._schemas:
            self._schemas[type_name] = self._writer.register_schema(
                name=type_name, encoding="ros2msg", data=message_definition(type_name).encode())
        qos = qos_yaml(qos_profiles or [{}])
        thash = type_hash(type_name)
        cid = self._writer.register_channel(
            topic=topic, message_encoding="cdr", schema_id=self._schemas[type_name],
            metadata={"offered_qos_profiles": qos, "topic_type_hash": thash})
        self.topics[topic] = _Topic(topic, type_name, cid, qos, thash)

    def write(self, topic: str, data: bytes, log_time_ns: int, publish_time_ns: int | None = None) -> None:
        """Append one CDR-serialised message received at ``log_time_ns`` and sent at
        ``publish_time_ns`` (the publisher's source timestamp, as rosbag2 records it; default the
        receive time), both in ns since the epoch."""
        if self.closed:
            raise ValueError(f"recording {self.path} is closed")
        t = self.topics.get(topic)
        if t is None:
            raise ValueError(f"topic {topic!r} was not added to the recording")
        self._writer.add_message(channel_id=t.channel_id, log_time=log_time_ns, data=bytes(data),
                                 publish_time=log_time_ns if publish_time_ns is None else publish_time_ns,
                                 sequence=0)
        t.count += 1
        self.start_ns = log_time_ns if self.start_ns is None else min(self.start_ns, log_time_ns)
        self.end_ns = max(self.end_ns, log_time_ns)

    def flush(self) -> None:
        """Push written chunks to the OS (does not close the current chunk)."""
        self._fh.flush()

    @property
    def message_count(self) -> int:
        return sum(t.count for t in self.topics.values())

    def close(self) -> None:
        """Finish the file (summary, statistics, indexes) and write ``metadata.yaml`` beside it."""
        if self.closed:
            return
        self._writer.finish()
        self._fh.close()
        self.closed = True
        write_bag_metadata(self.path, self)


def write_bag_metadata(mcap_path: Path, writer: BagWriter) -> Path:
    """rosbag2 ``metadata.yaml`` (version 9) for a single-file MCAP bag; returns its path."""
    start = writer.start_ns or 0
    info = {
        "version": 9,
        "storage_identifier": "mcap",
        "duration": {"nanoseconds": max(0, writer.end_ns - start)},
        "starting_time": {"nanoseconds_since_epoch": start},
        "message_count": writer.message_count,
        "topics_with_message_count": [
            {"topic_metadata": {"name": t.name, "type": t.type_name, "serialization_format": "cdr",
                                "offered_qos_profiles": t.qos, "type_description_hash": t.type_hash},
             "message_count": t.count}
            for t in writer.topics.values()],
        "compression_format": "",
        "compression_mode": "",
        "relative_file_paths": [mcap_path.name],
        "files": [{"path": mcap_path.name, "starting_time": {"nanoseconds_since_epoch": start},
                   "duration": {"nanoseconds": max(0, writer.end_ns - start)},
                   "message_count": writer.message_count}],
        "custom_data": {"recorded_by": f"mlv_ros {__version__}"},
        "ros_distro": ROS_DISTRO,
    }
    path = mcap_path.parent / "metadata.yaml"
    path.write_text(yaml.safe_dump({"rosbag2_bagfile_information": info}, sort_keys=False))
    return path


# --------------------------------------------------------------------------- reading
@dataclass
class BagMessage:
    topic: str
    type_name: str
    data: bytes
    log_time_ns: int


def read_bag(path, topics: list[str] | None = None) -> Iterator[BagMessage]:
    """Messages of an MCAP recording in log-time order (CDR bytes; deserialise with rclpy).

    Raises ``ValueError`` for a file that is not MCAP or has no ``cdr`` channels.
    """
    path = Path(path)
    if path.is_dir():
        path = _bag_file_in_dir(path)
    with open(path, "rb") as fh:
        try:
            reader = make_reader(fh)
            for schema, channel, message in reader.iter_messages(topics=topics, log_time_order=True):
                if channel.message_encoding != "cdr":
                    continue
                yield BagMessage(channel.topic, schema.name if schema else "", message.data, message.log_time)
        except Exception as exc:  # mcap raises several private exception types
            if isinstance(exc, (KeyboardInterrupt, SystemExit)):
                raise
            raise ValueError(f"cannot read {path} as MCAP: {exc}") from exc


def bag_topics(path) -> dict[str, dict]:
    """Topic → {type, count, qos, type_hash} from an MCAP file's summary."""
    path = Path(path)
    if path.is_dir():
        path = _bag_file_in_dir(path)
    with open(path, "rb") as fh:
        try:
            summary = make_reader(fh).get_summary()
        except Exception as exc:
            raise ValueError(f"cannot read {path} as MCAP: {exc}") from exc
    if summary is None:
        raise ValueError(f"{path} has no MCAP summary (unfinished recording? try `mlv-ros recover`)")
    counts = summary.statistics.channel_message_counts if summary.statistics else {}
    out = {}
    for cid, ch in summary.channels.items():
        schema = summary.schemas.get(ch.schema_id)
        out[ch.topic] = {"type": schema.name if schema else "", "count": counts.get(cid, 0),
                         "qos": ch.metadata.get("offered_qos_profiles", ""),
                         "type_hash": ch.metadata.get("topic_type_hash", "")}
    return out


def _bag_file_in_dir(directory: Path) -> Path:
    meta = directory / "metadata.yaml"
    if meta.is_file():
        info = yaml.safe_load(meta.read_text())["rosbag2_bagfile_information"]
        return directory / info["relative_file_paths"][0]
    files = sorted(directory.glob("*.mcap"))
    if not files:
        raise ValueError(f"no .mcap file in {directory}")
    return files[0]


# --------------------------------------------------------------------------- recovery
def recover(damaged, out) -> dict:
    """Rewrite a valid recording from a damaged one (e.g. the recorder was SIGKILLed).

    Reads the file record by record from the start (no summary or index needed) and keeps every
    message of every chunk that is complete; reading stops at the first truncated or corrupt
    record. Schemas, channels (with their QoS and type-hash metadata) and message times are
    kept as recorded. Returns ``{"messages": n, "topics": {topic: n}, "stopped_at": reason}``.
    """
    from mcap.records import Channel as ChannelRec
    from mcap.records import Message as MessageRec
    from mcap.records import Schema as SchemaRec
    from mcap.stream_reader import StreamReader

    damaged, out = Path(damaged), Path(out)
    if out.exists():
        raise FileExistsError(f"refusing to overwrite {out}")
    schemas, channels, counts = {}, {}, {}
    stopped = "end of file"
    with open(damaged, "rb") as fh, open(out, "wb") as oh:
        writer = Writer(oh, compression=CompressionType.ZSTD)
        writer.start(profile="ros2", library=f"mlv_ros {__version__} (recovered)")
        sid_map, cid_map = {}, {}
        try:
            for rec in StreamReader(fh, validate_crcs=True).records:
                if isinstance(rec, SchemaRec):
                    sid_map[rec.id] = writer.register_schema(rec.name, rec.encoding, rec.data)
                    schemas[rec.id] = rec.name
                elif isinstance(rec, ChannelRec):
                    cid_map[rec.id] = writer.register_channel(rec.topic, rec.message_encoding,
                                                              sid_map.get(rec.schema_id, 0), rec.metadata)
                    channels[rec.id] = rec.topic
                elif isinstance(rec, MessageRec) and rec.channel_id in cid_map:
                    writer.add_message(cid_map[rec.channel_id], rec.log_time, rec.data, rec.publish_time,
                                       rec.sequence)
                    topic = channels[rec.channel_id]
                    counts[topic] = counts.get(topic, 0) + 1
        except Exception as exc:  # truncated or corrupt tail: keep what came before it
            if isinstance(exc, (KeyboardInterrupt, SystemExit)):
                raise
            stopped = f"{type(exc).__name__}: {exc}"
        writer.finish()
    return {"messages": sum(counts.values()), "topics": counts, "stopped_at": stopped}
