"""Bag storage: writing (:class:`BagWriter`), reading (:func:`read_bag`, :func:`bag_info`), the
QoS a bag's metadata stores, and the rollback journal of a bag left in the middle of a write."""
from __future__ import annotations

import contextlib
import re
import shutil
from pathlib import Path

from beo_ros.ros.bag.msgtypes import (get_typestore, import_msg_class, msgtype_of,
                                      normalize_msgtype, service_definition)

STORAGES = ('sqlite3', 'mcap')


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
        self._conns = {}   # (topic, msgtype) -> connection
        self._types = {}   # topic -> its (first) msgtype
        self.counts = {}   # topic -> messages written, of all its types
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
                  rihs01: str | None = None, another_type: bool = False):
        """Add ``topic`` (once; another type for it is a ValueError, unless ``another_type``:
        a topic recorded in two types, such as two channels of an mcap file, gets a connection
        per type). Its definition comes from the typestore (KeyError for an unknown type), or
        is ``msgdef`` + ``rihs01`` as given (copied from another bag)."""
        msgtype = normalize_msgtype(msgtype)
        if (topic, msgtype) in self._conns:
            return self._conns[topic, msgtype]
        if topic in self._types and not another_type:
            raise ValueError(f'{topic}: already has type {self._types[topic]}')
        if not (msgdef and rihs01) and msgtype.split('/')[1] == 'srv':
            msgdef, rihs01 = service_definition(msgtype)   # rosbags has msg types only
        store = None if msgdef and rihs01 else get_typestore([msgtype])
        try:
            conn = self._writer.add_connection(
                topic, msgtype, typestore=store, msgdef=msgdef if store is None else None,
                rihs01=rihs01 if store is None else None,
                offered_qos_profiles=[_qos_for_bag(reliable, transient_local)])
        except storage_errors():
            self.failed = True
            raise
        self._conns[topic, msgtype] = conn
        self._types.setdefault(topic, msgtype)
        self.counts.setdefault(topic, 0)
        return conn

    def write(self, topic: str, msg, stamp_ns: int, msgtype: str | None = None):
        """Write one message; ``msg`` is an rclpy message, or CDR bytes with ``msgtype`` given."""
        if isinstance(msg, (bytes, bytearray, memoryview)):
            if msgtype is None and topic not in self._types:
                raise ValueError('raw bytes need msgtype for a new topic')
            data = bytes(msg)
        else:
            from rclpy.serialization import serialize_message
            msgtype = msgtype or msgtype_of(msg)
            data = serialize_message(msg)
        if msgtype is None:
            msgtype = self._types[topic]
        conn = self._conns.get((topic, normalize_msgtype(msgtype)))
        if conn is None:
            # add_topic refuses a type other than the topic's (unless added as another_type):
            # the bag would not deserialize
            conn = self.add_topic(topic, msgtype)
        try:
            self._writer.write(conn, int(stamp_ns), data)
        except storage_errors():
            self.failed = True
            raise
        self.counts[topic] += 1


def _db_files(bag_path) -> list:
    """The .db3 files of a bag: the file itself, or those in the bag directory."""
    p = Path(bag_path)
    return [p] if p.suffix == '.db3' else (sorted(p.glob('*.db3')) if p.is_dir() else [])


def hot_journal(bag_path) -> Path | None:
    """The hot rollback journal beside a bag's .db3 file (a recording killed in the middle of
    a transaction that had begun to change the database), or None. rosbags opens the database
    as immutable, ignoring it, and would read pages of the unfinished transaction: a torn or
    malformed database. As sqlite decides it, a journal is hot when its first byte is not 0:
    one killed before its header was written (the usual kill -9 of a recording, a few
    messages uncommitted) changed nothing in the database."""
    for db in _db_files(bag_path):
        journal = db.with_name(db.name + '-journal')
        if journal.is_file():
            with open(journal, 'rb') as f:
                if f.read(1) not in (b'', b'\0'):
                    return journal
    return None


def unmerged_wal(bag_path) -> Path | None:
    """The non-empty write-ahead log (``-wal``) beside a bag's .db3 file, or None: a recording
    in WAL mode that was not closed, its committed messages not yet checkpointed into the
    database. rosbags opens the database as immutable and would not see them (a closed
    connection checkpoints and deletes the log)."""
    for db in _db_files(bag_path):
        wal = db.with_name(db.name + '-wal')
        if wal.is_file() and wal.stat().st_size > 0:
            return wal
    return None


