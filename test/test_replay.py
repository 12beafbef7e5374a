"""Replay bags into the running BeoNode (real rclpy, in-process, one context per test).

Object clouds are partial views of boxes standing on a tilted table, built here in a camera
optical frame whose up vector is not an axis; with the shared OSD scans present, their objects
(through beo-pcd2bag) are replayed too. The node runs with a tiny model bank built by
``beo_ros.core.synthetic.make_tiny_bank``.
"""
import os
import threading
import time
from pathlib import Path

os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'OFF')

import numpy as np  # noqa: E402
import pytest  # noqa: E402
import rclpy  # noqa: E402
from builtin_interfaces.msg import Time  # noqa: E402
from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from geometry_msgs.msg import PoseStamped  # noqa: E402
from rclpy.executors import MultiThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import QoSProfile  # noqa: E402
from sensor_msgs.msg import PointCloud2  # noqa: E402
from std_msgs.msg import Header  # noqa: E402

from beo_ros.ros import bag  # noqa: E402
from beo_ros.ros.conversions import cloud_to_xyz, quaternion_to_rotation, xyz_to_cloud  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get('BEO_DATA_DIR', REPO.parent / 'shared' / 'data'))
T0 = bag.T0_NS
# camera optical frame (x right, y down, z forward) pitched 35 degrees down at the table
PITCH = np.deg2rad(35.0)
UP = np.array([0.0, -np.cos(PITCH), -np.sin(PITCH)])


def stamp_ns(header):
    return header.stamp.sec * 10**9 + header.stamp.nanosec


