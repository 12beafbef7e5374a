"""rosbag2 tools for beo_ros, without ros2cli or rosbag2: replay, record and PCD-scene conversion.

Bags are read and written with the pure-Python ``rosbags`` library (sqlite3 ``.db3`` and ``.mcap``
storage, detected from the bag's metadata), and messages cross into rclpy as raw CDR bytes
(``rclpy.serialization``) -- the same wire format, so nothing is converted on the way.

Console entry points:

``beo-replay BAG``
    Plays the ``sensor_msgs/PointCloud2`` topics of a bag (all topics with ``--all-topics``, or the
    ones named with ``--topics``) into the live graph, timed by the bag's receive timestamps divided
    by ``--rate`` (``--rate 0``: as fast as possible). Header stamps are left as recorded. Reports
    per-topic counts and the wall duration as a table (``--json`` for machine-readable output).
    Exit code 130 when Ctrl-C cuts it short (0 for a ``--loop`` replay that played), 143 on
    SIGTERM.
    In-process use: :func:`replay`.

``beo-record TOPIC[:TYPE] ... -o BAG``
    Records topics to a new bag until SIGINT or SIGTERM (either closes the bag, exit code 0),
    ``--duration`` or ``--count``. Types are discovered
    from the graph or given as ``TOPIC:pkg/msg/Type``. Message definitions of types that the
    rosbags Jazzy typestore lacks (e.g. ``beo_interfaces/msg/ObjectEstimate``) are parsed from the
    package's ``.msg`` files, so the bag is self-describing. In-process use: :func:`record`.

``beo-pcd2bag SCENE.pcd ... -o BAG``
    Labelled organized tabletop scenes (OSD format) -> one bag with, per scene (scenes ``--period``
    apart):

    - ``--topic`` (default ``/beo/input``), ``sensor_msgs/PointCloud2``: one cloud per segmented
      object (points x y z float32, frame ``camera``, sensor at the origin); objects with fewer
      than ``--min-points`` points are skipped. The objects of a scene follow each other
      ``--object-period`` apart (first at the scene stamp) so that each has a unique stamp and a
      node that keeps only the latest cloud gets time to process each one;
    - ``/beo/up``, ``geometry_msgs/Vector3Stamped``: unit up vector (table normal pointing towards
      the camera side, from an open3d RANSAC fit of the table points), frame ``camera``, scene
      stamp;
    - ``/beo/table_plane``, ``std_msgs/Float64MultiArray``: plane ``[a, b, c, d]`` with
      ``a x + b y + c z + d = 0``, ``(a, b, c)`` the up vector above (camera frame), scene stamp.

    Each message's bag (receive) timestamp equals its header stamp. A file without a label field
    is refused; a scene without object labels (>= 20) is skipped with a warning.

Bad arguments (numbers out of range, invalid topic or node names, an output that exists) exit 2
with one line; Ctrl-C, one line and exit code 130, SIGTERM 143 (beo-record: both stop the
recording and close the bag, exit code 0), leaving no partial pcd2bag bag.
"""
from __future__ import annotations

import argparse
import contextlib
import functools
import importlib
import json
import math
import os
import re
import shutil
import signal
import sys
import threading
import time
import weakref
from dataclasses import asdict, dataclass, field
from pathlib import Path

from beo_ros.cli import INTERRUPTED, count, interruptible, number

STORAGES = ('sqlite3', 'mcap')
CLOUD_TYPE = 'sensor_msgs/msg/PointCloud2'
UP_TOPIC = '/beo/up'
PLANE_TOPIC = '/beo/table_plane'
DEFAULT_INPUT_TOPIC = '/beo/input'
DEFAULT_FRAME = 'camera'
T0_NS = 1_700_000_000_000_000_000  # first stamp written by pcd2bag (and the demo)
MAX_NS = 2**63 - 1                 # bag timestamps are int64 nanoseconds
MAX_PERIOD_S = 86_400.0            # --period / --object-period bound of beo-pcd2bag


# ---------------------------------------------------------------------------------------------
# names
# ---------------------------------------------------------------------------------------------

def _name_reason(exc) -> str:
    """rcl's reason from a name validation error, on one line."""
    first = (str(exc).splitlines() or [type(exc).__name__])[0]
    first = re.sub(r', at \S+:\d+$', '', first).rstrip(': ')
    m = re.search(r'(?:is invalid|Invalid \w+ name): (.*)', first)
    return m.group(1) if m else first


def check_topic_name(name: str, node_name: str = 'beo') -> str:
    """``name`` expanded as a topic of node ``node_name`` in namespace ``/`` ('x' -> '/x');
    ``ValueError`` with rcl's reason if it is not a valid ROS 2 topic name."""
    from rclpy.expand_topic_name import expand_topic_name
    from rclpy.validate_full_topic_name import validate_full_topic_name
    try:
        full = expand_topic_name(name, node_name, '/')
        validate_full_topic_name(full)
    except Exception as e:  # noqa: BLE001 - rcl raises ValueError or NameValidationException
        raise ValueError(f'bad topic name {name!r}: {_name_reason(e)}') from None
    return full


def check_node_name(name: str) -> str:
    """``name`` if it is a valid ROS 2 node name, else ``ValueError`` with rcl's reason."""
    from rclpy.validate_node_name import validate_node_name
    try:
        validate_node_name(name)
    except Exception as e:  # noqa: BLE001
        raise ValueError(f'bad node name {name!r}: {_name_reason(e)}') from None
    return name


# ---------------------------------------------------------------------------------------------
# message types
# ---------------------------------------------------------------------------------------------

def normalize_msgtype(name: str) -> str:
    """'pkg/Type', 'pkg/msg/Type' or 'pkg.msg.Type' -> 'pkg/msg/Type'."""
    parts = [p for p in re.split(r'[/.]', name.strip()) if p]
    if len(parts) == 2:
        parts = [parts[0], 'msg', parts[1]]
    if len(parts) != 3 or parts[1] != 'msg':
        raise ValueError(f'not a message type name: {name!r} (expected pkg/msg/Type)')
    return '/'.join(parts)


def import_msg_class(msgtype: str):
    """The rclpy message class of 'pkg/msg/Type'; ``KeyError`` naming it if not installed."""
    pkg, _, name = normalize_msgtype(msgtype).split('/')
    if pkg == 'beo_interfaces':
        from beo_ros.ros.env import ensure_ament_prefix
        ensure_ament_prefix()
    try:
        return getattr(importlib.import_module(f'{pkg}.msg'), name)
    except (ImportError, AttributeError):
        raise KeyError(f'message type {pkg}/msg/{name} is not installed (no Python module '
                       f'{pkg}.msg with {name})') from None


def msgtype_of(msg) -> str:
    """'pkg/msg/Type' of an rclpy message instance or class."""
    cls = msg if isinstance(msg, type) else type(msg)
    return f'{cls.__module__.split(".")[0]}/msg/{cls.__name__}'


def _msg_search_dirs(pkg: str) -> list:
    """Directories that may hold ``pkg``'s ``.msg`` files: ament prefixes, then this checkout."""
    dirs = []
    prefixes = os.environ.get('AMENT_PREFIX_PATH', '')
    if pkg == 'beo_interfaces':
        try:
            from beo_ros.ros.env import ensure_ament_prefix
            ensure_ament_prefix()
            prefixes = os.environ.get('AMENT_PREFIX_PATH', '')
        except Exception:  # noqa: BLE001 - the source checkout below still works
            pass
    for prefix in [p for p in prefixes.split(os.pathsep) if p] + [sys.prefix]:
        dirs.append(Path(prefix) / 'share' / pkg / 'msg')
    try:  # next to the python package (some wheels ship the definitions there)
        mod = importlib.import_module(pkg)
        for p in getattr(mod, '__path__', []):
            dirs.append(Path(p) / 'msg')
    except Exception:  # noqa: BLE001
        pass
    dirs.append(Path(__file__).resolve().parents[3] / pkg / 'msg')  # source checkout
    return dirs


def _find_msg_file(msgtype: str) -> Path | None:
    pkg, _, name = msgtype.split('/')
    for d in _msg_search_dirs(pkg):
        f = d / f'{name}.msg'
        if f.is_file():
            return f
    return None


def _referenced_types(obj) -> set:
    """Every 'pkg/msg/Type' string nested anywhere in a rosbags field definition."""
    out = set()
    if isinstance(obj, str):
        if re.fullmatch(r'[A-Za-z0-9_]+/msg/[A-Za-z0-9_]+', obj):
            out.add(obj)
    elif isinstance(obj, (tuple, list)):
        for x in obj:
            out |= _referenced_types(x)
    return out


_TYPESTORE = None
_TYPESTORE_LOCK = threading.Lock()


def get_typestore(msgtypes=()):
    """The rosbags ROS 2 Jazzy typestore with ``msgtypes`` (and what they use) registered.

    Types missing from the stock store are parsed from their ``.msg`` files (ament share
    directories, or this source checkout for ``beo_interfaces``). Raises ``KeyError`` if a
    definition cannot be found.
    """
    global _TYPESTORE
    from rosbags.typesys import Stores, get_types_from_msg
    from rosbags.typesys import get_typestore as _get

    with _TYPESTORE_LOCK:
        if _TYPESTORE is None:
            _TYPESTORE = _get(Stores.ROS2_JAZZY)
        store = _TYPESTORE
        todo = [normalize_msgtype(t) for t in msgtypes]
        seen = set()
        while todo:
            t = todo.pop()
            if t in seen:
                continue
            seen.add(t)
            if t not in store.fielddefs:
                f = _find_msg_file(t)
                if f is None:
                    raise KeyError(f'no message definition found for {t}')
                store.register(get_types_from_msg(f.read_text(), t))
            todo.extend(_referenced_types(store.fielddefs[t]) - seen)
        return store


# ---------------------------------------------------------------------------------------------
# bag I/O
# ---------------------------------------------------------------------------------------------

def _storage_plugin(storage: str):
    from rosbags.rosbag2 import StoragePlugin
    if storage not in STORAGES:
        raise ValueError(f'storage must be one of {STORAGES}, got {storage!r}')
    return StoragePlugin.SQLITE3 if storage == 'sqlite3' else StoragePlugin.MCAP


def detect_storage(bag_path) -> str:
    """'sqlite3' or 'mcap' for a bag directory (from metadata.yaml / file suffix) or file."""
    p = Path(bag_path)
    meta = p / 'metadata.yaml'
    if meta.is_file():
        m = re.search(r'storage_identifier:\s*(\S+)', meta.read_text(errors='replace'))
        if not m:
            raise ValueError(f'{meta}: no storage_identifier (not a rosbag2 metadata.yaml?)')
        return m.group(1).strip('\'"')
    files = [p] if p.is_file() else list(p.glob('*'))
    for f in files:
        if f.suffix == '.mcap':
            return 'mcap'
        if f.suffix == '.db3':
            return 'sqlite3'
    raise ValueError(f'{bag_path}: not a rosbag2 bag (no metadata.yaml, .db3 or .mcap)')


