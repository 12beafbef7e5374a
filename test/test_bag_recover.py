"""Bags that were never closed (SIGKILL, crash, full disk): BagWriter.commit makes mcap data
durable too, and recover_bag / beo-bag-recover copy the intact messages into a closed bag."""
import os
import subprocess
import sys

import pytest

pytest.importorskip('rosbags')
pytest.importorskip('rclpy')

from beo_ros.ros import bag  # noqa: E402

# writes argv[3] messages on /a (latched) and /b, commits, writes argv[4] more on /a (of
# argv[5] bytes), then ends as SIGKILL would: no close, no flush of Python's buffers
KILLED_WRITER = r'''
import os, sys
from std_msgs.msg import String
from beo_ros.ros.bag import BagWriter
storage, path, n, extra = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
size = int(sys.argv[5]) if len(sys.argv) > 5 else 0
w = BagWriter(path, storage).open()
w.add_topic('/a', 'std_msgs/msg/String', transient_local=True)
for i in range(n):
    w.write('/a', String(data=f'a{i}:' + 'x' * 3000), 1000 + i)
    w.write('/b', String(data=f'b{i}'), 500 + i)   # stamps behind /a's: file order != time order
assert w.commit()
for i in range(extra):
    w.write('/a', String(data=f'lost{i}:' + 'y' * size), 5000 + i)
os._exit(9)
'''


def _killed_bag(tmp_path, storage, n=400, extra=3, size=0):
    out = tmp_path / 'killed'
    p = subprocess.run([sys.executable, '-c', KILLED_WRITER, storage, str(out), str(n),
                        str(extra), str(size)], capture_output=True, text=True, timeout=120)
    assert p.returncode == 9, p.stderr
    assert not (out / 'metadata.yaml').exists()
    return out


def _texts(path):
    from std_msgs.msg import String
    from rclpy.serialization import deserialize_message
    return [(t, deserialize_message(raw, String).data.split(':')[0])
            for t, _, _, raw in bag.read_bag(path)]


@pytest.mark.parametrize('storage', bag.STORAGES)
def test_a_killed_recording_recovers_what_was_committed(tmp_path, storage):
    """Before: an mcap recording killed with SIGKILL kept nothing (the chunk in memory, no
    footer; rosbags: 'File end magic is invalid'); now every committed message is recovered,
    with its topic's QoS, and only the messages after the last commit are lost."""
    killed = _killed_bag(tmp_path, storage)
    if storage == 'mcap':   # read on its own, it is refused (test_..._without_its_footer)
        with pytest.raises(ValueError, match='no mcap footer'):
            list(bag.read_bag(bag._bag_file(killed)))
    summary = bag.recover_bag(killed, tmp_path / 'new')
    assert summary == {'messages': 800, 'topics': {'/a': 400, '/b': 400}, 'storage': storage,
                       'lost_bytes': 0}
    info = bag.bag_info(tmp_path / 'new')   # a closed bag: metadata.yaml and all
    assert (tmp_path / 'new' / 'metadata.yaml').is_file() and info['message_count'] == 800
    got = _texts(tmp_path / 'new')
    assert sorted(got) == sorted([('/a', f'a{i}') for i in range(400)]
                                 + [('/b', f'b{i}') for i in range(400)])
    from rosbags.rosbag2 import Reader
    with Reader(tmp_path / 'new') as r:
        assert {c.topic: bag.recorded_latched(c) for c in r.connections} == {
            '/a': True, '/b': False}


