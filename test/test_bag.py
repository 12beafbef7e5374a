"""rosbag2 tools (beo_ros.ros.bag): writing/reading bags, replay and record with real rclpy, pcd2bag.

Bags are built into tmp dirs from generated clouds (or from the shared OSD scans, skipped when
absent); nothing derived from the data is ever written into the repository.
"""
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'OFF')

import numpy as np  # noqa: E402
import pytest  # noqa: E402
import rclpy  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.qos import qos_profile_sensor_data  # noqa: E402
from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402
from sensor_msgs.msg import PointCloud2  # noqa: E402
from std_msgs.msg import Float64MultiArray, String  # noqa: E402

from beo_ros.ros import bag  # noqa: E402
from beo_ros.ros.conversions import cloud_to_xyz  # noqa: E402

from _helpers import (REPO, T0, cli_env, make_cloud, signal_loop_replay,  # noqa: E402
                      wait_for_nodes, write_scene_pcd, write_test_bag)

DATA = Path(os.environ.get('BEO_DATA_DIR', REPO.parent / 'shared' / 'data'))


class Spinner:
    """Spins nodes of one context in a background thread."""

    def __init__(self, context, *nodes):
        self.ex = SingleThreadedExecutor(context=context)
        for n in nodes:
            self.ex.add_node(n)
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self):
        while not self._stop.is_set():
            self.ex.spin_once(timeout_sec=0.02)

    def close(self):
        self._stop.set()
        self.thread.join(5)
        self.ex.shutdown()


# ------------------------------------------------------------------------------------------
# sequential-reader style: write, read back with rosbags, check topics/counts/types/order/content
# ------------------------------------------------------------------------------------------

@pytest.mark.parametrize('storage', bag.STORAGES)
def test_write_read_back(tmp_path, storage):
    p = tmp_path / 'b'
    clouds = write_test_bag(p, storage)
    assert bag.detect_storage(p) == storage
    suffix = '.db3' if storage == 'sqlite3' else '.mcap'
    assert any(f.suffix == suffix for f in p.iterdir())

    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore
    store = get_typestore(Stores.ROS2_JAZZY)
    with Reader(p) as r:
        topics = {c.topic: (c.msgtype, c.msgcount) for c in r.connections}
        assert topics == {'/beo/input': ('sensor_msgs/msg/PointCloud2', 10),
                          '/chatter': ('std_msgs/msg/String', 5)}
        assert r.message_count == 15
        stamps, seen = [], []
        for conn, t, raw in r.messages():
            stamps.append(t)
            if conn.topic == '/beo/input':
                m = store.deserialize_cdr(raw, conn.msgtype)  # rosbags' own CDR reader
                i = len(seen)
                assert m.header.frame_id == 'camera'
                assert m.header.stamp.sec * 10**9 + m.header.stamp.nanosec == t
                assert m.width == 50 and m.point_step == 12
                pts = np.frombuffer(m.data.tobytes(), dtype='<f4').reshape(-1, 3)
                np.testing.assert_array_equal(pts, clouds[i])
                seen.append(t)
            else:
                assert store.deserialize_cdr(raw, conn.msgtype).data.startswith('hello')
        assert stamps == sorted(stamps)
        assert seen == [T0 + i * 10_000_000 for i in range(10)]

    # and the same bytes through rclpy
    msgs = [m for t, m, _ in bag.read_messages(p, topics={'/beo/input'})]
    assert len(msgs) == 10
    for m, pts in zip(msgs, clouds):
        xyz, dropped = cloud_to_xyz(m)
        assert dropped == 0
        np.testing.assert_array_equal(xyz.astype(np.float32), pts)

    info = bag.bag_info(p)
    assert info['storage'] == storage and info['message_count'] == 15
    assert info['topics']['/beo/input'] == {'type': 'sensor_msgs/msg/PointCloud2', 'count': 10}


def test_writer_refuses_existing_and_type_clash(tmp_path):
    p = tmp_path / 'b'
    write_test_bag(p, 'sqlite3', n=1)
    with pytest.raises(Exception, match='exists already'):
        bag.BagWriter(p, 'sqlite3').open()
    assert bag.bag_info(p)['message_count'] == 2   # the refused writer left the bag alone
    with bag.BagWriter(tmp_path / 'c', 'mcap') as w:
        w.add_topic('/x', 'std_msgs/String')
        with pytest.raises(ValueError, match='/x: already has type std_msgs/msg/String'):
            w.add_topic('/x', 'std_msgs/msg/Float64MultiArray')
    # write() checks the type of a message on a known topic too (a Header after a String
    # would be written and fail to deserialize later)
    from std_msgs.msg import Header, String
    with bag.BagWriter(tmp_path / 'd', 'sqlite3') as w:
        w.write('/x', String(data='a'), 1)
        with pytest.raises(ValueError, match='already has type std_msgs/msg/String'):
            w.write('/x', Header(), 2)
        w.write('/x', String(data='b'), 3)
        assert w.counts['/x'] == 2
    assert [m.data for _, m, _ in bag.read_messages(tmp_path / 'd')] == ['a', 'b']


def test_a_single_topic_string_is_one_topic_name(ros_env_context, tmp_path):
    """Before: read_bag matched a str ``topics`` by substring (``'/beo/input_raw'`` read
    /beo/input too, ``'/'`` read every topic) and replay took its characters for topic
    names; a single string is now one topic name."""
    p = tmp_path / 'b'
    with bag.BagWriter(p, 'sqlite3') as w:
        for i, topic in enumerate(('/beo/input', '/beo/input_raw', '/a')):
            w.write(topic, String(data=topic), 10 + i)
    assert [t for t, *_ in bag.read_bag(p, '/beo/input_raw')] == ['/beo/input_raw']
    assert [t for t, *_ in bag.read_bag(p, ['/beo/input_raw'])] == ['/beo/input_raw']
    assert list(bag.read_bag(p, '/')) == []
    assert [m.data for _, m, _ in bag.read_messages(p, '/a')] == ['/a']
    node = rclpy.create_node('replayer', context=ros_env_context)
    stats = bag.replay(p, node, topics='/a', rate=0, qos='best_effort')
    assert stats.messages == 1 and set(stats.topics) == {'/a'}


def test_msgtype_names():
    assert bag.normalize_msgtype('sensor_msgs/PointCloud2') == 'sensor_msgs/msg/PointCloud2'
    assert bag.normalize_msgtype('std_msgs.msg.String') == 'std_msgs/msg/String'
    with pytest.raises(ValueError, match="not a message type name: 'nope'"):
        bag.normalize_msgtype('nope')
    assert bag.msgtype_of(PointCloud2()) == 'sensor_msgs/msg/PointCloud2'
    assert bag.parse_remaps(['/a:=/b', '/c:=/d/e']) == {'/a': '/b', '/c': '/d/e'}
    with pytest.raises(ValueError, match="remap must be OLD:=NEW, got '/a=/b'"):
        bag.parse_remaps(['/a=/b'])
    assert bag.parse_topic_specs(['/a', '/b:std_msgs/String']) == {
        '/a': None, '/b': 'std_msgs/msg/String'}


def _beo_interfaces():
    try:
        from beo_ros.ros.conversions import interfaces
        return interfaces()
    except ImportError as e:
        pytest.skip(f'beo_interfaces not built ({e}); run scripts/setup')


@pytest.mark.parametrize('storage', bag.STORAGES)
def test_beo_interfaces_types_round_trip(tmp_path, storage):
    """ObjectEstimate is not in the rosbags typestore: its .msg definitions get registered."""
    msgs = _beo_interfaces()
    est = msgs.ObjectEstimate(label='chair', probability=0.75, class_names=['chair', 'desk'],
                              class_probabilities=[0.75, 0.25], status='ok')
    est.header.frame_id = 'camera'
    est.hypotheses = [msgs.YawHypothesis(label='chair', yaw=0.5, score=-3.0)]
    _, est.completed_cloud = make_cloud(3)
    p = tmp_path / 'e'
    with bag.BagWriter(p, storage) as w:
        w.write('/beo/estimates', est, T0)
        w.write('/beo/estimates', serialize_message(est), T0 + 1,
                msgtype='beo_interfaces/msg/ObjectEstimate')
    from rosbags.rosbag2 import Reader
    with Reader(p) as r:
        (conn,) = r.connections
        assert conn.msgtype == 'beo_interfaces/msg/ObjectEstimate'
        assert 'YawHypothesis' in conn.msgdef.data  # self-describing bag
        store = bag.get_typestore([conn.msgtype])
        for _, _, raw in r.messages():
            m = store.deserialize_cdr(raw, conn.msgtype)
            assert m.label == 'chair' and m.hypotheses[0].yaw == 0.5
            back = deserialize_message(raw, msgs.ObjectEstimate)
            assert back.label == 'chair' and list(back.class_names) == ['chair', 'desk']
            assert back.completed_cloud.width == 50