def to_time(ns):
    return Time(sec=ns // 10**9, nanosec=ns % 10**9)


def box_view(i, spacing=0.01, rng_seed=None):
    """Camera-frame points of the faces of box ``i`` that the sensor (origin) sees.

    The box stands on the table 0.7 m below the camera, ~1.1 m ahead, at a yaw and size that
    depend on ``i``.
    """
    rng = np.random.default_rng(i if rng_seed is None else rng_seed)
    fwd = np.array([0.0, 0.0, 1.0]) - UP * UP[2]
    fwd /= np.linalg.norm(fwd)
    side = np.cross(UP, fwd)
    half = np.array([0.12 + 0.03 * (i % 3), 0.08 + 0.02 * (i % 2), 0.10 + 0.03 * (i % 4)])
    yaw = 0.4 * i + 0.3
    c, s = np.cos(yaw), np.sin(yaw)
    axes = np.stack([c * fwd + s * side, -s * fwd + c * side, UP])   # box axes in the camera
    centre = 1.1 * fwd + (0.25 * ((i % 3) - 1)) * side + (-0.7 + half[2]) * UP
    pts = []
    for k in range(3):
        for sign in (-1.0, 1.0):
            normal = sign * axes[k]
            fc = centre + sign * half[k] * axes[k]
            if normal @ (-fc) <= 0 or (k == 2 and sign < 0):   # back faces and the bottom
                continue
            a, b = [j for j in range(3) if j != k]
            u = np.arange(-half[a], half[a] + 1e-9, spacing)
            v = np.arange(-half[b], half[b] + 1e-9, spacing)
            uu, vv = np.meshgrid(u, v, indexing='ij')
            pts.append(fc + uu.reshape(-1, 1) * axes[a] + vv.reshape(-1, 1) * axes[b])
    pts = np.concatenate(pts)
    pts += rng.normal(scale=0.002, size=pts.shape)
    return pts.astype(np.float32)


def write_box_bag(path, n, period_ns, storage='sqlite3', spacing=0.01, topic='/beo/input'):
    """n box views on ``topic`` (header stamp == bag time == T0 + i * period); returns inputs."""
    inputs = []
    with bag.BagWriter(path, storage) as w:
        for i in range(n):
            ns = T0 + i * period_ns
            pts = box_view(i % 7, spacing, rng_seed=i)
            w.write(topic, xyz_to_cloud(pts, Header(stamp=to_time(ns), frame_id='camera')), ns)
            inputs.append((ns, pts))
    return inputs


# ------------------------------------------------------------------------------------------
# fixtures: tiny bank, node harness
# ------------------------------------------------------------------------------------------

@pytest.fixture(scope='module')
def bank(request):
    """The tiny model bank (conftest: beo_ros.core.synthetic.make_tiny_bank), loaded once."""
    try:
        from beo_ros.ros.conversions import interfaces
        interfaces()
    except ImportError as e:
        pytest.skip(f'beo_interfaces not built ({e}); run scripts/setup')
    import beo_ros
    return beo_ros.load_models(request.getfixturevalue('ros_tiny_model_dir'))


class NodeHarness:
    """BeoNode + a listener + a replay node in one fresh context, spun in a background thread."""

    def __init__(self, bank, up=UP, domain_id=None, **params):
        from beo_ros.ros.node import BeoNode
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx, domain_id=domain_id)
        overrides = [Parameter('up_vector', value=[float(v) for v in up]),
                     Parameter('sensor_origin', value=[0.0, 0.0, 0.0]),
                     Parameter('diagnostics_period', value=0.1)]
        overrides += [Parameter(k, value=v) for k, v in params.items()]
        self.node = BeoNode(context=self.ctx, bank=bank, parameter_overrides=overrides)
        self.listener = rclpy.create_node('listener', context=self.ctx)
        self.player = rclpy.create_node('player', context=self.ctx)
        from beo_ros.ros.conversions import interfaces
        msgs = interfaces()
        self.lock = threading.Lock()
        self.estimates, self.completed, self.poses, self.diags = [], [], [], []
        q = QoSProfile(depth=1000)
        for typ, topic, store in ((msgs.ObjectEstimate, '/beo/estimates', self.estimates),
                                  (PointCloud2, '/beo/completed', self.completed),
                                  (PoseStamped, '/beo/pose', self.poses),
                                  (DiagnosticArray, '/diagnostics', self.diags)):
            self.listener.create_subscription(typ, topic, lambda m, s=store: self._add(s, m), q)
        self.ex = MultiThreadedExecutor(num_threads=4, context=self.ctx)
        self.ex.add_node(self.node)
        self.ex.add_node(self.listener)
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _add(self, store, m):
        with self.lock:
            store.append(m)

    def _spin(self):
        while not self.stop.is_set():
            self.ex.spin_once(timeout_sec=0.05)

    def replay(self, path, **kw):
        kw.setdefault('wait_subscribers', 1)
        kw.setdefault('wait_timeout', 10.0)
        return bag.replay(path, self.player, **kw)

    def wait_idle(self, timeout=120.0, settle=0.5):
        """Until every received cloud is accounted for and nothing changed for ``settle`` s."""
        t0 = time.monotonic()
        last, t_last = None, time.monotonic()
        while time.monotonic() - t0 < timeout:
            c = self.node.counters()
            done = c['processed'] + c['dropped_stale'] + c['rejected'] + c['errors']
            snap = (c['received'], done, len(self.estimates), len(self.completed))
            if snap != last:
                last, t_last = snap, time.monotonic()
            elif done >= c['received'] and time.monotonic() - t_last > settle:
                return c
            time.sleep(0.05)
        raise TimeoutError(f'node not idle after {timeout} s: {self.node.counters()}')

    def close(self):
        # stop spinning, then let the callbacks in the executor's pool finish before shutdown
        from beo_ros.ros.node import drain_executor
        self.stop.set()
        self.thread.join(timeout=5.0)
        drain_executor(self.ex)
        self.node.destroy_node()
        self.listener.destroy_node()
        self.player.destroy_node()
        rclpy.try_shutdown(context=self.ctx)
        self.thread.join(5)


@pytest.fixture
def harness(bank, ros_domain_id):
    hs = []

    def make(**kw):
        # a domain per test: endpoints of the test before must not count as subscribers
        h = NodeHarness(bank, domain_id=ros_domain_id, **kw)
        hs.append(h)
        return h
    yield make
    for h in hs:
        h.close()