def _check_no_hot_journal(bag_path):
    journal = hot_journal(bag_path)
    if journal is not None:
        raise ValueError(f'{journal}: the bag was left in the middle of a write (its rollback '
                         'journal is there): read it through beo-bag-recover BAG -o NEW')
    wal = unmerged_wal(bag_path)
    if wal is not None:   # reading on would leave out what the log holds, without a word
        raise ValueError(f'{wal}: the bag holds messages in its write-ahead log that are not in '
                         'its database (a recording that was not closed?): read it through '
                         'beo-bag-recover BAG -o NEW')


def _metadata_info(meta: Path):
    """The ``rosbag2_bagfile_information`` mapping of a metadata.yaml, parsed as rosbags
    parses it; ruamel's YAMLError, KeyError, TypeError, OSError for one that does not read."""
    from ruamel.yaml import YAML
    return YAML(typ='safe').load(meta.read_text())['rosbag2_bagfile_information']


def _listed_files(meta: Path):
    """The file names a metadata.yaml lists (``relative_file_paths``), or the YAML error or
    KeyError of one that does not read (cut off, ...)."""
    try:
        return {Path(str(x)).name for x in _metadata_info(meta)['relative_file_paths']}
    except Exception as e:  # noqa: BLE001 - ruamel's YAMLError, KeyError, TypeError
        return e


def _check_split_files(bag_path, files: list):
    """ValueError naming the files of a bag directory of several .db3 / .mcap files (a split
    recording) whose metadata.yaml does not read or does not list them all: rosbags would
    fail without naming them, or read the listed ones only."""
    p = Path(bag_path)
    listed = _listed_files(p / 'metadata.yaml')
    if isinstance(listed, Exception):
        if len(files) < 2:
            return   # rosbags' own error says it
        what = f'does not read ({" ".join(str(listed).split()) or type(listed).__name__})'
    else:
        unlisted = [f.name for f in files if f.name not in listed]
        if not unlisted:
            return
        what = f'does not list {", ".join(unlisted)}'
    raise ValueError(f'{bag_path}: its metadata.yaml {what} (a recording that was not '
                     f'closed?); the files of the bag: {", ".join(f.name for f in files)}: '
                     'play or read each file itself, or make a closed bag of each with '
                     'beo-bag-recover FILE -o NEW')


MCAP_MAGIC = b'\x89MCAP0\r\n'   # an mcap file's first and last 8 bytes


def _check_mcap_footer(bag_path):
    """ValueError naming an mcap file of a bag (or the file itself) that starts as an mcap
    file and does not end as one: a recording that was not closed, left without its footer.
    rosbags says 'File end magic is invalid.'; beo-bag-recover reads it."""
    p = Path(bag_path)
    files = [p] if p.suffix == '.mcap' else (sorted(p.glob('*.mcap')) if p.is_dir() else [])
    for f in files:
        with contextlib.suppress(OSError), open(f, 'rb') as fh:
            head = fh.read(8)
            size = fh.seek(0, 2)
            fh.seek(max(size - 8, 8))
            if head == MCAP_MAGIC and fh.read(8) != MCAP_MAGIC:
                raise ValueError(f'{f}: no mcap footer (a recording that was not closed?): '
                                 f'make a closed bag of it with beo-bag-recover {f} -o NEW')


def _check_readable(bag_path):
    """ValueError for a .db3 left in the middle of a write (:func:`hot_journal`), an .mcap
    file without its footer (:func:`_check_mcap_footer`), or a bag
    directory without metadata.yaml (a recording that was not closed), or whose metadata.yaml
    does not read or list all its files (:func:`_check_split_files`), saying what to do and
    naming the files; rosbags would call the directory itself the missing metadata file."""
    _check_no_hot_journal(bag_path)
    p = Path(bag_path)
    if not p.is_dir():
        _check_mcap_footer(p)
        return
    files = sorted(f for f in p.iterdir() if f.suffix in ('.db3', '.mcap'))
    if (p / 'metadata.yaml').exists():
        _check_split_files(p, files)
        _check_mcap_footer(p)
        return
    if len(files) > 1:
        raise ValueError(f'{bag_path}: no metadata.yaml (a recording that was not closed?); '
                         f'the files of the bag: {", ".join(f.name for f in files)}: play or '
                         'read each file itself, or make a closed bag of each with '
                         'beo-bag-recover FILE -o NEW')
    how = f'play or read {files[0]} itself, or ' if files else ''
    raise ValueError(f'{bag_path}: no metadata.yaml (a recording that was not closed?): '
                     f'{how}make a closed bag of it with beo-bag-recover {bag_path} -o NEW')


ZSTD_MAGIC = b'\x28\xb5\x2f\xfd'   # a zstd frame's first bytes; CDR's first byte is 0


