# Copyright 2026 The mlv_ros authors
#
# Licensed under the Apache License, Version 2.0 (the "License");
# you may not use this file except in compliance with the License.
# You may obtain a copy of the License at
#
#     http://www.apache.org/licenses/LICENSE-2.0
#
# Unless required by applicable law or agreed to in writing, software
# distributed under the License is distributed on an "AS IS" BASIS,
# WITHOUT WARRANTIES OR CONDITIONS OF ANY KIND, either express or implied.
# See the License for the specific language governing permissions and
# limitations under the License.

"""
MCAP recordings the way rosbag2 writes them, without rosbag2 (not on PyPI).

What ``ros2 bag record -s mcap`` (ROS 2 Jazzy) produces and what we reproduce, following
rosbag2's ``jazzy`` branch (github.com/ros2/rosbag2, commit 64717ee8):

* MCAP profile ``ros2``; one schema per message type, named ``pkg/msg/Type``, encoding
  ``ros2msg``: the type's ``.msg`` text followed, for every type it depends on (depth first, each
  once), by a line of 80 ``=``, a line ``MSG: pkg/Type`` and that type's ``.msg`` text;
* one channel per topic, message encoding ``cdr``, metadata ``offered_qos_profiles`` (the
  publishers' QoS as a YAML text: a sequence of QoS maps) and ``topic_type_hash`` (``RIHS01_…``)
  (``rosbag2_storage_mcap/src/mcap_storage.cpp``, ``MCAPStorage::create_topic``);
* messages with ``log_time`` = receive time and ``publish_time`` = the publisher's send time (ns
  since the epoch), sequence 0 (``MCAPStorage::write``);
* a ``rosbag2`` MCAP metadata record with one key, ``serialized_metadata``: the bag metadata as
  YAML, written when the file is opened and again, final, before it is closed
  (``MCAPStorage::update_metadata``, called by ``rosbag2_cpp/src/rosbag2_cpp/writers/
  sequential_writer.cpp`` in ``open`` and ``close``);
* zstd-compressed chunks; a ``metadata.yaml`` next to the ``.mcap`` when the file is closed
  (``rosbag2_storage/src/rosbag2_storage/metadata_io.cpp``), so the directory is a rosbag2 bag.

The bag metadata is version 9 as ``rosbag2_storage/include/rosbag2_storage/yaml.hpp`` encodes it:
bag and file times as ``{nanoseconds}`` / ``{nanoseconds_since_epoch}``; each topic's
``offered_qos_profiles`` a *sequence of maps* (``rosbag2_storage/src/rosbag2_storage/qos.cpp``:
policies by name, ``deadline``/``lifespan``/``liveliness_lease_duration`` as ``{sec, nsec}``).
Versions before 9 stored that sequence as one YAML string; rosbag2 Jazzy reads a version-9 file
only in the sequence form.

This module needs no rclpy: payloads are CDR bytes; message definitions come from the installed
``share/<pkg>/msg/*.msg`` files (the ament index).
"""

from __future__ import annotations

from dataclasses import dataclass, field
import importlib
import json
import os
from pathlib import Path
import re
import struct
from typing import Iterator

from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer
from mlv_ros import __version__, qos
from mlv_ros.core.analysis.findings import FINDING_ARRAY_FIELDS
import yaml

ROS_DISTRO = 'jazzy'
_PRIMITIVES = {
    'bool',
    'byte',
    'char',
    'float32',
    'float64',
    'int8',
    'uint8',
    'int16',
    'uint16',
    'int32',
    'uint32',
    'int64',
    'uint64',
    'string',
    'wstring',
}
_SEPARATOR = '=' * 80


# --------------------------------------------------------------------------- definitions
def _share_dirs() -> list[Path]:
    prefixes = [p for p in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if p]
    import sys

    prefixes.append(sys.prefix)  # the venv is an ament prefix too
    return [Path(p) / 'share' for p in dict.fromkeys(prefixes)]


def _msg_file(pkg: str, name: str, suffix: str = '.msg') -> Path:
    for share in _share_dirs():
        path = share / pkg / 'msg' / (name + suffix)
        if path.is_file():
            return path
    raise FileNotFoundError(f'no {suffix} for {pkg}/msg/{name} under any AMENT_PREFIX_PATH share/')


def _split_type(type_name: str) -> tuple[str, str]:
    parts = type_name.split('/')
    if len(parts) == 3 and parts[1] == 'msg':
        return parts[0], parts[2]
    if len(parts) == 2:
        return parts[0], parts[1]
    raise ValueError(f'not a message type name: {type_name!r} (want pkg/msg/Type)')


def _field_types(text: str, pkg: str) -> list[str]:
    """Complex field types ``pkg/Type`` referenced by a .msg text, in order."""
    out = []
    for line in text.splitlines():
        line = line.split('#', 1)[0].strip()
        if not line:
            continue
        ftype, _, rest = line.partition(' ')
        if re.match(r'^\s*\w+\s*=', rest):  # constant: TYPE NAME=value
            continue
        base = re.sub(r'\[.*\]$', '', ftype)
        base = re.sub(r'<=\d+$', '', base)
        if base in _PRIMITIVES:
            continue
        if base == 'Header':
            base = 'std_msgs/Header'
        if '/' not in base:
            base = f'{pkg}/{base}'
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
            dpkg, dname = dep.split('/')
            dtext = _msg_file(dpkg, dname).read_text()
            parts.append(f'{_SEPARATOR}\nMSG: {dep}\n{dtext}')
            visit(dtext, dpkg)

    visit(root, pkg)
    return '\n'.join(parts)