def lockstep(h, timeout=60.0):
    """on_publish callback: after each cloud, wait until the node has dealt with it."""
    base = h.node.counters()['received']

    def cb(topic, raw, t):
        cb.sent += 1
        start = time.monotonic()
        while time.monotonic() - start < timeout:
            c = h.node.counters()
            done = c['processed'] + c['rejected'] + c['errors'] + c['dropped_stale']
            if c['received'] - base >= cb.sent and done >= c['received']:
                return
            time.sleep(0.005)
        raise TimeoutError(f'node did not take cloud {cb.sent} within {timeout} s')
    cb.sent = 0
    return cb


def check_estimates(h, inputs, up):
    """Every input has exactly one estimate, completed cloud and pose; all geometric checks."""
    by_stamp = {stamp_ns(e.header): e for e in h.estimates}
    completed = {stamp_ns(m.header): m for m in h.completed}
    poses = {stamp_ns(m.header): m for m in h.poses}
    assert sorted(by_stamp) == sorted(ns for ns, _ in inputs), 'every object gets one estimate'
    up = np.asarray(up, float) / np.linalg.norm(up)
    for ns, pts in inputs:
        e = by_stamp[ns]
        assert e.header.frame_id == 'camera'
        assert e.label in list(e.class_names) + ['unknown']
        assert np.isfinite(e.probability) and 0.0 <= e.probability <= 1.0
        p = e.pose.position
        pos = np.array([p.x, p.y, p.z])
        q = e.pose.orientation
        quat = np.array([q.x, q.y, q.z, q.w])
        assert np.isfinite(pos).all() and np.isfinite(quat).all()
        centroid = np.asarray(pts, float).mean(axis=0)
        assert np.linalg.norm(pos - centroid) < 0.3, (pos, centroid)
        # up axis respected: the object's vertical axis is the given up vector, so the only
        # free rotation is the yaw about it
        r = quaternion_to_rotation(quat)
        np.testing.assert_allclose(r[:, 2], up, atol=1e-3)
        assert abs(np.linalg.det(r) - 1.0) < 1e-3
        ps = poses[ns]
        assert ps.header.frame_id == 'camera'
        np.testing.assert_allclose([ps.pose.position.x, ps.pose.position.y, ps.pose.position.z],
                                   pos, atol=1e-6)
        cc = completed[ns]
        assert cc.header.frame_id == 'camera'
        cpts, dropped = cloud_to_xyz(cc)
        assert dropped == 0 and np.isfinite(cpts).all()
        if len(cpts):
            assert np.linalg.norm(cpts.mean(axis=0) - centroid) < 0.3
            assert np.linalg.norm(cpts - centroid, axis=1).max() < 1.0
    return by_stamp


def result_key(by_stamp):
    """(label, yaw) per stamp, the yaw taken from the best hypothesis."""
    return {ns: (e.label, round(float(e.hypotheses[0].yaw), 6) if len(e.hypotheses) else None)
            for ns, e in by_stamp.items()}


# ------------------------------------------------------------------------------------------
# tests
# ------------------------------------------------------------------------------------------

@pytest.mark.parametrize('storage', bag.STORAGES)
def test_replay_into_node_every_object_estimated(harness, tmp_path, storage):
    p = tmp_path / 'boxes'
    inputs = write_box_bag(p, 6, 50_000_000, storage)
    h = harness()
    stats = h.replay(p, rate=0, on_publish=lockstep(h))
    assert stats.messages == 6
    c = h.wait_idle()
    assert c['received'] == 6 and c['processed'] == 6 and c['dropped_stale'] == 0
    check_estimates(h, inputs, UP)


def test_replay_same_bag_same_outputs(harness, tmp_path):
    p = tmp_path / 'boxes'
    inputs = write_box_bag(p, 5, 50_000_000)
    runs = []
    for _ in range(2):
        h = harness()
        h.replay(p, rate=0, on_publish=lockstep(h))
        h.wait_idle()
        runs.append(result_key(check_estimates(h, inputs, UP)))
    assert runs[0] == runs[1]


