"""Bag tools (beo_ros.ros.bag): fixes found in review -- acknowledged delivery at --rate 0, write
and read errors as one line, the recorded QoS, remaps onto one topic, SIGTERM, empty topics.

Helpers come from _helpers.py, fixtures from conftest.py.
"""
import json
import os
import subprocess
import sys
import threading
import time
from types import SimpleNamespace

# as in test_bag.py: no discovery outside the process unless the environment asks for it
os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'OFF')

import numpy as np  # noqa: E402
import pytest  # noqa: E402
import rclpy  # noqa: E402

from beo_ros.ros import bag  # noqa: E402

from _helpers import (T0, cli_env, make_cloud, signal_loop_replay, stamp,  # noqa: E402
                      write_scene_pcd, write_test_bag)

CODE = 'import sys; from beo_ros.ros.bag import {0}; sys.exit({0}(sys.argv[1:]))'


# ------------------------------------------------------------------------------------------
# 1. reliable delivery at --rate 0: the keep-last history must not wrap before acknowledgement
# ------------------------------------------------------------------------------------------

class FakePublisher:
    """Stands in for an rclpy publisher: records publishes and acknowledgement waits."""

    def __init__(self, topic, depth, reliable=True, acked=True):
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        self.topic_name = topic
        self.qos_profile = QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE
                                      if reliable else ReliabilityPolicy.BEST_EFFORT)
        self.acked = acked
        self.events = []

    def publish(self, data):
        self.events.append('pub')

    def wait_for_all_acked(self, timeout):
        self.events.append('ack')
        return self.acked

    def get_subscription_count(self):
        return 1


@pytest.mark.parametrize('acked', [True, False])
def test_replay_waits_for_acknowledgements_before_the_history_wraps(tmp_path, monkeypatch,
                                                                   acked):
    """A reliable publisher of depth 3 waits for acknowledgements after every 3rd message and at
    the end; what was not acknowledged in time is counted (the old code never waited: at
    --rate 0 a subscriber in another process got 43-91 of 100 large clouds, reported as 100)."""
    write_test_bag(tmp_path / 'b', 'sqlite3', n=7, extra_topic=False)
    pubs = {}

    def fake(node, msgtype, topic, qos, depth, latched=False):
        return pubs.setdefault(topic, FakePublisher(topic, depth, qos == 'reliable', acked))
    monkeypatch.setattr(bag.player, '_publisher', fake)
    node = SimpleNamespace(get_topic_names_and_types=lambda: [],
                           resolve_topic_name=lambda t: t if t.startswith('/') else '/' + t)
    stats = bag.replay(tmp_path / 'b', node, rate=0, depth=3, ack_timeout=0)
    assert stats.messages == 7
    events = ''.join('P' if e == 'pub' else 'A' for e in pubs['/beo/input'].events)
    assert events == 'PPPAPPPAPA'
    assert stats.unacked == (0 if acked else 7)
    assert ('not acknowledged' in stats.table()) == (not acked)

    pubs.clear()   # best effort: nothing acknowledges, nothing to wait for
    stats = bag.replay(tmp_path / 'b', node, rate=0, depth=3, qos='best_effort')
    assert pubs['/beo/input'].events == ['pub'] * 7 and stats.unacked == 0


SUBSCRIBER = r'''
import sys, time, rclpy
from rclpy.qos import QoSProfile
from sensor_msgs.msg import PointCloud2
rclpy.init(args=[])
node = rclpy.create_node('beo_test_sub')
got = []
node.create_subscription(PointCloud2, '/beo/input', lambda m: got.append(1),
                         QoSProfile(depth=100))   # reliable, keep-last 100, volatile
want = int(sys.argv[1])
last = time.monotonic()
while len(got) < want and time.monotonic() - last < 5.0:   # 5 s without a message: done
    n = len(got)
    rclpy.spin_once(node, timeout_sec=0.1)
    if len(got) > n:
        last = time.monotonic()
print(len(got), flush=True)
'''