def type_hash(type_name: str) -> str:
    """``RIHS01_…`` type-description hash of ``pkg/msg/Type`` (from rosidl's generated .json)."""
    pkg, name = _split_type(type_name)
    data = json.loads(_msg_file(pkg, name, '.json').read_text())
    full = f'{pkg}/msg/{name}'
    for entry in data.get('type_hashes', []):
        if entry.get('type_name') == full:
            return entry['hash_string']
    raise ValueError(f'no type hash for {full} in its .json')


# rmw's RMW_DURATION_INFINITE, which rosbag2 writes for a publisher's unset deadline, lifespan
# and liveliness lease duration.
INFINITE_DURATION = {'sec': 9223372036, 'nsec': 854775807}
# rosbag2 starts a bag's and a file's starting_time at std::chrono::nanoseconds::max() and lowers
# it with each message (sequential_writer.cpp, init_metadata/write): an empty bag keeps it.
_NO_MESSAGE_TIME = 2**63 - 1
# Keys of one QoS profile, in the order qos.cpp's convert<rclcpp::QoS>::encode writes them.
QOS_KEYS = (
    'history',
    'depth',
    'reliability',
    'durability',
    'deadline',
    'lifespan',
    'liveliness',
    'liveliness_lease_duration',
    'avoid_ros_namespace_conventions',
)


class _RosbagYamlDumper(yaml.SafeDumper):
    """
    Block YAML laid out as yaml-cpp emits it (what rosbag2 writes).

    yaml-cpp indents a sequence under its key and writes an empty string as ``""`` and an empty
    node as ``~``; PyYAML's defaults differ only in layout, not in content.
    """

    def increase_indent(self, flow=False, indentless=False):
        return super().increase_indent(flow, False)

    def ignore_aliases(self, data):
        return True  # yaml-cpp writes repeated values out, never as anchors


_RosbagYamlDumper.add_representer(
    str,
    lambda d, s: (
        d.represent_scalar('tag:yaml.org,2002:str', s, style='"')
        if s == ''
        else d.represent_str(s)
    ),
)
_RosbagYamlDumper.add_representer(
    type(None), lambda d, _: d.represent_scalar('tag:yaml.org,2002:null', '~')
)


def rosbag2_yaml(data) -> str:
    """Return ``data`` as YAML text as rosbag2 writes it (``YAML::Dump``: no final newline)."""
    return yaml.dump(
        data,
        Dumper=_RosbagYamlDumper,
        sort_keys=False,
        default_flow_style=False,
        width=1 << 30,
        allow_unicode=True,
    ).rstrip('\n')


def offered_qos(profiles: list[dict]) -> list[dict]:
    """
    ``offered_qos_profiles`` as rosbag2 Jazzy writes them: one map per publisher.

    Parameters
    ----------
    profiles : list of dict
        Each with ``history`` (keep_last | keep_all), ``depth``, ``reliability`` (reliable |
        best_effort) and ``durability`` (volatile | transient_local); a missing key takes
        RELIABLE, VOLATILE, KEEP_LAST(10).

    Returns
    -------
    list of dict
        Maps with the keys of :data:`QOS_KEYS`, in that order: the durations infinite
        (``{sec, nsec}``), liveliness automatic, as rmw reports a publisher that sets none.

    """
    return [
        {
            'history': p.get('history', 'keep_last'),
            'depth': int(p.get('depth', 10)),
            'reliability': p.get('reliability', 'reliable'),
            'durability': p.get('durability', 'volatile'),
            'deadline': dict(INFINITE_DURATION),
            'lifespan': dict(INFINITE_DURATION),
            'liveliness': 'automatic',
            'liveliness_lease_duration': dict(INFINITE_DURATION),
            'avoid_ros_namespace_conventions': False,
        }
        for p in profiles
    ]


# Policies as rosbag2 wrote them before version 9: rmw's enum values (rmw/types.h).
_POLICY_NUMBERS = {
    'history': {0: 'system_default', 1: 'keep_last', 2: 'keep_all', 3: 'unknown'},
    'reliability': {
        0: 'system_default',
        1: 'reliable',
        2: 'best_effort',
        3: 'unknown',
        4: 'best_available',
    },
    'durability': {
        0: 'system_default',
        1: 'transient_local',
        2: 'volatile',
        3: 'unknown',
        4: 'best_available',
    },
    'liveliness': {
        0: 'system_default',
        1: 'automatic',
        3: 'manual_by_topic',
        4: 'unknown',
        5: 'best_available',
    },
}


def parse_offered_qos(value) -> list[dict]:
    """
    Parse recorded ``offered_qos_profiles`` into a list of maps with policies by name.

    Accepts the version-9 sequence, the YAML string of MCAP channel metadata and of metadata.yaml
    before version 9 (recordings of an earlier mlv_ros carry the string form in version 9 too),
    and empty values; policies written as numbers (rosbag2 before version 9) are turned into
    their names.
    """
    if isinstance(value, str):
        try:
            value = yaml.safe_load(value) if value.strip() else []
        except yaml.YAMLError:
            return []
    if not isinstance(value, list):
        return []
    out = []
    for p in value:
        if isinstance(p, dict):
            p = dict(p)
            for key, names in _POLICY_NUMBERS.items():
                if isinstance(p.get(key), int) and not isinstance(p[key], bool):
                    p[key] = names.get(p[key], 'unknown')
            out.append(p)
    return out