def _qos_for_bag(reliable: bool = True, transient_local: bool = False):
    """The offered QoS stored in the bag metadata (as ros2 bag writes it)."""
    from rosbags.interfaces import (Qos, QosDurability, QosHistory, QosLiveliness,
                                    QosReliability, QosTime)
    zero = QosTime(sec=0, nsec=0)
    return Qos(history=QosHistory.UNKNOWN, depth=0,
               reliability=QosReliability.RELIABLE if reliable else QosReliability.BEST_EFFORT,
               durability=QosDurability.TRANSIENT_LOCAL if transient_local
               else QosDurability.VOLATILE,
               deadline=zero, lifespan=zero, liveliness=QosLiveliness.AUTOMATIC,
               liveliness_lease_duration=zero, avoid_ros_namespace_conventions=False)


def storage_errors() -> tuple:
    """Exception types of a failing bag write or read: the file system's (disk full, ...), the
    sqlite3 databases' (``sqlite3.Error`` when writing, ``apsw.Error`` when reading) and
    rosbags' own."""
    import sqlite3

    from rosbags.rosbag2 import ReaderError, WriterError
    errors = [OSError, sqlite3.Error, ReaderError, WriterError]
    try:
        import apsw
        errors.append(apsw.Error)
    except ImportError:   # only the sqlite3 reader of rosbags uses it
        pass
    return tuple(errors)


class BagWriter:
    """Writes rclpy messages (or raw CDR bytes) to a new rosbag2 bag.

    >>> with BagWriter(path, storage='mcap') as w:
    ...     w.write('/beo/input', cloud_msg, stamp_ns)

    A write that fails (disk full, ...) marks the writer ``failed``: leaving the ``with`` block
    then aborts it instead of closing it, so that no metadata.yaml claims messages the storage
    lost (sqlite rolls the open transaction back on such errors). :meth:`commit` makes what is
    written so far survive a crash (:func:`recover_bag` reads it back).
    """

    def __init__(self, path, storage: str = 'sqlite3'):
        from rosbags.rosbag2 import Writer
        self.path = Path(path)
        self.storage = storage
        self._writer = Writer(self.path, version=Writer.VERSION_LATEST,
                              storage_plugin=_storage_plugin(storage))
        self._conns = {}
        self.counts = {}
        self.failed = False
        self._opened = False
        self.committed = 0   # messages made durable by the last commit()

    @property
    def storage_file(self) -> Path:
        """The .db3 / .mcap file of the bag."""
        return self.path / f'{self.path.name}.{"db3" if self.storage == "sqlite3" else "mcap"}'

    def open(self):
        existed = self.path.exists() or self.path.is_symlink()
        try:
            self._writer.open()
        except Exception:
            if not existed and self.path.is_dir():   # made, but no database in it
                shutil.rmtree(self.path, ignore_errors=True)
            raise
        self._opened = True   # the directory is ours: it may be removed after a failure
        return self

    def close(self):
        try:
            self._writer.close()
        except Exception:
            self.failed = True
            self.abort()
            raise

    def abort(self):
        """Close without metadata.yaml; the file keeps what :meth:`commit` committed."""
        with contextlib.suppress(Exception):
            self._writer.abort()

    def commit(self) -> bool:
        """Make what is written so far survive a crash or SIGKILL -> True if done.

        sqlite3: commit the transaction (the .db3 file then reads on its own, without
        metadata.yaml). mcap: end the pending chunk and flush the file; without the footer
        that :meth:`close` writes, :func:`recover_bag` reads it back."""
        storage = self._writer.storage
        try:
            if self.storage == 'sqlite3':
                conn = getattr(storage, 'conn', None)
                if conn is None:
                    return False
                conn.commit()
            else:
                if storage is None or not hasattr(storage, 'close_chunk'):
                    return False
                if storage.chunk.bio.tell():
                    storage.close_chunk()
                storage.bio.flush()
        except Exception:
            self.failed = True
            raise
        self.committed = sum(self.counts.values())
        return True

    def __enter__(self):
        return self.open()

    def __exit__(self, *exc):
        if self.failed:
            self.abort()
        else:
            self.close()

    def add_topic(self, topic: str, msgtype: str, *, reliable: bool = True,
                  transient_local: bool = False, msgdef: str | None = None,
                  rihs01: str | None = None):
        """Add ``topic`` (once; another type for it is a ValueError). Its definition comes from
        the typestore (KeyError for an unknown type), or is ``msgdef`` + ``rihs01`` as given
        (copied from another bag)."""
        msgtype = normalize_msgtype(msgtype)
        if topic in self._conns:
            if self._conns[topic].msgtype != msgtype:
                raise ValueError(f'{topic}: already has type {self._conns[topic].msgtype}')
            return self._conns[topic]
        store = None if msgdef and rihs01 else get_typestore([msgtype])
        try:
            conn = self._writer.add_connection(
                topic, msgtype, typestore=store, msgdef=msgdef if store is None else None,
                rihs01=rihs01 if store is None else None,
                offered_qos_profiles=[_qos_for_bag(reliable, transient_local)])
        except storage_errors():
            self.failed = True
            raise
        self._conns[topic] = conn
        self.counts[topic] = 0
        return conn

    def write(self, topic: str, msg, stamp_ns: int, msgtype: str | None = None):
        """Write one message; ``msg`` is an rclpy message, or CDR bytes with ``msgtype`` given."""
        if isinstance(msg, (bytes, bytearray, memoryview)):
            if msgtype is None and topic not in self._conns:
                raise ValueError('raw bytes need msgtype for a new topic')
            data = bytes(msg)
        else:
            from rclpy.serialization import serialize_message
            msgtype = msgtype or msgtype_of(msg)
            data = serialize_message(msg)
        conn = self._conns.get(topic)
        if conn is None or (msgtype is not None and msgtype != conn.msgtype):
            # add_topic refuses a type other than the topic's: the bag would not deserialize
            conn = self.add_topic(topic, msgtype)
        try:
            self._writer.write(conn, int(stamp_ns), data)
        except storage_errors():
            self.failed = True
            raise
        self.counts[topic] += 1


def hot_journal(bag_path) -> Path | None:
    """The non-empty rollback journal beside a bag's .db3 file (a recording killed in the
    middle of a transaction), or None. rosbags opens the database as immutable, ignoring it,
    and would read pages of the unfinished transaction: a torn or malformed database."""
    p = Path(bag_path)
    dbs = [p] if p.suffix == '.db3' else (sorted(p.glob('*.db3')) if p.is_dir() else [])
    for db in dbs:
        journal = db.with_name(db.name + '-journal')
        if journal.is_file() and journal.stat().st_size > 0:
            return journal
    return None


def _check_no_hot_journal(bag_path):
    journal = hot_journal(bag_path)
    if journal is not None:
        raise ValueError(f'{journal}: the bag was left in the middle of a write (its rollback '
                         'journal is there): read it through beo-bag-recover BAG -o NEW')


def read_bag(bag_path, topics=None):
    """Yield ``(topic, msgtype, timestamp_ns, raw_cdr_bytes)`` in timestamp order. ValueError
    for a .db3 left in the middle of a write (see :func:`hot_journal`)."""
    from rosbags.rosbag2 import Reader
    _check_no_hot_journal(bag_path)
    with Reader(Path(bag_path)) as reader:
        conns = [c for c in reader.connections if topics is None or c.topic in topics]
        if not conns:
            return
        for conn, t, raw in reader.messages(connections=conns):
            yield conn.topic, conn.msgtype, t, bytes(raw)


def read_messages(bag_path, topics=None):
    """Yield ``(topic, rclpy_message, timestamp_ns)``, deserialized with rclpy."""
    from rclpy.serialization import deserialize_message
    classes = {}
    for topic, msgtype, t, raw in read_bag(bag_path, topics):
        if msgtype not in classes:
            classes[msgtype] = import_msg_class(msgtype)
        yield topic, deserialize_message(raw, classes[msgtype]), t


def bag_info(bag_path) -> dict:
    """Storage, duration and ``{topic: {'type', 'count'}}`` of a bag."""
    from rosbags.rosbag2 import Reader
    _check_no_hot_journal(bag_path)
    with Reader(Path(bag_path)) as reader:
        topics = {}
        for c in reader.connections:
            d = topics.setdefault(c.topic, {'type': c.msgtype, 'count': 0})
            d['count'] += c.msgcount
        return {'path': str(bag_path), 'storage': detect_storage(bag_path),
                'start_ns': reader.start_time if reader.message_count else 0,
                'duration_s': reader.duration / 1e9 if reader.message_count else 0.0,
                'message_count': reader.message_count, 'topics': topics}


MCAP_MAGIC = b'\x89MCAP0\r\n'
_MCAP_FOOTER_HEAD = b'\x02\x14' + bytes(7)   # opcode 2, length 20


def _mcap_record_ends(path, trust_footer: bool = True) -> tuple[list, bool]:
    """-> (offsets just past each intact record of an mcap file's data section, ascending, the
    header's first; whether the file was closed: it ends in a footer and the magic, and
    ``trust_footer``). A record is intact when all its bytes are there and, for a chunk, its
    records decompress to their stated size (and checksum, if one was stored)."""
    from rosbags.rosbag2.storage_mcap import decompress
    size = os.path.getsize(path)
    with open(path, 'rb') as f:
        magic = f.read(8)
        if not magic:
            raise ValueError(f'{path}: empty file: nothing to recover')
        if magic != MCAP_MAGIC[:len(magic)]:
            raise ValueError(f'{path}: not an mcap file (no magic at its start)')
        head = f.read(9)
        if (len(head) < 9 or head[0] != 0x01
                or 17 + int.from_bytes(head[1:], 'little') > size):
            raise ValueError(f'{path}: cut off before the end of its header record: nothing '
                             'to recover')
        if trust_footer and size >= 8 + 37:
            f.seek(size - 37)
            tail = f.read(37)
            if tail[:9] == _MCAP_FOOTER_HEAD and tail[-8:] == MCAP_MAGIC:
                return [size], True
        pos, ends = 8, []
        while pos + 9 <= size:
            f.seek(pos)
            op, length = f.read(1)[0], int.from_bytes(f.read(8), 'little')
            # 0x0f data end, 0x02 footer: the summary after them was being written
            if not 0x01 <= op <= 0x10 or op in (0x02, 0x0f) or pos + 9 + length > size:
                break
            if op == 0x06 and not _chunk_decompresses(f.read(length), decompress):
                break
            pos += 9 + length
            ends.append(pos)
    return ends, False


def _chunk_decompresses(body: bytes, decompress) -> bool:
    """Whether a chunk record's body (start, end, uncompressed size, crc, compression, records)
    holds records that decompress to their stated size (and crc, if not 0)."""
    usize = int.from_bytes(body[16:24], 'little')
    crc = int.from_bytes(body[24:28], 'little')
    n = int.from_bytes(body[28:32], 'little')
    if 32 + n + 8 > len(body) or 32 + n + 8 + int.from_bytes(body[32 + n:40 + n], 'little') \
            != len(body):
        return False
    try:
        decompress(body[40 + n:], body[32:32 + n].decode(errors='replace'), usize, crc)
    except Exception:  # noqa: BLE001 - ReaderError, zstd's and lz4's own errors, MemoryError
        return False
    return True