def cdr_payload(raw) -> bytes:
    """The CDR bytes of a stored message: as they are, or decompressed if they are a zstd
    frame -- a bag recorded with per-message compression (``ros2 bag record
    --compression-mode message``) read from its .db3 / .mcap file, without the metadata.yaml
    that says so. ValueError for a frame that does not decompress."""
    data = bytes(raw)
    if data[:4] == ZSTD_MAGIC:
        from rosbags.rosbag2.storage_mcap import DECOMPRESSORS
        try:
            data = DECOMPRESSORS['zstd'](data, 0)
        except Exception as e:  # noqa: BLE001 - zstd's own error type
            raise ValueError(f'a zstd-compressed message does not decompress: {e}') from None
    return data


def _align_metadata_qos(reader) -> None:
    """Give each connection that an open bag directory's metadata.yaml lists the offered QoS
    its storage file stores for that topic and type, where the two differ. rosbags pairs them
    by topic, type *and* QoS, and reads no message of a connection whose metadata.yaml QoS
    (an empty or hand-edited ``offered_qos_profiles``) does not pair with the file's."""
    storages = getattr(reader.storage, 'storages', None)
    if not storages:   # a .db3 / .mcap file read directly: its connections are its own
        return
    conns = reader.storage.connections
    for i, c in enumerate(conns):
        same = [x for s in storages for x in s.connections
                if x.topic == c.topic and x.msgtype == c.msgtype
                and (not x.digest or not c.digest or x.digest == c.digest)]
        if same and not any(x.ext == c.ext for x in same):
            conns[i] = c._replace(ext=same[0].ext)


def _mcap_channels(path):
    """Yield ``(topic, metadata)`` of the channel records of an mcap file, those in its chunks
    included; stops quietly where the file does not read (a diagnosis, not a reader)."""
    import io

    from rosbags.rosbag2.storage_mcap import decompress

    def string(b):
        n = int.from_bytes(b.read(4), 'little')
        return b.read(n).decode(errors='replace')

    def channels(b, end):
        while b.tell() + 9 <= end:
            op, length = b.read(1)[0], int.from_bytes(b.read(8), 'little')
            body = b.read(length)
            if len(body) != length:
                return
            if op == 0x04:   # channel: id, schema id, topic, message encoding, metadata
                rec = io.BytesIO(body[4:])
                topic, _ = string(rec), string(rec)
                meta = rec.read(int.from_bytes(rec.read(4), 'little'))
                pairs, mb = {}, io.BytesIO(meta)
                while mb.tell() < len(meta):
                    key = string(mb)
                    pairs[key] = string(mb)
                yield topic, pairs
            elif op == 0x06:   # chunk: start, end, size, crc, compression, records
                usize = int.from_bytes(body[16:24], 'little')
                crc = int.from_bytes(body[24:28], 'little')
                n = int.from_bytes(body[28:32], 'little')
                data = decompress(body[40 + n:], body[32:32 + n].decode(), usize, crc)
                yield from channels(io.BytesIO(data), len(data))

    with contextlib.suppress(Exception), open(path, 'rb') as f:
        size = f.seek(0, 2)
        f.seek(8)   # past the magic
        yield from channels(f, size)


def _qos_texts(bag_path):
    """Yield ``(file, topic, offered_qos_profiles)`` of what a bag stores: its metadata.yaml's
    topics, its .db3 files' topics tables, its .mcap files' channels; what does not read is
    left out."""
    import sqlite3
    p = Path(bag_path)
    meta = p / 'metadata.yaml'
    if meta.is_file():
        topics = []
        with contextlib.suppress(Exception):
            topics = [t['topic_metadata']
                      for t in _metadata_info(meta)['topics_with_message_count']]
        for t in topics:
            if isinstance(t, dict) and 'offered_qos_profiles' in t:
                yield meta, t.get('name'), t['offered_qos_profiles']
    files = [p] if p.is_file() else (sorted(p.iterdir()) if p.is_dir() else [])
    for f in files:
        if f.suffix == '.db3':
            rows = []
            with contextlib.suppress(sqlite3.Error), contextlib.closing(
                    sqlite3.connect(f'file:{f}?immutable=1', uri=True)) as db:
                rows = db.execute('SELECT name, offered_qos_profiles FROM topics').fetchall()
            yield from ((f, topic, text) for topic, text in rows)
        elif f.suffix == '.mcap':
            for topic, pairs in _mcap_channels(f):
                if 'offered_qos_profiles' in pairs:
                    yield f, topic, pairs['offered_qos_profiles']