# --------------------------------------------------------------------------- writing
@dataclass
class _Topic:
    name: str
    type_name: str
    channel_id: int
    qos: list  # offered_qos_profiles, version-9 maps
    type_hash: str
    count: int = 0


def bag_metadata(
    file_name: str,
    topics,
    start_ns: int | None,
    end_ns: int,
    custom_data: dict[str, str] | None = None,
) -> dict:
    """
    rosbag2 bag metadata, version 9, of a single-file MCAP bag.

    Keys and their order are those of ``convert<BagMetadata>::encode`` in rosbag2_storage's
    ``yaml.hpp`` (``jazzy``); it is what goes under ``rosbag2_bagfile_information`` in
    ``metadata.yaml`` and, serialised, into the ``rosbag2`` MCAP metadata record.

    Parameters
    ----------
    file_name : str
        The ``.mcap`` file's name, relative to the bag directory.
    topics : iterable
        Objects with ``name``, ``type_name``, ``qos`` (version-9 QoS maps), ``type_hash`` and
        ``count``, in channel order (every registered topic, messages or not, as rosbag2 does).
    start_ns, end_ns : int
        Receive times of the first and last message; ``start_ns`` None for a bag without
        messages (rosbag2 then leaves starting_time at its initial maximum).
    custom_data : dict of str to str, optional
        The bag's ``custom_data`` map, written as given; None or empty writes a null node
        (``custom_data: ~``), as yaml-cpp writes an empty map.

    """
    topics = list(topics)
    start = _NO_MESSAGE_TIME if start_ns is None else start_ns
    duration = 0 if start_ns is None else max(0, end_ns - start_ns)
    count = sum(t.count for t in topics)
    return {
        'version': 9,
        'storage_identifier': 'mcap',
        'duration': {'nanoseconds': duration},
        'starting_time': {'nanoseconds_since_epoch': start},
        'message_count': count,
        'topics_with_message_count': [
            {
                'topic_metadata': {
                    'name': t.name,
                    'type': t.type_name,
                    'serialization_format': 'cdr',
                    'offered_qos_profiles': [dict(q) for q in t.qos],
                    'type_description_hash': t.type_hash,
                },
                'message_count': t.count,
            }
            for t in topics
        ],
        # MCAP compresses whole chunks inside the storage plugin: rosbag2 leaves these empty.
        'compression_format': '',
        'compression_mode': '',
        'relative_file_paths': [file_name],
        'files': [
            {
                'path': file_name,
                'starting_time': {'nanoseconds_since_epoch': start},
                'duration': {'nanoseconds': duration},
                'message_count': count,
            }
        ],
        # yaml-cpp writes an empty map as a null node (``custom_data: ~``).
        'custom_data': dict(custom_data) if custom_data else None,
        'ros_distro': ROS_DISTRO,
    }


def write_rosbag2_record(writer: Writer, metadata: dict) -> None:
    """Add the ``rosbag2`` MCAP metadata record (``MCAPStorage::update_metadata``)."""
    writer.add_metadata('rosbag2', {'serialized_metadata': rosbag2_yaml(metadata)})


class _DiskFile:
    """
    The MCAP writer's output: unbuffered, so it knows what reached the file.

    Every ``write`` goes straight to the OS. When one fails (disk full ``ENOSPC``, file size limit
    ``EFBIG``, ``EIO``) everything written before it is in the file, and the record that failed
    can be cut off with :meth:`truncate`, leaving a file that ends on a whole record.
    """

    def __init__(self, path: Path):
        self._fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o644)
        self._pos = 0
        self.closed = False

    def write(self, data) -> int:
        view = memoryview(data).cast('B')
        while view:
            n = os.write(self._fd, view)
            self._pos += n
            view = view[n:]
        return len(data)

    def tell(self) -> int:
        return self._pos

    def flush(self) -> None:
        """Every write is already with the OS; make it survive a power loss too (fsync)."""
        os.fsync(self._fd)

    def truncate(self, size: int) -> None:
        os.ftruncate(self._fd, size)
        os.lseek(self._fd, size, os.SEEK_SET)
        self._pos = size

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            os.close(self._fd)