def _bag_file(src) -> Path:
    """The .db3 / .mcap file of a bag directory (or the file itself)."""
    p = Path(src)
    if p.is_file():
        if p.suffix not in ('.db3', '.mcap'):
            raise ValueError(f'{src}: not a .db3 or .mcap file')
        return p
    if not p.is_dir():
        raise ValueError(f'{src}: no such bag')
    files = sorted(f for f in p.iterdir() if f.suffix in ('.db3', '.mcap'))
    if len(files) != 1:
        raise ValueError(f'{src}: expected one .db3 or .mcap file, found '
                         f'{len(files) or "none"}')
    return files[0]


class _Damaged(Exception):
    """rosbags could not read a (repaired) bag to its end."""


def recover_bag(src, dst, *, storage: str | None = None) -> dict:
    """Copy every intact message of a bag that was never closed (a recording ended by SIGKILL,
    a crash or a full disk: no metadata.yaml, an mcap file without its footer) into a new,
    closed bag ``dst``, as ``ros2 bag reindex`` and ``mcap recover`` would.

    ``src``: bag directory or its .db3 / .mcap file; ``storage``: dst's (default src's).
    -> ``{'messages', 'topics': {topic: count}, 'storage', 'lost_bytes'}``; ``lost_bytes``:
    the tail of an mcap file after its last intact record (0 for sqlite3): a record cut off or
    damaged, or a chunk that does not decompress to its size, and all after it. A closed mcap
    file whose index does not read is read as if it had none. ValueError for a source that is
    not a bag, an mcap file cut off inside its header, or a database that does not read.
    """
    import tempfile
    path = _bag_file(src)
    storage = storage or ('mcap' if path.suffix == '.mcap' else 'sqlite3')
    dst = Path(dst)
    ends, closed = _mcap_record_ends(path) if path.suffix == '.mcap' else ([], True)
    dst.parent.mkdir(parents=True, exist_ok=True)   # as rosbags' writer would
    end = os.path.getsize(path)
    with tempfile.TemporaryDirectory(prefix='.beo_recover_', dir=dst.parent) as tmp:
        tmp = Path(tmp)
        if path.suffix == '.db3':
            try:
                topics = _copy_messages(_rolled_back(path, tmp), dst, storage, False)
            except _Damaged as e:
                raise ValueError(f'{path}: {e}') from None
        else:
            topics = None
            if closed:
                try:
                    topics = _copy_messages(path, dst, storage, False)
                except _Damaged:   # its summary (index) is damaged: scan the data instead
                    ends, _ = _mcap_record_ends(path, trust_footer=False)
            if topics is None:
                topics, end = _longest_readable_prefix(path, ends, dst, storage, tmp)
    return {'messages': sum(topics.values()), 'topics': topics, 'storage': storage,
            'lost_bytes': os.path.getsize(path) - end if path.suffix == '.mcap' else 0}


def _longest_readable_prefix(path: Path, ends: list, dst: Path, storage: str, tmp: Path):
    """Copy the longest prefix of whole records of mcap file ``path`` (ending at one of
    ``ends``) that rosbags reads to its end into ``dst`` -> ({topic: count}, its end). The
    usual case is all of them; a record can be whole yet damaged inside, and damage ends what
    reads, so the rest is a bisection. Each try writes a bag under ``tmp``; the best one is
    moved to ``dst``."""
    def attempt(i):
        trial = tmp / str(i) / dst.name
        trial.parent.mkdir()
        try:
            return _copy_messages(_repaired(path, ends[i], tmp), trial, storage, True), trial
        except _Damaged:
            return None, None

    best, bag_dir = attempt(len(ends) - 1)
    lo = len(ends) - 1 if best is not None else -1   # ends[lo] reads (-1: none known)
    hi = lo if best is not None else len(ends) - 2   # none after hi does
    while lo < hi:
        mid = (lo + hi + 1) // 2
        got, trial = attempt(mid)
        if got is None:
            hi = mid - 1
            continue
        if bag_dir is not None:
            shutil.rmtree(bag_dir)
        best, bag_dir, lo = got, trial, mid
    if best is None:
        raise ValueError(f'{path}: no record after its header reads: nothing to recover')
    os.replace(bag_dir, dst)
    return best, ends[lo]


def _rolled_back(db: Path, tmp: Path) -> Path:
    """``db``, or a copy of it in ``tmp`` with its hot journal rolled back (see
    :func:`hot_journal`)."""
    journal = hot_journal(db)
    if journal is None:
        return db
    import sqlite3
    copy = tmp / db.name
    shutil.copyfile(db, copy)
    shutil.copyfile(journal, tmp / journal.name)
    with contextlib.closing(sqlite3.connect(copy)) as conn:
        conn.execute('SELECT COUNT(*) FROM sqlite_master').fetchone()
    return copy


def _repaired(path: Path, end: int, tmp: Path) -> Path:
    """A copy in ``tmp`` of the first ``end`` bytes of mcap file ``path`` (whole records),
    closed by a data end and a footer without a summary: readers scan its data."""
    out = tmp / path.name
    with open(path, 'rb') as fin, open(out, 'wb') as fout:
        sent = 0
        while sent < end:
            n = os.sendfile(fout.fileno(), fin.fileno(), sent, end - sent)
            if n == 0:
                raise ValueError(f'{path}: shorter than {end} bytes')   # shrank meanwhile
            sent += n
        fout.seek(end)
        fout.write(b'\x0f' + (4).to_bytes(8, 'little') + bytes(4))   # data end, no crc
        fout.write(_MCAP_FOOTER_HEAD + bytes(20) + MCAP_MAGIC)
    return out


def _copy_messages(readable: Path, dst: Path, storage: str, unindexed: bool) -> dict:
    """Copy the topics and messages of bag file ``readable`` into a new bag ``dst`` ->
    ``{topic: count}``. _Damaged (and no ``dst``) when rosbags cannot read it to its end;
    the errors of writing ``dst`` (an unknown type, a full disk) as they are."""
    from rosbags.rosbag2 import Reader
    topics = {}
    reader = Reader(readable)
    try:
        reader.open()
        conns = list(reader.connections)
        for c in conns:   # a damaged channel or schema record: no valid type name
            normalize_msgtype(c.msgtype)
        # an unindexed (repaired) mcap file: its messages in file order (the reader would
        # refuse stamps that go back, e.g. two topics; the new bag indexes them)
        # (its end is exclusive: by default 2^63-1, the largest stamp there is)
        messages = iter(reader.storage.messages_scan(conns, stop=1 << 64) if unindexed
                        else reader.messages())
    except Exception as e:  # noqa: BLE001 - rosbags' errors, struct.error, MemoryError, ...
        with contextlib.suppress(Exception):
            reader.close()
        raise _Damaged(_one_line(e)) from e
    try:
        with _removed_on_error(BagWriter(dst, storage)) as writer:
            for c in conns:
                try:   # the bag's own definition: its bytes were written with it
                    definition = _own_definition(c)
                except KeyError:   # none in the bag: the installed one
                    definition = {}
                writer.add_topic(c.topic, c.msgtype, reliable=recorded_reliable(c),
                                 transient_local=recorded_latched(c), **definition)
                topics.setdefault(c.topic, 0)
            while True:
                try:
                    conn, t, raw = next(messages)
                except StopIteration:
                    break
                except Exception as e:  # noqa: BLE001 - as above
                    raise _Damaged(_one_line(e)) from e
                writer.write(conn.topic, bytes(raw), t, conn.msgtype)
                topics[conn.topic] += 1
    finally:
        with contextlib.suppress(Exception):
            reader.close()
    return topics


def _one_line(exc) -> str:
    """An exception as one line: its type and its message's lines joined."""
    text = ' '.join(str(exc).split())
    return f'{type(exc).__name__}: {text}' if text else type(exc).__name__


def _own_definition(conn) -> dict:
    """``{'msgdef', 'rihs01'}`` of a bag connection from the bag itself (an mcap file read
    without metadata.yaml has no hash: it is computed from the definition); KeyError when the
    bag has no ros2msg definition of it."""
    from rosbags.interfaces import MessageDefinitionFormat
    from rosbags.typesys import Stores, get_types_from_msg
    from rosbags.typesys import get_typestore as rosbags_typestore
    msgdef = conn.msgdef
    if msgdef.format != MessageDefinitionFormat.MSG or not msgdef.data.strip():
        raise KeyError(f'no message definition found for {conn.msgtype} (neither installed nor '
                       'in the bag)')
    rihs01 = conn.digest
    if not rihs01:
        try:
            store = rosbags_typestore(Stores.EMPTY)
            store.register(get_types_from_msg(msgdef.data, conn.msgtype))
            rihs01 = store.hash_rihs01(conn.msgtype)
        except Exception as e:  # noqa: BLE001 - rosbags' parse errors have no common base
            raise KeyError(f'{conn.msgtype}: the definition in the bag does not parse '
                           f'({e})') from None
    return {'msgdef': msgdef.data, 'rihs01': rihs01}


@contextlib.contextmanager
def _removed_on_error(writer):
    """Open ``writer``; close it on success, abort it and remove its bag on any exception."""
    with writer:
        try:
            yield writer
        except BaseException:
            writer.failed = True
            writer.abort()
            shutil.rmtree(writer.path, ignore_errors=True)
            raise


# ---------------------------------------------------------------------------------------------
# replay
# ---------------------------------------------------------------------------------------------

@dataclass
class TopicStats:
    topic: str            # topic published on (after remapping)
    bag_topic: str        # topic in the bag
    msgtype: str
    count: int = 0
    bytes: int = 0
    subscribers: int = 0  # matched subscriptions when replay ended