def test_cli_replay_rate_0_delivers_every_cloud_to_a_reliable_subscriber_of_another_process(
        tmp_path, ros_domain_id):
    n = 100
    pts = np.random.default_rng(0).normal(size=(20_000, 3)).astype(np.float32)
    from std_msgs.msg import Header
    from beo_ros.ros.conversions import xyz_to_cloud
    with bag.BagWriter(tmp_path / 'b', 'mcap') as w:
        for i in range(n):
            ns = T0 + i * 10_000_000
            w.write('/beo/input', xyz_to_cloud(pts, Header(stamp=stamp(ns), frame_id='c')), ns)
    env = cli_env(ros_domain_id)
    sub = subprocess.Popen([sys.executable, '-c', SUBSCRIBER, str(n)], env=env,
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        rep = subprocess.run([sys.executable, '-c', CODE.format('replay_main'),
                              str(tmp_path / 'b'), '--rate', '0', '--wait-subscribers', '1',
                              '--wait-timeout', '30', '--json'],
                             env=env, capture_output=True, text=True, timeout=120)
        assert rep.returncode == 0, rep.stderr
        assert json.loads(rep.stdout)['unacked'] == 0
        out, err = sub.communicate(timeout=60)
    finally:
        if sub.poll() is None:
            sub.kill()
    assert int(out.strip()) == n, err


# ------------------------------------------------------------------------------------------
# 2. beo-record: write errors (disk full) and SIGKILL
# ------------------------------------------------------------------------------------------

# beo-record in a subprocess, fed by a publisher of 100 kB strings on /big (its own context in
# a thread), every sqlite3 batch committed (COMMIT_PERIOD_S = 0); argv[1]: file size limit
# (bytes, 0: none), argv[2]: messages to publish, argv[3:]: beo-record's arguments
RECORDER = r'''
import resource, sys, threading, time
limit, n = int(sys.argv[1]), int(sys.argv[2])
if limit:   # a full disk, as far as the writes of this process go (EFBIG; SIGXFSZ is ignored)
    resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
import rclpy
from std_msgs.msg import String
from beo_ros.ros import bag
bag.recorder.COMMIT_PERIOD_S = 0.0

def publish():
    ctx = rclpy.Context()
    rclpy.init(args=[], context=ctx)
    node = rclpy.create_node('beo_test_big', context=ctx)
    pub = node.create_publisher(String, '/big', 1000)
    while pub.get_subscription_count() == 0:
        time.sleep(0.05)
    for i in range(n):
        pub.publish(String(data='x' * 100_000))
        time.sleep(0.05)
    print('published', flush=True)
    time.sleep(3600)
threading.Thread(target=publish, daemon=True).start()
sys.exit(bag.record_main(sys.argv[3:]))
'''


@pytest.mark.parametrize('storage', bag.STORAGES)
def test_cli_record_on_a_full_disk_is_one_line_exit_2_and_leaves_no_lying_metadata(
        tmp_path, ros_domain_id, storage):
    """Before: sqlite3.OperationalError traceback, exit 1, and a metadata.yaml counting messages
    the database had rolled back; mcap: an unreadable file (later: removed; now what was
    committed is kept, and beo-bag-recover reads it back)."""
    out = tmp_path / 'rec'
    p = subprocess.run([sys.executable, '-c', RECORDER, str(1_000_000), '100',
                        '/big:std_msgs/msg/String', '-o', str(out), '--storage', storage,
                        '--duration', '60'],
                       env=cli_env(ros_domain_id), capture_output=True, text=True, timeout=120)
    assert p.returncode == 2, p.stderr
    lines = [ln for ln in p.stderr.splitlines() if ln.startswith('beo-record')]
    assert len(lines) == 1 and 'Traceback' not in p.stderr, p.stderr
    assert f'cannot write {out}' in lines[0], lines[0]
    assert not (out / 'metadata.yaml').exists()
    # what is said to be kept is what reads back
    import re
    kept = int(re.search(r'keeps the (\d+) message', lines[0]).group(1))
    assert 1 <= kept < 10 and 'beo-bag-recover' in lines[0]
    if storage == 'sqlite3':
        assert len(list(bag.read_bag(out / 'rec.db3'))) == kept
    summary = bag.recover_bag(out, tmp_path / 'recovered')
    assert summary['messages'] == kept and summary['topics'] == {'/big': kept}


def _committed(db):
    """Messages committed to the sqlite3 file ``db`` so far (read-only; 0 before it exists)."""
    import sqlite3
    try:
        with sqlite3.connect(f'file:{db}?mode=ro', uri=True) as c:
            return c.execute('SELECT COUNT(*) FROM messages').fetchone()[0]
    except sqlite3.Error:
        return 0


def test_sigkilled_sqlite3_recording_keeps_what_was_committed(tmp_path, ros_domain_id):
    import signal
    out = tmp_path / 'rec'
    p = subprocess.Popen([sys.executable, '-c', RECORDER, '0', '5', '/big:std_msgs/msg/String',
                          '-o', str(out), '--duration', '600'],
                         env=cli_env(ros_domain_id), stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    db = out / 'rec.db3'

    def committed():
        return _committed(db)
    try:
        end = time.monotonic() + 60
        while committed() < 5 and time.monotonic() < end and p.poll() is None:
            time.sleep(0.05)
        assert committed() == 5
        p.send_signal(signal.SIGKILL)
        p.communicate(timeout=30)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == -signal.SIGKILL
    assert not (out / 'metadata.yaml').exists()
    got = list(bag.read_bag(db))   # the .db3 file reads on its own
    assert len(got) == 5 and all(t == '/big' and m == 'std_msgs/msg/String' for t, m, _, _ in got)


def test_a_burst_followed_by_quiet_is_committed(tmp_path, ros_env_context):
    """Before: the writes were committed only when a later message came, so a burst and then
    silence stayed uncommitted (1 of 7 messages in the .db3 after kill -9)."""
    from std_msgs.msg import String
    pub_node = rclpy.create_node('talker', context=ros_env_context)
    rec_node = rclpy.create_node('recorder', context=ros_env_context)
    pub = pub_node.create_publisher(String, '/chatter', 100)
    ready, stop, result = threading.Event(), threading.Event(), {}
    out = tmp_path / 'rec'
    th = threading.Thread(target=lambda: result.setdefault('s', bag.record(
        rec_node, out, ['/chatter:std_msgs/msg/String'], stop=stop, ready=ready,
        commit_every=1.0)))
    th.start()

    def committed():
        return _committed(out / 'rec.db3')
    try:
        assert ready.wait(10)
        end = time.monotonic() + 10
        while pub.get_subscription_count() == 0 and time.monotonic() < end:
            time.sleep(0.02)
        pub.publish(String(data='first'))
        end = time.monotonic() + 10
        while committed() < 1 and time.monotonic() < end:
            time.sleep(0.02)
        assert committed() == 1
        for i in range(4):   # within a second of that commit, then nothing more
            pub.publish(String(data=f'burst {i}'))
        end = time.monotonic() + 10
        while committed() < 5 and time.monotonic() < end:
            time.sleep(0.05)
        assert committed() == 5
    finally:
        stop.set()
        th.join(10)
    assert result['s'].messages == 5


def test_a_write_error_leaves_no_subscription_behind(tmp_path, ros_env_context, monkeypatch):
    """Before: a disk full while recording, with a topic that never had a publisher, failed
    again while listing that topic in the bag, so the recorder's subscriptions and executor
    were never destroyed (BagWriteError all the same)."""
    from std_msgs.msg import String
    pub_node = rclpy.create_node('talker', context=ros_env_context)
    rec_node = rclpy.create_node('recorder', context=ros_env_context)
    pub = pub_node.create_publisher(String, '/chatter', 100)
    real_write, real_add = bag.BagWriter.write, bag.BagWriter.add_topic

    def full(self, *args, **kwargs):
        self.failed = True
        raise OSError(28, 'No space left on device')

    def add_topic(self, *args, **kwargs):   # a full disk takes no more writes at all
        if self.failed:
            full(self)
        return real_add(self, *args, **kwargs)
    monkeypatch.setattr(bag.BagWriter, 'write', full)
    monkeypatch.setattr(bag.BagWriter, 'add_topic', add_topic)
    errors = []

    def run():
        try:
            bag.record(rec_node, tmp_path / 'rec', ['/chatter:std_msgs/msg/String',
                                                    '/never:std_msgs/msg/String'], wait=0)
        except bag.BagWriteError as e:
            errors.append(e)
    th = threading.Thread(target=run)
    th.start()
    end = time.monotonic() + 10
    while th.is_alive() and time.monotonic() < end:
        if pub.get_subscription_count():
            pub.publish(String(data='x'))
        time.sleep(0.05)
    th.join(10)
    monkeypatch.setattr(bag.BagWriter, 'write', real_write)
    assert not th.is_alive() and len(errors) == 1 and 'No space left' in str(errors[0])
    assert not list(rec_node.subscriptions)


# ------------------------------------------------------------------------------------------
# 3. beo-replay of a corrupt sqlite3 bag
# ------------------------------------------------------------------------------------------

def test_cli_replay_of_a_bag_corrupt_part_way_is_one_line_exit_2_with_what_was_played(
        tmp_path, capsys, keep_signal_handlers):
    """Before: apsw.CorruptError traceback, exit 1."""
    p = tmp_path / 'b'
    with bag.BagWriter(p, 'sqlite3') as w:   # 200 clouds of 12 kB
        for i in range(200):
            w.write('/beo/input', make_cloud(i, n=1000, ns=T0 + i)[1], T0 + i)
    db = p / 'b.db3'
    size = db.stat().st_size
    with open(db, 'r+b') as f:   # a page in the middle of the messages
        f.seek(size // 2)
        f.write(b'\xff' * 8192)
    assert bag.replay_main([str(p), '--rate', '0', '--json']) == 2
    out, err = capsys.readouterr()
    assert 'Traceback' not in err
    (line,) = err.splitlines()
    assert line.startswith(f'beo-replay: cannot read {p}: database disk image is malformed')
    played = json.loads(out)['messages']
    assert 0 < played < 200 and f'(after {played} message(s))' in line


# ------------------------------------------------------------------------------------------
# 4. the offered QoS stored by record is that of the publisher matched
# ------------------------------------------------------------------------------------------

def test_record_stores_the_qos_of_a_publisher_that_appears_after_it_started(
        ros_env_context, tmp_path):
    """A typed topic recorded before its publisher exists: the bag used to store the QoS seen
    at the start (volatile, best effort), so a latched topic was replayed volatile."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from rosbags.rosbag2 import Reader
    from std_msgs.msg import String
    rec_node = rclpy.create_node('recorder', context=ros_env_context)
    ready, result = threading.Event(), {}
    th = threading.Thread(target=lambda: result.setdefault('s', bag.record(
        rec_node, tmp_path / 'r', ['/latched:std_msgs/msg/String',
                                   '/never:std_msgs/msg/String'],
        count=1, ready=ready)))
    th.start()
    assert ready.wait(10)
    pub_node = rclpy.create_node('talker', context=ros_env_context)
    pub = pub_node.create_publisher(String, '/latched', QoSProfile(
        depth=1, reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL))
    pub.publish(String(data='static'))   # a latched message reaches a late subscriber
    th.join(30)
    assert not th.is_alive()
    assert result['s'].topics['/latched']['count'] == 1
    with Reader(tmp_path / 'r') as r:
        conns = {c.topic: c for c in r.connections}
        assert bag.recorded_latched(conns['/latched'])
        assert set(conns) == {'/latched', '/never'} and not bag.recorded_latched(conns['/never'])
    player = rclpy.create_node('player', context=ros_env_context)
    stats = bag.replay(tmp_path / 'r', player, all_topics=True, rate=0)
    assert stats.latched == ['/latched'] and stats.topics['/latched'].count == 1


def test_record_stops_at_count_within_a_batch(ros_env_context, tmp_path):
    """A burst longer than ``count`` arrives in one spin: only its first ``count`` messages are
    written, the topics recorded only listed."""
    from std_msgs.msg import String
    pub_node = rclpy.create_node('talker', context=ros_env_context)
    rec_node = rclpy.create_node('recorder', context=ros_env_context)
    pub = pub_node.create_publisher(String, '/chatter', 100)
    ready, result = threading.Event(), {}
    th = threading.Thread(target=lambda: result.setdefault('s', bag.record(
        rec_node, tmp_path / 'r', ['/chatter', '/never:std_msgs/msg/String'], storage='mcap',
        count=5, ready=ready)))
    th.start()
    assert ready.wait(10)
    end = time.monotonic() + 10
    while pub.get_subscription_count() == 0 and time.monotonic() < end:
        time.sleep(0.02)
    for i in range(8):
        pub.publish(String(data=f'm{i}'))
    th.join(30)
    assert not th.is_alive()
    s = result['s']
    assert (s.stopped_by, s.messages) == ('count', 5)
    assert s.topics == {'/chatter': {'type': 'std_msgs/msg/String', 'count': 5},
                        '/never': {'type': 'std_msgs/msg/String', 'count': 0}}
    assert bag.bag_info(tmp_path / 'r')['topics'] == s.topics
    assert [m.data for _, m, _ in bag.read_messages(tmp_path / 'r')] == [
        f'm{i}' for i in range(5)]


# ------------------------------------------------------------------------------------------
# 8. bag_span_s counts only the messages sent
# ------------------------------------------------------------------------------------------

def test_interrupted_replay_span_leaves_out_the_message_never_sent(ros_env_context, tmp_path):
    """Before, the stamp of the message being waited for counted: 10 s here."""
    write_test_bag(tmp_path / 'b', 'sqlite3', n=2, period_ns=10_000_000_000, extra_topic=False)
    stop = threading.Event()
    node = rclpy.create_node('player', context=ros_env_context)
    stats = bag.replay(tmp_path / 'b', node, rate=1.0, stop=stop,
                       on_publish=lambda *a: stop.set())
    assert stats.interrupted and stats.messages == 1 and stats.bag_span_s == 0.0
    stats = bag.replay(tmp_path / 'b', node, rate=0)
    assert stats.messages == 2 and stats.bag_span_s == pytest.approx(10.0)


# ------------------------------------------------------------------------------------------
# 5. remaps that would put two types on one topic; 10. --topics with --all-topics
# ------------------------------------------------------------------------------------------

@pytest.mark.parametrize('extra', [
    ['--all-topics', '-r', '/beo/input:=/x', '-r', '/chatter:=/x'],
    ['--all-topics', '-r', '/beo/input:=/chatter'],
    ['--all-topics', '-r', '/beo/input:=chatter'],
])
def test_cli_replay_refuses_two_types_on_one_topic(tmp_path, capsys, keep_signal_handlers,
                                                   extra):
    """Before: an RCLError traceback from create_publisher, exit 1 (still so for a relative
    remap target, 'chatter' for /chatter, until it was expanded as the publisher does)."""
    write_test_bag(tmp_path / 'b', 'sqlite3', n=2)
    assert bag.replay_main([str(tmp_path / 'b'), '--rate', '0', *extra]) == 2
    out, err = capsys.readouterr()
    assert 'would both be played on' in err and 'Traceback' not in err and out == '', err
    assert len(err.splitlines()) == 1


def test_replay_refuses_a_topic_of_another_type_in_the_graph(ros_env_context, tmp_path):
    from std_msgs.msg import String
    write_test_bag(tmp_path / 'b', 'sqlite3', n=2, extra_topic=False)
    other = rclpy.create_node('other', context=ros_env_context)
    other.create_publisher(String, '/taken', 10)
    player = rclpy.create_node('player', context=ros_env_context)
    with pytest.raises(KeyError, match='/taken has type std_msgs/msg/String in the ROS graph'):
        bag.replay(tmp_path / 'b', player, remap={'/beo/input': '/taken'}, rate=0)


def test_cli_replay_refuses_topics_with_all_topics(tmp_path, capsys):
    write_test_bag(tmp_path / 'b', 'sqlite3', n=1)
    with pytest.raises(SystemExit) as ei:   # --all-topics used to be ignored
        bag.replay_main([str(tmp_path / 'b'), '--topics', '/chatter', '--all-topics'])
    assert ei.value.code == 2
    assert '--topics and --all-topics exclude each other' in capsys.readouterr().err


def test_cli_replay_refuses_wait_timeout_without_wait_subscribers(tmp_path, capsys):
    write_test_bag(tmp_path / 'b', 'sqlite3', n=1)
    with pytest.raises(SystemExit) as ei:   # it used to be ignored: nothing was waited for
        bag.replay_main([str(tmp_path / 'b'), '--wait-timeout', '30'])
    assert ei.value.code == 2
    assert '--wait-timeout is for --wait-subscribers N' in capsys.readouterr().err


def test_cli_replay_wait_timeout_says_what_to_check(tmp_path, capsys, monkeypatch,
                                                    ros_domain_id):
    """--wait-subscribers with nobody subscribing: the line used to stop at the counts
    (matched: {'/beo/input': 0}); it now names the usual causes, with this process's domain
    and discovery range."""
    write_test_bag(tmp_path / 'b', 'sqlite3', n=1)
    monkeypatch.setenv('ROS_DOMAIN_ID', str(ros_domain_id))
    monkeypatch.setenv('ROS_AUTOMATIC_DISCOVERY_RANGE', 'OFF')
    code = bag.replay_main([str(tmp_path / 'b'), '--wait-subscribers', '1',
                            '--wait-timeout', '0.2'])
    assert code == 3
    err = capsys.readouterr().err
    assert err.startswith('beo-replay: waited 0.2 s for 1 subscriber(s); matched: ') and \
        err.count('\n') == 1, err
    assert (f'start the subscriber first, e.g. beo-node; it must run with the same '
            f'ROS_DOMAIN_ID, here {ros_domain_id}, and ROS_AUTOMATIC_DISCOVERY_RANGE, here OFF'
            in err), err


# ------------------------------------------------------------------------------------------
# 7. SIGTERM ends beo-replay with 143
# ------------------------------------------------------------------------------------------

def test_cli_loop_replay_ended_by_sigterm_exits_143(tmp_path, ros_domain_id):
    """Before, SIGTERM was taken as Ctrl-C: a --loop replay exited 0."""
    import signal
    rc, _, err = signal_loop_replay(tmp_path, ros_domain_id, signal.SIGTERM)
    assert rc == 143, err
    assert 'beo-replay: terminated' in err and 'Traceback' not in err, err


# ------------------------------------------------------------------------------------------
# 6. beo-demo: discovery off whatever the user's setting
# ------------------------------------------------------------------------------------------

def test_demo_forces_discovery_off(monkeypatch):
    """Before, setdefault let a user's LOCALHOST win: the demo's node and listener talked to
    other processes. The caller's setting is put back afterwards."""
    from beo_ros.ros import demo, node
    monkeypatch.setenv('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    seen = {}

    def fake_node(*a, **k):   # the node starts in the demo's rclpy context
        seen['range'] = os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE']
        raise RuntimeError('stop here')
    monkeypatch.setattr(node, 'BeoNode', fake_node)
    with pytest.raises(RuntimeError, match='stop here'):
        demo.run_node_on_bag('bag', 'model', None, (0.0, 0.0, 1.0), (0.0, 0.0, 0.0))
    assert seen['range'] == 'OFF'
    assert os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] == 'LOCALHOST'


# ------------------------------------------------------------------------------------------
# 9. a pcd2bag run without clouds; replays with nothing to play say why
# ------------------------------------------------------------------------------------------

def test_cli_pcd2bag_without_any_cloud_exits_2_and_writes_no_bag(tmp_path, capsys):
    """Before: a bag with 0 clouds, exit 0, '1 object(s) ( points)'."""
    scene = write_scene_pcd(tmp_path / 's.pcd')
    out = tmp_path / 'b'
    assert bag.pcd2bag_main([str(scene), '-o', str(out), '--min-points', '100000']) == 2
    err = capsys.readouterr().err
    assert 'no object with at least 100000 points' in err and 'Traceback' not in err
    assert not out.exists()


def test_cli_pcd2bag_onto_a_full_disk_is_one_line_exit_2_and_no_bag(tmp_path):
    """Before: a traceback of sqlite3.OperationalError 'disk I/O error', exit 1 (an mcap bag
    gave OSError, which was caught)."""
    scene = write_scene_pcd(tmp_path / 's.pcd')
    out = tmp_path / 'b'
    code = ('import resource, signal, sys; signal.signal(signal.SIGXFSZ, signal.SIG_IGN); '
            'resource.setrlimit(resource.RLIMIT_FSIZE, (6000, 6000)); '
            'from beo_ros.ros import bag; sys.exit(bag.pcd2bag_main(sys.argv[1:]))')
    p = subprocess.run([sys.executable, '-c', code, str(scene), '-o', str(out)],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 2, p.stderr
    assert p.stderr.startswith(f'beo-pcd2bag: cannot write {out}: ') and \
        p.stderr.count('\n') == 1, p.stderr
    assert not out.exists()


def test_cli_replay_says_why_there_is_nothing_to_play(tmp_path, capsys, keep_signal_handlers):
    from std_msgs.msg import String
    with bag.BagWriter(tmp_path / 'empty', 'sqlite3') as w:   # a cloud topic with 0 messages
        w.add_topic('/beo/input', bag.CLOUD_TYPE)
    with bag.BagWriter(tmp_path / 'strings', 'sqlite3') as w:
        w.write('/chatter', String(data='x'), T0)
    assert bag.replay_main([str(tmp_path / 'empty'), '--rate', '0']) == 1
    assert 'nothing to play: no messages on /beo/input' in capsys.readouterr().err
    assert bag.replay_main([str(tmp_path / 'strings'), '--rate', '0']) == 1
    assert ('no sensor_msgs/msg/PointCloud2 topic (it has /chatter: --all-topics plays them)'
            in capsys.readouterr().err)


def _bag_with_a_service_event_topic(path, storage):
    """/s (3 String) and a service event topic (3 lifecycle_msgs/srv/GetState_Event), as
    ros2 bag record --all-services writes them."""
    from lifecycle_msgs.srv import GetState_Event
    from rclpy.serialization import serialize_message
    from rosbags.rosbag2 import StoragePlugin, Writer
    from std_msgs.msg import String
    w = Writer(path, version=Writer.VERSION_LATEST, storage_plugin=StoragePlugin.SQLITE3
               if storage == 'sqlite3' else StoragePlugin.MCAP)
    w.open()
    cs = w.add_connection('/s', 'std_msgs/msg/String', typestore=bag.get_typestore())
    ce = w.add_connection('/node/get_state/_service_event', 'lifecycle_msgs/srv/GetState_Event',
                          msgdef='uint8 structure_needs_at_least_one_member\n',
                          rihs01='RIHS01_' + '0' * 64)
    for i in range(3):
        w.write(cs, 10 + i, serialize_message(String(data=str(i))))
        w.write(ce, 20 + i, serialize_message(GetState_Event()))
    w.close()


@pytest.mark.parametrize('storage', bag.STORAGES)
def test_a_bag_with_a_service_event_topic_plays_and_recovers(ros_env_context, tmp_path,
                                                              storage):
    """Jazzy's ros2 bag records service events (--all-services) as topics of type
    pkg/srv/Type_Event. Before: beo-replay --all-topics refused the whole bag ('not a message
    type name') and recover_bag of the .db3 too; now they are played and copied."""
    _bag_with_a_service_event_topic(tmp_path / 'b', storage)
    node = rclpy.create_node('player', context=ros_env_context)
    stats = bag.replay(tmp_path / 'b', node, all_topics=True, rate=0, qos='best_effort')
    assert {t: s.count for t, s in stats.topics.items()} == {
        '/s': 3, '/node/get_state/_service_event': 3}
    if storage == 'sqlite3':   # (an mcap file's srv type name defeats rosbags' own parser)
        summary = bag.recover_bag(tmp_path / 'b', tmp_path / 'new')
        assert summary['topics'] == {'/s': 3, '/node/get_state/_service_event': 3}
    from lifecycle_msgs.srv import GetState_Event
    assert bag.msgtype_of(GetState_Event) == 'lifecycle_msgs/srv/GetState_Event'


@pytest.mark.parametrize('storage', bag.STORAGES)
def test_record_stores_a_service_event_topic_and_reads_it_back(ros_env_context, tmp_path,
                                                               ros_interfaces, storage):
    """The events of a service with introspection on (/<service>/_service_event, type
    beo_interfaces/srv/Classify_Event). Before: record refused them ('no message definition
    found for beo_interfaces/srv/Classify_Event': it looked for a .msg file, and rosbags'
    parser files srv types under pkg/srv/msg/); now their definition comes from Classify.srv,
    with rosidl's hash, and the bag reads back and recovers from its file alone."""
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import qos_profile_system_default
    from rclpy.service_introspection import ServiceIntrospectionState
    from rosbags.rosbag2 import Reader
    from beo_interfaces.srv import Classify
    server = rclpy.create_node('server', context=ros_env_context)
    srv = server.create_service(Classify, '/classify_x',
                                lambda req, resp: Classify.Response(success=req.has_up))
    srv.configure_introspection(server.get_clock(), qos_profile_system_default,
                                ServiceIntrospectionState.CONTENTS)
    client = server.create_client(Classify, '/classify_x')
    topic = '/classify_x/_service_event'
    rec_node = rclpy.create_node('recorder', context=ros_env_context)
    ready, result = threading.Event(), {}
    th = threading.Thread(target=lambda: result.setdefault('s', bag.record(
        rec_node, tmp_path / 'r', [f'{topic}:beo_interfaces/srv/Classify_Event'],
        storage=storage, count=2, ready=ready)))
    th.start()
    assert ready.wait(10)
    ex = SingleThreadedExecutor(context=ros_env_context)
    ex.add_node(server)
    future = client.call_async(Classify.Request(has_up=True))
    ex.spin_until_future_complete(future, timeout_sec=10)
    end = time.monotonic() + 20
    while th.is_alive() and time.monotonic() < end:
        ex.spin_once(timeout_sec=0.05)
    th.join(10)
    ex.shutdown()
    assert not th.is_alive() and future.result().success
    assert result['s'].topics == {topic: {'type': 'beo_interfaces/srv/Classify_Event',
                                          'count': 2}}
    events = [m for _, m, _ in bag.read_messages(tmp_path / 'r')]
    assert [(e.info.event_type, len(e.request), len(e.response)) for e in events] == [
        (1, 1, 0), (2, 0, 1)]   # REQUEST_RECEIVED, RESPONSE_SENT
    assert events[0].request[0].has_up and events[1].response[0].success
    with Reader(tmp_path / 'r') as r:
        digest = r.connections[0].digest
    from beo_ros.ros.bag.msgtypes import _find_msg_file
    hashes = json.loads(_find_msg_file('beo_interfaces/srv/Classify').with_suffix('.json')
                        .read_text())['type_hashes']
    assert {'type_name': 'beo_interfaces/srv/Classify_Event', 'hash_string': digest} in hashes
    # the bag's own definition, read without metadata.yaml (an mcap file has no hash: it is
    # computed from the definition)
    (tmp_path / 'r' / 'metadata.yaml').unlink()
    from beo_ros.ros.bag.recover import _own_definition
    with Reader(next((tmp_path / 'r').iterdir())) as r:
        assert _own_definition(r.connections[0])['rihs01'] == digest
    summary = bag.recover_bag(tmp_path / 'r', tmp_path / 'new')
    assert summary['topics'] == {topic: 2}
    assert [m.info.event_type for _, m, _ in bag.read_messages(tmp_path / 'new')] == [1, 2]


@pytest.mark.parametrize('topic', ['/beo/up', 'beo/table_plane', '~/up'])
def test_cli_pcd2bag_refuses_the_up_or_plane_topic_as_cloud_topic_before_reading(
        tmp_path, capsys, topic):
    """Before: every scene was read, then 'beo-pcd2bag: /beo/up: already has type
    sensor_msgs/msg/PointCloud2' (exit 2, no usage line), naming neither --topic nor the clash."""
    out = tmp_path / 'b'
    with pytest.raises(SystemExit) as e:
        bag.pcd2bag_main([str(write_scene_pcd(tmp_path / 's.pcd')), '-o', str(out),
                          '--topic', topic])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith('usage: beo-pcd2bag') and 'Traceback' not in err
    assert f"error: the object cloud topic {topic!r} is the " in err and 'give another' in err
    assert not out.exists()
    with pytest.raises(ValueError, match='give another'):   # before a scene is read
        bag.pcd_to_bag([tmp_path / 'missing.pcd'], out, topic=topic)


def test_cli_pcd2bag_calls_a_directory_a_directory(tmp_path, capsys):
    """Before: 'beo-pcd2bag: error: no such file: DIR' for a scene path that is a directory
    (it exists; e.g. the folder of the scenes given instead of its files)."""
    with pytest.raises(SystemExit) as e:
        bag.pcd2bag_main([str(tmp_path), '-o', str(tmp_path / 'b')])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert f'error: a directory, not a PCD file: {tmp_path}' in err and 'no such' not in err
    with pytest.raises(SystemExit):
        bag.pcd2bag_main([str(tmp_path / 'x.pcd'), '-o', str(tmp_path / 'b')])
    assert f'error: no such file: {tmp_path / "x.pcd"}' in capsys.readouterr().err


def test_a_relative_bag_topic_is_type_checked_by_its_full_name(ros_env_context, tmp_path):
    """A bag topic 'relchat' (no leading '/') is published on /relchat. Before: the checks of
    one type per topic looked up 'relchat', found nothing, and create_publisher failed with
    an RCLError; now they use /relchat, as the graph and the other bag topics name it."""
    from std_msgs.msg import Int32, String
    p = tmp_path / 'b'
    with bag.BagWriter(p, 'sqlite3') as w:
        w.write('relchat', String(data='x'), 10)
    other = rclpy.create_node('other', context=ros_env_context)
    other.create_publisher(Int32, '/relchat', 10)
    player = rclpy.create_node('player', context=ros_env_context)
    with pytest.raises(KeyError, match='/relchat has type std_msgs/msg/Int32 in the ROS graph; '
                                       'cannot play relchat'):
        bag.replay(p, player, all_topics=True, rate=0)
    q = tmp_path / 'q'
    with bag.BagWriter(q, 'sqlite3') as w:
        w.write('/both', Int32(data=1), 10)
        w.write('both', String(data='x'), 11)
    with pytest.raises(KeyError, match='would both be played on /both'):
        bag.replay(q, player, all_topics=True, rate=0)
    # one topic recorded in two types (as recover keeps two mcap channels): before, the advice
    # was to remap one of them, which cannot part two types of one topic
    t = tmp_path / 't'
    with bag.BagWriter(t, 'mcap') as w:
        w.add_topic('/two', 'std_msgs/msg/Int32')
        w.add_topic('/two', 'std_msgs/msg/String', another_type=True)
        w.write('/two', Int32(data=1), 10)
        w.write('/two', String(data='x'), 11)
        w.write('/one', Int32(data=2), 12)
    with pytest.raises(KeyError, match=r'/two was recorded in two types \(std_msgs/msg/Int32, '
                                       r'std_msgs/msg/String\) and one topic plays in one type'):
        bag.replay(t, player, all_topics=True, rate=0)
    assert bag.replay(t, player, topics='/one', rate=0).messages == 1


def _fake_replay_node():
    return SimpleNamespace(get_topic_names_and_types=lambda: [],
                           resolve_topic_name=lambda t: t if t.startswith('/') else '/' + t)


def test_replay_times_messages_by_stamp_over_rate(tmp_path, monkeypatch):
    """rate 4: a message 10 ms after the first (bag time) is due 2.5 ms after the pass began."""
    write_test_bag(tmp_path / 'b', 'sqlite3', n=3, extra_topic=False)   # stamps 10 ms apart
    monkeypatch.setattr(bag.player, '_publisher',
                        lambda node, msgtype, topic, qos, depth, latched=False:
                        FakePublisher(topic, depth))
    deadlines = []

    def no_sleep(deadline, stop, tick=None, period=0.05):
        deadlines.append(deadline)
        return True
    monkeypatch.setattr(bag.player, '_sleep_until', no_sleep)
    bag.replay(tmp_path / 'b', _fake_replay_node(), rate=4.0)
    assert np.allclose(np.subtract(deadlines, deadlines[0]), [0, 0.0025, 0.005])


def test_wait_for_subscribers_counts_each_topics_subscribers_and_waits_for_clock(monkeypatch):
    """wait_subscribers=2 with one subscriber times out; with the data topics matched and no
    /clock subscriber, the wait lasts CLOCK_GRACE_S more (a use_sim_time node may be starting)."""
    stats = bag.ReplayStats(bag='b', storage='sqlite3', rate=1.0)
    pubs = {'/a': FakePublisher('/a', 10)}   # one subscriber
    with pytest.raises(TimeoutError, match='for 2 subscriber'):
        bag.player._wait_for_subscribers(pubs, None, 2, 0.05, None, stats)
    monkeypatch.setattr(bag.player, 'CLOCK_GRACE_S', 0.2)
    clock = SimpleNamespace(get_subscription_count=lambda: 0)
    assert bag.player._wait_for_subscribers(pubs, clock, 1, 5.0, None, stats)
    assert stats.waited_s >= 0.2


def test_make_qos_of_a_latched_topic_is_reliable_even_when_best_effort_is_asked():
    from rclpy.qos import DurabilityPolicy, ReliabilityPolicy
    q = bag.player.make_qos('best_effort', 5, latched=True)
    assert (q.reliability, q.durability, q.depth) == (
        ReliabilityPolicy.RELIABLE, DurabilityPolicy.TRANSIENT_LOCAL, 5)
    assert bag.player.make_qos('best_effort').reliability == ReliabilityPolicy.BEST_EFFORT


@pytest.mark.parametrize('rate', [float('inf'), -1.0, float('nan')])
def test_replay_refuses_a_rate_that_is_not_a_finite_number_at_least_0(tmp_path, rate):
    with pytest.raises(ValueError, match='rate must be a finite number >= 0'):
        bag.replay(tmp_path / 'b', _fake_replay_node(), rate=rate)


def test_a_bag_whose_last_stamp_is_the_last_clock_time_plays_with_the_clock(tmp_path,
                                                                            monkeypatch):
    """/clock holds MAX_NS itself: only a stamp past it is refused."""
    from std_msgs.msg import String
    from beo_ros.ros.bag.scenes import MAX_NS
    with bag.BagWriter(tmp_path / 'b', 'sqlite3') as w:
        w.write('/chatter', String(data='x'), MAX_NS)
    monkeypatch.setattr(bag.player, '_publisher',
                        lambda node, msgtype, topic, qos, depth, latched=False:
                        FakePublisher(topic, depth))
    stats = bag.replay(tmp_path / 'b', _fake_replay_node(), all_topics=True, rate=0,
                       clock_hz=10.0)
    assert stats.messages == 1 and stats.clock_messages == 1
    with bag.BagWriter(tmp_path / 'c', 'sqlite3') as w:
        w.write('/chatter', String(data='x'), MAX_NS + 1)
    with pytest.raises(bag.player.ClockRangeError):
        bag.replay(tmp_path / 'c', _fake_replay_node(), all_topics=True, rate=0, clock_hz=10.0)


@pytest.mark.parametrize('name, why', [
    # rcl's reason alone: not its 'topic name ... is invalid: ' or 'Invalid topic name: '
    # prefix, its ', at FILE.c:LINE' suffix, or the caret lines below
    ('{foo}', 'unknown substitution: {foo}'),
    ('/a//b', "topic name must not contain repeated '/'"),
    ('/~', "topic name must not have tilde '~' unless it is the first character"),
    # expands ('{ns}' is '/'), and only the expanded name is invalid
    ('a/{ns}', "topic name must not end with a '/'")])
def test_check_topic_name_gives_rcls_reason_on_one_line(name, why):
    from beo_ros.ros.bag.msgtypes import check_topic_name
    with pytest.raises(ValueError) as e:
        check_topic_name(name)
    assert str(e.value) == f'bad topic name {name!r}: {why}'


def test_check_topic_and_node_names():
    from beo_ros.ros.bag.msgtypes import check_node_name, check_topic_name
    assert check_topic_name('~/x', 'player') == '/player/x'   # the node's private namespace
    assert check_topic_name('{node}/x', 'player') == '/player/x'
    assert check_node_name('beo_replay') == 'beo_replay'
    for name, why in (('bad-name', "node name must not contain characters other than "
                                   "alphanumerics or '_'"),
                      ('1abc', 'node name must not start with a number')):
        with pytest.raises(ValueError) as e:
            check_node_name(name)
        assert str(e.value) == f'bad node name {name!r}: {why}'


def test_message_type_names_of_topics_messages_services_and_actions():
    from beo_ros.ros.bag.msgtypes import import_msg_class, msgtype_of, normalize_msgtype
    for name, full in ((' std_msgs/String\n', 'std_msgs/msg/String'),
                       ('lifecycle_msgs.srv.GetState_Event', 'lifecycle_msgs/srv/GetState_Event'),
                       ('pkg/action/Fib_FeedbackMessage', 'pkg/action/Fib_FeedbackMessage')):
        assert normalize_msgtype(name) == full
    for name in ('pkg/foo/Type', 'pkg/msg/sub/Type', 'String'):
        with pytest.raises(ValueError, match=f'not a message type name: {name!r}'):
            normalize_msgtype(name)
    # an action's feedback topic type (no action package is installed: a stand-in class)
    feedback = type('Fib_FeedbackMessage', (), {'__module__': 'pkg.action._fib'})
    assert msgtype_of(feedback) == 'pkg/action/Fib_FeedbackMessage'
    with pytest.raises(KeyError, match='std_msgs/msg/NoSuchType is not installed'):
        import_msg_class('std_msgs/msg/NoSuchType')   # the module is, the class is not
    from beo_ros.ros.bag.msgtypes import _referenced_types
    assert _referenced_types([('goal', (2, 'pkg/action/Fib_Goal')), ('n', (1, ('int32', 0)))]
                             ) == {'pkg/action/Fib_Goal'}


def test_definitions_of_a_message_named_like_a_service_part_and_of_a_srv_field(monkeypatch,
                                                                               tmp_path):
    # a msg type whose name ends in _Event is read from its .msg file (only srv types are
    # parts of a .srv file); a .srv field of a message type of its own package, named
    # relatively, is that package's msg type (rosbags files it under pkg/srv/msg/)
    from beo_ros.ros.bag.msgtypes import _definition, types_from_msg
    share = tmp_path / 'share' / 'foo_msgs'
    (share / 'msg').mkdir(parents=True)
    (share / 'msg' / 'Door_Event').with_suffix('.msg').write_text('int32 a\n')
    (share / 'srv').mkdir()
    (share / 'srv' / 'Open.srv').write_text('Door door\n--- \nbool ok\n')   # (a blank after ---)
    monkeypatch.setenv('AMENT_PREFIX_PATH', str(tmp_path))
    assert _definition('foo_msgs/msg/Door_Event') == 'int32 a\n'
    assert _definition('foo_msgs/srv/Open_Request') == 'Door door\n'
    assert _definition('foo_msgs/srv/Open_Response') == '\nbool ok\n'
    types = types_from_msg(_definition('foo_msgs/srv/Open_Request'), 'foo_msgs/srv/Open_Request')
    assert types['foo_msgs/srv/Open_Request'][1][0][1][1] == 'foo_msgs/msg/Door'