@dataclass
class BagWriter:
    """
    Write a rosbag2-compatible MCAP file.

    Parameters
    ----------
    path : path-like
        The ``.mcap`` file to create (its directory is created). Refuses to overwrite.
    chunk_size : int
        Bytes per chunk before it is compressed and written (a SIGKILL loses at most the chunk
        being filled; every completed chunk is on disk).
    compression : {"zstd", "lz4", "none"}

    Attributes
    ----------
    error : OSError or None
        The write error that stopped the recording (disk full, file too large, I/O error). The
        file then ends after the last record written whole; :meth:`write` refuses more, and
        :meth:`close` writes ``metadata.yaml`` for the messages in the file, without an MCAP
        summary (``mlv-ros recover`` rewrites a complete file from it).
    custom_data : dict of str to str
        Extra ``custom_data`` of the bag metadata (``recorded_by`` is always there).

    """

    path: Path
    chunk_size: int = 1 << 20
    compression: str = 'zstd'
    topics: dict = field(default_factory=dict)
    custom_data: dict = field(default_factory=dict)

    def __post_init__(self):
        self.path = Path(self.path)
        comp = {
            'zstd': CompressionType.ZSTD,
            'lz4': CompressionType.LZ4,
            'none': CompressionType.NONE,
        }
        if self.compression not in comp:
            raise ValueError(
                f'compression must be one of {sorted(comp)}, got {self.compression!r}'
            )
        if self.path.exists():
            raise FileExistsError(f'refusing to overwrite existing recording {self.path}')
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._fh = _DiskFile(self.path)
        self._schemas: dict[str, int] = {}
        self.start_ns: int | None = None
        self.end_ns = 0
        self.closed = False
        self.error: OSError | None = None
        try:
            self._writer = Writer(
                self._fh, chunk_size=self.chunk_size, compression=comp[self.compression]
            )
            self._writer.start(profile='ros2', library=f'mlv_ros {__version__}')
            # rosbag2 writes the (still empty) bag metadata when it opens a file, so even a file
            # whose writer was killed carries its version, distro and custom data.
            write_rosbag2_record(self._writer, self.metadata())
        except OSError:
            self.discard()  # not even the header fits: leave nothing behind
            raise

    def _guarded(self, op, *args, **kwargs):
        """
        Run one writer operation, undoing what a failed write left in the file.

        On a write error the file is cut back to where the operation began (a whole record) and
        closed, and the error is kept.
        """
        if self.error is not None:
            raise ValueError(f'recording {self.path} stopped after a write error: {self.error}')
        mark = self._fh.tell()
        try:
            return op(*args, **kwargs)
        except OSError as exc:
            self.error = exc
            try:
                self._fh.truncate(mark)
            except OSError:
                pass  # the reader then stops at the cut record; what came before stays readable
            self._fh.close()
            raise

    def add_topic(
        self, topic: str, type_name: str, qos_profiles: list[dict] | None = None
    ) -> None:
        """
        Register a topic (idempotent).

        Parameters
        ----------
        topic : str
            The topic name as recorded (the MCAP channel's topic); a name already registered
            is left as it is.
        type_name : str
            ``pkg/msg/Type``.
        qos_profiles : list of dict, optional
            The publishers' QoS (see :func:`offered_qos`); one default profile if omitted.

        """
        if topic in self.topics:
            return
        if type_name not in self._schemas:
            self._schemas[type_name] = self._guarded(
                self._writer.register_schema,
                name=type_name,
                encoding='ros2msg',
                data=message_definition(type_name).encode(),
            )
        offered = offered_qos(qos_profiles or [{}])
        thash = type_hash(type_name)
        cid = self._guarded(
            self._writer.register_channel,
            topic=topic,
            message_encoding='cdr',
            schema_id=self._schemas[type_name],
            metadata={'offered_qos_profiles': rosbag2_yaml(offered), 'topic_type_hash': thash},
        )
        self.topics[topic] = _Topic(topic, type_name, cid, offered, thash)

    def write(
        self, topic: str, data: bytes, log_time_ns: int, publish_time_ns: int | None = None
    ) -> None:
        """
        Append one CDR-serialised message with its receive and publish times.

        The message was received at ``log_time_ns`` and sent at ``publish_time_ns`` (the
        publisher's source timestamp, as rosbag2 records it; default the receive time), both in ns
        since the epoch.

        Raises ``OSError`` when the file cannot take it (see :attr:`error`: the recording stops
        there) and ``ValueError`` once it has stopped or is closed.
        """
        if self.closed:
            raise ValueError(f'recording {self.path} is closed')
        t = self.topics.get(topic)
        if t is None:
            raise ValueError(f'topic {topic!r} was not added to the recording')
        self._guarded(
            self._writer.add_message,
            channel_id=t.channel_id,
            log_time=log_time_ns,
            data=bytes(data),
            publish_time=log_time_ns if publish_time_ns is None else publish_time_ns,
            sequence=0,
        )
        t.count += 1
        self.start_ns = log_time_ns if self.start_ns is None else min(self.start_ns, log_time_ns)
        self.end_ns = max(self.end_ns, log_time_ns)

    def flush(self) -> None:
        """
        Sync the chunks written so far to disk.

        Chunks go to the OS unbuffered as they complete; this makes them survive a power loss. Does
        not close the current chunk. A failing sync (EIO) is kept in :attr:`error` like a failing
        write; the next write reports it.
        """
        if self.error is None and not self.closed:
            try:
                self._guarded(self._fh.flush)
            except OSError:
                pass

    @property
    def message_count(self) -> int:
        return sum(t.count for t in self.topics.values())

    def metadata(self) -> dict:
        """Return the bag metadata, version 9, of what has been written so far."""
        return bag_metadata(
            self.path.name,
            self.topics.values(),
            self.start_ns,
            self.end_ns,
            {'recorded_by': f'mlv_ros {__version__}', **self.custom_data},
        )

    def close(self) -> None:
        """
        Finish the file and write ``metadata.yaml`` beside it.

        Finishing writes the final ``rosbag2`` record, the summary, statistics and indexes.

        After a write error (:attr:`error`, or one while finishing) the file keeps the records
        written whole and no summary; ``metadata.yaml`` then counts the messages in it. Raises
        ``OSError`` if ``metadata.yaml`` cannot be written.
        """
        if self.closed:
            return
        if self.error is None:
            try:
                self._guarded(write_rosbag2_record, self._writer, self.metadata())
                self._guarded(self._writer.finish)
            except OSError:
                pass  # self.error says why; the file ends on the last whole record
        self._fh.close()
        self.closed = True
        if self.error is not None:
            self._count_written()
        write_bag_metadata(self.path, self)

    def discard(self) -> None:
        """Close without finishing and delete the file (a start that failed before recording)."""
        self._fh.close()
        self.closed = True
        self.path.unlink(missing_ok=True)

    def _count_written(self) -> None:
        """
        Set the topics' counts and the times to the messages that are in the file.

        Those are the messages of the chunks written whole, read from their message indexes
        (nothing is decompressed).
        """
        from mcap.records import MessageIndex
        from mcap.stream_reader import StreamReader

        by_channel = {t.channel_id: t for t in self.topics.values()}
        for t in by_channel.values():
            t.count = 0
        self.start_ns, self.end_ns = None, 0
        with open(self.path, 'rb') as fh:
            try:
                for rec in StreamReader(fh, emit_chunks=True).records:
                    if (
                        isinstance(rec, MessageIndex)
                        and rec.channel_id in by_channel
                        and rec.records
                    ):
                        by_channel[rec.channel_id].count += len(rec.records)
                        times = [t for t, _ in rec.records]
                        self.start_ns = (
                            min(times) if self.start_ns is None else min(self.start_ns, *times)
                        )
                        self.end_ns = max(self.end_ns, *times)
            except Exception as exc:  # the file has no footer: reading ends at its last record
                if isinstance(exc, (KeyboardInterrupt, SystemExit)):
                    raise