@dataclass
class ReplayStats:
    """What :func:`replay` sent."""

    bag: str
    storage: str
    rate: float
    loops: int = 0                      # completed passes over the bag
    messages: int = 0
    bytes: int = 0
    wall_s: float = 0.0                 # from the first to the last publish
    bag_span_s: float = 0.0             # bag timestamp span of the messages sent in a pass
    waited_s: float = 0.0               # time spent in --wait-subscribers
    interrupted: bool = False
    topics: dict = field(default_factory=dict)   # published topic -> TopicStats
    skipped: dict = field(default_factory=dict)  # bag topic -> type not installed (all_topics)
    latched: list = field(default_factory=list)  # published topics played transient-local
    clock_messages: int = 0                      # /clock messages published (clock_hz)
    # messages published before an acknowledgement wait that timed out (reliable publishers):
    # a reliable subscriber may have lost up to this many (``ack_timeout`` of :func:`replay`)
    unacked: int = 0

    @property
    def messages_per_s(self) -> float:
        return self.messages / self.wall_s if self.wall_s > 0 else float('inf')

    def to_dict(self) -> dict:
        d = asdict(self)
        d['messages_per_s'] = round(self.messages_per_s, 3) if self.wall_s > 0 else None
        d['mbytes_per_s'] = (round(self.bytes / 1e6 / self.wall_s, 3) if self.wall_s > 0
                             else None)
        return d

    def table(self) -> str:
        rows = [('topic', 'bag topic', 'type', 'count', 'MB', 'subs')]
        for s in self.topics.values():
            rows.append((s.topic, s.bag_topic, s.msgtype, str(s.count), f'{s.bytes / 1e6:.2f}',
                         str(s.subscribers)))
        widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
        lines = ['  '.join(c.ljust(w) for c, w in zip(r, widths)).rstrip() for r in rows]
        lines.insert(1, '  '.join('-' * w for w in widths))
        rate = 'max' if self.rate == 0 else f'{self.rate:g}x'
        lines.append(f'{self.messages} messages, {self.bytes / 1e6:.2f} MB in {self.wall_s:.3f} s '
                     f'(bag span {self.bag_span_s:.3f} s, rate {rate}, {self.loops} pass(es)'
                     f'{", interrupted" if self.interrupted else ""})')
        if self.clock_messages:
            lines.append(f'{self.clock_messages} /clock messages')
        if self.latched:
            lines.append('played transient-local, as recorded: ' + ', '.join(self.latched))
        if self.unacked:
            lines.append(f'{self.unacked} message(s) not acknowledged by every reliable '
                         'subscriber in time (maybe lost)')
        if self.skipped:
            lines.append(f'{len(self.skipped)} topic(s) skipped, type not installed: '
                         + ', '.join(f'{t} ({m})' for t, m in self.skipped.items()))
        return '\n'.join(lines)


def parse_remaps(remaps) -> dict:
    """['OLD:=NEW', ...] -> {OLD: NEW}; ``ValueError`` if NEW is not a valid topic name or OLD is
    remapped twice."""
    out = {}
    for r in remaps or ():
        if ':=' not in r:
            raise ValueError(f'remap must be OLD:=NEW, got {r!r}')
        old, new = r.split(':=', 1)
        if not old or not new:
            raise ValueError(f'remap must be OLD:=NEW, got {r!r}')
        check_topic_name(new)
        if out.get(old, new) != new:
            raise ValueError(f'{old} is remapped twice: to {out[old]} and to {new}')
        out[old] = new
    return out


def make_qos(kind: str = 'reliable', depth: int = 10, latched: bool = False):
    """Keep-last ``depth``, ``kind`` reliability, volatile; ``latched``: reliable and
    transient-local whatever ``kind`` (what a latched topic's subscribers ask for)."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    if kind not in ('reliable', 'best_effort'):
        raise ValueError(f'qos must be reliable or best_effort, got {kind!r}')
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                      reliability=ReliabilityPolicy.RELIABLE if kind == 'reliable' or latched
                      else ReliabilityPolicy.BEST_EFFORT,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL if latched
                      else DurabilityPolicy.VOLATILE)


def _offered_profiles(conn) -> list:
    """The offered QoS profiles a bag's metadata stores for a connection (maybe none)."""
    return getattr(getattr(conn, 'ext', None), 'offered_qos_profiles', None) or []


def recorded_latched(conn) -> bool:
    """Whether a bag connection was recorded from transient-local ("latched") publishers only,
    such as /tf_static: every offered QoS profile in the bag metadata is TRANSIENT_LOCAL."""
    profiles = _offered_profiles(conn)
    return bool(profiles) and all(
        getattr(getattr(q, 'durability', None), 'name', '') == 'TRANSIENT_LOCAL'
        for q in profiles)


def recorded_reliable(conn) -> bool:
    """Whether a bag connection had a reliable publisher (or the bag stores no QoS for it)."""
    profiles = _offered_profiles(conn)
    return not profiles or any(
        getattr(getattr(q, 'reliability', None), 'name', '') == 'RELIABLE' for q in profiles)


def _sleep_until(deadline: float, stop: threading.Event | None, tick=None,
                 period: float = 0.05) -> bool:
    """Sleep until time.monotonic() >= deadline; False if ``stop`` got set first. ``tick()``
    is called with time.monotonic() every ``period`` s while sleeping (a replay's /clock)."""
    next_tick = time.monotonic() + period
    while True:
        now = time.monotonic()
        left = deadline - now
        if stop is not None and stop.is_set():
            return False
        if left <= 0:
            return True
        if tick is not None and now >= next_tick:
            tick(now)
            next_tick += period * max(1, math.ceil((now - next_tick) / period))
            continue   # the tick took time: look at the clock again
        # here now < next_tick whenever there is a tick
        time.sleep(min(left, 0.05, next_tick - now if tick is not None else left))


_PUBLISHERS = weakref.WeakKeyDictionary()   # node -> {(topic, type, qos, depth, latched): pub}


def _publisher(node, msgtype: str, topic: str, qos: str, depth: int, latched: bool = False):
    """A publisher of ``node``, reused across replays (destroying one right after the last
    publish could drop reliable messages still in flight, creating one per replay piles up)."""
    cache = _PUBLISHERS.setdefault(node, {})
    key = (topic, msgtype, qos, depth, latched)
    if key not in cache:
        cache[key] = node.create_publisher(import_msg_class(msgtype), topic,
                                           make_qos(qos, depth, latched))
    return cache[key]


# how long a reliable publisher waits for its subscribers to acknowledge what it has sent
# before its keep-last history would overwrite a message not yet delivered
ACK_TIMEOUT_S = 5.0


class _AckGate:
    """Keeps a reliable keep-last publisher from overwriting messages its subscribers have not
    acknowledged: after every ``depth`` publishes since the last complete acknowledgement,
    :meth:`published` waits (``Publisher.wait_for_all_acked``, in 0.1 s steps so that ``stop``
    is seen) until they are all acknowledged or ``timeout`` s pass. Those that were not are
    counted in ``stats.unacked``. Best-effort publishers are not gated (nothing acknowledges)."""

    def __init__(self, timeout: float, stats, stop: threading.Event | None):
        self.timeout, self.stats, self.stop = timeout, stats, stop
        self._sent = {}   # id(publisher) -> [publisher, depth, publishes since the last wait]

    def published(self, pub) -> None:
        entry = self._sent.get(id(pub))
        if entry is None:
            from rclpy.qos import ReliabilityPolicy
            q = pub.qos_profile
            if q.reliability != ReliabilityPolicy.RELIABLE:
                return
            entry = self._sent[id(pub)] = [pub, max(1, int(q.depth)), 0]
        entry[2] += 1
        if entry[2] >= entry[1]:
            self._wait(entry)

    def flush(self) -> None:
        """Wait for the acknowledgement of everything sent (the end of a replay)."""
        for entry in self._sent.values():
            if entry[2]:
                self._wait(entry)

    def _wait(self, entry) -> None:
        from rclpy.duration import Duration
        pub, _, n = entry
        deadline = time.monotonic() + self.timeout
        while True:
            left = deadline - time.monotonic()
            if pub.wait_for_all_acked(Duration(nanoseconds=int(max(0.0, min(left, 0.1)) * 1e9))):
                break
            if left <= 0 or (self.stop is not None and self.stop.is_set()):
                self.stats.unacked += n
                break
        entry[2] = 0


def _publish_clock(pub, stamp_ns: int, stats) -> None:
    from rosgraph_msgs.msg import Clock
    from beo_ros.ros.conversions import stamp_from_ns
    msg = Clock(clock=stamp_from_ns(stamp_ns))
    pub.publish(msg)
    stats.clock_messages += 1


# with wait_subscribers and clock_hz: how long to wait for a /clock subscriber once the data
# topics have theirs (a use_sim_time node subscribes to /clock when it starts; without one,
# nothing needs /clock and the replay starts after this pause)
CLOCK_GRACE_S = 1.0


def _clock_tick(pub, stats, t_start: float, bag_t0: int, rate: float, t_next: int,
                now: float) -> None:
    """Publish the bag time at monotonic time ``now`` of a replay that started at ``t_start``,
    never past ``t_next``, the stamp of the message about to be sent (/clock must not step
    back when that message's own clock follows)."""
    _publish_clock(pub, min(bag_t0 + round((now - t_start) * rate * 1e9), t_next), stats)


def _check_output_types(node, conns, remap) -> None:
    """``KeyError`` if two bag topics of different types would be published on one topic (by
    remapping), or a published topic has another type in the graph already (rcl refuses the
    publisher)."""
    outs = {}
    for c in conns:
        out = remap.get(c.topic, c.topic)
        if outs.setdefault(out, (c.msgtype, c.topic))[0] != c.msgtype:
            typ, first = outs[out]
            raise KeyError(f'{first} ({typ}) and {c.topic} ({c.msgtype}) would both be played '
                           f'on {out}: one topic has one type; remap one of them elsewhere')
    graph = dict(node.get_topic_names_and_types())
    for out, (typ, bag_topic) in outs.items():
        others = sorted({normalize_msgtype(t) for t in graph.get(out, ())} - {typ})
        if others:
            raise KeyError(f'{out} has type {others[0]} in the ROS graph; cannot play '
                           f'{bag_topic} ({typ}) on it')


class BagReadError(ValueError):
    """A bag turned out unreadable (corrupt database, truncated file) during :func:`replay`;
    ``stats``: what was played before."""

    def __init__(self, message: str, stats: ReplayStats):
        super().__init__(message)
        self.stats = stats


def _replay_connections(reader, bag_path, topics, all_topics: bool, remap: dict) -> list:
    """The connections of the open bag ``reader`` to play: those of ``topics``, all of them
    (``all_topics``) or the PointCloud2 ones. ``KeyError`` for a topic in ``topics`` or a
    remapped topic that is not in the bag."""
    if topics:
        wanted = set(topics)
        missing = wanted - {c.topic for c in reader.connections}
        if missing:
            raise KeyError(f'topics not in bag {bag_path}: {sorted(missing)}')
        conns = [c for c in reader.connections if c.topic in wanted]
    elif all_topics:
        conns = list(reader.connections)
        for c in conns:   # a damaged channel or schema record: no valid type name
            normalize_msgtype(c.msgtype)
    else:
        conns = [c for c in reader.connections if c.msgtype == CLOUD_TYPE]
    unknown = set(remap) - {c.topic for c in reader.connections}
    if unknown:   # a typo would otherwise play on the old name
        raise KeyError(f'remapped topics not in bag {bag_path}: {sorted(unknown)}')
    return conns


def _replay_publishers(node, conns, remap: dict, stats: ReplayStats, qos: str, depth: int,
                       strict: bool) -> tuple[list, dict, dict]:
    """Publishers for the connections to play -> (the connections kept, {bag topic: publisher},
    {published topic: its first publisher}); adds their topics to ``stats.topics`` (and
    ``stats.latched``). A topic of a type not installed raises ``KeyError`` if ``strict`` (it
    was asked for), else it is left out and listed in ``stats.skipped``."""
    kept, pubs, pub_by_out = [], {}, {}
    for c in conns:
        out = remap.get(c.topic, c.topic)
        if c.topic in stats.skipped:
            continue
        if c.topic not in pubs:
            try:
                latched = recorded_latched(c)
                # keep every latched message for late subscribers (one per static
                # broadcaster on /tf_static), not only the last ``depth``
                pubs[c.topic] = _publisher(node, c.msgtype, out, qos,
                                           max(depth, int(getattr(c, 'msgcount', 0) or 0))
                                           if latched else depth, latched)
                if latched:
                    stats.latched.append(out)
            except KeyError:   # type not installed: fatal only for a topic asked for
                if strict:
                    raise
                stats.skipped[c.topic] = c.msgtype
                continue
            pub_by_out.setdefault(out, pubs[c.topic])
            stats.topics.setdefault(out, TopicStats(out, c.topic, c.msgtype))
        kept.append(c)
    return kept, pubs, pub_by_out


