"""beo-bag-recover: the intact messages of a bag that was never closed, copied into a new bag."""
from __future__ import annotations

import contextlib
import functools
import os
import shutil
from pathlib import Path

from beo_ros.ros.bag.msgtypes import (get_typestore, hash_rihs01, normalize_msgtype,
                                      types_from_msg)
from beo_ros.ros.bag.recorder import BagWriteError
from beo_ros.ros.bag.storage import (MCAP_MAGIC, BagWriter, bad_qos, cdr_payload,
                                     hot_journal, not_cdr, recorded_latched,
                                     recorded_reliable, storage_errors, unmerged_wal)


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
        records = decompress(body[40 + n:], body[32:32 + n].decode(errors='replace'), usize, crc)
    except Exception:  # noqa: BLE001 - ReaderError, zstd's and lz4's own errors, MemoryError
        return False
    return _messages_in_time_range(records, int.from_bytes(body[0:8], 'little'),
                                   int.from_bytes(body[8:16], 'little'))


def _messages_in_time_range(records: bytes, start: int, end: int) -> bool:
    """Whether a chunk's records are whole and its messages' log times within the chunk's
    ``[start, end]`` (without a crc, a damaged stamp shows only there)."""
    pos = 0
    while pos < len(records):
        if pos + 9 > len(records):
            return False
        op, length = records[pos], int.from_bytes(records[pos + 1:pos + 9], 'little')
        if pos + 9 + length > len(records):
            return False
        if op == 0x05:   # message: channel id (2), sequence (4), log time (8), ...
            if length < 22:
                return False
            log_time = int.from_bytes(records[pos + 15:pos + 23], 'little')
            if not start <= log_time <= end:
                return False
        pos += 9 + length
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
    if not files:
        raise ValueError(f'{src}: expected one .db3 or .mcap file, found none')
    if len(files) > 1:   # a split recording
        raise ValueError(f'{src}: expected one .db3 or .mcap file, found {len(files)}: '
                         f'{", ".join(f.name for f in files)}: recover each file '
                         '(beo-bag-recover FILE -o NEW)')
    return files[0]


class _Damaged(Exception):
    """rosbags could not read a (repaired) bag to its end."""


class _NotCdr(ValueError):
    """A bag of messages that are not CDR (:func:`not_cdr`): not damage, not to be copied."""