def write_bag_metadata(mcap_path: Path, writer: BagWriter) -> Path:
    """rosbag2 ``metadata.yaml`` (version 9) for a single-file MCAP bag; returns its path."""
    path = Path(mcap_path).parent / 'metadata.yaml'
    try:
        path.write_text(rosbag2_yaml({'rosbag2_bagfile_information': writer.metadata()}))
    except OSError:
        path.unlink(missing_ok=True)  # a half-written file would pass for the bag's metadata
        raise
    return path


def read_bag_metadata(directory) -> dict:
    """
    ``rosbag2_bagfile_information`` of a bag directory's ``metadata.yaml``, any version.

    Each topic's ``offered_qos_profiles`` comes back as a list of maps, whether the file stores
    the version-9 sequence or the older YAML string (our runs before this format fix, or rosbag2
    before version 9).
    """
    info = yaml.safe_load((Path(directory) / 'metadata.yaml').read_text())[
        'rosbag2_bagfile_information'
    ]
    for entry in info.get('topics_with_message_count') or []:
        meta = entry.get('topic_metadata', {})
        meta['offered_qos_profiles'] = parse_offered_qos(meta.get('offered_qos_profiles', []))
    return info


# --------------------------------------------------------------------------- reading
@dataclass
class BagMessage:
    topic: str
    type_name: str
    data: bytes
    log_time_ns: int
    # Fields of our messages appended after the recording was made (from its schema; None when
    # the schema does not tell): pass to :func:`deserialize` / :func:`current_cdr`.
    missing: tuple | None = ()


def read_bag(
    path, topics: list[str] | None = None, any_namespace: bool = False
) -> Iterator[BagMessage]:
    """
    Messages of an MCAP recording in log-time order (CDR bytes; deserialise with rclpy).

    Parameters
    ----------
    path : str or Path
        The MCAP file, or a rosbag2 directory holding one.
    topics : list of str, optional
        Only these topics (default: all).
    any_namespace : bool
        ``topics`` are graph topics by their root names (:mod:`mlv_ros.qos`), read in whatever
        namespace the recording holds them (a run under ``--namespace study2`` records
        ``/study2/mlv/frames``); each message's ``topic`` is then the root name. Other topics
        (``/diagnostics``) keep their names.

    Raises
    ------
    ValueError
        A file that is not MCAP; with ``any_namespace``, a recording holding graph topics of
        more than one namespace (which one is meant cannot be told).

    """
    path = Path(path)
    if path.is_dir():
        path = _bag_file_in_dir(path)
    with open(path, 'rb') as fh:
        try:
            reader = make_reader(fh)
            missing: dict = {}  # schema id → fields that schema lacks
            names: dict = {}  # channel id → the name to give its messages (None: not wanted)
            namespaces: dict = {}  # namespace → a topic recorded in it (any_namespace)
            for schema, channel, message in reader.iter_messages(
                topics=None if any_namespace else topics, log_time_order=True
            ):
                if channel.message_encoding != 'cdr':
                    continue
                if any_namespace:
                    if channel.id not in names:
                        names[channel.id] = _root_name(channel.topic, topics, namespaces, path)
                    topic = names[channel.id]
                    if topic is None:
                        continue
                else:
                    topic = channel.topic
                name = schema.name if schema else ''
                if channel.schema_id not in missing:
                    text = (
                        schema.data.decode(errors='replace')
                        if schema and schema.encoding == 'ros2msg'
                        else ''
                    )
                    missing[channel.schema_id] = (
                        fields_missing_from(name, text) if name in _APPENDED_FIELDS else ()
                    )
                yield BagMessage(
                    topic, name, message.data, message.log_time, missing[channel.schema_id]
                )
        except Exception as exc:  # mcap raises several private exception types
            if isinstance(exc, (KeyboardInterrupt, SystemExit, SeveralNamespacesError)):
                raise
            raise ValueError(f'cannot read {path} as MCAP: {exc}') from exc