def _wait_for_subscribers(pubs: dict, clock, wait_subscribers: int, wait_timeout: float,
                          stop: threading.Event | None, stats: ReplayStats) -> bool:
    """Wait until every publisher of ``pubs`` has ``wait_subscribers`` matched subscriptions
    and ``clock`` (if any) one, or ``CLOCK_GRACE_S`` more; ``TimeoutError`` after
    ``wait_timeout`` s. False if ``stop`` got set first (``stats.interrupted``); the time
    waited goes to ``stats.waited_s``."""
    t_wait = time.monotonic()
    deadline = t_wait + wait_timeout
    clock_grace = None   # once the data topics match, up to 1 s more for /clock
    while True:
        counts = {p.topic_name: p.get_subscription_count() for p in pubs.values()}
        short = {t: c for t, c in counts.items() if c < wait_subscribers}
        if not short:
            if clock is None or clock.get_subscription_count() > 0:
                break
            clock_grace = clock_grace or time.monotonic() + CLOCK_GRACE_S
            if time.monotonic() >= clock_grace:
                break
        if stop is not None and stop.is_set():
            stats.interrupted = True
            return False
        if short and time.monotonic() > deadline:
            raise TimeoutError(f'waited {wait_timeout:g} s for {wait_subscribers} '
                               f'subscriber(s); matched: {short}')
        time.sleep(0.02)
    stats.waited_s = time.monotonic() - t_wait
    return True


class _Player:
    """Sends the messages of ``conns`` of an open bag with ``pubs`` ({bag topic: publisher}),
    timed as :func:`replay` describes, and counts them in ``stats``."""

    def __init__(self, reader, conns, pubs: dict, remap: dict, stats: ReplayStats, *,
                 rate: float, clock, clock_hz: float, stop: threading.Event | None,
                 on_publish, ack_timeout: float):
        self.reader, self.conns, self.pubs, self.remap = reader, conns, pubs, remap
        self.stats, self.rate, self.clock, self.clock_hz = stats, rate, clock, clock_hz
        self.stop, self.on_publish = stop, on_publish
        self.acks = _AckGate(ack_timeout, stats, stop)
        self._t_first = None   # monotonic time of the first publish
        self._t_start = None   # monotonic time of the pass's first message (rate > 0)

    def play(self, n_passes: int | None) -> None:
        """Pass after pass over the bag, ``n_passes`` times (None: until stopped), then wait
        for the acknowledgement of what was sent."""
        while n_passes is None or self.stats.loops < n_passes:
            bag_t0 = self._play_pass()
            if self.stats.interrupted:
                break
            self.stats.loops += 1
            if bag_t0 is None:  # nothing to play: don't spin forever with --loop
                break
        self.acks.flush()

    def _play_pass(self) -> int | None:
        """One pass over the bag -> the stamp of its first message (None: it has none)."""
        self._t_start = None
        bag_t0 = None            # stamp of the pass's first message: the timing's origin
        sent_t0 = sent_t1 = None  # stamps of the first and last message sent
        for conn, t, raw in self.reader.messages(connections=self.conns):
            if bag_t0 is None:
                bag_t0 = t
            if not self._wait_until_due(t, bag_t0):
                self.stats.interrupted = True
                break
            if self.clock is not None:
                _publish_clock(self.clock, t, self.stats)
            self._send(conn, t, raw)
            sent_t0 = t if sent_t0 is None else sent_t0
            sent_t1 = t
        if sent_t0 is not None:   # not the message an interrupt kept from being sent
            self.stats.bag_span_s = (sent_t1 - sent_t0) / 1e9
        return bag_t0

    def _wait_until_due(self, t: int, bag_t0: int) -> bool:
        """Wait until the message stamped ``t`` is due (publishing /clock in between); False
        if ``stop`` got set first."""
        if self.rate > 0:
            if self._t_start is None:
                self._t_start = time.monotonic()
            tick = None if self.clock is None else functools.partial(
                _clock_tick, self.clock, self.stats, self._t_start, bag_t0, self.rate, t)
            return _sleep_until(self._t_start + (t - bag_t0) / 1e9 / self.rate, self.stop, tick,
                                1.0 / self.clock_hz if self.clock_hz > 0 else 0.05)
        return not (self.stop is not None and self.stop.is_set())

    def _send(self, conn, t: int, raw) -> None:
        """Publish one message of the bag and count it."""
        data = bytes(raw)
        pub = self.pubs[conn.topic]
        pub.publish(data)
        self.acks.published(pub)
        now = time.monotonic()
        self._t_first = now if self._t_first is None else self._t_first
        # from the first to the last publish, kept current for a BagReadError's stats
        self.stats.wall_s = now - self._t_first
        ts = self.stats.topics[self.remap.get(conn.topic, conn.topic)]
        ts.count += 1
        ts.bytes += len(data)
        self.stats.messages += 1
        self.stats.bytes += len(data)
        if self.on_publish is not None:
            self.on_publish(ts.topic, data, t)


def replay(bag_path, node, *, topics=None, all_topics: bool = False, remap=None,
           rate: float = 1.0, loop: bool = False, loops: int | None = None,
           qos: str = 'reliable', depth: int = 10, wait_subscribers: int = 0,
           wait_timeout: float = 10.0, stop: threading.Event | None = None,
           on_publish=None, clock_hz: float = 0.0,
           ack_timeout: float = ACK_TIMEOUT_S) -> ReplayStats:
    """Publish the messages of a bag with ``node``'s publishers; returns what was sent.

    Args:
        bag_path: rosbag2 directory (sqlite3 or mcap) or a single ``.db3``/``.mcap`` file.
        node: an rclpy Node; it need not be spun (publishing does not need an executor). Its
            publishers are created on first use and reused by later replays with that node.
        topics: bag topics to play (any type; ``KeyError`` if one's type is not installed);
            default: every PointCloud2 topic, or every topic with ``all_topics`` (topics of
            types not installed are then skipped, listed in ``stats.skipped``).
        remap: ``{bag_topic: published_topic}`` or a list of ``'OLD:=NEW'`` strings.
        rate: timing factor: a message is sent at ``t0 + (stamp - first_stamp) / rate``; ``0``
            publishes as fast as possible.
        loop: repeat until ``stop`` is set; ``loops`` caps the number of passes (default 1).
        qos: 'reliable' or 'best_effort' (history keep-last ``depth``, volatile). A reliable
            publisher waits for its subscribers' acknowledgements after every ``depth``
            messages (at most ``ack_timeout`` s; what was not acknowledged by then is counted in
            ``stats.unacked``) and at the end, so that a fast replay (``rate=0``) does not
            overwrite undelivered messages in its history; best-effort subscribers can still
            miss messages (nothing tells the publisher). A topic
            recorded from transient-local publishers only (``recorded_latched``, e.g.
            /tf_static) is played reliable and transient-local, as recorded, so that late and
            transient-local subscribers (tf2's static listener) get it; ``stats.latched``
            lists such topics.
        wait_subscribers: before sending, wait until every played topic has at least this many
            matched subscriptions, at most ``wait_timeout`` s (then raise ``TimeoutError``).
        stop: set it (e.g. from a signal handler) to end early; ``stats.interrupted`` is then True.
        on_publish: ``callable(published_topic, raw_bytes, bag_stamp_ns)`` after every publish.
        clock_hz: > 0: also publish the bag time on /clock (``rosgraph_msgs/Clock``, best
            effort, depth 1, as ``ros2 bag play --clock``) before every message and at this
            rate in between, for nodes with ``use_sim_time``; ``stats.clock_messages``.
    """
    from rosbags.rosbag2 import Reader
    if not (math.isfinite(rate) and rate >= 0):
        raise ValueError(f'rate must be a finite number >= 0, got {rate}')
    if not (math.isfinite(clock_hz) and clock_hz >= 0):
        raise ValueError(f'clock_hz must be a finite number >= 0, got {clock_hz}')
    remap = parse_remaps(remap) if isinstance(remap, (list, tuple)) else dict(remap or {})
    bag_path = Path(bag_path)
    n_passes = loops if loops is not None else (None if loop else 1)
    stats = ReplayStats(bag=str(bag_path), storage=detect_storage(bag_path), rate=float(rate))
    _check_no_hot_journal(bag_path)
    try:
        with Reader(bag_path) as reader:
            conns = _replay_connections(reader, bag_path, topics, all_topics, remap)
            _check_output_types(node, conns, remap)
            conns, pubs, pub_by_out = _replay_publishers(node, conns, remap, stats, qos, depth,
                                                         strict=bool(topics))
            if not conns:
                return stats
            # made before the wait, so that discovery matches /clock with the data topics
            # best effort, depth 1, volatile: rclcpp's ClockQoS
            clock = (_publisher(node, 'rosgraph_msgs/msg/Clock', '/clock', 'best_effort', 1)
                     if clock_hz > 0 else None)
            if wait_subscribers > 0 and not _wait_for_subscribers(
                    pubs, clock, wait_subscribers, wait_timeout, stop, stats):
                return stats
            _Player(reader, conns, pubs, remap, stats, rate=rate, clock=clock, clock_hz=clock_hz,
                    stop=stop, on_publish=on_publish, ack_timeout=ack_timeout).play(n_passes)
            for out, ts in stats.topics.items():
                ts.subscribers = pub_by_out[out].get_subscription_count()
    except TimeoutError:   # --wait-subscribers (an OSError too)
        raise
    except storage_errors() as e:   # a corrupt database, a truncated file
        raise BagReadError(str(e) or type(e).__name__, stats) from e
    return stats


# ---------------------------------------------------------------------------------------------
# record
# ---------------------------------------------------------------------------------------------

COMMIT_PERIOD_S = 1.0   # beo-record commits its bag at least this often


class BagWriteError(Exception):
    """A bag could not be written (disk full, I/O error); the message says what is left."""


def _write_failure(writer, exc) -> str:
    """One line on a failed recording, after ``writer`` was aborted: the error, and what is
    left of the bag (its .db3 / .mcap file with the committed messages, or nothing: a bag with
    nothing committed is removed)."""
    reason = f'cannot write {writer.path}: {exc}'
    if not writer._opened:
        return reason
    if writer.storage == 'sqlite3':
        import sqlite3
        try:
            with contextlib.closing(sqlite3.connect(f'file:{writer.storage_file}?mode=ro',
                                                    uri=True)) as db:
                kept = db.execute('SELECT COUNT(*) FROM messages').fetchone()[0]
        except sqlite3.Error:
            kept = 0
    else:
        kept = writer.committed
    if kept:
        how = ('no metadata.yaml: play or read that file itself, or' if writer.storage ==
               'sqlite3' else 'no footer:')
        return (f'{reason}; {writer.storage_file} keeps the {kept} message(s) committed before '
                f'the error ({how} beo-bag-recover {writer.path} -o NEW makes a closed bag of '
                'them)')
    shutil.rmtree(writer.path, ignore_errors=True)
    return f'{reason}; the unfinished bag was removed (nothing in it was committed)'