# ------------------------------------------------------------------------------------------
# replay / record in-process (one context per test)
# ------------------------------------------------------------------------------------------

def collect(node, topic, msg_type=PointCloud2, qos=qos_profile_sensor_data):
    got = []
    node.create_subscription(msg_type, topic, lambda m: got.append(m), qos)
    return got


def wait_for(pred, timeout=10.0):
    t0 = time.monotonic()
    while not pred():
        if time.monotonic() - t0 > timeout:
            return False
        time.sleep(0.01)
    return True


@pytest.mark.parametrize('storage', bag.STORAGES)
def test_replay_in_process(ros_env_context, tmp_path, storage):
    p = tmp_path / 'b'
    clouds = write_test_bag(p, storage, n=10, period_ns=20_000_000)
    pub_node = rclpy.create_node('replayer', context=ros_env_context)
    sub_node = rclpy.create_node('listener', context=ros_env_context)
    from rclpy.qos import QoSProfile
    got = collect(sub_node, '/remapped', qos=QoSProfile(depth=100))
    chatter = collect(sub_node, '/chatter', String, QoSProfile(depth=100))
    spin = Spinner(ros_env_context, sub_node)
    try:
        stats = bag.replay(p, pub_node, remap=['/beo/input:=/remapped'], rate=1.0,
                           wait_subscribers=1, wait_timeout=5.0)
        assert wait_for(lambda: len(got) == 10)
    finally:
        spin.close()
    assert stats.messages == 10 and stats.loops == 1 and not stats.interrupted
    assert set(stats.topics) == {'/remapped'}  # PointCloud2 topics only by default
    s = stats.topics['/remapped']
    assert (s.bag_topic, s.msgtype, s.count, s.subscribers) == (
        '/beo/input', 'sensor_msgs/msg/PointCloud2', 10, 1)
    assert chatter == []
    # timing follows the bag: 9 gaps of 20 ms
    assert stats.bag_span_s == pytest.approx(0.18, abs=1e-6)
    assert 0.17 <= stats.wall_s < 0.6
    for m, pts in zip(got, clouds):
        np.testing.assert_array_equal(cloud_to_xyz(m)[0].astype(np.float32), pts)
    d = stats.to_dict()
    json.dumps(d)
    assert d['topics']['/remapped']['count'] == 10
    assert '/remapped' in stats.table()


def test_replay_rate_loop_topics_and_stop(ros_env_context, tmp_path):
    p = tmp_path / 'b'
    write_test_bag(p, 'mcap', n=10, period_ns=100_000_000)   # 0.9 s span
    node = rclpy.create_node('replayer', context=ros_env_context)
    t = time.monotonic()
    stats = bag.replay(p, node, rate=0, loops=3, all_topics=True)
    assert time.monotonic() - t < 0.9     # rate 0: no sleeping
    assert stats.loops == 3 and stats.messages == 45
    assert stats.topics['/chatter'].count == 15 and stats.topics['/beo/input'].count == 30
    # the bytes are counted per topic too (CDR payloads, as in the total)
    assert stats.topics['/chatter'].bytes > 0
    assert stats.topics['/chatter'].bytes + stats.topics['/beo/input'].bytes == stats.bytes

    stats = bag.replay(p, node, rate=10.0, topics=['/chatter'])
    assert stats.messages == 5 and set(stats.topics) == {'/chatter'}
    assert 0.075 <= stats.wall_s < 0.4    # 0.8 s of bag time at 10x

    with pytest.raises(KeyError):
        bag.replay(p, node, topics=['/nope'])
    with pytest.raises(TimeoutError):
        bag.replay(p, node, wait_subscribers=1, wait_timeout=0.2)

    stop = threading.Event()
    threading.Timer(0.3, stop.set).start()
    stats = bag.replay(p, node, rate=1.0, loop=True, stop=stop)
    assert stats.interrupted and stats.messages < 10


def test_replay_best_effort_reaches_sensor_qos_subscriber(ros_env_context, tmp_path):
    p = tmp_path / 'b'
    write_test_bag(p, 'sqlite3', n=5, period_ns=10_000_000)
    pub_node = rclpy.create_node('replayer', context=ros_env_context)
    sub_node = rclpy.create_node('listener', context=ros_env_context)
    got = collect(sub_node, '/beo/input')
    spin = Spinner(ros_env_context, sub_node)
    try:
        stats = bag.replay(p, pub_node, qos='best_effort', wait_subscribers=1)
        assert wait_for(lambda: len(got) == 5, 5)
    finally:
        spin.close()
    assert stats.topics['/beo/input'].subscribers == 1
    # the publisher in the graph is best effort (a reliable one would reach this subscriber
    # too, so the messages alone cannot tell)
    from rclpy.qos import ReliabilityPolicy
    infos = [i for i in sub_node.get_publishers_info_by_topic('/beo/input')
             if i.node_name == 'replayer']
    assert infos and all(i.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT
                         for i in infos)


def test_record_in_process_then_read_back(ros_env_context, tmp_path):
    """record() from a live publisher; the bag is readable by rosbags and rclpy."""
    pub_node = rclpy.create_node('talker', context=ros_env_context)
    rec_node = rclpy.create_node('recorder', context=ros_env_context)
    cloud_pub = pub_node.create_publisher(PointCloud2, '/beo/input', 10)
    arr_pub = pub_node.create_publisher(Float64MultiArray, '/beo/table_plane', 10)
    out = tmp_path / 'rec'
    ready = threading.Event()
    result = {}

    def run():
        result['stats'] = bag.record(rec_node, out, ['/beo/input', '/beo/table_plane:'
                                                     'std_msgs/msg/Float64MultiArray'],
                                     storage='mcap', wait=5.0, count=8, ready=ready)
    th = threading.Thread(target=run)
    th.start()
    assert ready.wait(10)
    assert wait_for(lambda: cloud_pub.get_subscription_count() == 1
                    and arr_pub.get_subscription_count() == 1, 5)
    sent = []
    for i in range(4):
        pts, m = make_cloud(i)
        sent.append(pts)
        cloud_pub.publish(m)
        arr_pub.publish(Float64MultiArray(data=[0.0, 0.0, 1.0, float(i)]))
        time.sleep(0.02)
    th.join(10)
    assert not th.is_alive()
    stats = result['stats']
    assert stats.stopped_by == 'count' and stats.messages == 8
    assert stats.topics == {'/beo/input': {'type': 'sensor_msgs/msg/PointCloud2', 'count': 4},
                            '/beo/table_plane': {'type': 'std_msgs/msg/Float64MultiArray',
                                                 'count': 4}}
    info = bag.bag_info(out)
    assert info['storage'] == 'mcap' and info['message_count'] == 8
    clouds = [m for t, m, _ in bag.read_messages(out, {'/beo/input'})]
    for m, pts in zip(clouds, sent):
        np.testing.assert_array_equal(cloud_to_xyz(m)[0].astype(np.float32), pts)
    planes = [list(m.data) for t, m, _ in bag.read_messages(out, {'/beo/table_plane'})]
    assert planes == [[0.0, 0.0, 1.0, float(i)] for i in range(4)]


def _record_beside_a_string_talker(ros_env_context, ros_domain_id, path, topics):
    """``bag.record`` of ``topics`` for 0.2 s into ``path`` by a node of ``ros_env_context``
    while a node of another context (as another process would be) publishes String on
    /chatter -> (stats, recorder node, the warnings it logged)."""
    ctx = rclpy.Context()
    rclpy.init(args=[], context=ctx, domain_id=ros_domain_id)
    try:
        pub_node = rclpy.create_node('talker', context=ctx)
        rec_node = rclpy.create_node('recorder', context=ros_env_context)
        pub_node.create_publisher(String, '/chatter', 10)
        assert wait_for(lambda: rec_node.get_publishers_info_by_topic('/chatter'), 10)
        warned = []
        rec_node.get_logger().warning = lambda msg, **kw: warned.append(msg)
        stats = bag.record(rec_node, path, topics, duration=0.2)
    finally:
        rclpy.try_shutdown(context=ctx)
    return stats, rec_node, warned


def test_record_warns_of_publishers_of_another_type_than_recorded(ros_env_context, tmp_path,
                                                                   ros_domain_id):
    """/chatter:std_msgs/msg/Int32 while /chatter's publisher sends String: nothing can be
    recorded. Before: 0 messages and not a word; now a warning names the type left out."""
    stats, _, warned = _record_beside_a_string_talker(
        ros_env_context, ros_domain_id, tmp_path / 'r', ['/chatter:std_msgs/msg/Int32'])
    assert stats.messages == 0
    assert warned == ['/chatter has publishers of std_msgs/msg/String: their messages are not '
                      'recorded (the topic is recorded as std_msgs/msg/Int32)']