class SeveralNamespacesError(ValueError):
    """A recording holds the graph's topics in more than one namespace."""


def _root_name(recorded: str, wanted, namespaces: dict, path) -> str | None:
    """
    Return the name :func:`read_bag` gives messages of topic ``recorded``.

    The name it gives with ``any_namespace``, or None when the topic is not wanted; ``namespaces``
    collects the namespaces of the graph topics seen.
    """
    split = qos.split_graph_topic(recorded)
    if split is None:
        return recorded if wanted is None or recorded in wanted else None
    namespace, topic = split
    namespaces.setdefault(namespace, recorded)
    if len(namespaces) > 1:
        raise SeveralNamespacesError(
            f"{path} holds the graph's topics in several namespaces "
            f'({", ".join(sorted(namespaces))}): '
            'read it with a tool that takes topic names (e.g. `ros2 bag play --topics ...`), '
            'or record '
            'one graph per file'
        )
    return topic if wanted is None or topic in wanted else None


# Fields appended to our messages after recordings were made with the older definition
# (type name → (name, CDR kind, default) in the order they were appended): such a recording
# stays readable. A recording lacks some last part of each tuple (the fields appended after it).
_APPENDED_FIELDS = {
    # verdict (uint8 0 = ok), verdict_reasons (string ""); then study_id (string ""); then run_id
    # ...; then segment_origin (uint8 0 = unknown) and its confidence; MotionMetrics
    # then the segment uncertainties and findings (empty, ES phase −1: none); then both the
    # degraded segments (empty: none or the whole phase); then both the tag evidence (empty).
    'mlv_msgs/msg/ModelState': (
        ('verdict', 'uint8', 0),
        ('verdict_reasons', 'string', ''),
        ('study_id', 'string', ''),
        ('run_id', 'string', ''),
        ('segment_origin', 'uint8', 0),
        ('segment_origin_confidence', 'float64', 0.0),
        ('degraded_segments', 'sequence', ()),
        ('tag_ecc', 'sequence', ()),
        ('tag_ecc_unc', 'sequence', ()),
    ),
    'mlv_msgs/msg/MotionMetrics': (
        ('verdict', 'uint8', 0),
        ('verdict_reasons', 'string', ''),
        ('study_id', 'string', ''),
        ('run_id', 'string', ''),
        ('segment_origin', 'uint8', 0),
        ('segment_origin_confidence', 'float64', 0.0),
        *((n, 'sequence', ()) for n in ('segment_err_unc', 'segment_ecc_unc', 'segment_ell_unc')),
        ('findings_es_phase', 'int32', -1),
        *((n, 'sequence', ()) for n in FINDING_ARRAY_FIELDS),
        ('segment_class', 'sequence', ()),
        ('degraded_segments', 'sequence', ()),
        ('segment_tag_ecc', 'sequence', ()),
        ('segment_tag_ecc_unc', 'sequence', ()),
    ),
    # study_id (string ""); then run_id (string ""); TagPoints then line_normal (empty: grid),
    # TaggedFrame then tag_lines (0: a grid)
    'mlv_msgs/msg/TaggedFrame': (
        ('study_id', 'string', ''),
        ('run_id', 'string', ''),
        ('tag_lines', 'uint8', 0),
    ),
    'mlv_msgs/msg/TagPoints': (
        ('study_id', 'string', ''),
        ('run_id', 'string', ''),
        ('line_normal', 'sequence', ()),
    ),
}


# Fields appended together (one change of the definition), oldest first: an older recording
# lacks whole groups only, so only these are tried when the schema is not known.
_APPENDED_GROUPS = {
    'mlv_msgs/msg/ModelState': (2, 1, 1, 2, 1, 2),
    'mlv_msgs/msg/MotionMetrics': (2, 1, 1, 21, 1, 2),
    'mlv_msgs/msg/TaggedFrame': (1, 1, 1),
    'mlv_msgs/msg/TagPoints': (1, 1, 1),
}


def _older_definitions(type_name: str, n: int) -> list[int]:
    """How many of the last appended fields each older definition lacks, newest first."""
    sizes = _APPENDED_GROUPS.get(type_name, (1,) * n)
    return [sum(sizes[-i:]) for i in range(1, len(sizes) + 1)]


def _field_names(definition: str) -> list[str]:
    """Field names of the top-level message of a ``ros2msg`` definition (constants left out)."""
    names = []
    for line in definition.split(_SEPARATOR)[0].splitlines():
        line = line.split('#', 1)[0].strip()
        parts = line.split()
        if len(parts) >= 2 and '=' not in parts[1] and '=' not in parts[0]:
            names.append(parts[1])
    return names


def fields_missing_from(type_name: str, definition: str) -> tuple | None:
    """
    Return the appended fields a recording's ``ros2msg`` schema of ``type_name`` lacks.

    See :data:`_APPENDED_FIELDS`: ``()`` for the current definition, ``None`` when it cannot tell
    (no schema text, or not a known older definition).
    """
    appended = _APPENDED_FIELDS.get(type_name, ())
    names = _field_names(definition) if definition else []
    if not names:
        return None
    absent = [i for i, (name, _, _) in enumerate(appended) if name not in names]
    if absent and absent != list(range(absent[0], len(appended))):
        return None  # not a suffix: not one of our older definitions
    return appended[absent[0]:] if absent else ()