@dataclass
class RecordStats:
    bag: str
    storage: str
    messages: int = 0
    wall_s: float = 0.0
    stopped_by: str = ''
    topics: dict = field(default_factory=dict)   # topic -> {'type', 'count'}

    def to_dict(self) -> dict:
        return asdict(self)

    def table(self) -> str:
        rows = [('topic', 'type', 'count')] + [(t, d['type'], str(d['count']))
                                               for t, d in self.topics.items()]
        widths = [max(len(r[i]) for r in rows) for i in range(3)]
        lines = ['  '.join(c.ljust(w) for c, w in zip(r, widths)).rstrip() for r in rows]
        lines.insert(1, '  '.join('-' * w for w in widths))
        lines.append(f'{self.messages} messages in {self.wall_s:.3f} s -> {self.bag} '
                     f'({self.storage}, stopped by {self.stopped_by})')
        return '\n'.join(lines)


def parse_topic_specs(specs) -> dict:
    """['/a', '/b:pkg/msg/T', ...] -> {'/a': None, '/b': 'pkg/msg/T'}.

    ``ValueError`` for a bad topic name or type, or a topic given twice with different types.
    """
    out = {}
    for s in specs:
        topic, sep, typ = s.partition(':')
        if not topic:
            raise ValueError(f'bad topic spec {s!r}')
        check_topic_name(topic)
        typ = normalize_msgtype(typ) if sep else None
        old = out.get(topic)
        if old and typ and old != typ:
            raise ValueError(f'{topic} is given twice, as {old} and as {typ}')
        out[topic] = typ or old
    return out


def resolve_topic_types(node, topics: dict, wait: float = 10.0,
                        stop: threading.Event | None = None) -> dict:
    """Fill in ``None`` types from the graph (waiting up to ``wait`` s); ``KeyError`` if not found,
    ``KeyboardInterrupt`` if ``stop`` gets set first, ``ValueError`` if two names of one topic
    ('x' and '/x') are given different types."""
    resolved = {}
    for t, typ in topics.items():
        name = node.resolve_topic_name(t)
        old = resolved.get(name)
        if old and typ and old != typ:
            raise ValueError(f'{name} is given twice, as {old} and as {typ}')
        resolved[name] = typ or old
    topics = resolved
    deadline = time.monotonic() + wait
    while True:
        missing = [t for t, typ in topics.items() if typ is None]
        if not missing:
            return topics
        graph = dict(node.get_topic_names_and_types())
        for t in missing:
            if graph.get(t):
                topics[t] = normalize_msgtype(graph[t][0])
        if all(typ is not None for typ in topics.values()):
            return topics
        if stop is not None and stop.is_set():
            raise KeyboardInterrupt('interrupted while waiting for publishers of: ' + ', '.join(
                t for t, typ in topics.items() if typ is None))
        if time.monotonic() > deadline:
            raise KeyError('no publisher found within {:g} s for: {}'.format(
                wait, ', '.join(t for t, typ in topics.items() if typ is None)))
        time.sleep(0.05)