def recover_bag(src, dst, *, storage: str | None = None) -> dict:
    """Copy every intact message of a bag that was never closed (a recording ended by SIGKILL,
    a crash or a full disk: no metadata.yaml, an mcap file without its footer) into a new,
    closed bag ``dst``, as ``ros2 bag reindex`` and ``mcap recover`` would.

    ``src``: bag directory or its .db3 / .mcap file; ``storage``: dst's (default src's).
    -> ``{'messages', 'topics': {topic: count}, 'storage', 'lost_bytes'}``; ``lost_bytes``:
    the tail of an mcap file after its last intact record (0 for sqlite3): a record cut off or
    damaged, a chunk that does not decompress to its size, or one with a message that does not
    deserialize or is stamped outside the chunk's time range, and all after it. A closed mcap
    file whose index does not read is read as if it had none. ValueError for a source that is
    not a bag, an mcap file cut off inside its header, or a database that does not read;
    :class:`BagWriteError` when the new bag cannot be written (a full disk: nothing is left).
    """
    import tempfile
    path = _bag_file(src)
    storage = storage or ('mcap' if path.suffix == '.mcap' else 'sqlite3')
    dst = Path(dst)
    ends, closed = _mcap_record_ends(path) if path.suffix == '.mcap' else ([], True)
    try:
        dst.parent.mkdir(parents=True, exist_ok=True)   # as rosbags' writer would
        end = os.path.getsize(path)
        with tempfile.TemporaryDirectory(prefix='.beo_recover_', dir=dst.parent) as tmp:
            tmp = Path(tmp)
            if path.suffix == '.db3':
                try:
                    topics = _copy_messages(_rolled_back(path, tmp), dst, storage, False)
                except _Damaged as e:
                    raise ValueError(bad_qos(path) or f'{path}: {e}') from None
            else:
                topics = None
                if closed:
                    try:
                        topics = _copy_messages(path, dst, storage, False)
                    except _Damaged:   # its summary (index) is damaged: scan the data instead
                        ends, _ = _mcap_record_ends(path, trust_footer=False)
                if topics is None:
                    topics, end = _longest_readable_prefix(path, ends, dst, storage, tmp)
    except _NotCdr as e:   # from a copy of path, maybe: named by path
        raise ValueError(f'{path}: {e}') from None
    except storage_errors() as e:   # the source reads (above, or as _Damaged): a full disk, ...
        raise BagWriteError(f'cannot write {dst}: {e}') from e
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
    if best is None:   # QoS profiles that do not parse: no prefix with that channel reads
        problem = bad_qos(path)
        if problem:
            raise ValueError(problem)
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
    :func:`hot_journal`), or with the transactions of its write-ahead log (``-wal``: a
    recording in WAL mode that was killed before checkpointing them) moved into it: rosbags
    opens a database as immutable, ignoring both. ``db`` and its files are left as they are."""
    journal, wal = hot_journal(db), unmerged_wal(db)
    if journal is None and wal is None:
        return db
    import sqlite3
    copy = tmp / db.name
    shutil.copyfile(db, copy)
    for f in (journal, wal):
        if f is not None:
            shutil.copyfile(f, tmp / f.name)
    with contextlib.closing(sqlite3.connect(copy)) as conn:
        conn.execute('SELECT COUNT(*) FROM sqlite_master').fetchone()
        if wal is not None:
            conn.execute('PRAGMA wal_checkpoint(TRUNCATE)').fetchone()
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
    topics, checks = {}, {}   # checks: {connection id: _cdr_check of its type}
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
    problem = not_cdr(conns)
    if problem:
        reader.close()
        raise _NotCdr(problem)
    try:
        with _removed_on_error(BagWriter(dst, storage)) as writer:
            for c in conns:
                try:   # the bag's own definition: its bytes were written with it
                    definition = _own_definition(c)
                except KeyError:   # none in the bag: the installed one
                    definition = {}
                # a topic of two types (two mcap channels): both are kept
                writer.add_topic(c.topic, c.msgtype, reliable=recorded_reliable(c),
                                 transient_local=recorded_latched(c), another_type=True,
                                 **definition)
                topics.setdefault(c.topic, 0)
                if readable.suffix == '.mcap':   # no crc to tell a damaged message
                    checks[c.id] = _cdr_check(c, definition)
            while True:
                try:
                    conn, t, raw = next(messages)
                except StopIteration:
                    break
                except Exception as e:  # noqa: BLE001 - as above
                    raise _Damaged(_one_line(e)) from e
                try:   # the new bag's messages are not compressed
                    raw = cdr_payload(raw)
                    if checks.get(conn.id) is not None:
                        checks[conn.id](raw)
                except Exception as e:  # noqa: BLE001 - SerdeError, MemoryError, ...
                    raise _Damaged(f'{conn.topic}: a message stamped {t} does not '
                                   f'deserialize ({_one_line(e)})') from e
                writer.write(conn.topic, raw, t, conn.msgtype)
                topics[conn.topic] += 1
            copied = sum(topics.values())
            if not unindexed and readable.suffix == '.mcap' and copied != reader.message_count:
                # the index leaves out a message stamped outside its chunk's time range
                raise _Damaged(f'{copied} message(s) read of the {reader.message_count} its '
                               'summary counts')
    finally:
        with contextlib.suppress(Exception):
            reader.close()
    return topics


def _cdr_check(conn, definition: dict):
    """A callable that raises for CDR bytes that do not deserialize as ``conn``'s type (the
    bag's own ``definition``, or the installed one), or None when the type does not parse."""
    from rosbags.typesys import Stores
    from rosbags.typesys import get_typestore as rosbags_typestore
    try:
        if definition:
            store = rosbags_typestore(Stores.EMPTY)
            store.register(types_from_msg(definition['msgdef'], conn.msgtype))
        else:
            store = get_typestore([conn.msgtype])
    except Exception:  # noqa: BLE001 - rosbags' parse errors have no common base
        return None
    return functools.partial(store.deserialize_cdr, typename=conn.msgtype)


def _one_line(exc) -> str:
    """An exception as one line: its type and its message's lines joined."""
    text = ' '.join(str(exc).split())
    return f'{type(exc).__name__}: {text}' if text else type(exc).__name__


def _own_definition(conn) -> dict:
    """``{'msgdef', 'rihs01'}`` of a bag connection from the bag itself (an mcap file read
    without metadata.yaml has no hash: it is computed from the definition); KeyError when the
    bag has no ros2msg definition of it."""
    from rosbags.interfaces import MessageDefinitionFormat
    from rosbags.typesys import Stores
    from rosbags.typesys import get_typestore as rosbags_typestore
    msgdef = conn.msgdef
    if msgdef.format != MessageDefinitionFormat.MSG or not msgdef.data.strip():
        raise KeyError(f'no message definition found for {conn.msgtype} (neither installed nor '
                       'in the bag)')
    rihs01 = conn.digest
    if not rihs01:
        try:
            store = rosbags_typestore(Stores.EMPTY)
            store.register(types_from_msg(msgdef.data, conn.msgtype))
            rihs01 = hash_rihs01(store, conn.msgtype)
        except Exception as e:  # noqa: BLE001 - rosbags' parse errors have no common base
            raise KeyError(f'{conn.msgtype}: the definition in the bag does not parse '
                           f'({e})') from None
    return {'msgdef': msgdef.data, 'rihs01': rihs01}


@contextlib.contextmanager
def _removed_on_error(writer):
    """Open ``writer``; close it on success, abort it and remove its bag on any exception,
    closing's own included (a full disk when the mcap summary or metadata.yaml is written)."""
    try:
        with writer:
            try:
                yield writer
            except BaseException:
                writer.failed = True   # aborted, not closed
                raise
    except BaseException:
        if writer._opened:   # the directory is ours, not one that was there
            writer.abort()
            shutil.rmtree(writer.path, ignore_errors=True)
        raise