def _cdr_defaults(data: bytes, fields) -> bytes:
    """
    Return CDR message ``data`` with ``fields`` appended, aligned as CDR aligns them.

    ``data`` is a CDR message with its 4-byte encapsulation header; ``fields`` are (name, kind,
    default) each, aligned relative to the end of the header.
    """
    little = data[1] & 1  # representation id 0x0001 = CDR little endian, 0x0000 big endian
    order = 'little' if little else 'big'
    out = bytearray(data)
    for _name, kind, value in fields:
        if kind == 'uint8':
            out += int(value).to_bytes(1, order)
        elif kind == 'int32':
            out += b'\0' * (-(len(out) - 4) % 4)
            out += int(value).to_bytes(4, order, signed=True)
        elif kind == 'float64':
            out += b'\0' * (-(len(out) - 4) % 8)
            out += struct.pack('<d' if little else '>d', float(value))
        elif kind == 'sequence':  # an empty sequence: its length 0
            out += b'\0' * (-(len(out) - 4) % 4)
            out += (0).to_bytes(4, order)
        elif kind == 'string':
            raw = str(value).encode() + b'\0'
            out += b'\0' * (-(len(out) - 4) % 4)
            out += len(raw).to_bytes(4, order) + raw
        else:  # pragma: no cover - only the kinds above are ever appended
            raise ValueError(f'no CDR default for {kind}')
    return bytes(out)


def _type_name(msg_class) -> str:
    return f'{msg_class.__module__.split(".")[0]}/msg/{msg_class.__name__}'


def _reads_defaults(msg, fields) -> bool:
    """
    Check whether the appended ``fields`` read back as the defaults they were appended with.

    Under a wrong older definition the bytes can parse yet shift, and a default then reads as part
    of another field (e.g. a float from a string's length).
    """
    for name, kind, value in fields:
        got = getattr(msg, name)
        if (len(got) != 0) if kind == 'sequence' else (got != value):
            return False
    return True


def _read_as(data: bytes, msg_class, missing: tuple | None):
    """
    (message, the fields that were appended) for ``data``.

    With ``missing`` known (from the recording's schema, :func:`fields_missing_from`) those are
    appended. Without, the current definition is tried, then the one before the last group of
    fields (:data:`_APPENDED_GROUPS`) was appended, then the oldest, then those in between, and a
    guess counts only when its appended fields read back as their defaults
    (:func:`_reads_defaults`): under a wrong older definition the bytes can parse (appended
    strings read as a verdict of 1 and empty reasons; a ModelState of before the study id with
    the newest group appended read a float from a string's length).
    """
    from rclpy.serialization import deserialize_message

    if missing is not None:
        return deserialize_message(
            _cdr_defaults(data, missing) if missing else data, msg_class
        ), missing
    try:
        return deserialize_message(data, msg_class), ()
    except Exception as exc:  # rclpy raises its private RMWError
        appended = _APPENDED_FIELDS.get(_type_name(msg_class), ())
        n = len(appended)
        ends = _older_definitions(_type_name(msg_class), n)
        if len(data) >= 4 and ends:
            for k in dict.fromkeys([ends[0], ends[-1], *ends[-2:0:-1]]):
                candidate = _cdr_defaults(data, appended[-k:])
                try:
                    msg = deserialize_message(candidate, msg_class)
                except Exception:
                    continue
                if _reads_defaults(msg, appended[-k:]):
                    return msg, appended[-k:]
        raise exc


def message_class(type_name: str):
    """
    Return the generated Python message class of a type named as rosbag2 names it.

    Parameters
    ----------
    type_name : str
        ``pkg/msg/Type``, e.g. ``sensor_msgs/msg/PointCloud2``.

    Returns
    -------
    type
        The class (its package is imported).

    """
    pkg, _, name = type_name.split('/')
    return getattr(importlib.import_module(f'{pkg}.msg'), name)


def deserialize(data: bytes, msg_class, missing: tuple | None = None):
    """
    Deserialise a recorded message with rclpy, also one recorded before fields were appended.

    Fields appended to our message definitions later (:data:`_APPENDED_FIELDS`) read as their
    defaults.

    Parameters
    ----------
    data : bytes
        The recorded CDR.
    msg_class : type
        The message class.
    missing : tuple, optional
        The fields the recording lacks (:attr:`BagMessage.missing`, from its schema); found by
        trying when not given.

    Raises
    ------
    ValueError
        The bytes are not a ``msg_class`` message under any of its definitions.

    """
    try:
        return _read_as(data, msg_class, missing)[0]
    except Exception as exc:
        raise ValueError(f'cannot deserialise {msg_class.__name__}: {exc}') from None


def current_cdr(data: bytes, msg_class, missing: tuple | None = None) -> bytes:
    """
    Return ``data`` as the current definition of ``msg_class`` serialises it.

    A message recorded before fields were appended gets their defaults appended (what a live
    subscriber can read); a current one comes back unchanged.

    Raises
    ------
    ValueError
        The bytes are not a ``msg_class`` message under any of its definitions.

    """
    if missing is None:
        try:
            missing = _read_as(data, msg_class, None)[1]
        except Exception as exc:
            raise ValueError(f'cannot deserialise {msg_class.__name__}: {exc}') from None
    return _cdr_defaults(data, missing) if missing else data