def _subscription_qos(node, topic: str, depth: int = 100):
    """Reliable/transient-local only if every current publisher offers it (as ros2 bag does)."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    infos = node.get_publishers_info_by_topic(topic)
    reliable = bool(infos) and all(i.qos_profile.reliability == ReliabilityPolicy.RELIABLE
                                   for i in infos)
    latched = bool(infos) and all(i.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL
                                  for i in infos)
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                      reliability=ReliabilityPolicy.RELIABLE if reliable
                      else ReliabilityPolicy.BEST_EFFORT,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL if latched
                      else DurabilityPolicy.VOLATILE)


class _Recorder:
    """Subscribes ``topics`` ({topic: msgtype}) as their publishers appear, spinning ``node`` with
    ``executor`` (added to it and shut down if ``own_exec``), and writes what they receive to the
    open ``writer`` in batches, counted in ``stats``, as :func:`record` describes."""

    def __init__(self, node, writer: BagWriter, topics: dict, stats: RecordStats, *, executor,
                 own_exec: bool, commit_every: float):
        self.node, self.writer, self.topics, self.stats = node, writer, topics, stats
        self.executor, self.own_exec, self.commit_every = executor, own_exec, commit_every
        self.subs = []
        self.unsubscribed = dict(topics)
        self._pending = []   # (topic, stamp ns, raw CDR) received and not yet written
        self._lock = threading.Lock()
        self._t0 = self._t_poll = self._t_commit = time.monotonic()
        self._uncommitted = False
        self._added = False   # the node is in our own executor

    def start(self, ready: threading.Event | None) -> None:
        """List the topics, subscribe those with publishers, then signal ``ready``."""
        for topic, typ in self.topics.items():
            self.stats.topics[topic] = {'type': typ, 'count': 0}
        self._subscribe_new()
        if self.own_exec:
            self.executor.add_node(self.node)
            self._added = True
        if ready is not None:
            ready.set()
        self._t0 = self._t_poll = self._t_commit = time.monotonic()

    def run(self, count: int | None, duration: float | None, stop: threading.Event) -> None:
        """Spin, subscribe, write and commit until ``count`` messages, ``duration`` s or
        ``stop``; ``stats.stopped_by`` says which."""
        while True:
            self.executor.spin_once(timeout_sec=0.05)
            if self.unsubscribed and time.monotonic() - self._t_poll > 0.05:
                self._t_poll = time.monotonic()
                self._subscribe_new()
            self._write_pending(count)
            self._commit_if_due()
            stopped_by = self._stop_reason(count, duration, stop)
            if stopped_by:
                self.stats.stopped_by = stopped_by
                break

    def finish(self) -> None:
        """Take the wall time, list the never-published topics in the bag (empty, unless the
        writer failed), drop the subscriptions and the executor if it is ours: also after a
        failure part-way through :meth:`start`, or one of these writes."""
        self.stats.wall_s = time.monotonic() - self._t0
        try:
            if not self.writer.failed:
                for topic, typ in self.unsubscribed.items():   # never published: listed, empty
                    self.writer.add_topic(topic, typ, reliable=False)
        finally:
            for s in self.subs:
                self.node.destroy_subscription(s)
            if self.own_exec:
                if self._added:
                    self.executor.remove_node(self.node)
                self.executor.shutdown()

    def _callback_for(self, topic: str):
        """A raw subscription callback queueing the message of ``topic``, stamped at receipt."""
        def cb(raw):
            with self._lock:
                self._pending.append((topic, self.node.get_clock().now().nanoseconds,
                                      bytes(raw)))
        return cb

    def _subscribe_new(self) -> None:
        """Subscribe to topics that now have publishers, with QoS adapted to their offers."""
        node = self.node
        for topic, typ in list(self.unsubscribed.items()):
            if not node.get_publishers_info_by_topic(topic):
                continue
            qos = _subscription_qos(node, topic)
            # the bag's offered QoS is that of the publishers matched now (a latched
            # publisher that appears after the recording started is replayed latched)
            self.writer.add_topic(topic, typ, reliable=qos.reliability.name == 'RELIABLE',
                                  transient_local=qos.durability.name == 'TRANSIENT_LOCAL')
            self.subs.append(node.create_subscription(import_msg_class(typ), topic,
                                                      self._callback_for(topic), qos, raw=True))
            del self.unsubscribed[topic]

    def _write_pending(self, count: int | None) -> None:
        """Write the messages received so far (none beyond ``count`` in total)."""
        with self._lock:
            batch, self._pending[:] = list(self._pending), []
        for topic, t, raw in batch:
            if count is not None and self.stats.messages >= count:
                break
            self.writer.write(topic, raw, t, self.topics[topic])
            self.stats.topics[topic]['count'] += 1
            self.stats.messages += 1
            self._uncommitted = True

    def _commit_if_due(self) -> None:
        """Commit what is written if ``commit_every`` s passed since the last commit."""
        # also when nothing new came: a burst followed by quiet is committed too
        if self._uncommitted and time.monotonic() - self._t_commit >= self.commit_every:
            self._t_commit = time.monotonic()
            self.writer.commit()
            self._uncommitted = False

    def _stop_reason(self, count: int | None, duration: float | None,
                     stop: threading.Event) -> str:
        """'count', 'duration' or 'interrupt' when the recording is to end, else ''."""
        if count is not None and self.stats.messages >= count:
            return 'count'
        if duration is not None and time.monotonic() - self._t0 >= duration:
            return 'duration'
        if stop.is_set():
            return 'interrupt'
        return ''


def record(node, bag_path, topics, *, storage: str = 'sqlite3', wait: float = 10.0,
           duration: float | None = None, count: int | None = None,
           stop: threading.Event | None = None, ready: threading.Event | None = None,
           executor=None, commit_every: float | None = None) -> RecordStats:
    """Record ``topics`` to a new bag at ``bag_path``, spinning ``node`` in the calling thread.

    Args:
        node: rclpy Node that only this call spins (its context must be initialized).
        topics: ``{topic: msgtype or None}`` / list of ``'TOPIC[:TYPE]'``; ``None`` types are
            discovered from the graph within ``wait`` s.
        duration: stop after this many seconds of recording; ``count``: after this many messages
            in total; ``stop``: an Event to end the recording (e.g. set by SIGINT).
        ready: set once all subscriptions exist (useful to start publishers in tests).
        commit_every: commit the messages written at least every this many seconds (default
            ``COMMIT_PERIOD_S``, 1 s), so that a crash or SIGKILL keeps them: a .db3 file then
            reads on its own (there is no metadata.yaml), an mcap file through
            :func:`recover_bag` (it has no footer).
    Messages are stored as received (raw CDR), stamped with the node clock at receipt. A topic is
    subscribed once it has a publisher (typed topics may have none yet), with reliability and
    durability adapted to what its publishers offer. ``KeyError``, before the bag is created,
    for a type without a definition or Python module; ``KeyboardInterrupt``, with no bag, if
    ``stop`` is set while untyped topics wait for a publisher. :class:`BagWriteError` when the
    bag cannot be written (disk full, ...): its message says what is left of the bag; no
    metadata.yaml is written then, a bag with nothing readable in it is removed.
    """
    from rclpy.executors import SingleThreadedExecutor
    if isinstance(topics, (list, tuple)):
        topics = parse_topic_specs(topics)
    stop = stop or threading.Event()
    topics = resolve_topic_types(node, dict(topics), wait, stop)
    for typ in set(topics.values()):   # before the bag exists: a bad type leaves no bag
        get_typestore([typ])
        import_msg_class(typ)
    stats = RecordStats(bag=str(bag_path), storage=storage)
    commit_every = COMMIT_PERIOD_S if commit_every is None else commit_every
    writer = BagWriter(bag_path, storage)
    own_exec = executor is None
    executor = executor or SingleThreadedExecutor(context=node.context)
    recorder = _Recorder(node, writer, topics, stats, executor=executor, own_exec=own_exec,
                         commit_every=commit_every)
    try:
        with writer:
            try:
                recorder.start(ready)
                recorder.run(count, duration, stop)
            finally:
                recorder.finish()
    except storage_errors() as e:
        raise BagWriteError(_write_failure(writer, e)) from None
    return stats


# ---------------------------------------------------------------------------------------------
# PCD scenes -> bag
# ---------------------------------------------------------------------------------------------

class NoObjects(ValueError):
    """A scene without object labels (>= 20): nothing to segment, and no up vector worth writing."""


def scene_messages(scene_path, *, min_points: int = 50):
    """Segment one labelled scene -> ``(objects [(object_id, (n,3) points)], up (3,), plane (4,))``.

    Objects come from the OSD labels (``scans.segment_objects``), the up vector from a RANSAC fit
    of the table points (``scans.fit_table_plane``), oriented towards the sensor. A file without
    a label field is a ``PCDError``; one with no object label, :class:`NoObjects`.
    """
    import numpy as np

    from beo_ros.core import scans
    scene = scans.load_scene(scene_path)
    if not (scene.labels >= scans.FIRST_OBJECT_LABEL).any():
        raise NoObjects(f'{scene_path}: no objects (labels >= {scans.FIRST_OBJECT_LABEL})')
    objects = sorted(scans.segment_objects(scene, min_points=min_points).items())
    try:
        up, d = scans.fit_table_plane(scene)
    except ValueError as e:
        raise ValueError(f'{scene_path}: {e}') from e
    up = np.asarray(up, dtype=np.float64)
    norm = np.linalg.norm(up)
    up, d = up / norm, float(d) / norm
    return objects, up, np.array([up[0], up[1], up[2], d])


def _scene_stamps(counts, period: float, object_period: float, t0_ns: int) -> list:
    """Per scene (``counts``: its number of objects): ``(scene stamp, [object stamps])``."""
    step = int(round(object_period * 1e9))
    out, last = [], None
    for i, n in enumerate(counts):
        ns = int(t0_ns + round(i * period * 1e9))
        if last is not None:
            ns = max(ns, last + max(step, 1))
        objs = [ns + j * step if step else ns + j for j in range(n)]
        last = objs[-1] if objs else ns
        out.append((ns, objs))
    return out


def pcd_to_bag(scenes, bag_path, *, storage: str = 'sqlite3', topic: str = DEFAULT_INPUT_TOPIC,
               frame_id: str = DEFAULT_FRAME, period: float = 2.0, object_period: float = 0.25,
               min_points: int = 50, t0_ns: int = T0_NS) -> dict:
    """Write the segmented objects of labelled PCD scenes to a bag (see the module docstring).

    Scene ``i`` starts at ``t0 + i * period`` (or ``object_period`` after the previous scene's last
    object if that is later); its up vector and plane carry that stamp, its objects follow
    ``object_period`` apart (first one at the scene stamp), so every cloud has a unique stamp.
    Scenes without object labels are skipped (listed in ``'skipped'``); ``ValueError`` if none is
    left, for a bad scene or topic name, or stamps past int64 nanoseconds. No bag is left behind
    on any failure (Ctrl-C included).

    Returns ``{'bag', 'storage', 'scenes': [{'scene', 'stamp_ns', 'objects': [{'id', 'points',
    'centroid', 'stamp_ns'}], 'up', 'plane'}], 'skipped': [{'scene', 'reason'}],
    'topics': {topic: count}}``.
    """
    import numpy as np
    from geometry_msgs.msg import Vector3, Vector3Stamped
    from std_msgs.msg import Float64MultiArray, Header

    from beo_ros.ros.conversions import stamp_from_ns, xyz_to_cloud
    if not (math.isfinite(period) and math.isfinite(object_period)):
        raise ValueError('period and object_period must be finite numbers')
    if period < 0 or object_period < 0:
        raise ValueError('period and object_period must be >= 0')
    topic = check_topic_name(topic)
    summary = {'bag': str(bag_path), 'storage': storage, 'scenes': [], 'skipped': [],
               'topics': {}}
    # every scene is read before the bag is opened: a bad one leaves no half-written bag
    read = []
    for scene in scenes:
        try:
            read.append((scene, *scene_messages(scene, min_points=min_points)))
        except NoObjects as e:
            summary['skipped'].append({'scene': str(scene), 'reason': str(e)})
    if not read:
        raise ValueError('no scene with objects: ' + '; '.join(
            s['reason'] for s in summary['skipped']))
    if not any(objects for _, objects, _, _ in read):   # a bag without a single cloud
        raise ValueError(f'no object with at least {min_points} points (--min-points) in any '
                         'scene: no cloud to write, no bag written')
    stamps = _scene_stamps([len(objects) for _, objects, _, _ in read], period, object_period,
                           t0_ns)
    if max(max([ns, *objs]) for ns, objs in stamps) > MAX_NS:
        raise ValueError(f'--period {period:g} s / --object-period {object_period:g} s put the '
                         f'stamps of {len(read)} scene(s) past int64 nanoseconds (year 2262)')
    existed = Path(bag_path).exists()
    try:
        with BagWriter(bag_path, storage) as w:
            w.add_topic(topic, CLOUD_TYPE)
            w.add_topic(UP_TOPIC, 'geometry_msgs/msg/Vector3Stamped')
            w.add_topic(PLANE_TOPIC, 'std_msgs/msg/Float64MultiArray')
            for (scene, objects, up, plane), (ns, obj_ns) in zip(read, stamps):
                header = Header(stamp=stamp_from_ns(ns), frame_id=frame_id)
                entry = {'scene': str(scene), 'stamp_ns': ns, 'objects': [],
                         'up': up.tolist(), 'plane': plane.tolist()}
                w.write(UP_TOPIC, Vector3Stamped(header=header, vector=Vector3(
                    x=float(up[0]), y=float(up[1]), z=float(up[2]))), ns)
                w.write(PLANE_TOPIC, Float64MultiArray(data=[float(v) for v in plane]), ns)
                for (obj_id, pts), t in zip(objects, obj_ns):
                    pts = np.asarray(pts, dtype=np.float32)
                    header = Header(stamp=stamp_from_ns(t), frame_id=frame_id)
                    w.write(topic, xyz_to_cloud(pts, header), t)
                    entry['objects'].append({'id': int(obj_id), 'points': int(len(pts)),
                                             'centroid': pts.mean(axis=0).tolist(),
                                             'stamp_ns': t})
                summary['scenes'].append(entry)
            summary['topics'] = dict(w.counts)
    except BaseException:
        if not existed:   # a half-written bag would only be refused by the next run
            shutil.rmtree(bag_path, ignore_errors=True)
        raise
    return summary


# ---------------------------------------------------------------------------------------------
# command line
# ---------------------------------------------------------------------------------------------

def _install_sigint(stop: threading.Event, sigterm: bool = True):
    """SIGINT (and SIGTERM with ``sigterm``) sets ``stop``; a second one raises
    KeyboardInterrupt. Without ``sigterm``, SIGTERM keeps :func:`interruptible`'s handler
    (exit code 143)."""
    def handler(signum, frame):  # noqa: ARG001
        if stop.is_set():  # second Ctrl-C: give up immediately
            raise KeyboardInterrupt
        stop.set()
    signal.signal(signal.SIGINT, handler)
    if sigterm:
        signal.signal(signal.SIGTERM, handler)


def _ros_setup():
    try:
        from beo_ros.ros.env import ensure_ament_prefix
        ensure_ament_prefix()
    except Exception:  # noqa: BLE001 - only needed for beo_interfaces types
        pass


@contextlib.contextmanager
def _cli_node(name, sigterm_stops: bool = True):
    """rclpy context and node for a command-line tool; yields (node, stop event set on
    SIGINT, and on SIGTERM with ``sigterm_stops``), and destroys the node and shuts rclpy down
    on the way out."""
    _ros_setup()
    import rclpy
    stop = threading.Event()
    # no command-line arguments: rcl would take the tool's own ones (-r OLD:=NEW) as remap rules
    rclpy.init(args=[], signal_handler_options=rclpy.signals.SignalHandlerOptions.NO)
    node = rclpy.create_node(name)
    _install_sigint(stop, sigterm_stops)
    try:
        yield node, stop
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


def _output_problem(path) -> str | None:
    """Why a new bag cannot be made at ``path`` (it exists, or a parent is a file), or None."""
    p = Path(path)
    if p.exists() or p.is_symlink():
        return f'{path} exists already'
    for parent in p.parents:   # rosbags makes the missing ones
        if parent.exists():
            if not parent.is_dir():
                return f'cannot create {path}: {parent} is not a directory'
            break
    return None


def _nothing_to_play(args, stats) -> str:
    """Why a replay sent nothing: its topics are empty, or the bag has none that matches."""
    if stats.topics:
        return 'no messages on ' + ', '.join(sorted(s.bag_topic for s in stats.topics.values()))
    if args.topics or args.all_topics:
        return 'no matching topics'
    try:
        others = sorted(bag_info(args.bag)['topics'])
    except Exception:  # noqa: BLE001 - only a hint
        others = []
    hint = f' (it has {", ".join(others)}: --all-topics plays them)' if others else ''
    return f'the bag has no {CLOUD_TYPE} topic{hint}'


@interruptible('beo-replay')
def replay_main(argv=None) -> int:
    p = argparse.ArgumentParser(
        prog='beo-replay', description='Play the PointCloud2 topics of a rosbag2 bag (sqlite3 or '
        'mcap) into the ROS 2 graph, timed by the bag timestamps.')
    p.add_argument('bag', help='bag directory (or a single .db3 / .mcap file)')
    p.add_argument('-r', '--remap', action='append', default=[], metavar='OLD:=NEW',
                   help='publish bag topic OLD on NEW (repeatable)')
    p.add_argument('--rate', type=number(0), default=1.0,
                   help='speed factor on the bag timing; 0 = as fast as possible (default 1)')
    p.add_argument('--loop', action='store_true', help='replay until interrupted')
    p.add_argument('--topics', nargs='+', metavar='TOPIC',
                   help='bag topics to play, any type (default: all PointCloud2 topics)')
    p.add_argument('--all-topics', action='store_true', help='play every topic of the bag')
    p.add_argument('--qos', choices=('reliable', 'best_effort'), default='reliable',
                   help='publisher reliability (default reliable; keep-last, volatile); '
                        'topics recorded from transient-local publishers (e.g. /tf_static) '
                        'are played reliable and transient-local, as recorded')
    p.add_argument('--depth', type=count(1), default=10,
                   help='publisher history depth (default 10); a reliable publisher waits for '
                        'its subscribers to acknowledge every DEPTH messages')
    p.add_argument('--ack-timeout', type=number(0), default=ACK_TIMEOUT_S, metavar='S',
                   help='how long a reliable publisher waits for those acknowledgements before '
                        'it goes on and counts the messages as unacknowledged (maybe lost; '
                        f'default {ACK_TIMEOUT_S:g})')
    p.add_argument('--clock', type=number(0), nargs='?', const=40.0, default=0.0, metavar='HZ',
                   help='also publish the bag time on /clock, before every message and at HZ '
                        '(default 40) in between, for nodes run with use_sim_time:=true; '
                        'put it after BAG or write --clock=HZ (before BAG, "--clock BAG" '
                        'would read BAG as HZ); with --loop the clock goes back at each pass')
    p.add_argument('--wait-subscribers', type=count(0), default=0, metavar='N',
                   help='wait until every played topic has N matched subscribers')
    p.add_argument('--wait-timeout', type=number(0), default=10.0, metavar='S',
                   help='give up waiting for subscribers after S seconds (default 10; exit 3)')
    p.add_argument('--node-name', default='beo_replay')
    p.add_argument('--json', action='store_true', help='print the report as JSON')
    args = p.parse_args(argv)
    if args.topics and args.all_topics:
        p.error('--topics and --all-topics exclude each other')
    try:
        remap = parse_remaps(args.remap)
        check_node_name(args.node_name)
    except ValueError as e:
        p.error(str(e))
    if not Path(args.bag).exists():
        p.error(f'no such bag: {args.bag}')
    code = 0
    # SIGTERM ends a replay with 143 (interruptible); SIGINT is how a --loop replay stops
    with _cli_node(args.node_name, sigterm_stops=False) as (node, stop):
        try:
            stats = replay(args.bag, node, topics=args.topics, all_topics=args.all_topics,
                           remap=remap, rate=args.rate, loop=args.loop, qos=args.qos,
                           depth=args.depth, wait_subscribers=args.wait_subscribers,
                           wait_timeout=args.wait_timeout, stop=stop, clock_hz=args.clock,
                           ack_timeout=args.ack_timeout)
            time.sleep(0.2)  # let reliable transports drain before the publishers go away
            for topic, typ in stats.skipped.items():
                print(f'beo-replay: warning: skipping {topic}: message type {typ} is not '
                      'installed', file=sys.stderr)
            print(json.dumps(stats.to_dict(), indent=2) if args.json else stats.table())
            if stats.unacked:
                print(f'beo-replay: warning: {stats.unacked} message(s) were not acknowledged by '
                      f'every reliable subscriber within --ack-timeout {args.ack_timeout:g} s; '
                      'a slow or stalled subscriber may have lost them', file=sys.stderr)
            if stats.messages == 0 and not stats.interrupted:
                print(f'beo-replay: nothing to play: {_nothing_to_play(args, stats)}',
                      file=sys.stderr)
                code = 1
            # Ctrl-C is how a --loop replay ends once it plays; otherwise it cut the replay short
            if stats.interrupted and not (args.loop and stats.messages):
                print(f'beo-replay: interrupted after {stats.messages} message(s)',
                      file=sys.stderr)
                code = INTERRUPTED
        except TimeoutError as e:
            print(f'beo-replay: {e}', file=sys.stderr)
            code = 3
        except KeyError as e:
            print(f'beo-replay: {e.args[0]}', file=sys.stderr)
            code = 2
        except BagReadError as e:   # corrupt part way: what was played before it
            if e.stats.messages:
                print(json.dumps(e.stats.to_dict(), indent=2) if args.json
                      else e.stats.table())
            print(f'beo-replay: cannot read {args.bag}: {e} (after {e.stats.messages} '
                  'message(s))', file=sys.stderr)
            code = 2
        except (ValueError, *storage_errors()) as e:   # not a bag, or a corrupt one
            print(f'beo-replay: cannot read {args.bag}: {e}', file=sys.stderr)
            code = 2
    return code


@interruptible('beo-record')
def record_main(argv=None) -> int:
    p = argparse.ArgumentParser(
        prog='beo-record', description='Record ROS 2 topics to a new rosbag2 bag (sqlite3 or '
        'mcap) until Ctrl-C, --duration or --count.')
    p.add_argument('topics', nargs='+', metavar='TOPIC[:TYPE]',
                   help='topic, optionally with its type (e.g. /beo/estimates:'
                   'beo_interfaces/msg/ObjectEstimate); otherwise discovered from the graph')
    p.add_argument('-o', '--output', required=True, metavar='BAG', help='new bag directory')
    p.add_argument('--storage', choices=STORAGES, default='sqlite3')
    p.add_argument('--wait', type=number(0), default=10.0, metavar='S',
                   help='seconds to wait for publishers of untyped topics (default 10; exit 2)')
    p.add_argument('--duration', type=number(0, lo_open=True), metavar='S',
                   help='stop after S seconds')
    p.add_argument('--count', type=count(1), metavar='N',
                   help='stop after N messages (all topics)')
    p.add_argument('--node-name', default='beo_record')
    p.add_argument('--json', action='store_true', help='print the report as JSON')
    args = p.parse_args(argv)
    try:
        specs = parse_topic_specs(args.topics)
        check_node_name(args.node_name)
    except ValueError as e:
        p.error(str(e))
    problem = _output_problem(args.output)
    if problem:
        p.error(problem)
    code = 0
    with _cli_node(args.node_name) as (node, stop):
        try:
            stats = record(node, args.output, specs, storage=args.storage, wait=args.wait,
                           duration=args.duration, count=args.count, stop=stop)
            print(json.dumps(stats.to_dict(), indent=2) if args.json else stats.table())
        except KeyError as e:
            print(f'beo-record: {e.args[0]}', file=sys.stderr)
            code = 2
        except ValueError as e:   # 'x' and '/x' given different types
            print(f'beo-record: {e}', file=sys.stderr)
            code = 2
        except BagWriteError as e:   # disk full, ...: what is left of the bag
            print(f'beo-record: {e}', file=sys.stderr)
            code = 2
        except OSError as e:
            print(f'beo-record: cannot write {args.output}: {e}', file=sys.stderr)
            code = 2
        except KeyboardInterrupt as e:   # before recording started (while waiting for types)
            print(f'beo-record: {e.args[0] if e.args else "interrupted"}', file=sys.stderr)
            code = INTERRUPTED
    return code


@interruptible('beo-pcd2bag')
def pcd2bag_main(argv=None) -> int:
    p = argparse.ArgumentParser(
        prog='beo-pcd2bag', description='Labelled organized PCD scenes (OSD format) -> rosbag2 bag '
        f'with one PointCloud2 per segmented object, the table-implied up vector on {UP_TOPIC} '
        f'(geometry_msgs/Vector3Stamped) and the table plane a,b,c,d on {PLANE_TOPIC} '
        '(std_msgs/Float64MultiArray), all in the camera frame.')
    p.add_argument('scenes', nargs='+', metavar='SCENE.pcd')
    p.add_argument('-o', '--output', required=True, metavar='BAG', help='new bag directory')
    p.add_argument('--storage', choices=STORAGES, default='sqlite3')
    p.add_argument('--topic', default=DEFAULT_INPUT_TOPIC,
                   help=f'object cloud topic (default {DEFAULT_INPUT_TOPIC})')
    p.add_argument('--frame', default=DEFAULT_FRAME, help=f'frame id (default {DEFAULT_FRAME})')
    p.add_argument('--period', type=number(0, MAX_PERIOD_S), default=2.0, metavar='S',
                   help=f'seconds between scenes (default 2, at most {MAX_PERIOD_S:g})')
    p.add_argument('--object-period', type=number(0, MAX_PERIOD_S), default=0.25, metavar='S',
                   help='seconds between the objects of one scene (default 0.25, at most '
                   f'{MAX_PERIOD_S:g})')
    p.add_argument('--min-points', type=count(0), default=50,
                   help='skip objects with fewer points (default 50)')
    p.add_argument('--json', action='store_true', help='print the summary as JSON')
    args = p.parse_args(argv)
    missing = [s for s in args.scenes if not Path(s).is_file()]
    if missing:
        p.error(f'no such file: {", ".join(missing)}')
    try:
        check_topic_name(args.topic)
    except ValueError as e:
        p.error(str(e))
    problem = _output_problem(args.output)
    if problem:
        p.error(problem)
    try:
        summary = pcd_to_bag(args.scenes, args.output, storage=args.storage, topic=args.topic,
                             frame_id=args.frame, period=args.period,
                             object_period=args.object_period, min_points=args.min_points)
    except ValueError as e:   # PCDError and bad scenes (no table plane, ...) are ValueErrors
        print(f'beo-pcd2bag: {e}', file=sys.stderr)
        return 2
    except OSError as e:
        print(f'beo-pcd2bag: cannot write {args.output}: {e}', file=sys.stderr)
        return 2
    for s in summary['skipped']:
        print(f'beo-pcd2bag: warning: skipped {s["reason"]}', file=sys.stderr)
    for s in summary['scenes']:
        if not s['objects']:
            print(f'beo-pcd2bag: warning: {s["scene"]}: no object with at least '
                  f'{args.min_points} points (--min-points); only its up vector and plane are '
                  'written', file=sys.stderr)
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        for s in summary['scenes']:
            up = ', '.join(f'{v:+.3f}' for v in s['up'])
            pts = (f' ({", ".join(str(o["points"]) for o in s["objects"])} points)'
                   if s['objects'] else '')
            print(f'{Path(s["scene"]).name}: {len(s["objects"])} object(s){pts}, up ({up})')
        print(' '.join(f'{t}: {n}' for t, n in summary['topics'].items()) + f' -> {args.output} '
              f'({args.storage})')
    return 0


@interruptible('beo-bag-recover')
def recover_main(argv=None) -> int:
    p = argparse.ArgumentParser(
        prog='beo-bag-recover', description='Copy the intact messages of a bag that was never '
        'closed (a recording ended by SIGKILL, a crash or a full disk: no metadata.yaml, or an '
        'mcap file without its footer) into a new, closed bag.')
    p.add_argument('bag', help='bag directory, or its .db3 / .mcap file')
    p.add_argument('-o', '--output', required=True, metavar='BAG', help='new bag directory')
    p.add_argument('--storage', choices=STORAGES,
                   help="the new bag's storage (default: the old one's)")
    p.add_argument('--json', action='store_true', help='print the summary as JSON')
    args = p.parse_args(argv)
    problem = _output_problem(args.output)
    if problem:
        p.error(problem)
    try:
        summary = recover_bag(args.bag, args.output, storage=args.storage)
    except (ValueError, KeyError) as e:   # not a bag, nothing intact, a type without a definition
        print(f'beo-bag-recover: {e.args[0] if isinstance(e, KeyError) else e}',
              file=sys.stderr)
        return 2
    except storage_errors() as e:
        print(f'beo-bag-recover: {args.bag}: {e}', file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        topics = ' '.join(f'{t}: {n}' for t, n in summary['topics'].items()) or 'no topics'
        lost = (f'; {summary["lost_bytes"]} bytes after the last intact record were left '
                'out' if summary['lost_bytes'] else '')
        print(f'{summary["messages"]} message(s) ({topics}) -> {args.output} '
              f'({summary["storage"]}){lost}')
    return 0


if __name__ == '__main__':
    sys.exit(replay_main())