def test_replay_up_axis_respected_other_up(harness, tmp_path):
    """Same clouds rotated so that up is +z: poses rotate about +z (the node's up_vector)."""
    fwd = np.array([0.0, 0.0, 1.0]) - UP * UP[2]
    fwd /= np.linalg.norm(fwd)
    r = np.stack([fwd, np.cross(UP, fwd), UP])   # rows: new axes; UP -> +z
    assert np.linalg.det(r) == pytest.approx(1.0)
    np.testing.assert_allclose(r @ UP, [0, 0, 1], atol=1e-9)
    p = tmp_path / 'boxes_z'
    inputs = []
    with bag.BagWriter(p, 'mcap') as w:
        for i in range(4):
            ns = T0 + i * 10**8
            pts = (box_view(i) @ r.T).astype(np.float32)
            w.write('/beo/input', xyz_to_cloud(pts, Header(stamp=to_time(ns), frame_id='camera')),
                    ns)
            inputs.append((ns, pts))
    h = harness(up=[0.0, 0.0, 1.0])
    h.replay(p, rate=0, on_publish=lockstep(h))
    h.wait_idle()
    check_estimates(h, inputs, [0.0, 0.0, 1.0])


def test_replay_osd_scenes(harness, tmp_path):
    """Real Kinect objects via beo-pcd2bag, replayed with the scene's up vector."""
    scene = DATA / 'osd' / 'learn' / 'learn33.pcd'
    if not scene.is_file():
        pytest.skip(f'OSD scans not found under {DATA}')
    out = tmp_path / 'osd'
    summary = bag.pcd_to_bag([scene], out, object_period=0.1)
    up = summary['scenes'][0]['up']
    inputs = [(o['stamp_ns'], cloud_to_xyz(m)[0])
              for o, (_, m, _) in zip(summary['scenes'][0]['objects'],
                                      bag.read_messages(out, {'/beo/input'}))]
    h = harness(up=up)
    stats = h.replay(out, rate=0, on_publish=lockstep(h))
    assert stats.topics['/beo/input'].count == len(inputs) > 0
    h.wait_idle()
    check_estimates(h, inputs, up)


def rss_mb():
    with open('/proc/self/status') as f:
        for line in f:
            if line.startswith('VmRSS:'):
                return int(line.split()[1]) / 1024.0
    return float('nan')


def processing_seconds(h, path):
    """Fastest seconds per cloud, receipt to estimate, of a bag replayed in lockstep once the
    node's warm-up is done (the estimates' own ``latency``: this replay's clouds only). The
    fastest, not the median: this machine stalls the whole process now and then for up to
    seconds (one cloud: convert 0.5 s, estimate 1.7 s, publish 0.5 s, against 0 / 10 / 1 ms),
    and a stall only makes a cloud slower."""
    assert h.node.wait_ready(60)
    with h.lock:
        h.estimates.clear()
    h.replay(path, rate=0, on_publish=lockstep(h))
    h.wait_idle()
    with h.lock:
        latency = [e.latency for e in h.estimates]
    assert latency
    return float(np.min(latency))