def bad_qos(bag_path) -> str | None:
    """One line naming the file, the topic and the field of offered QoS profiles that a bag
    stores and that do not parse (not YAML, or not a list of profiles), or None. rosbags fails
    on them with a TypeError, or a message that names neither topic nor bag."""
    from rosbags.rosbag2.metadata import parse_qos
    for f, topic, text in _qos_texts(bag_path):
        try:
            parse_qos(text)
        except Exception as e:  # noqa: BLE001 - TypeError, KeyError, ReaderError, ...
            why = ' '.join(str(e).split())
            return (f'{f}: topic {topic}: offered_qos_profiles is not a list of QoS profiles '
                    f'({type(e).__name__}{": " + why if why else ""})')
    return None


def not_cdr(conns) -> str | None:
    """What is wrong with bag connections of which one is not CDR-encoded (an mcap channel's
    message encoding, such as 'json'), or None. rosbags reads their bytes as they are, and
    they would be played or copied as CDR: mis-decoded."""
    for c in conns:
        fmt = getattr(getattr(c, 'ext', None), 'serialization_format', 'cdr')
        if fmt != 'cdr':
            return (f'topic {c.topic} is encoded as {fmt!r}, not cdr: only CDR-encoded '
                    'messages are supported')
    return None


@contextlib.contextmanager
def _reader(bag_path):
    """A rosbags Reader of ``bag_path``, open; ValueError naming the file, topic and field when
    it does not open because of offered QoS profiles that do not parse (:func:`bad_qos`), or
    naming the topic of messages that are not CDR (:func:`not_cdr`)."""
    from rosbags.rosbag2 import Reader
    reader = Reader(Path(bag_path))
    try:
        reader.open()
    except Exception:
        problem = bad_qos(bag_path)
        if problem:
            raise ValueError(problem) from None
        raise
    try:
        storages = getattr(reader.storage, 'storages', None) or [reader.storage]
        problem = not_cdr([c for s in storages for c in s.connections])
        if problem:
            raise ValueError(f'{bag_path}: {problem}')
        yield reader
    finally:
        reader.close()


@contextlib.contextmanager
def _open_reader(bag_path):
    """A rosbags Reader of ``bag_path``, open (:func:`_reader`), its metadata's QoS aligned
    with its storage's (:func:`_align_metadata_qos`)."""
    with _reader(bag_path) as reader:
        _align_metadata_qos(reader)
        yield reader


def _topic_set(topics):
    """``topics`` (None, one topic name, or an iterable of names) as a set of names, or None
    (every topic). A single string is one name: ``c.topic in '/beo/input'`` matched by
    substring (``/beo`` too), and ``set('/a')`` is its characters."""
    if topics is None:
        return None
    return {topics} if isinstance(topics, str) else set(topics)


def read_bag(bag_path, topics=None):
    """Yield ``(topic, msgtype, timestamp_ns, raw_cdr_bytes)`` in timestamp order, of every
    topic or of ``topics`` (one topic name or several). ValueError for a .db3 left in the
    middle of a write (see :func:`hot_journal`)."""
    topics = _topic_set(topics)
    _check_readable(bag_path)
    with _open_reader(bag_path) as reader:
        conns = [c for c in reader.connections if topics is None or c.topic in topics]
        if not conns:
            return
        for conn, t, raw in reader.messages(connections=conns):
            yield conn.topic, conn.msgtype, t, cdr_payload(raw)


def read_messages(bag_path, topics=None):
    """Yield ``(topic, rclpy_message, timestamp_ns)``, deserialized with rclpy."""
    from rclpy.serialization import deserialize_message
    classes = {}
    for topic, msgtype, t, raw in read_bag(bag_path, topics):
        if msgtype not in classes:
            classes[msgtype] = import_msg_class(msgtype)
        yield topic, deserialize_message(raw, classes[msgtype]), t


def bag_info(bag_path) -> dict:
    """Storage, duration and ``{topic: {'type', 'count'}}`` of a bag; a topic recorded in
    several types (mcap channels) has them all in 'type', comma-separated."""
    _check_readable(bag_path)
    with _reader(bag_path) as reader:
        topics = {}
        for c in reader.connections:
            d = topics.setdefault(c.topic, {'type': c.msgtype, 'count': 0})
            if c.msgtype not in d['type'].split(', '):
                d['type'] += f', {c.msgtype}'
            d['count'] += c.msgcount
        return {'path': str(bag_path), 'storage': detect_storage(bag_path),
                'start_ns': reader.start_time if reader.message_count else 0,
                'duration_s': reader.duration / 1e9 if reader.message_count else 0.0,
                'message_count': reader.message_count, 'topics': topics}