def bag_topics(path) -> dict[str, dict]:
    """Topic → {type, count, qos, type_hash} from an MCAP file's summary."""
    path = Path(path)
    if path.is_dir():
        path = _bag_file_in_dir(path)
    with open(path, 'rb') as fh:
        try:
            summary = make_reader(fh).get_summary()
        except Exception as exc:
            raise ValueError(f'cannot read {path} as MCAP: {exc}') from exc
    if summary is None:
        raise ValueError(
            f'{path} has no MCAP summary (unfinished recording? try `mlv-ros recover`)'
        )
    counts = summary.statistics.channel_message_counts if summary.statistics else {}
    out = {}
    for cid, ch in summary.channels.items():
        schema = summary.schemas.get(ch.schema_id)
        out[ch.topic] = {
            'type': schema.name if schema else '',
            'count': counts.get(cid, 0),
            'qos': ch.metadata.get('offered_qos_profiles', ''),
            'type_hash': ch.metadata.get('topic_type_hash', ''),
        }
    return out


def _bag_file_in_dir(directory: Path) -> Path:
    if (directory / 'metadata.yaml').is_file():
        # rosbag2 may store the path with the bag directory in front (older versions did).
        return directory / Path(read_bag_metadata(directory)['relative_file_paths'][0]).name
    files = sorted(directory.glob('*.mcap'))
    if not files:
        raise ValueError(f'no .mcap file in {directory}')
    return files[0]


# --------------------------------------------------------------------------- recovery
def recover(damaged, out) -> dict:
    """
    Rewrite a valid recording from a damaged one (e.g. the recorder was SIGKILLed).

    Reads the file record by record from the start (no summary or index needed) and keeps every
    message of every chunk that is complete; reading stops at the first truncated or corrupt
    record. Schemas, channels (with their QoS and type-hash metadata) and message times are
    kept as recorded; a final ``rosbag2`` metadata record describes what was recovered (the
    damaged file has only the one written when it was opened). Returns ``{"messages": n,
    "topics": {topic: n}, "stopped_at": reason}``.
    """
    from mcap.stream_reader import StreamReader

    damaged, out = Path(damaged), Path(out)
    if out.exists():
        raise FileExistsError(f'refusing to overwrite {out}')
    stopped = 'end of file'
    with open(damaged, 'rb') as fh, open(out, 'wb') as oh:
        writer = Writer(oh, compression=CompressionType.ZSTD)
        writer.start(profile='ros2', library=f'mlv_ros {__version__} (recovered)')
        copy = _RecordCopy(writer)
        try:
            for rec in StreamReader(fh, validate_crcs=True).records:
                copy.add(rec)
        except Exception as exc:  # truncated or corrupt tail: keep what came before it
            if isinstance(exc, (KeyboardInterrupt, SystemExit)):
                raise
            stopped = f'{type(exc).__name__}: {exc}'
        write_rosbag2_record(
            writer,
            bag_metadata(
                out.name,
                copy.topics.values(),
                copy.start_ns,
                copy.end_ns,
                copy.custom_data if isinstance(copy.custom_data, dict) else None,
            ),
        )
        writer.finish()
    counts = copy.counts
    return {'messages': sum(counts.values()), 'topics': counts, 'stopped_at': stopped}


class _RecordCopy:
    """
    Copy a recording's records one by one into a new one, keeping what a final record needs.

    Parameters
    ----------
    writer : mcap.writer.Writer
        The new recording, started.

    """

    def __init__(self, writer: Writer):
        self.writer = writer
        self.schemas, self.channels, self.counts = {}, {}, {}
        self.topics: dict[int, _Topic] = {}
        self.custom_data = None
        self.start_ns, self.end_ns = None, 0
        self.sid_map, self.cid_map = {}, {}

    def add(self, rec) -> None:
        """Copy a schema, channel or message record; read the rosbag2 custom data; skip others."""
        from mcap.records import Channel as ChannelRec
        from mcap.records import Message as MessageRec
        from mcap.records import Metadata as MetadataRec
        from mcap.records import Schema as SchemaRec

        writer = self.writer
        if isinstance(rec, SchemaRec):
            self.sid_map[rec.id] = writer.register_schema(rec.name, rec.encoding, rec.data)
            self.schemas[rec.id] = rec.name
        elif isinstance(rec, ChannelRec):
            self.cid_map[rec.id] = writer.register_channel(
                rec.topic,
                rec.message_encoding,
                self.sid_map.get(rec.schema_id, 0),
                rec.metadata,
            )
            self.channels[rec.id] = rec.topic
            self.topics[rec.id] = _Topic(
                rec.topic,
                self.schemas.get(rec.schema_id, ''),
                self.cid_map[rec.id],
                parse_offered_qos(rec.metadata.get('offered_qos_profiles', '')),
                rec.metadata.get('topic_type_hash', ''),
            )
        elif isinstance(rec, MetadataRec) and rec.name == 'rosbag2':
            try:
                self.custom_data = yaml.safe_load(
                    rec.metadata.get('serialized_metadata', '')
                ).get('custom_data')
            except (yaml.YAMLError, AttributeError):
                pass
        elif isinstance(rec, MessageRec) and rec.channel_id in self.cid_map:
            writer.add_message(
                self.cid_map[rec.channel_id],
                rec.log_time,
                rec.data,
                rec.publish_time,
                rec.sequence,
            )
            topic = self.channels[rec.channel_id]
            self.counts[topic] = self.counts.get(topic, 0) + 1
            self.topics[rec.channel_id].count += 1
            t = rec.log_time
            self.start_ns = t if self.start_ns is None else min(self.start_ns, t)
            self.end_ns = max(self.end_ns, t)