@pytest.mark.parametrize('speedup', [2, 10])
def test_replay_faster_than_processing(harness, tmp_path, speedup):
    """Input at 2x / 10x the processing rate: stale clouds are dropped and counted, memory stays
    bounded, and the newest cloud is the one processed (the last estimate is the last cloud)."""
    h = harness()
    warm = tmp_path / 'warm'
    write_box_bag(warm, 5, 10**8, spacing=0.003)
    proc0 = processing_seconds(h, warm)
    n = 40 if speedup == 2 else 80
    period = max(int(proc0 / speedup * 1e9), 1_000_000)
    p = tmp_path / f'fast{speedup}'
    inputs = write_box_bag(p, n, period, spacing=0.003)   # 13-25k points, ~250 kB each
    burst_mb = sum(pts.nbytes for _, pts in inputs) / 2**20
    rss = []
    for burst in range(2):   # the second burst must not grow memory: nothing queues up
        # The second burst is replayed at the rate measured just before it. A load on the
        # machine that ended between the bursts once left it slower than the node (CI,
        # 2026-11-23: 272 ms per cloud measured before the first burst, ~12 ms in the second).
        proc = proc0 if burst == 0 else processing_seconds(h, warm)
        rate = proc0 / proc   # burst 0: 1.0, the bag's own timing
        c0 = h.node.counters()
        with h.lock:
            h.estimates.clear()
            h.diags.clear()
        t = time.monotonic()
        stats = h.replay(p, rate=rate)
        send_s = time.monotonic() - t
        c = h.wait_idle()
        rss.append(rss_mb())
        d = {k: c[k] - c0[k] for k in c}
        assert stats.messages == n
        assert 0 < d['received'] <= n
        assert d['dropped_stale'] > 0, d
        assert d['processed'] < n, d
        assert d['processed'] + d['dropped_stale'] + d['rejected'] + d['errors'] == d['received']
        # the newest cloud wins: estimates in stamp order, the last one is the last cloud sent
        with h.lock:
            stamps = [stamp_ns(e.header) for e in h.estimates]
        assert stamps == sorted(stamps) and len(stamps) == d['processed']
        assert stamps[-1] == inputs[-1][0]
        # dropped clouds are reported on /diagnostics
        time.sleep(0.3)
        with h.lock:
            diag = [dict((kv.key, kv.value) for kv in s.values)
                    for a in h.diags for s in a.status if s.hardware_id == 'beo_ros']
        assert diag and int(diag[-1]['dropped_stale']) == c['dropped_stale']
        print(f'speedup {speedup} burst {burst}: proc {proc * 1e3:.1f} ms/cloud, sent {n} '
              f'({burst_mb:.0f} MB) in {send_s:.2f} s = {n / send_s:.0f} msg/s, processed '
              f'{d["processed"]}, dropped {d["dropped_stale"]}, RSS {rss[-1]:.0f} MB')
    assert rss[1] - rss[0] < max(8.0, 0.25 * burst_mb), (rss, burst_mb)


def test_demo_runs_end_to_end(tmp_path, ros_tiny_model_dir):
    """beo-demo on the tiny bank: every rendered view gets an estimate, table + PNG written."""
    try:
        from beo_ros.ros.conversions import interfaces
        interfaces()
    except ImportError as e:
        pytest.skip(f'beo_interfaces not built ({e}); run scripts/setup')
    from beo_ros.ros import demo
    out = tmp_path / 'demo_out'
    t = time.monotonic()
    assert demo.main(['--out', str(out), '--model', str(ros_tiny_model_dir)]) == 0
    import json
    res = json.loads((out / 'results.json').read_text())
    assert res['inputs'] == res['estimated'] >= 2
    assert all(r['label'] is not None and r['completed_points'] >= 0 for r in res['results'])
    # turns (deg) under which the completed shape looks the same: quarter turns only
    assert all(set(r['symmetric_turns_deg']) <= {90, 180, 270} for r in res['results'])
    png = out / 'beo_demo.png'
    assert png.is_file() and png.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'
    print(f'demo on the tiny bank: {time.monotonic() - t:.1f} s')