def test_record_unknown_topic_times_out(ros_env_context, tmp_path):
    node = rclpy.create_node('recorder', context=ros_env_context)
    with pytest.raises(KeyError, match='/nobody'):
        bag.record(node, tmp_path / 'x', ['/nobody'], wait=0.2)


def test_record_beo_interfaces_topic(ros_env_context, tmp_path):
    msgs = _beo_interfaces()
    pub_node = rclpy.create_node('talker', context=ros_env_context)
    rec_node = rclpy.create_node('recorder', context=ros_env_context)
    pub = pub_node.create_publisher(msgs.ObjectEstimate, '/beo/estimates', 10)
    ready, result = threading.Event(), {}
    th = threading.Thread(target=lambda: result.setdefault('s', bag.record(
        rec_node, tmp_path / 'est', ['/beo/estimates'], wait=5.0, count=3, ready=ready)))
    th.start()
    assert ready.wait(10) and wait_for(lambda: pub.get_subscription_count() == 1, 5)
    for i in range(3):
        pub.publish(msgs.ObjectEstimate(label=f'obj{i}', probability=0.5))
        time.sleep(0.02)
    th.join(10)
    assert result['s'].topics['/beo/estimates']['type'] == 'beo_interfaces/msg/ObjectEstimate'
    labels = [m.label for _, m, _ in bag.read_messages(tmp_path / 'est')]
    assert labels == ['obj0', 'obj1', 'obj2']
    from rosbags.rosbag2 import Reader
    with Reader(tmp_path / 'est') as r:
        store = bag.get_typestore(['beo_interfaces/msg/ObjectEstimate'])
        assert [store.deserialize_cdr(raw, c.msgtype).label
                for c, _, raw in r.messages()] == labels


# ------------------------------------------------------------------------------------------
# command line
# ------------------------------------------------------------------------------------------

@pytest.mark.parametrize('main', ['replay_main', 'record_main', 'pcd2bag_main'])
def test_cli_help(main, capsys):
    with pytest.raises(SystemExit) as e:
        getattr(bag, main)(['--help'])
    assert e.value.code == 0
    assert 'usage:' in capsys.readouterr().out