def test_an_mcap_file_cut_anywhere_gives_a_prefix_of_its_messages(tmp_path):
    """A file cut mid-record (a full disk, a crash while a chunk was written) keeps the
    messages of its intact chunks; cut inside its header it says there is nothing to
    recover and leaves no bag behind."""
    killed = _killed_bag(tmp_path, 'mcap', n=1000, extra=0)   # 3 MB: 1 MiB chunks
    data = bag._bag_file(killed).read_bytes()
    cuts = [0, 5, 30, 60, len(data) // 3, len(data) // 2, len(data) - 1, len(data)]
    counts = []
    for i, cut in enumerate(cuts):
        src = tmp_path / f'cut{i}.mcap'
        src.write_bytes(data[:cut])
        dst = tmp_path / f'rec{i}'
        if cut < 60:
            with pytest.raises(ValueError, match='empty|header'):
                bag.recover_bag(src, dst)
            assert not dst.exists()
            continue
        summary = bag.recover_bag(src, dst)
        counts.append(summary['messages'])
        assert len(list(bag.read_bag(dst))) == summary['messages']
        assert (summary['lost_bytes'] > 0) == (cut < len(data))
    assert counts == sorted(counts) and counts[0] == 0 and counts[-1] == 2000
    assert 0 < counts[2] < 2000   # half the file: its first chunk
    assert not [p for p in tmp_path.iterdir() if p.name.startswith('.beo_recover_')]


def test_a_closed_bag_is_copied_whole_into_the_other_storage(tmp_path):
    from std_msgs.msg import String
    src = tmp_path / 'closed'
    with bag.BagWriter(src, 'mcap') as w:
        for i in range(5):
            w.write('/s', String(data=str(i)), 10 + i)
    summary = bag.recover_bag(src, tmp_path / 'copy', storage='sqlite3')
    assert summary == {'messages': 5, 'topics': {'/s': 5}, 'storage': 'sqlite3',
                       'lost_bytes': 0}
    assert bag.detect_storage(tmp_path / 'copy') == 'sqlite3'
    assert [raw for *_, raw in bag.read_bag(tmp_path / 'copy')] == [
        raw for *_, raw in bag.read_bag(src)]


def test_cli_recover(tmp_path, capsys):
    killed = _killed_bag(tmp_path, 'mcap', n=3)
    assert bag.recover_main([str(killed), '-o', str(tmp_path / 'ok')]) == 0
    out = capsys.readouterr().out
    assert out.strip() == f'6 message(s) (/a: 3 /b: 3) -> {tmp_path / "ok"} (mcap)'
    deep = tmp_path / 'new' / 'dirs' / 'bag'   # missing parents are made, as for beo-record
    assert bag.recover_main([str(killed), '-o', str(deep), '--storage', 'sqlite3']) == 0
    assert bag.bag_info(deep)['message_count'] == 6
    capsys.readouterr()
    (tmp_path / 'junk.mcap').write_bytes(b'not an mcap file at all')
    for src, why in ((tmp_path / 'nope', 'no such bag'), (tmp_path / 'junk.mcap', 'not an mcap'),
                     (tmp_path / 'ok' / 'metadata.yaml', 'not a .db3 or .mcap')):
        assert bag.recover_main([str(src), '-o', str(tmp_path / 'x')]) == 2
        err = capsys.readouterr().err
        assert err.startswith('beo-bag-recover: ') and why in err and len(err.splitlines()) == 1
        assert not (tmp_path / 'x').exists()
    with pytest.raises(SystemExit):   # the output exists already
        bag.recover_main([str(killed), '-o', str(tmp_path / 'ok')])
    assert 'exists already' in capsys.readouterr().err


def test_commit_of_an_mcap_writer_without_new_messages_is_harmless(tmp_path):
    from std_msgs.msg import String
    with bag.BagWriter(tmp_path / 'b', 'mcap') as w:
        assert w.commit()   # nothing written yet
        w.write('/s', String(data='a'), 1)
        assert w.commit() and w.commit() and w.committed == 1
        w.write('/s', String(data='b'), 2)
    assert [t for _, _, t, _ in bag.read_bag(tmp_path / 'b')] == [1, 2]
    assert os.path.getsize(tmp_path / 'b' / 'b.mcap') > 0


@pytest.mark.parametrize('storage', bag.STORAGES)
def test_a_type_beo_ros_does_not_know_is_copied_with_the_bags_own_definition(tmp_path, storage):
    """Bags of other recorders (ros2 bag record) may carry types beo_ros has no .msg file for:
    the new bag takes the old one's definition (before: KeyError)."""
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore
    store = get_typestore(Stores.EMPTY)
    store.register(get_types_from_msg('int32 a\n', 'my_pkg/msg/Thing'))
    # an mcap file read without metadata.yaml has no hash: the copy computes it again
    src, digest = tmp_path / 'other', store.hash_rihs01('my_pkg/msg/Thing')
    with bag.BagWriter(src, storage) as w:
        with pytest.raises(KeyError):
            w.add_topic('/t', 'my_pkg/msg/Thing')
        w.add_topic('/t', 'my_pkg/msg/Thing', msgdef='int32 a\n', rihs01=digest)
        for i in range(3):
            w.write('/t', bytes([0, 1, 0, 0, i, 0, 0, 0]), 10 + i)
    assert bag.recover_bag(src, tmp_path / 'new')['topics'] == {'/t': 3}
    with Reader(tmp_path / 'new') as r:
        (c,) = r.connections
        assert (c.msgtype, c.msgdef.data.strip(), c.digest) == ('my_pkg/msg/Thing', 'int32 a',
                                                                digest)
    assert [raw[4] for *_, raw in bag.read_bag(tmp_path / 'new')] == [0, 1, 2]


def _records(data):
    """(opcode, offset) of the top-level records of mcap bytes, up to the data end."""
    pos, out = 8, []
    while pos + 9 <= len(data):
        op, length = data[pos], int.from_bytes(data[pos + 1:pos + 9], 'little')
        out.append((op, pos))
        if op in (0x02, 0x0f):
            break
        pos += 9 + length
    return out


def test_a_zstd_chunk_that_does_not_decompress_ends_what_is_recovered(tmp_path):
    """ros2 bag records mcap with zstd chunks; one that fails to decompress (zstd raises its
    own error type) ends the intact part. Before: a traceback from beo-bag-recover."""
    from rosbags.rosbag2 import CompressionFormat, CompressionMode
    from std_msgs.msg import String
    src = tmp_path / 'z'
    w = bag.BagWriter(src, 'mcap')
    w._writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    with w:
        for batch in range(3):   # a chunk per commit
            for i in range(4):
                w.write('/s', String(data=f'{batch}.{i}'), 10 * batch + i)
            w.commit()
    data = bytearray(bag._bag_file(src).read_bytes()[:-37])   # no footer: never closed
    chunks = [pos for op, pos in _records(data) if op == 0x06]
    assert len(chunks) == 3
    # the third chunk's zstd frame magic: after opcode and length (9), times, sizes and crc
    # (28), the compression name (4 + 4) and the records' length (8)
    data[chunks[2] + 9 + 28 + 8 + 8] ^= 0xFF
    cut = tmp_path / 'cut.mcap'
    cut.write_bytes(bytes(data))
    assert bag.recover_main([str(cut), '-o', str(tmp_path / 'new')]) == 0
    assert [t for _, _, t, _ in bag.read_bag(tmp_path / 'new')] == [0, 1, 2, 3, 10, 11, 12, 13]


def test_a_sqlite3_bag_killed_mid_transaction_is_read_without_its_torn_pages(tmp_path):
    """An uncommitted transaction larger than sqlite's page cache spills into the .db3 and
    leaves a rollback journal; rosbags opens the file as immutable, ignoring the journal.
    Before: read_bag and recover_bag read a torn database (committed messages missing or
    duplicated, or 'database disk image is malformed'); now reading it directly is refused
    and recover_bag rolls the journal back in a copy and gets exactly the committed ones."""
    killed = _killed_bag(tmp_path, 'sqlite3', n=300, extra=1500, size=3000)   # 4.5 MB
    journal = bag.hot_journal(killed)
    assert journal is not None and journal.stat().st_size > 0
    for path in (killed, bag._bag_file(killed)):
        with pytest.raises(ValueError, match='beo-bag-recover'):
            list(bag.read_bag(path))
        with pytest.raises(ValueError, match='beo-bag-recover'):
            bag.bag_info(path)
    summary = bag.recover_bag(killed, tmp_path / 'new')
    assert summary['topics'] == {'/a': 300, '/b': 300}
    assert sorted(_texts(tmp_path / 'new')) == sorted(
        [('/a', f'a{i}') for i in range(300)] + [('/b', f'b{i}') for i in range(300)])
    assert journal.is_file()   # the source is left as it was


def test_a_sqlite3_bag_killed_with_a_few_messages_uncommitted_reads_directly(tmp_path):
    """kill -9 with a few messages written since the last commit (a recording of a steady
    topic) leaves a journal whose header was never written (first byte 0): sqlite ignores
    it, the database holds exactly the committed messages. Before: read_bag, bag_info and
    beo-replay of the .db3 were refused ('left in the middle of a write'), against the docs
    ('play or read its .db3 file itself')."""
    killed = _killed_bag(tmp_path, 'sqlite3')
    db = bag._bag_file(killed)
    journal = db.with_name(db.name + '-journal')
    assert journal.is_file() and journal.stat().st_size > 0
    assert journal.read_bytes()[:1] == b'\0'
    assert bag.hot_journal(killed) is None
    assert sorted(_texts(db)) == sorted([('/a', f'a{i}') for i in range(400)]
                                        + [('/b', f'b{i}') for i in range(400)])
    assert bag.bag_info(db)['message_count'] == 800


@pytest.mark.parametrize('storage', bag.STORAGES)
def test_a_bag_directory_without_metadata_names_what_is_missing_and_what_to_do(
        tmp_path, storage, capsys, keep_signal_handlers):
    """Before: 'Expected metadata file 'BAG' does not exist.' (rosbags names the directory as
    the missing file) from beo-replay BAG, read_bag and bag_info of a recording that was not
    closed; now: no metadata.yaml, its file to play directly or beo-bag-recover."""
    killed = _killed_bag(tmp_path, storage, n=3, extra=0)
    for read in (lambda: list(bag.read_bag(killed)), lambda: bag.bag_info(killed)):
        with pytest.raises(ValueError, match='no metadata.yaml') as e:
            read()
        assert str(bag._bag_file(killed)) in str(e.value) and 'beo-bag-recover' in str(e.value)
    assert bag.replay_main([str(killed)]) == 2
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and 'no metadata.yaml' in err and 'beo-bag-recover' in err, err


# beo-bag-recover with a file size limit: a full disk, as far as the writes of this process go
FULL_DISK_RECOVER = r'''
import resource, signal, sys
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)   # EFBIG instead
resource.setrlimit(resource.RLIMIT_FSIZE, (int(sys.argv[1]), int(sys.argv[1])))
from beo_ros.ros import bag
sys.exit(bag.recover_main(sys.argv[2:]))
'''


def _recover_onto_a_full_disk(tmp_path, storage, closed):
    """beo-bag-recover of a killed (or a ``closed``) bag of 20 messages onto a disk that holds
    20 kB -> (the new bag's path, the finished process)."""
    src = _killed_bag(tmp_path, storage, n=20, extra=0)
    if closed:
        bag.recover_bag(src, tmp_path / 'closed')
        src = tmp_path / 'closed'
    out = tmp_path / 'out' / 'new'
    return out, subprocess.run([sys.executable, '-c', FULL_DISK_RECOVER, '20000', str(src),
                                '-o', str(out)], capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize('storage', bag.STORAGES)
@pytest.mark.parametrize('closed', [True, False])
def test_cli_recover_onto_a_full_disk_names_the_new_bag(tmp_path, storage, closed):
    """Before: 'beo-bag-recover: SRC: disk I/O error' (or 'File too large'), as if the source
    bag were damaged; now the new bag it could not write is named, and nothing is left."""
    out, p = _recover_onto_a_full_disk(tmp_path, storage, closed)
    assert p.returncode == 2, p.stderr
    assert p.stderr.startswith(f'beo-bag-recover: cannot write {out}: ') and \
        p.stderr.count('\n') == 1, p.stderr


def test_a_recovery_that_fails_while_closing_leaves_no_new_bag(tmp_path):
    """A closed mcap bag copied onto a full disk fails when the new bag is closed (its summary
    is written). Before: the half-written new bag (its .mcap, no metadata.yaml) was left."""
    out, p = _recover_onto_a_full_disk(tmp_path, 'mcap', closed=True)
    assert p.returncode == 2, p.stderr
    assert list((tmp_path / 'out').iterdir()) == []


def _three_chunk_bag(tmp_path, close):
    """An mcap bag of three chunks of 4 messages on /s (stamps 0-3, 10-13, 20-23) -> its bytes
    (without the footer, as if killed, unless ``close``) and the chunks' offsets."""
    from std_msgs.msg import String
    src = tmp_path / f'three{close}'
    with bag.BagWriter(src, 'mcap') as w:
        for batch in range(3):
            for i in range(4):
                w.write('/s', String(data=f'{batch}.{i}'), 10 * batch + i)
            w.commit()
    data = bytearray(bag._bag_file(src).read_bytes())
    if not close:
        data = data[:-37]
    return data, [pos for op, pos in _records(data) if op == 0x06]


@pytest.mark.parametrize('damage', ['record length', 'zeroed tail', 'channel type'])
def test_a_chunk_damaged_inside_ends_what_is_recovered(tmp_path, damage):
    """A chunk whose bytes are all there but damaged inside: the chunks before it are
    recovered. Before: OverflowError / 'Truncated record' tracebacks or one-line errors with
    nothing recovered (fuzz probe: 942 of 3222 single-byte flips lost intact chunks)."""
    data, chunks = _three_chunk_bag(tmp_path, close=False)
    body = chunks[2] + 9 + 28 + 4 + 0 + 8   # uncompressed records of the third chunk
    if damage == 'record length':   # its first message record claims 2^63 bytes
        data[body + 8] ^= 0x80
    elif damage == 'zeroed tail':
        data[body:] = bytes(len(data) - body)
    cut = tmp_path / 'damaged.mcap'
    if damage == 'channel type':   # the first chunk holds the schema and channel: all lost
        data[data.index(b'std_msgs/msg/String') + 10] = ord('?')   # std_msgs/m?g/String
    cut.write_bytes(bytes(data))
    assert bag.recover_main([str(cut), '-o', str(tmp_path / 'new')]) == 0
    stamps = [t for _, _, t, _ in bag.read_bag(tmp_path / 'new')]
    assert stamps == ([] if damage == 'channel type' else [0, 1, 2, 3, 10, 11, 12, 13])


def test_a_damaged_last_record_loses_only_itself(tmp_path):
    """A killed file whose last record is a whole chunk that rosbags cannot read (the type
    name of a schema first written in it is damaged): every record before it is recovered
    (the bisection's upper end, when not all records read, is the record before the last)."""
    from std_msgs.msg import Int32, String
    src = tmp_path / 'two_types'
    with bag.BagWriter(src, 'mcap') as w:
        for batch in range(2):
            w.write('/s', String(data=str(batch)), batch)
            w.commit()
        w.write('/i', Int32(data=2), 2)   # its schema and channel in the third chunk
        w.commit()
    data = bytearray(bag._bag_file(src).read_bytes())
    records = _records(data)
    last = [pos for op, pos in records if op == 0x06][-1]
    del data[last + 9 + int.from_bytes(data[last + 1:last + 9], 'little'):]   # killed
    data[data.index(b'std_msgs/msg/Int32') + 10] = ord('?')   # std_msgs/m?g/Int32
    cut = tmp_path / 'damaged.mcap'
    cut.write_bytes(bytes(data))
    summary = bag.recover_bag(cut, tmp_path / 'new')
    assert summary['topics'] == {'/s': 2}
    assert summary['lost_bytes'] == len(data) - last   # the record before it is kept


def test_a_closed_mcap_file_whose_index_is_damaged_is_read_by_scanning(tmp_path):
    """Before: MemoryError, OverflowError or struct.error tracebacks from the summary."""
    data, _ = _three_chunk_bag(tmp_path, close=True)
    summary_start = int.from_bytes(data[-37 + 9:-37 + 17], 'little')
    for i in range(summary_start, len(data) - 37, 7):
        data[i] ^= 0xFF
    cut = tmp_path / 'closed.mcap'
    cut.write_bytes(bytes(data))
    summary = bag.recover_bag(cut, tmp_path / 'new')
    # left out: the data end record (13 bytes) and the summary after it
    assert summary['messages'] == 12 and summary['lost_bytes'] == len(data) - summary_start + 13
    assert [t for _, _, t, _ in bag.read_bag(tmp_path / 'new')] == [
        0, 1, 2, 3, 10, 11, 12, 13, 20, 21, 22, 23]


def test_the_largest_stamp_survives_recovery(tmp_path):
    """rosbags' scan of an unindexed file ends before 2^63-1 unless told otherwise."""
    from std_msgs.msg import String
    src = tmp_path / 'max'
    stamps = [0, 1, 2 ** 63 - 2, 2 ** 63 - 1]
    with bag.BagWriter(src, 'mcap') as w:
        for t in stamps:
            w.write('/s', String(data=str(t)), t)
    data = bag._bag_file(src).read_bytes()[:-37]   # never closed
    (tmp_path / 'cut.mcap').write_bytes(data)
    bag.recover_bag(tmp_path / 'cut.mcap', tmp_path / 'new')
    assert [t for _, _, t, _ in bag.read_bag(tmp_path / 'new')] == stamps


@pytest.mark.parametrize('close', [False, True])
@pytest.mark.parametrize('damage', ['log time', 'cdr header'])
def test_a_damaged_message_in_a_chunk_without_crc_ends_what_is_recovered(tmp_path, damage,
                                                                         close):
    """rosbags writes chunks without a crc: a flipped byte inside a message record showed
    nowhere. Before: a stamp moved years ahead or a CDR header that does not deserialize was
    copied as it was (in a closed file the message stamped outside its chunk was dropped),
    with lost_bytes 0 for a closed file; now that chunk ends what is recovered and its bytes
    are counted in lost_bytes."""
    data, chunks = _three_chunk_bag(tmp_path, close)
    message = chunks[2] + 9 + 28 + 4 + 8   # the third chunk's first record: a message
    # after its opcode and length (9): channel id (2), sequence (4), log time (8), publish
    # time (8), then the CDR bytes
    data[message + (9 + 6 + 5 if damage == 'log time' else 9 + 22 + 1)] ^= 0xFF
    cut = tmp_path / 'flipped.mcap'
    cut.write_bytes(bytes(data))
    summary = bag.recover_bag(cut, tmp_path / 'new')
    assert summary['messages'] == 8 and summary['lost_bytes'] >= len(data) - chunks[2] - 37
    assert [t for _, _, t, _ in bag.read_bag(tmp_path / 'new')] == [0, 1, 2, 3, 10, 11, 12, 13]


@pytest.mark.parametrize('storage', bag.STORAGES)
def test_a_bag_of_zstd_compressed_messages_is_read_and_recovered_as_cdr(ros_env_context,
                                                                         tmp_path, storage):
    """ros2 bag record --compression-mode message stores each message as a zstd frame; only
    metadata.yaml says so. Before: read_bag (and beo-replay) of its storage file yielded the
    compressed bytes as CDR, recover_bag copied them into an uncompressed bag (sqlite3:
    garbage messages, no word of it) or recovered nothing (mcap)."""
    from rosbags.rosbag2 import CompressionFormat, CompressionMode
    from std_msgs.msg import String
    src = tmp_path / 'z'
    w = bag.BagWriter(src, storage)
    w._writer.set_compression(CompressionMode.MESSAGE, CompressionFormat.ZSTD)
    with w:
        for i in range(3):
            w.write('/s', String(data=f'hello {i}'), 10 + i)
    want = [(10 + i, f'hello {i}') for i in range(3)]
    assert _texts(src) == _texts(bag._bag_file(src)) == [('/s', 'hello 0'), ('/s', 'hello 1'),
                                                         ('/s', 'hello 2')]
    assert bag.recover_bag(src, tmp_path / 'new')['topics'] == {'/s': 3}
    assert [(t, m.data) for _, m, t in bag.read_messages(tmp_path / 'new')] == want
    import rclpy
    sent = []
    bag.replay(bag._bag_file(src), rclpy.create_node('player', context=ros_env_context),
               all_topics=True, rate=0, qos='best_effort',
               on_publish=lambda topic, raw, t: sent.append(raw[:2]))
    assert sent == [b'\x00\x01'] * 3   # CDR, little endian


def test_a_sqlite3_bag_killed_in_wal_mode_recovers_what_its_wal_holds(tmp_path):
    """A recording in WAL mode killed before a checkpoint: the committed messages are in the
    -wal file. Before: recover (rosbags opens the database as immutable) left them out; now
    they are copied, and the killed bag's files are left as they were."""
    import hashlib
    import shutil
    import sqlite3
    from std_msgs.msg import String
    src = tmp_path / 'src'
    with bag.BagWriter(src, 'sqlite3') as w:
        for i in range(3):
            w.write('/chatter', String(data=f'm{i}'), 10 + i)
    killed = tmp_path / 'killed'
    killed.mkdir()
    conn = sqlite3.connect(src / 'src.db3')
    try:
        conn.execute('PRAGMA journal_mode=WAL')
        conn.execute('PRAGMA wal_autocheckpoint=0')
        conn.execute('INSERT INTO messages (topic_id, timestamp, data) '
                     'SELECT topic_id, timestamp + 100, data FROM messages')
        conn.commit()
        for f in src.glob('src.db3*'):   # as a SIGKILL leaves them: no checkpoint
            shutil.copyfile(f, killed / f.name)
    finally:
        conn.close()
    assert (killed / 'src.db3-wal').stat().st_size > 0

    def digests():
        return {f.name: hashlib.sha256(f.read_bytes()).hexdigest() for f in killed.iterdir()}

    before = digests()
    # read as it is, the bag gave the 3 checkpointed messages without a word
    for read in (lambda: list(bag.read_bag(killed)), lambda: bag.bag_info(killed)):
        with pytest.raises(ValueError, match=r'src\.db3-wal: .*write-ahead log.*beo-bag-recover'):
            read()
    summary = bag.recover_bag(killed, tmp_path / 'new')
    assert summary['messages'] == 6
    assert [t for _, _, t, _ in bag.read_bag(tmp_path / 'new')] == [10, 11, 12, 110, 111, 112]
    assert digests() == before


@pytest.mark.parametrize('storage', bag.STORAGES)
@pytest.mark.parametrize('metadata', ['none', 'stale', 'cut'])
def test_a_split_bag_that_was_not_closed_names_its_files(tmp_path, storage, metadata, capsys,
                                                         keep_signal_handlers):
    """A split recording killed in its second file: no metadata.yaml, one that lists the
    first file only, or one cut off. Before: messages that named no file (or the second file
    silently left out, or 'expected one .db3 or .mcap file, found 2'); now the files are
    named, with what to do."""
    import shutil
    from std_msgs.msg import String
    ext = 'db3' if storage == 'sqlite3' else 'mcap'
    split = tmp_path / 'split'
    for i in range(2):
        with bag.BagWriter(tmp_path / f'part{i}', storage) as w:
            w.write('/chatter', String(data=str(i)), 10 + i)
        split.mkdir(exist_ok=True)
        shutil.copyfile(tmp_path / f'part{i}' / f'part{i}.{ext}', split / f'split_{i}.{ext}')
    if metadata != 'none':
        text = (tmp_path / 'part0' / 'metadata.yaml').read_text().replace('part0.', 'split_0.')
        (split / 'metadata.yaml').write_text(text if metadata == 'stale'
                                             else text[:len(text) // 2] + '\n  - [')
    names = f'split_0.{ext}, split_1.{ext}'
    for read in (lambda: list(bag.read_bag(split)), lambda: bag.bag_info(split)):
        with pytest.raises(ValueError) as e:
            read()
        assert f'the files of the bag: {names}:' in str(e.value), e.value
    assert bag.replay_main([str(split), '--all-topics', '--rate', '0']) == 2
    err = capsys.readouterr().err
    assert err.startswith(f'beo-replay: cannot read {split}: ') and names in err and \
        err.count('\n') == 1, err
    assert bag.recover_main([str(split), '-o', str(tmp_path / 'new')]) == 2
    err = capsys.readouterr().err
    assert err == (f'beo-bag-recover: {split}: expected one .db3 or .mcap file, found 2: '
                   f'{names}: recover each file (beo-bag-recover FILE -o NEW)\n'), err


def test_mcap_channels_not_encoded_as_cdr_are_refused(tmp_path, capsys, keep_signal_handlers):
    """An mcap channel with message_encoding 'json'. Before: its JSON bytes were read,
    played and copied as CDR (recover: 0 messages, the file counted as lost bytes); now
    read_bag, bag_info, beo-replay and beo-bag-recover refuse it, naming the topic."""
    import json
    from rosbags.rosbag2 import StoragePlugin, Writer
    p = tmp_path / 'b'
    w = Writer(p, version=Writer.VERSION_LATEST, storage_plugin=StoragePlugin.MCAP)
    w.open()
    c = w.add_connection('/chatter', 'std_msgs/msg/String', serialization_format='json',
                         typestore=bag.get_typestore(['std_msgs/msg/String']))
    w.write(c, 10, json.dumps({'data': 'hello'}).encode())
    w.close()
    meta = p / 'metadata.yaml'   # as if metadata.yaml had it right: only the file says json
    meta.write_text(meta.read_text().replace('serialization_format: json',
                                             'serialization_format: cdr'))
    file = bag._bag_file(p)
    why = "topic /chatter is encoded as 'json', not cdr: only CDR-encoded messages are supported"
    for target in (p, file):
        for read in (lambda: list(bag.read_bag(target)), lambda: bag.bag_info(target)):
            with pytest.raises(ValueError) as e:
                read()
            assert str(e.value) == f'{target}: {why}'
        assert bag.replay_main([str(target), '--all-topics', '--rate', '0']) == 2
        err = capsys.readouterr().err   # (after warnings of modules imported for the first time)
        assert err.endswith(f'\nbeo-replay: cannot read {target}: {target}: {why}\n') or \
            err == f'beo-replay: cannot read {target}: {target}: {why}\n', err
    assert bag.recover_main([str(file), '-o', str(tmp_path / 'new')]) == 2
    assert capsys.readouterr().err == f'beo-bag-recover: {file}: {why}\n'
    assert not (tmp_path / 'new').exists()


@pytest.mark.parametrize('storage', bag.STORAGES)
@pytest.mark.parametrize('closed', [True, False])
def test_an_mcap_topic_recorded_in_two_types_keeps_both(tmp_path, storage, closed):
    """One topic, two mcap channels of different types (String and Int32 on /x). Before:
    recover_bag failed with '/x: already has type std_msgs/msg/String' and made no bag; now
    the new bag has a connection per type, and every message reads back as its own type."""
    from rosbags.rosbag2 import Reader, StoragePlugin, Writer
    from rclpy.serialization import serialize_message
    from std_msgs.msg import Int32, String
    p = tmp_path / 'b'
    w = Writer(p, version=Writer.VERSION_LATEST, storage_plugin=StoragePlugin.MCAP)
    w.open()
    store = bag.get_typestore(['std_msgs/msg/String', 'std_msgs/msg/Int32'])
    a = w.add_connection('/x', 'std_msgs/msg/String', typestore=store)
    b = w.add_connection('/x', 'std_msgs/msg/Int32', typestore=store)
    for i in range(3):
        w.write(a, 10 + 2 * i, serialize_message(String(data=str(i))))
        w.write(b, 11 + 2 * i, serialize_message(Int32(data=i)))
    w.close()
    src = bag._bag_file(p)
    if not closed:   # as a killed recording leaves it: no footer, no metadata.yaml
        src.write_bytes(src.read_bytes()[:-37])
        (p / 'metadata.yaml').unlink()
    summary = bag.recover_bag(src, tmp_path / 'new', storage=storage)
    assert summary['topics'] == {'/x': 6}
    with Reader(tmp_path / 'new') as r:
        assert sorted((c.topic, c.msgtype, c.msgcount) for c in r.connections) == [
            ('/x', 'std_msgs/msg/Int32', 3), ('/x', 'std_msgs/msg/String', 3)]
    # (bag_info used to say std_msgs/msg/String, count 6)
    assert bag.bag_info(tmp_path / 'new')['topics'] == {
        '/x': {'type': 'std_msgs/msg/String, std_msgs/msg/Int32', 'count': 6}}
    assert [m for _, m, _ in bag.read_messages(tmp_path / 'new')] == [
        m for i in range(3) for m in (String(data=str(i)), Int32(data=i))]


def test_an_mcap_file_without_its_footer_is_refused_naming_beo_bag_recover(
        tmp_path, capsys, keep_signal_handlers):
    """An mcap file a killed recording left (no footer), read as it is or in a bag directory
    whose metadata.yaml lists it. Before: rosbags' 'File end magic is invalid.', from
    read_bag, bag_info and beo-replay ('cannot read ...: File end magic is invalid. (after
    0 message(s))'); now one line naming the file and beo-bag-recover, which reads it."""
    from std_msgs.msg import String
    with bag.BagWriter(tmp_path / 'b', 'mcap') as w:
        w.write('/a', String(data='x'), 10)
    file = bag._bag_file(tmp_path / 'b')
    file.write_bytes(file.read_bytes()[:-37])
    why = (f'{file}: no mcap footer (a recording that was not closed?): make a closed bag of '
           f'it with beo-bag-recover {file} -o NEW')
    for target in (file, tmp_path / 'b'):
        for read in (lambda: list(bag.read_bag(target)), lambda: bag.bag_info(target)):
            with pytest.raises(ValueError) as e:
                read()
            assert str(e.value) == why
        assert bag.replay_main([str(target), '--all-topics', '--rate', '0']) == 2
        assert capsys.readouterr().err.endswith(f'beo-replay: cannot read {target}: {why}\n')
    assert bag.recover_bag(file, tmp_path / 'new')['topics'] == {'/a': 1}


def test_an_mcap_file_of_its_header_only_recovers_nothing_and_one_without_a_header_is_refused(
        tmp_path):
    """Cut right after its header record (all of it there): an empty bag, nothing lost. A
    record other than a header after the magic (here a footer) is no mcap file to recover."""
    data, _ = _three_chunk_bag(tmp_path, close=False)
    second = _records(data)[1][1]   # the header ends where the next record starts
    src = tmp_path / 'head.mcap'
    src.write_bytes(bytes(data[:second]))
    assert bag.recover_bag(src, tmp_path / 'new') == {
        'messages': 0, 'topics': {}, 'storage': 'mcap', 'lost_bytes': 0}
    src.write_bytes(bag.MCAP_MAGIC + b'\x02' + bytes(8))
    with pytest.raises(ValueError, match='cut off before the end of its header record'):
        bag.recover_bag(src, tmp_path / 'new2')
    assert not (tmp_path / 'new2').exists()


def test_a_whole_record_at_the_end_of_a_killed_mcap_file_is_not_lost(tmp_path):
    """A record of no body (9 bytes: opcode and length) that ends the file is whole."""
    data, _ = _three_chunk_bag(tmp_path, close=False)
    data_end = [pos for op, pos in _records(data) if op == 0x0f][0]
    src = tmp_path / 'tail.mcap'   # killed after its data: no data end, no summary
    src.write_bytes(bytes(data[:data_end]) + b'\x0c' + bytes(8))   # an (empty) metadata record
    summary = bag.recover_bag(src, tmp_path / 'new')
    assert summary['messages'] == 12 and summary['lost_bytes'] == 0


def test_a_record_of_an_unknown_opcode_ends_what_is_recovered(tmp_path):
    """The third chunk's opcode flipped from 0x06 to 0x16 (none of mcap's): damage, its bytes
    and all after them are lost, as counted in lost_bytes."""
    data, chunks = _three_chunk_bag(tmp_path, close=False)
    data[chunks[2]] ^= 0x10
    src = tmp_path / 'op.mcap'
    src.write_bytes(bytes(data))
    summary = bag.recover_bag(src, tmp_path / 'new')
    assert summary['messages'] == 8 and summary['lost_bytes'] == len(data) - chunks[2]


@pytest.mark.parametrize('storage', bag.STORAGES)
def test_the_recovered_bag_keeps_each_topics_recorded_qos(tmp_path, storage):
    """Reliable or best effort, latched or not: as the source recorded them."""
    from rosbags.rosbag2 import Reader
    from std_msgs.msg import String
    src = tmp_path / 'qos'
    qos = {'/rel': (True, False), '/be': (False, False), '/latched': (True, True)}
    with bag.BagWriter(src, storage) as w:
        for topic, (reliable, latched) in qos.items():
            w.add_topic(topic, 'std_msgs/msg/String', reliable=reliable, transient_local=latched)
            w.write(topic, String(data=topic), 10)
    bag.recover_bag(src, tmp_path / 'new')
    with Reader(tmp_path / 'new') as r:
        assert {c.topic: (bag.recorded_reliable(c), bag.recorded_latched(c))
                for c in r.connections} == qos


def _add_thing_topic(w):
    """Topic /t of type my_pkg/msg/Thing (int32 a), which is not installed, with its
    definition and hash, on BagWriter ``w``."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore
    store = get_typestore(Stores.EMPTY)
    store.register(get_types_from_msg('int32 a\n', 'my_pkg/msg/Thing'))
    w.add_topic('/t', 'my_pkg/msg/Thing', msgdef='int32 a\n',
                rihs01=store.hash_rihs01('my_pkg/msg/Thing'))


def test_a_damaged_message_of_a_type_beo_ros_does_not_know_ends_what_is_recovered(tmp_path):
    """Its CDR bytes are checked against the bag's own definition (the installed typestore
    has no such type)."""
    src = tmp_path / 'other'
    with bag.BagWriter(src, 'mcap') as w:
        _add_thing_topic(w)
        for batch in range(3):   # a chunk per commit
            for i in range(2):
                w.write('/t', bytes([0, 1, 0, 0, i, 0, 0, 0]), 10 * batch + i)
            w.commit()
    data = bytearray(bag._bag_file(src).read_bytes()[:-37])   # never closed
    chunks = [pos for op, pos in _records(data) if op == 0x06]
    assert len(chunks) == 3
    # the third chunk's first message: its CDR header's second byte (see the test above)
    data[chunks[2] + 9 + 28 + 4 + 8 + 9 + 22 + 1] ^= 0xFF
    (tmp_path / 'cut.mcap').write_bytes(bytes(data))
    summary = bag.recover_bag(tmp_path / 'cut.mcap', tmp_path / 'new')
    assert summary['messages'] == 4
    assert [t for _, _, t, _ in bag.read_bag(tmp_path / 'new')] == [0, 1, 10, 11]


def test_a_definition_the_bag_gives_in_another_format_is_not_read_as_a_msg_file(tmp_path):
    """Only a ros2msg definition in the bag is used: one labelled ros2idl (here .msg text, as
    if an IDL file) of a type that is not installed leaves the type unknown."""
    src = tmp_path / 'other'
    with bag.BagWriter(src, 'mcap') as w:
        _add_thing_topic(w)
        w.write('/t', bytes([0, 1, 0, 0, 7, 0, 0, 0]), 1)
    data = bytearray(bag._bag_file(src).read_bytes()[:-37])   # never closed
    at = data.index(b'ros2msg', data.index(b'my_pkg/msg/Thing'))   # the schema's encoding
    data[at:at + 7] = b'ros2idl'
    (tmp_path / 'cut.mcap').write_bytes(bytes(data))
    with pytest.raises(KeyError, match='no message definition found for my_pkg/msg/Thing'):
        bag.recover_bag(tmp_path / 'cut.mcap', tmp_path / 'new')


def test_a_new_bag_directory_that_another_process_made_meanwhile_is_not_removed(tmp_path,
                                                                              monkeypatch):
    """recover_bag removes the new bag after a failure only if it made its directory: one
    that appeared between the check that it does not exist and the open is someone else's."""
    from std_msgs.msg import String
    src = tmp_path / 'src'
    with bag.BagWriter(src, 'mcap') as w:
        w.write('/s', String(data='x'), 10)
    dst = tmp_path / 'new'
    real_open = bag.BagWriter.open

    def racing_open(self):
        dst.mkdir()
        (dst / 'theirs').write_text('keep')
        return real_open(self)

    monkeypatch.setattr(bag.BagWriter, 'open', racing_open)
    with pytest.raises(bag.BagWriteError, match='exists already'):
        bag.recover_bag(src, dst)
    assert (dst / 'theirs').read_text() == 'keep'