def test_demo_counters_count_every_published_estimate(tmp_path, ros_tiny_model_dir,
                                                      monkeypatch):
    """results.json's node_counters are taken once the node's workers are done: a worker
    counts a cloud 'processed' after publishing it, and the snapshot taken as the last estimate
    arrived said 'processed': 9 with 10 of 10 estimated (here forced by a slow count)."""
    try:
        from beo_ros.ros.conversions import interfaces
        interfaces()
    except ImportError as e:
        pytest.skip(f'beo_interfaces not built ({e}); run scripts/setup')
    from beo_ros.ros import demo
    from beo_ros.ros.node import BeoNode
    count = BeoNode._count

    def slow_count(self, key, n=1):
        if key == 'processed':
            time.sleep(0.5)
        count(self, key, n)
    monkeypatch.setattr(BeoNode, '_count', slow_count)
    out = tmp_path / 'demo_out'
    assert demo.main(['--out', str(out), '--model', str(ros_tiny_model_dir)]) == 0
    import json
    res = json.loads((out / 'results.json').read_text())
    c = res['node_counters']
    assert res['estimated'] == res['inputs'] == c['received'] == c['processed'], c


def test_demo_on_a_full_disk_is_one_line_exit_2(tmp_path, ros_tiny_model_dir, monkeypatch,
                                                capsys):
    """The demo bag written with sqlite3 storage onto a full disk. Before: a traceback of
    sqlite3.OperationalError (only OSError was caught); now one line, exit 2, no --out left."""
    import sqlite3

    from beo_ros.ros import demo

    def full_disk(*args, **kwargs):
        raise sqlite3.OperationalError('disk I/O error')
    monkeypatch.setattr(demo, 'write_bag', full_disk)
    out = tmp_path / 'demo_out'
    assert demo.main(['--out', str(out), '--model', str(ros_tiny_model_dir), '--storage',
                      'sqlite3']) == 2
    err = capsys.readouterr().err
    assert err == 'beo-demo: error: disk I/O error\n', err
    assert not out.exists()


def test_demo_that_cannot_start_ros_says_so_in_one_line(tmp_path, ros_tiny_model_dir,
                                                         monkeypatch, capsys):
    """ROS_DOMAIN_ID=abc: one line and exit code 1, as beo-node. Before: a traceback of
    rclpy's RCLError."""
    from beo_ros.ros import demo
    monkeypatch.setenv('ROS_DOMAIN_ID', 'abc')
    out = tmp_path / 'demo_out'
    assert demo.main(['--out', str(out), '--model', str(ros_tiny_model_dir)]) == 1
    err = capsys.readouterr().err
    assert err.startswith('beo-demo: cannot start ROS: RCLError: ') and err.count('\n') == 1, err
    assert not out.exists()


def test_demo_default_model(tmp_path):
    """beo-demo as shipped: no --model, the shipped model (skipped until it is in models/)."""
    try:
        from beo_ros.ros.conversions import interfaces
        interfaces()
    except ImportError as e:
        pytest.skip(f'beo_interfaces not built ({e}); run scripts/setup')
    from beo_ros.ros import demo
    if not (Path(demo._default_model_dir()) / 'manifest.json').is_file():
        pytest.skip(f'no shipped model at {demo._default_model_dir()}')
    out = tmp_path / 'demo_out'
    t = time.monotonic()
    assert demo.main(['--out', str(out)]) == 0
    import json
    res = json.loads((out / 'results.json').read_text())
    assert res['inputs'] == res['estimated'] == len(res['results']) >= 2
    assert (out / 'beo_demo.png').is_file()
    print(f'demo on the shipped model: {time.monotonic() - t:.1f} s, '
          f'{res["correct"]}/{res["inputs"]} labels right')


def test_demo_figure_takes_class_names_with_dollar_signs(tmp_path):
    """Class names may hold '$' (they name files): the demo's panel titles are plain text, not
    mathtext ('p$$q' failed the savefig with a ParseException)."""
    from beo_ros.ros import demo
    rng = np.random.default_rng(0)
    inputs = [dict(stamp_ns=i, true_class=name, points=rng.normal(size=(50, 3)))
              for i, name in enumerate(('p$$q', 'a$_$', 'box'))]
    rows = [dict(label=name, true_class=name, probability=0.5)
            for name in ('p$$q', 'a$x$', 'box')]
    demo.plot(inputs, rows, {0: rng.normal(size=(20, 3))}, tmp_path / 'demo.png')
    assert (tmp_path / 'demo.png').stat().st_size > 0