def test_cli_record_and_replay_subprocesses(tmp_path, ros_domain_id):
    """beo-record and beo-replay as separate processes on a private domain."""
    env = cli_env(ros_domain_id)
    src = tmp_path / 'src'
    write_test_bag(src, 'sqlite3', n=6, period_ns=100_000_000)
    out = tmp_path / 'out'
    code = 'import sys; from beo_ros.ros.bag import {}; sys.exit({}(sys.argv[1:]))'
    rec = subprocess.Popen(
        [sys.executable, '-c', code.format('record_main', 'record_main'),
         '/beo/copy:sensor_msgs/msg/PointCloud2', '-o', str(out), '--count', '6', '--json'],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        rep = subprocess.run(
            [sys.executable, '-c', code.format('replay_main', 'replay_main'), str(src),
             '--remap', '/beo/input:=/beo/copy', '--wait-subscribers', '1', '--wait-timeout',
             '20', '--clock', '--json'],
            env=env, capture_output=True, text=True, timeout=60)
        assert rep.returncode == 0, rep.stderr
        rstats = json.loads(rep.stdout)
        assert rstats['messages'] == 6 and rstats['topics']['/beo/copy']['count'] == 6
        # --clock without a value: 40 Hz: one before each of the 6 messages and about 3 in
        # each of the 5 gaps of 0.1 s
        assert 15 <= rstats['clock_messages'] <= 30
        o, e = rec.communicate(timeout=30)
    finally:
        if rec.poll() is None:
            rec.kill()
    assert rec.returncode == 0, e
    assert json.loads(o)['messages'] == 6
    got = [cloud_to_xyz(m)[0] for _, m, _ in bag.read_messages(out)]
    want = [cloud_to_xyz(m)[0] for _, m, _ in bag.read_messages(src, {'/beo/input'})]
    assert len(got) == 6
    for a, b in zip(got, want):
        np.testing.assert_array_equal(a, b)


def test_cli_replay_errors(tmp_path, capsys):
    with pytest.raises(SystemExit):
        bag.replay_main([str(tmp_path / 'missing')])
    with pytest.raises(SystemExit):
        bag.replay_main([str(tmp_path), '--remap', 'bad'])
    with pytest.raises(SystemExit):
        bag.replay_main([str(tmp_path), '--rate', '-1'])


def test_cli_replay_of_what_is_not_a_bag_exits_2_with_a_message(tmp_path, capsys):
    (tmp_path / 'empty').mkdir()
    (tmp_path / 'x.db3').write_text('garbage')
    (tmp_path / 'x.mcap').write_text('garbage')
    (tmp_path / 'meta').mkdir()
    (tmp_path / 'meta' / 'metadata.yaml').write_text('rosbag2_bagfile_information:\n  version: [\n')
    for name, why in (('empty', 'not a rosbag2 bag'), ('x.db3', 'database'), ('x.mcap', ''),
                      ('meta', 'storage_identifier')):
        assert bag.replay_main([str(tmp_path / name)]) == 2, name
        err = capsys.readouterr().err
        assert 'beo-replay: cannot read' in err and why in err and 'Traceback' not in err, err


def test_cli_replay_of_a_metadata_yaml_that_does_not_parse_is_one_line(tmp_path, capsys):
    """Before: the YAML error's own lines (the bad line, a caret) followed the message."""
    (tmp_path / 'b').mkdir()
    (tmp_path / 'b' / 'metadata.yaml').write_text(
        'rosbag2_bagfile_information:\n\tstorage_identifier: sqlite3\n')
    assert bag.replay_main([str(tmp_path / 'b')]) == 2
    err = capsys.readouterr().err
    assert err.startswith('beo-replay: cannot read') and err.count('\n') == 1, err


@pytest.mark.parametrize('extra, message', [
    (['--rate', 'nan'], "argument --rate: must be a finite number, got 'nan'"),
    (['--rate', 'inf'], "argument --rate: must be a finite number, got 'inf'"),
    (['--rate', '-1'], 'argument --rate: must be in [0, inf), got -1'),
    (['--depth', '0'], 'argument --depth: must be in [1, 2147483647], got 0'),
    (['--depth', '-1'], 'argument --depth: must be in [1, 2147483647], got -1'),
    # before: a TypeError traceback from rclpy's QoSProfile, exit 1
    (['--depth', '2147483648'], 'argument --depth: must be in [1, 2147483647], got 2147483648'),
    (['--wait-subscribers', '-1'], 'argument --wait-subscribers: must be in [0, inf), got -1'),
    (['--wait-timeout', 'nan'], "argument --wait-timeout: must be a finite number, got 'nan'"),
    (['--wait-timeout', '-1'], 'argument --wait-timeout: must be in [0, inf), got -1'),
    (['--clock=nan'], "argument --clock: must be a finite number, got 'nan'"),
    (['--clock', '-5'], 'argument --clock: must be in [0, inf), got -5'),
    (['--remap', '/beo/input:=bad!'], "bad topic name 'bad!'"),
    (['--remap', '/beo/input:=/a', '--remap', '/beo/input:=/b'], 'remapped twice'),
    (['--node-name', 'bad name'], "bad node name 'bad name'"),
])
def test_cli_replay_bad_arguments_refused(tmp_path, capsys, extra, message):
    write_test_bag(tmp_path / 'b', 'sqlite3', n=1)
    with pytest.raises(SystemExit) as ei:
        bag.replay_main([str(tmp_path / 'b'), *extra])
    assert ei.value.code == 2
    err = capsys.readouterr().err
    assert message in err and 'Traceback' not in err, err


def test_cli_replay_refuses_a_remap_of_a_topic_not_in_the_bag(tmp_path, capsys,
                                                               keep_signal_handlers):
    # like --topics: a typo used to play on the old name, with exit code 0
    write_test_bag(tmp_path / 'b', 'sqlite3', n=2)
    assert bag.replay_main([str(tmp_path / 'b'), '--rate', '0',
                            '--remap', '/beo/inptu:=/x']) == 2
    out, err = capsys.readouterr()
    assert "remapped topics not in bag" in err and '/beo/inptu' in err and out == ''


@pytest.mark.parametrize('extra, message', [
    (['--duration', 'nan'], "argument --duration: must be a finite number, got 'nan'"),
    (['--duration', 'inf'], "argument --duration: must be a finite number, got 'inf'"),
    (['--duration', '-1'], 'argument --duration: must be in (0, inf), got -1'),
    (['--duration', '0'], 'argument --duration: must be in (0, inf), got 0'),
    (['--wait', 'nan'], "argument --wait: must be a finite number, got 'nan'"),
    (['--wait', '-1'], 'argument --wait: must be in [0, inf), got -1'),
    (['--count', '0'], 'argument --count: must be in [1, inf), got 0'),
    (['--count', '-3'], 'argument --count: must be in [1, inf), got -3'),
    (['--node-name', 'bad name'], "bad node name 'bad name'"),
    (['/bad topic:std_msgs/msg/String'], "bad topic name '/bad topic'"),
    (['/x:sensor_msgs/msg/PointCloud2'],
     '/x is given twice, as std_msgs/msg/String and as sensor_msgs/msg/PointCloud2'),
])
def test_cli_record_bad_arguments_refused(tmp_path, capsys, extra, message):
    out = tmp_path / 'r'
    with pytest.raises(SystemExit) as ei:
        topics, opts = (extra, []) if extra[0].startswith('/') else ([], extra)
        bag.record_main(['/x:std_msgs/msg/String', *topics, '-o', str(out), '--duration', '0.1',
                         *opts])
    assert ei.value.code == 2
    err = capsys.readouterr().err
    assert message in err and 'Traceback' not in err, err
    assert not out.exists()


def test_cli_record_and_pcd2bag_refuse_an_output_under_a_file(tmp_path, capsys):
    (tmp_path / 'afile').write_text('x')
    out = str(tmp_path / 'afile' / 'sub')
    scene = write_scene_pcd(tmp_path / 's.pcd')
    for main, args in ((bag.record_main, ['/x:std_msgs/msg/String', '-o', out]),
                       (bag.pcd2bag_main, [str(scene), '-o', out])):
        with pytest.raises(SystemExit) as ei:
            main(args)
        assert ei.value.code == 2
        err = capsys.readouterr().err
        assert 'afile is not a directory' in err and 'Traceback' not in err, err


def test_topic_specs_and_types_of_one_topic():
    assert bag.parse_topic_specs(['/a:std_msgs/String', '/a', '/a:std_msgs/msg/String']) == {
        '/a': 'std_msgs/msg/String'}
    with pytest.raises(ValueError, match='given twice'):
        bag.parse_topic_specs(['/a:std_msgs/String', '/a:sensor_msgs/PointCloud2'])
    with pytest.raises(ValueError, match='bad topic name'):
        bag.parse_topic_specs(['/a b'])
    assert bag.check_topic_name('x') == '/x'
    with pytest.raises(ValueError, match="bad topic name '/a//b'.*repeated"):
        bag.check_topic_name('/a//b')


def test_record_refuses_two_names_of_one_topic_with_different_types(ros_env_context, tmp_path):
    node = rclpy.create_node('rec_names', context=ros_env_context)
    with pytest.raises(ValueError, match='/x is given twice'):
        bag.record(node, tmp_path / 'r', {'x': 'std_msgs/msg/String',
                                          '/x': 'sensor_msgs/msg/PointCloud2'}, duration=0.1)
    assert not (tmp_path / 'r').exists()


def test_record_interrupted_while_waiting_for_publishers_says_so(ros_env_context, tmp_path):
    node = rclpy.create_node('rec_wait', context=ros_env_context)
    stop = threading.Event()
    threading.Timer(0.3, stop.set).start()
    t = time.monotonic()
    with pytest.raises(KeyboardInterrupt, match='interrupted while waiting for publishers of: '
                       '/nopub'):
        bag.record(node, tmp_path / 'r', ['/nopub'], wait=30, stop=stop)
    assert time.monotonic() - t < 10
    assert not (tmp_path / 'r').exists()


def test_cli_sigint_before_anything_is_played_or_recorded_exits_130(tmp_path, ros_domain_id):
    """beo-replay waiting for subscribers and beo-record waiting for a publisher, interrupted:
    exit code 130, one line, no traceback (the replay used to exit 0, the recorder 2 with 'no
    publisher found within 30 s')."""
    import signal
    env = cli_env(ros_domain_id)
    write_test_bag(tmp_path / 'b', 'sqlite3', n=2)
    code = 'import sys; from beo_ros.ros.bag import {0}; sys.exit({0}(sys.argv[1:]))'
    procs = [subprocess.Popen([sys.executable, '-c', code.format(main), *args], env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for main, args in (
                 ('replay_main', [str(tmp_path / 'b'), '--wait-subscribers', '1',
                                  '--wait-timeout', '30']),
                 ('record_main', ['/nopub', '-o', str(tmp_path / 'r'), '--wait', '30']))]
    try:
        wait_for_nodes(ros_domain_id, {'beo_replay', 'beo_record'})
        time.sleep(1.0)   # from their node's appearance to their wait: well under a second
        results = []
        for p in procs:
            p.send_signal(signal.SIGINT)
            out, err = p.communicate(timeout=30)
            results.append((p.returncode, out, err))
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
    (rc_play, _, err_play), (rc_rec, _, err_rec) = results
    assert rc_play == 130 and 'beo-replay: interrupted' in err_play, err_play
    assert rc_rec == 130 and 'beo-record: interrupted' in err_rec, err_rec
    for err in (err_play, err_rec):
        assert 'Traceback' not in err and 'no publisher found' not in err, err
    assert not (tmp_path / 'r').exists()


def test_cli_record_terminated_while_waiting_for_a_publisher_exits_143(tmp_path, ros_domain_id):
    """SIGTERM before the recording started: 143 and 'terminated', as SIGTERM anywhere else.
    Before: 130 and 'interrupted', the exit code of Ctrl-C."""
    import signal
    code = ('import sys; from beo_ros.ros.bag import record_main; '
            'sys.exit(record_main(sys.argv[1:]))')
    p = subprocess.Popen([sys.executable, '-c', code, '/nopub', '-o', str(tmp_path / 'r'),
                          '--wait', '30'], env=cli_env(ros_domain_id), stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    try:
        wait_for_nodes(ros_domain_id, {'beo_record'})
        time.sleep(1.0)   # from its node's appearance to its wait: well under a second
        p.send_signal(signal.SIGTERM)
        _, err = p.communicate(timeout=30)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 143, err
    assert 'beo-record: terminated while waiting for publishers of: /nopub' in err, err
    assert 'Traceback' not in err and not (tmp_path / 'r').exists()


def test_cli_loop_replay_ended_by_sigint_exits_0(tmp_path, ros_domain_id):
    """With --loop, Ctrl-C is the normal end once the replay plays."""
    import signal
    # it plays its first message as soon as its node is up
    rc, out, err = signal_loop_replay(tmp_path, ros_domain_id, signal.SIGINT, settle=2.0)
    assert rc == 0, err
    assert 'interrupted' in out and 'Traceback' not in err


def test_cli_tools_that_cannot_start_ros_say_so_in_one_line(tmp_path, monkeypatch, capsys,
                                                           keep_signal_handlers):
    """ROS_DOMAIN_ID=abc: one line and exit code 1, as beo-node ('cannot start'). Before: a
    traceback of rclpy's RCLError."""
    write_test_bag(tmp_path / 'b', 'sqlite3', n=1)
    monkeypatch.setenv('ROS_DOMAIN_ID', 'abc')
    for prog, run in (('beo-replay', lambda: bag.replay_main([str(tmp_path / 'b')])),
                      ('beo-record', lambda: bag.record_main(['/x', '-o', str(tmp_path / 'r')]))):
        with pytest.raises(SystemExit) as e:
            run()
        assert e.value.code == 1
        err = capsys.readouterr().err
        assert err.startswith(f'{prog}: cannot start ROS: RCLError: ') and 'ROS_DOMAIN_ID' in err
        assert err.count('\n') == 1, err
    assert not (tmp_path / 'r').exists()


@pytest.mark.parametrize('prog, args', [
    ('beo-node', ['-m', 'beo_ros.node']),
    ('beo-replay', ['-m', 'beo_ros.ros.bag', 'BAG']),
    ('beo-record', ['-c', 'import sys; from beo_ros.ros.bag import record_main; '
                          'sys.exit(record_main(sys.argv[1:]))', '/x:std_msgs/msg/String',
                    '-o', 'REC']),
    ('beo-demo', ['-m', 'beo_ros.ros.demo', '--out', 'DEMO', '--model', 'MODEL'])])
def test_commands_on_a_domain_id_over_232_say_so_in_one_line(tmp_path, ros_tiny_model_dir,
                                                             prog, args):
    """ROS_DOMAIN_ID=233 (rcl takes it): before, Fast DDS ended the process when the node was
    made, exit 1 with its own two lines on stdout and nothing on stderr (beo-demo after
    writing its bag)."""
    write_test_bag(tmp_path / 'b', 'sqlite3', n=1)
    subs = {'BAG': str(tmp_path / 'b'), 'REC': str(tmp_path / 'r'),
            'DEMO': str(tmp_path / 'demo'), 'MODEL': str(ros_tiny_model_dir)}
    p = subprocess.run([sys.executable, *[subs.get(a, a) for a in args]],
                       env=cli_env(233), capture_output=True, text=True, timeout=120, cwd=REPO)
    assert p.returncode == 1, (p.stdout, p.stderr)
    assert p.stderr.startswith(f'{prog}: cannot start') and p.stderr.count('\n') == 1, p.stderr
    assert 'ROS_DOMAIN_ID 233 is over 232' in p.stderr and 'RTPS' not in p.stdout, p.stdout
    assert not (tmp_path / 'r').exists() and not (tmp_path / 'demo').exists()


def test_bag_tools_with_stdout_reader_gone_end_quietly_with_141(tmp_path, ros_domain_id):
    """stdout a pipe whose reader has exited. Before: beo-replay said 'cannot read BAG:
    [Errno 32] Broken pipe' (exit 2), beo-pcd2bag ended in a traceback (exit 1)."""
    write_test_bag(tmp_path / 'b', 'sqlite3', n=1)
    scene = write_scene_pcd(tmp_path / 's.pcd')
    for args in (['-m', 'beo_ros.ros.bag', str(tmp_path / 'b'), '--rate', '0'],
                 ['-c', 'import sys; from beo_ros.ros.bag import pcd2bag_main; '
                        'sys.exit(pcd2bag_main(sys.argv[1:]))', str(scene), '-o',
                  str(tmp_path / 'p')]):
        r, w = os.pipe()
        os.close(r)
        p = subprocess.run([sys.executable, *args], stdout=w, stderr=subprocess.PIPE,
                           text=True, env=cli_env(ros_domain_id), timeout=120)
        os.close(w)
        assert p.returncode == 141 and p.stderr == '', p.stderr
    assert (tmp_path / 'p' / 'metadata.yaml').exists()


def test_cli_node_ignores_the_tools_own_remap_arguments(monkeypatch, keep_signal_handlers):
    # rclpy.init(args=None) took sys.argv: beo-replay -r /a:=/b became a global rcl remap too
    monkeypatch.setattr(sys, 'argv', ['beo-replay', 'bag', '-r', '/a:=/b', '-r', '/b:=/a'])
    with bag._cli_node('beo_replay_argv_test') as (node, _):
        assert node.resolve_topic_name('/a') == '/a'
        assert node.resolve_topic_name('/b') == '/b'


def _bag_with_uninstalled_type(path):
    """write_test_bag's bag plus 3 messages of foo_msgs/msg/Bar (a type with no Python module)
    on /foo."""
    from rosbags.typesys import Stores, get_typestore, get_types_from_msg
    store = get_typestore(Stores.ROS2_JAZZY)   # a store of its own: the shared one stays clean
    store.register(get_types_from_msg('int32 a\n', 'foo_msgs/msg/Bar'))
    Bar = store.types['foo_msgs/msg/Bar']
    with bag.BagWriter(path, 'sqlite3') as w:
        conn = w._writer.add_connection('/foo', 'foo_msgs/msg/Bar', typestore=store)
        for i in range(3):
            w._writer.write(conn, T0 + i, bytes(store.serialize_cdr(Bar(a=i), conn.msgtype)))
        for i in range(4):
            w.write('/beo/input', make_cloud(i)[1], T0 + 10 + i)


def test_replay_skips_topics_of_types_not_installed(ros_env_context, tmp_path):
    p = tmp_path / 'b'
    _bag_with_uninstalled_type(p)
    with pytest.raises(KeyError, match='is not installed'):
        bag.import_msg_class('foo_msgs/msg/Bar')
    node = rclpy.create_node('player', context=ros_env_context)
    stats = bag.replay(p, node, all_topics=True, rate=0)
    assert stats.skipped == {'/foo': 'foo_msgs/msg/Bar'} and set(stats.topics) == {'/beo/input'}
    assert stats.messages == 4 and '1 topic(s) skipped' in stats.table()
    with pytest.raises(KeyError, match='foo_msgs/msg/Bar is not installed'):
        bag.replay(p, node, topics=['/foo'], rate=0)


def test_cli_replay_of_types_not_installed(tmp_path, capsys, keep_signal_handlers):
    p = tmp_path / 'b'
    _bag_with_uninstalled_type(p)
    assert bag.replay_main([str(p), '--all-topics', '--rate', '0', '--json']) == 0
    out, err = capsys.readouterr()
    assert 'warning: skipping /foo: message type foo_msgs/msg/Bar is not installed' in err
    assert json.loads(out)['skipped'] == {'/foo': 'foo_msgs/msg/Bar'}
    assert bag.replay_main([str(p), '--topics', '/foo']) == 2
    err = capsys.readouterr().err
    assert 'foo_msgs/msg/Bar is not installed' in err and 'Traceback' not in err


def test_cli_record_of_an_unknown_type_leaves_no_bag(tmp_path, capsys, keep_signal_handlers):
    out = tmp_path / 'rb1'
    assert bag.record_main(['/x:foo_msgs/msg/Bar', '-o', str(out), '--duration', '1']) == 2
    assert 'foo_msgs/msg/Bar' in capsys.readouterr().err
    assert not out.exists()   # a re-run would be refused: 'exists already'


def test_pcd2bag_synthetic_scene(tmp_path):
    out = tmp_path / 'b'
    summary = bag.pcd_to_bag([write_scene_pcd(tmp_path / 's.pcd')], out, topic='objects')
    (scene,) = summary['scenes']
    assert [o['points'] for o in scene['objects']] == [300] and summary['skipped'] == []
    np.testing.assert_allclose(scene['up'], [0, -1, 0], atol=1e-6)
    assert bag.bag_info(out)['topics']['/objects']['count'] == 1   # 'objects' expanded


@pytest.mark.parametrize('extra, message', [
    (['--topic', 'bad topic!'], "bad topic name 'bad topic!'"),
    (['--period', '1e12'], 'argument --period: must be in [0, 86400], got 1e12'),
    (['--period', 'inf'], "argument --period: must be a finite number, got 'inf'"),
    (['--period', '-1'], 'argument --period: must be in [0, 86400], got -1'),
    (['--object-period', 'nan'], "argument --object-period: must be a finite number, got 'nan'"),
    (['--min-points', '-1'], 'argument --min-points: must be in [0, inf), got -1'),
])
def test_cli_pcd2bag_bad_arguments_refused(tmp_path, capsys, extra, message):
    out = tmp_path / 'b'
    with pytest.raises(SystemExit) as ei:
        bag.pcd2bag_main([str(write_scene_pcd(tmp_path / 's.pcd')), '-o', str(out), *extra])
    assert ei.value.code == 2
    err = capsys.readouterr().err
    assert message in err and 'Traceback' not in err, err
    assert not out.exists()


def test_pcd_to_bag_refuses_stamps_past_what_a_header_holds_and_leaves_no_bag(tmp_path):
    """Before: stamps between 2038 and int64 nanoseconds (2262) were written, their header
    stamps' int32 seconds wrapped to negative (bag stamp 2.2e18 ns, header sec -2094967296)."""
    scene = write_scene_pcd(tmp_path / 's.pcd')
    for kw in ({'period': 5e8}, {'t0_ns': bag.T0_NS * 2}, {'period': 1e12},
               {'object_period': 1e12}, {'period': float('nan')}):
        with pytest.raises(ValueError, match='2038|finite'):
            bag.pcd_to_bag([scene, scene], tmp_path / 'b', **kw)
        assert not (tmp_path / 'b').exists()


@pytest.mark.parametrize('exc', [KeyboardInterrupt, OverflowError])
def test_pcd_to_bag_leaves_no_partial_bag_on_any_failure(tmp_path, monkeypatch, exc):
    scene = write_scene_pcd(tmp_path / 's.pcd')
    real = bag.BagWriter.write

    def write(self, *a, **kw):   # fails after the first message is written
        if sum(self.counts.values()):
            raise exc('boom')
        return real(self, *a, **kw)
    monkeypatch.setattr(bag.BagWriter, 'write', write)
    with pytest.raises(exc):
        bag.pcd_to_bag([scene], tmp_path / 'b')
    assert not (tmp_path / 'b').exists()


def test_cli_pcd2bag_ctrl_c_is_one_line_and_no_bag(tmp_path, monkeypatch, capsys):
    scene = write_scene_pcd(tmp_path / 's.pcd')
    real = bag.BagWriter.write

    def write(self, *a, **kw):
        if sum(self.counts.values()) == 2:
            raise KeyboardInterrupt
        return real(self, *a, **kw)
    monkeypatch.setattr(bag.BagWriter, 'write', write)
    try:
        rc = bag.pcd2bag_main([str(scene), '-o', str(tmp_path / 'b')])
    except KeyboardInterrupt:   # would end the whole pytest session
        pytest.fail('KeyboardInterrupt escaped beo-pcd2bag')
    assert rc == 130
    err = capsys.readouterr().err
    assert err.strip() == 'beo-pcd2bag: interrupted'
    assert not (tmp_path / 'b').exists()


def test_cli_pcd2bag_scene_without_labels_or_objects(tmp_path, capsys):
    good = write_scene_pcd(tmp_path / 'good.pcd')
    nolabel = write_scene_pcd(tmp_path / 'nolabel.pcd', labels=False)
    noobj = write_scene_pcd(tmp_path / 'noobj.pcd', objects=False)
    # no label field: refused, naming the file, no bag
    assert bag.pcd2bag_main([str(good), str(nolabel), '-o', str(tmp_path / 'b1')]) == 2
    err = capsys.readouterr().err
    assert f'{nolabel}: no label field' in err and 'Traceback' not in err, err
    assert not (tmp_path / 'b1').exists()
    # labels but no object: skipped with a warning, no up vector for it
    assert bag.pcd2bag_main([str(good), str(noobj), '-o', str(tmp_path / 'b2'), '--json']) == 0
    out, err = capsys.readouterr()
    assert err.strip() == (f'beo-pcd2bag: warning: skipped {noobj}: no objects (labels >= 20)')
    summary = json.loads(out)
    assert [s['scene'] for s in summary['scenes']] == [str(good)]
    assert summary['skipped'] == [{'scene': str(noobj),
                                   'reason': f'{noobj}: no objects (labels >= 20)'}]
    assert bag.bag_info(tmp_path / 'b2')['topics']['/beo/up']['count'] == 1
    # nothing left: refused
    assert bag.pcd2bag_main([str(noobj), '-o', str(tmp_path / 'b3')]) == 2
    assert 'no scene with objects' in capsys.readouterr().err
    assert not (tmp_path / 'b3').exists()


def test_cli_pcd2bag_of_a_corrupt_scene_writes_no_bag(tmp_path, capsys):
    bad = tmp_path / 'bad.pcd'
    bad.write_bytes(b'# .PCD v0.7\nFIELDS x y z\nDATA ascii\n')
    assert bag.pcd2bag_main([str(bad), '-o', str(tmp_path / 'out')]) == 2
    assert 'beo-pcd2bag:' in capsys.readouterr().err
    assert not (tmp_path / 'out').exists()


# ------------------------------------------------------------------------------------------
# pcd2bag on the real OSD scans
# ------------------------------------------------------------------------------------------

def _osd_scenes(names):
    scenes = [DATA / 'osd' / 'learn' / f'{n}.pcd' for n in names]
    if not all(s.is_file() for s in scenes):
        pytest.skip(f'OSD scans not found under {DATA}')
    try:
        from beo_ros.core import scans  # noqa: F401
    except ImportError as e:
        pytest.skip(f'beo_ros.core.scans not available yet ({e})')
    return scenes


def _scene_object_ids(scene):
    from beo_ros.core.pcd import read_pcd
    pcd = read_pcd(scene)
    labels = np.asarray(pcd['label'] if isinstance(pcd, dict) else pcd.fields['label'])
    labels = labels.reshape(-1).astype(int)
    return sorted({int(v) // 10 for v in labels if v >= 20})


@pytest.mark.parametrize('storage', bag.STORAGES)
def test_pcd2bag_osd(tmp_path, storage):
    scenes = _osd_scenes(['learn0', 'learn33'])
    out = tmp_path / 'osd'
    assert bag.pcd2bag_main([*map(str, scenes), '-o', str(out), '--storage', storage,
                             '--period', '0.5', '--object-period', '0.25',
                             '--min-points', '1']) == 0
    info = bag.bag_info(out)
    assert info['storage'] == storage
    n_objects = sum(len(_scene_object_ids(s)) for s in scenes)
    assert info['topics']['/beo/input'] == {'type': 'sensor_msgs/msg/PointCloud2',
                                           'count': n_objects}
    assert info['topics']['/beo/up']['type'] == 'geometry_msgs/msg/Vector3Stamped'
    assert info['topics']['/beo/up']['count'] == 2
    assert info['topics']['/beo/table_plane']['count'] == 2
    scenes_read = []   # split the bag at each /beo/up: [up, plane, clouds...] per scene
    stamps = []
    for topic, m, t in bag.read_messages(out):
        stamps.append(t)
        if topic == '/beo/up':
            scenes_read.append({'t': t, 'up': m, 'clouds': []})
        elif topic == '/beo/table_plane':
            scenes_read[-1]['plane'] = m
        else:
            assert m.header.stamp.sec * 10**9 + m.header.stamp.nanosec == t
            scenes_read[-1]['clouds'].append(m)
    assert stamps == sorted(stamps)
    cloud_stamps = [T0 + j * 250_000_000 for j in range(len(scenes_read[0]['clouds']))]
    assert [s['t'] for s in scenes_read] == [T0, max(T0 + 500_000_000, cloud_stamps[-1] + 250_000_000)]
    # clouds have unique stamps; up and plane share the scene's first cloud's stamp
    assert len(set(stamps)) == len(stamps) - 2 * len(scenes_read)
    for sc, path in zip(scenes_read, scenes):
        assert len(sc['clouds']) == len(_scene_object_ids(path))
        up, plane = sc['up'], sc['plane']
        u = np.array([up.vector.x, up.vector.y, up.vector.z])
        assert up.header.frame_id == 'camera'
        assert np.linalg.norm(u) == pytest.approx(1.0, abs=1e-6)
        np.testing.assert_allclose(np.array(plane.data)[:3], u)
        # camera frame (z forward, y down): the table normal points "up" = mostly -y
        assert u[1] < -0.5
        for m in sc['clouds']:
            assert m.header.frame_id == 'camera'
            pts, dropped = cloud_to_xyz(m)
            assert dropped == 0 and len(pts) > 0 and np.isfinite(pts).all()
            assert 0.3 < np.median(pts[:, 2]) < 3.0     # in front of the camera, Kinect range
            # objects sit on (above) the table plane
            height = pts @ u + plane.data[3]
            assert np.median(height) > 0.0


def test_cli_record_stops_on_sigint_and_duration(tmp_path, ros_domain_id):
    import signal
    env = cli_env(ros_domain_id)
    code = ('import sys; from beo_ros.ros.bag import record_main; '
            'sys.exit(record_main(sys.argv[1:]))')
    out = tmp_path / 'sig'
    rec = subprocess.Popen([sys.executable, '-c', code, '/nobody:std_msgs/msg/String', '-o',
                            str(out), '--storage', 'mcap'], env=env, stdout=subprocess.PIPE,
                           stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 30
        while not out.exists() and time.monotonic() < deadline:   # bag opened = recording
            time.sleep(0.05)
        time.sleep(0.3)
        rec.send_signal(signal.SIGINT)
        o, e = rec.communicate(timeout=30)
    finally:
        if rec.poll() is None:
            rec.kill()
    assert rec.returncode == 0, e
    assert 'stopped by interrupt' in o
    assert bag.bag_info(out)['topics'] == {'/nobody': {'type': 'std_msgs/msg/String', 'count': 0}}

    t = time.monotonic()
    r = subprocess.run([sys.executable, '-c', code, '/nobody:std_msgs/String', '-o',
                        str(tmp_path / 'dur'), '--duration', '0.5', '--json'],
                       env=env, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)['stopped_by'] == 'duration'
    assert time.monotonic() - t < 20


def test_replay_plays_latched_topics_transient_local(ros_env_context, tmp_path):
    """A topic recorded from transient-local publishers (like /tf_static) is played
    transient-local: a transient-local subscriber that joins after the replay still gets
    it. A volatile topic is not kept for late subscribers."""
    from rclpy.qos import DurabilityPolicy, QoSProfile
    p = tmp_path / 'b'
    with bag.BagWriter(p, storage='mcap') as w:
        w.add_topic('/latched', 'std_msgs/msg/String', transient_local=True)
        w.add_topic('/plain', 'std_msgs/msg/String')
        w.write('/latched', String(data='static'), 1)
        w.write('/plain', String(data='volatile'), 2)
    pub_node = rclpy.create_node('replayer', context=ros_env_context)
    stats = bag.replay(p, pub_node, all_topics=True, rate=0, qos='best_effort')
    assert stats.latched == ['/latched'] and 'transient-local' in stats.table()
    sub_node = rclpy.create_node('late_listener', context=ros_env_context)
    latched_qos = QoSProfile(depth=10, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    late = collect(sub_node, '/latched', String, latched_qos)
    plain = collect(sub_node, '/plain', String, QoSProfile(depth=10))
    spin = Spinner(ros_env_context, sub_node)
    try:
        assert wait_for(lambda: [m.data for m in late] == ['static'], 5)
        time.sleep(0.3)
    finally:
        spin.close()
    assert plain == []


@pytest.mark.parametrize('storage', bag.STORAGES)
def test_a_bag_whose_metadata_qos_differs_from_its_files_is_read_whole(ros_env_context, tmp_path,
                                                                       storage):
    """rosbags pairs metadata.yaml's topics with the storage file's by their offered QoS too.
    Before: a metadata.yaml with an empty (or hand-edited) offered_qos_profiles gave 0 messages
    from read_bag and beo-replay, no error, while bag_info counted them all; now the file's
    QoS is used (so the latched topic is still played latched)."""
    import re
    p = tmp_path / 'b'
    with bag.BagWriter(p, storage) as w:
        w.add_topic('/latched', 'std_msgs/msg/String', transient_local=True)
        for i in range(3):
            w.write('/latched', String(data=str(i)), 10 + i)
    meta = p / 'metadata.yaml'
    text, n = re.subn(r'offered_qos_profiles:\n( {6}[ -].*\n)+', "offered_qos_profiles: ''\n",
                      meta.read_text())
    assert n == 1
    meta.write_text(text)
    assert bag.bag_info(p)['message_count'] == 3
    assert [t for _, _, t, _ in bag.read_bag(p)] == [10, 11, 12]
    node = rclpy.create_node('replayer', context=ros_env_context)
    stats = bag.replay(p, node, all_topics=True, rate=0, qos='best_effort')
    assert stats.messages == 3 and stats.latched == ['/latched']


def test_replay_publishes_the_bag_time_on_clock(ros_env_context, tmp_path):
    """clock_hz: /clock carries the bag time, before every message and in between, never
    going back; a node with use_sim_time follows it."""
    from rclpy.parameter import Parameter
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rosgraph_msgs.msg import Clock
    p = tmp_path / 'b'
    t0 = 1_700_000_000_000_000_000
    with bag.BagWriter(p, storage='sqlite3') as w:
        w.add_topic('/chatter', 'std_msgs/msg/String')
        for i in range(3):
            w.write('/chatter', String(data=str(i)), t0 + i * 200_000_000)
    pub_node = rclpy.create_node('replayer', context=ros_env_context)
    sub_node = rclpy.create_node('clock_listener', context=ros_env_context)
    sim_node = rclpy.create_node('sim', context=ros_env_context,
                                 parameter_overrides=[Parameter('use_sim_time', value=True)])
    clocks = collect(sub_node, '/clock', Clock,
                     QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT))
    spin = Spinner(ros_env_context, sub_node, sim_node)
    try:
        stats = bag.replay(p, pub_node, all_topics=True, rate=1.0, clock_hz=50.0,
                           wait_subscribers=0)
        assert wait_for(lambda: len(clocks) >= stats.clock_messages - 2, 5)
        assert wait_for(lambda: sim_node.get_clock().now().nanoseconds >= t0 + 400_000_000, 5)
    finally:
        spin.close()
    ns = [m.clock.sec * 1_000_000_000 + m.clock.nanosec for m in clocks]
    # 0.4 s of bag at 50 Hz: about 20 in between, plus one per message
    assert stats.clock_messages >= 15 and len(ns) >= 12
    assert ns == sorted(ns) and t0 <= ns[0] and ns[-1] == t0 + 400_000_000
    assert t0 + 400_000_000 in ns and t0 + 200_000_000 in ns
    assert len([v for v in ns if t0 < v < t0 + 200_000_000]) >= 3   # ticks between messages
    with pytest.raises(ValueError, match='clock_hz'):
        bag.replay(p, pub_node, clock_hz=float('nan'))


def test_replay_refuses_the_clock_of_a_bag_past_2038(ros_env_context, tmp_path):
    """A bag's int64 stamps go past 2038, /clock's int32 seconds do not: the clock is
    refused before anything is sent (it went out wrapped negative); without it the bag plays."""
    from beo_ros.ros.conversions import stamp_from_ns
    p = tmp_path / 'b'
    t0 = 2**31 * 1_000_000_000   # 2038-01-19T03:14:08
    with bag.BagWriter(p, storage='sqlite3') as w:
        w.add_topic('/chatter', 'std_msgs/msg/String')
        for i in range(2):
            w.write('/chatter', String(data=str(i)), t0 + i)
    node = rclpy.create_node('replayer', context=ros_env_context)
    with pytest.raises(ValueError, match='past 2038'):
        bag.replay(p, node, all_topics=True, rate=0, clock_hz=10.0)
    assert bag.replay(p, node, all_topics=True, rate=0).messages == 2
    with pytest.raises(ValueError, match='builtin_interfaces/Time'):
        stamp_from_ns(t0)
    assert stamp_from_ns(t0 - 1).sec == 2**31 - 1


def test_cli_replay_clock_of_a_bag_past_2038_is_not_called_unreadable(tmp_path, capsys,
                                                                      keep_signal_handlers):
    """Before: 'beo-replay: cannot read BAG: its stamps go past 2038 ...' for a bag that reads
    (and plays without --clock): the refusal names the clock, not the bag, as the problem."""
    p = tmp_path / 'b'
    with bag.BagWriter(p, storage='sqlite3') as w:
        w.add_topic('/chatter', 'std_msgs/msg/String')
        w.write('/chatter', String(data='x'), 2**31 * 1_000_000_000)
    assert bag.replay_main([str(p), '--all-topics', '--rate', '0', '--clock']) == 2
    out, err = capsys.readouterr()
    assert err.startswith(f'beo-replay: {p}: its stamps go past 2038 (') and \
        err.endswith('beyond what /clock (int32 seconds) holds: play it without the clock\n'), err
    assert 'cannot read' not in err and err.count('\n') == 1 and out == '', err


def test_replay_keeps_every_latched_message_for_late_subscribers(ros_env_context, tmp_path):
    """Three latched messages (three static broadcasters' /tf_static) all reach a late
    transient-local subscriber, even with --depth 1."""
    from rclpy.qos import DurabilityPolicy, QoSProfile
    p = tmp_path / 'b'
    with bag.BagWriter(p, storage='sqlite3') as w:
        w.add_topic('/static', 'std_msgs/msg/String', transient_local=True)
        for i, name in enumerate(('laser', 'camera', 'imu')):
            w.write('/static', String(data=name), i + 1)
    node = rclpy.create_node('replayer', context=ros_env_context)
    bag.replay(p, node, all_topics=True, rate=0, depth=1)
    sub_node = rclpy.create_node('late', context=ros_env_context)
    got = collect(sub_node, '/static', String,
                  QoSProfile(depth=10, durability=DurabilityPolicy.TRANSIENT_LOCAL))
    spin = Spinner(ros_env_context, sub_node)
    try:
        assert wait_for(lambda: len(got) == 3, 5), [m.data for m in got]
    finally:
        spin.close()
    assert [m.data for m in got] == ['laser', 'camera', 'imu']


def test_clock_ticks_never_pass_the_next_message_nor_the_deadline(monkeypatch):
    """A tick is stamped at the time it was decided, capped at the next message's stamp;
    a slow tick does not make the sleep overshoot its deadline."""
    class Pub:
        def __init__(self):
            self.stamps = []

        def publish(self, m):
            self.stamps.append(m.clock.sec * 1_000_000_000 + m.clock.nanosec)

    stats = bag.ReplayStats('b', 'mcap', 1.0)
    pub = Pub()
    t0 = 5_000_000_000
    # 0.3 s after the start at rate 1 would be t0 + 0.3 s; the next message is at t0 + 0.2 s
    bag._clock_tick(pub, stats, 10.0, t0, 1.0, t0 + 200_000_000, 10.3)
    bag._clock_tick(pub, stats, 10.0, t0, 2.0, t0 + 900_000_000, 10.1)
    assert pub.stamps == [t0 + 200_000_000, t0 + 200_000_000] and stats.clock_messages == 2

    fake = [0.0]
    monkeypatch.setattr(bag.player.time, 'monotonic', lambda: fake[0])
    monkeypatch.setattr(bag.player.time, 'sleep', lambda d: fake.__setitem__(0, fake[0] + d))
    ticks = []

    def slow_tick(now):   # takes 4 ms
        ticks.append(now)
        fake[0] += 0.004

    for deadline in (0.0999, 0.1, 0.2337):
        fake[0], ticks[:] = 0.0, []
        assert bag._sleep_until(deadline, None, slow_tick, 0.025)
        assert deadline <= fake[0] < deadline + 1e-9
        assert len(ticks) >= int(deadline / 0.025) - 1 and all(t < deadline for t in ticks)


def test_replay_waits_for_a_clock_subscriber_with_its_data_subscribers(ros_env_context, tmp_path):
    """With wait_subscribers and clock_hz, /clock is matched before the first message when a
    use_sim_time node listens (no wait beyond its data topics); without a /clock subscriber
    the replay starts after a grace of CLOCK_GRACE_S."""
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rosgraph_msgs.msg import Clock
    p = tmp_path / 'b'
    write_test_bag(p, 'sqlite3', n=2, period_ns=10_000_000)
    pub_node = rclpy.create_node('replayer', context=ros_env_context)
    sub_node = rclpy.create_node('listener', context=ros_env_context)
    collect(sub_node, '/beo/input')
    stats = bag.replay(p, pub_node, rate=0, wait_subscribers=1, clock_hz=40.0)
    assert bag.CLOCK_GRACE_S - 0.05 <= stats.waited_s < bag.CLOCK_GRACE_S + 2.0
    clocks = collect(sub_node, '/clock', Clock,
                     QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT))
    spin = Spinner(ros_env_context, sub_node)
    try:
        stats = bag.replay(p, pub_node, rate=0, wait_subscribers=1, clock_hz=40.0)
        assert wait_for(lambda: len(clocks) == 2, 5)
    finally:
        spin.close()
    assert stats.waited_s < bag.CLOCK_GRACE_S - 0.1


@pytest.mark.parametrize('storage', bag.STORAGES)
@pytest.mark.parametrize('qos', ['- [not yaml', '- history: 1'])   # not YAML; no depth
def test_offered_qos_profiles_that_do_not_parse_are_one_line_naming_bag_topic_and_field(
        tmp_path, capsys, monkeypatch, keep_signal_handlers, storage, qos):
    """Before: a TypeError or KeyError traceback (QoS stored in the .db3 / .mcap file), or a
    message naming neither the topic nor the field (in metadata.yaml)."""
    import rosbags.rosbag2.writer
    p = tmp_path / 'b'
    with monkeypatch.context() as m:   # what the bag stores as its topic's offered QoS
        m.setattr(rosbags.rosbag2.writer, 'dump_qos_v9', lambda profiles: qos)
        with bag.BagWriter(p, storage) as w:
            w.write('/chatter', String(data='x'), 10)
    file = bag._bag_file(p)
    for target, named in ((p, p / 'metadata.yaml'), (file, file)):
        want = f'{named}: topic /chatter: offered_qos_profiles is not a list of QoS profiles ('
        for read in (lambda: list(bag.read_bag(target)), lambda: bag.bag_info(target)):
            with pytest.raises(ValueError) as e:
                read()
            assert str(e.value).startswith(want) and '\n' not in str(e.value), e.value
        assert bag.replay_main([str(target), '--all-topics', '--rate', '0']) == 2
        err = capsys.readouterr().err
        assert err.startswith(f'beo-replay: cannot read {target}: {want}') and \
            err.count('\n') == 1, err
    assert bag.recover_main([str(file), '-o', str(tmp_path / 'new')]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f'beo-bag-recover: {file}: topic /chatter: offered_qos_profiles') \
        and err.count('\n') == 1 and not (tmp_path / 'new').exists(), err


def test_record_normalizes_a_type_given_as_pkg_type(ros_env_context, tmp_path, ros_domain_id):
    """{'/chatter': 'std_msgs/String'} given to record(). Before: the type was kept as given,
    so the topic's own publishers were warned about as of another type and the stats had a
    type name that is not pkg/msg/Type; now it is std_msgs/msg/String throughout."""
    stats, rec_node, warned = _record_beside_a_string_talker(
        ros_env_context, ros_domain_id, tmp_path / 'r', {'/chatter': 'std_msgs/String'})
    assert warned == []
    assert stats.topics == {'/chatter': {'type': 'std_msgs/msg/String', 'count': 0}}
    assert bag.bag_info(tmp_path / 'r')['topics'] == {
        '/chatter': {'type': 'std_msgs/msg/String', 'count': 0}}
    assert bag.resolve_topic_types(rec_node, {'x': 'std_msgs/String', '/x': None}) == {
        '/x': 'std_msgs/msg/String'}


def test_a_bag_topic_that_is_not_a_valid_topic_name_is_one_line_and_plays_remapped(
        tmp_path, capsys, keep_signal_handlers):
    """Before: rclpy's InvalidTopicNameException traceback (several lines, exit 1); now one
    line naming the topic and the remap that plays it, and the remapped replay plays."""
    p = tmp_path / 'b'
    with bag.BagWriter(p, 'sqlite3') as w:
        w.write('/bad topic!', String(data='x'), 10)
    assert bag.replay_main([str(p), '--all-topics', '--rate', '0']) == 2
    out, err = capsys.readouterr()
    assert err.startswith(f"beo-replay: {p}: topic '/bad topic!' is not a valid ROS topic name (") \
        and err.endswith('remap it to one (--remap OLD:=NEW) to play it\n') \
        and err.count('\n') == 1 and out == '', err
    assert bag.replay_main([str(p), '--all-topics', '--rate', '0', '--json',
                            '--remap', '/bad topic!:=/good']) == 0
    stats = json.loads(capsys.readouterr().out)
    assert stats['messages'] == 1 and list(stats['topics']) == ['/good']


def test_the_clock_range_of_a_bag_is_that_of_its_last_stamp(ros_env_context, tmp_path):
    """rosbags' end_time is one past the last stamp. Before: a last stamp of 2**63 - 1 (the
    int64 maximum) was reported as 9223372036854775808 ns, which no int64 holds, and a bag
    whose last stamp is the last one /clock holds was refused."""
    from beo_ros.ros.conversions import MAX_STAMP_NS
    node = rclpy.create_node('replayer', context=ros_env_context)
    for name, last in (('max', 2**63 - 1), ('edge', MAX_STAMP_NS)):
        with bag.BagWriter(tmp_path / name, storage='sqlite3') as w:
            w.write('/chatter', String(data='a'), 10)
            w.write('/chatter', String(data='b'), last)
    with pytest.raises(ValueError) as e:
        bag.replay(tmp_path / 'max', node, all_topics=True, rate=0, clock_hz=10.0)
    assert f'({2**63 - 1} ns)' in str(e.value), e.value
    stats = bag.replay(tmp_path / 'edge', node, all_topics=True, rate=0, clock_hz=10.0)
    assert stats.messages == 2 and stats.clock_messages == 2


def test_detect_storage_reads_a_quoted_storage_identifier(tmp_path):
    for quoted in ("'mcap'", '"sqlite3"'):
        (tmp_path / 'metadata.yaml').write_text(
            f'rosbag2_bagfile_information:\n  storage_identifier: {quoted}\n')
        assert bag.detect_storage(tmp_path) == quoted.strip('\'"')


def test_a_connection_without_stored_qos_is_reliable_and_not_latched():
    """A bag that stores no offered QoS profiles for a topic (older recorders)."""
    from types import SimpleNamespace
    for ext in (None, SimpleNamespace(offered_qos_profiles=[])):
        conn = SimpleNamespace(ext=ext)
        assert bag.recorded_reliable(conn) and not bag.recorded_latched(conn)


@pytest.mark.parametrize('storage', bag.STORAGES)
def test_info_of_a_bag_without_messages_starts_at_0(tmp_path, storage):
    with bag.BagWriter(tmp_path / 'b', storage) as w:
        w.add_topic('/s', 'std_msgs/msg/String')
    info = bag.bag_info(tmp_path / 'b')
    assert (info['start_ns'], info['duration_s'], info['message_count']) == (0, 0.0, 0)


def test_an_empty_write_ahead_log_beside_a_db3_holds_nothing_and_is_not_refused(tmp_path):
    """A -wal file of 0 bytes (a WAL-mode database after its checkpoint) is no sign of
    messages missing from the database."""
    with bag.BagWriter(tmp_path / 'b', 'sqlite3') as w:
        w.write('/s', String(data='x'), 10)
    db = bag._bag_file(tmp_path / 'b')
    db.with_name(db.name + '-wal').write_bytes(b'')
    assert bag.storage.unmerged_wal(tmp_path / 'b') is None
    assert [t for _, _, t, _ in bag.read_bag(tmp_path / 'b')] == [10]


def test_an_mcap_file_of_its_magic_only_is_refused_as_without_footer(tmp_path):
    f = tmp_path / 'm.mcap'
    f.write_bytes(bag.MCAP_MAGIC)
    with pytest.raises(ValueError, match='no mcap footer'):
        list(bag.read_bag(f))


def test_a_single_file_bag_whose_metadata_does_not_read_gets_rosbags_own_error(tmp_path):
    """The list of a bag's files is for split recordings; with one file rosbags' error says it."""
    with bag.BagWriter(tmp_path / 'b', 'sqlite3') as w:
        w.write('/s', String(data='x'), 10)
    meta = tmp_path / 'b' / 'metadata.yaml'
    meta.write_text(meta.read_text()[:40] + '\n  - [')
    with pytest.raises(Exception) as e:
        list(bag.read_bag(tmp_path / 'b'))
    assert 'the files of the bag' not in str(e.value)
