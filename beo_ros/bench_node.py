"""beo-bench's node phase: a real BeoNode fed by a rosbag2 replay at fixed rates (open loop)
and cloud by cloud (closed loop); :func:`node_bench` gives the ``node`` entry of bench.json.

The replay runs in a process of its own (:func:`_replay_probe`, started by
:func:`_replay_rate`), like ``ros2 bag play``.
"""
from __future__ import annotations

import json
import math
import os
import sys
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np


BAG_HZ = 10.0       # message spacing in the bench bag; replay rate factor = rate / BAG_HZ


def log(*a):
    """A progress line on stderr (beo-bench's log)."""
    print(*a, file=sys.stderr, flush=True)


def _node_clouds(X, n, idx, limit, rng, size=1.0):
    """Rendered partial views (points (m, 3) float32, sensor at the origin) of ``limit`` objects.

    Each cloud is rendered from its own viewpoint, the grid ``size`` metres across (the
    model's scale, as beo-demo renders); it is translated so its sensor is at the origin,
    which is the node's (fixed) ``sensor_origin``."""
    from beo_ros.core.synthetic import random_partial_view, render_view_points
    clouds = []
    for i in idx[:limit]:
        occ = X[i].reshape((n,) * 3) > 0.5
        _, yaw, az, el, _ = random_partial_view(occ, rng)
        pts, origin = render_view_points(occ, yaw, az, el, distance=max(2.0, 2.0 * size),
                                         size=size, rng=rng)
        if len(pts) >= 100:  # the node rejects clouds below min_points; keep real objects
            clouds.append(np.asarray(pts - origin, dtype=np.float32))
    return clouds


def _write_node_bag(path, clouds, n_msgs):
    """A rosbag2 (sqlite3) of ``n_msgs`` clouds on /beo/input, cycling ``clouds``, BAG_HZ apart;
    each header stamp equals its bag stamp (unique, so estimates can be matched to sends)."""
    from std_msgs.msg import Header

    from beo_ros.ros.bag import T0_NS, BagWriter
    from beo_ros.ros.conversions import stamp_from_ns, xyz_to_cloud
    with BagWriter(path) as w:
        for j in range(n_msgs):
            t = T0_NS + int(round(j * 1e9 / BAG_HZ))
            hdr = Header(frame_id='camera', stamp=stamp_from_ns(t))
            w.write('/beo/input', xyz_to_cloud(clouds[j % len(clouds)], hdr), t)


def _pct(a, q):
    return float(np.percentile(a, q)) if len(a) else float('nan')


def _ms(v):
    """Milliseconds ``v`` for the log: 'n/a' for NaN (no or a single estimate)."""
    return format(v, '.0f') if math.isfinite(v) else 'n/a'


def _replay_probe(cfg_json=None):
    """Child process of :func:`node_bench`: a separate ROS process, like ``ros2 bag play``
    plus a consumer. Replays the bag at one rate until ``n`` clouds are sent and records, per
    header stamp, when each cloud was published and when its ``~/estimates`` arrived
    (``time.monotonic``: CLOCK_MONOTONIC, the same clock in every process). Prints JSON."""
    cfg = json.loads(cfg_json if cfg_json is not None else sys.argv[1])
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor

    from beo_ros.ros.bag import replay
    from beo_ros.ros.conversions import interfaces, ns_from_stamp
    ctx = Context()
    rclpy.init(args=[], context=ctx, domain_id=int(cfg['domain']))
    node = rclpy.create_node('beo_bench_player', context=ctx)
    sent, got = {}, {}
    lock = threading.Lock()

    def on_est(m):
        with lock:
            got[ns_from_stamp(m.header.stamp)] = time.monotonic()
    node.create_subscription(interfaces().ObjectEstimate, '/beo/estimates', on_est, 1000)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    th = threading.Thread(target=ex.spin, daemon=True)
    th.start()
    end = time.monotonic() + 20
    while node.count_publishers('/beo/estimates') < 1 and time.monotonic() < end:
        time.sleep(0.05)
    time.sleep(0.5)  # let the node's estimates publisher match our subscription
    stop = threading.Event()
    n = int(cfg['n'])

    def on_publish(topic, data, stamp_ns):
        sent[stamp_ns] = time.monotonic()
        if len(sent) >= n:
            stop.set()
    stats = replay(cfg['bag'], node, topics=['/beo/input'], rate=float(cfg['rate']) / BAG_HZ,
                   stop=stop, on_publish=on_publish, wait_subscribers=1, wait_timeout=20.0)
    quiet = time.monotonic()
    last = -1
    while time.monotonic() - quiet < float(cfg.get('quiet_s', 1.5)):  # estimates still coming
        time.sleep(0.05)
        with lock:
            if len(got) != last:
                last, quiet = len(got), time.monotonic()
    with lock:
        print(json.dumps({'sent': {str(k): v for k, v in sent.items()},
                          'got': {str(k): v for k, v in got.items()}, 'wall_s': stats.wall_s}),
              flush=True)
    rclpy.try_shutdown(context=ctx)   # ends ex.spin()
    th.join(timeout=5.0)
    ex.shutdown(timeout_sec=2.0)
    node.destroy_node()


def bench_domain(pid):
    """The ROS domain id of the node phase for process ``pid``: 215-232, the upper of the
    two ranges whose DDS ports stay clear of Linux's ephemeral ports (ROS 2 "About Domain
    ID"; the tests' subprocesses use 10-99 of the lower one)."""
    return 215 + int(pid) % 18


def _node_ros():
    """The ROS names the node phase uses; raises when ROS, rosbags or beo_interfaces is
    missing."""
    import rclpy
    from rclpy.context import Context
    from rclpy.parameter import Parameter
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import PointCloud2
    from std_msgs.msg import Header

    __import__('rosbags')  # the bag and its player need it
    from beo_ros.ros.conversions import interfaces, ns_from_stamp, stamp_from_ns, xyz_to_cloud
    from beo_ros.ros.node import BeoNode, make_executor
    return SimpleNamespace(
        rclpy=rclpy, Context=Context, Parameter=Parameter,
        qos_profile_sensor_data=qos_profile_sensor_data, PointCloud2=PointCloud2, Header=Header,
        ns_from_stamp=ns_from_stamp, stamp_from_ns=stamp_from_ns, xyz_to_cloud=xyz_to_cloud,
        BeoNode=BeoNode, make_executor=make_executor, msgs=interfaces())


class _BenchNode:
    """The BeoNode under test and a client node (publishes /beo/input, receives
    ``~/estimates``) spun by the executor of beo-node in a thread of their own."""

    def __init__(self, ros, ctx, clouds):
        self.ros, self.ctx, self.clouds = ros, ctx, clouds
        self.node = self.client = self.executor = None
        self.got = {}   # header stamp (ns) -> perf_counter when the estimate arrived
        self.cond = threading.Condition()

    def start(self, bank, args):
        """Create the nodes (``close`` destroys what was created, also after a failure)."""
        ros = self.ros
        overrides = [ros.Parameter('input_topics', value=['/beo/input'])]
        if args.node_workers:
            overrides.append(ros.Parameter('workers', value=int(args.node_workers)))
        if args.node_blas_threads is not None:
            overrides.append(ros.Parameter('blas_threads', value=int(args.node_blas_threads)))
        if args.node_worker_processes >= 0:
            overrides.append(ros.Parameter('worker_processes',
                                           value=int(args.node_worker_processes)))
        self.node = ros.BeoNode('beo', context=self.ctx, bank=bank,
                                parameter_overrides=overrides)
        self.workers = int(self.node.worker_threads)  # threads used (>= worker_processes)
        self.procs = int(self.node.get_parameter('worker_processes').value)
        self.client = ros.rclpy.create_node('beo_bench_client', context=self.ctx)
        self.client.create_subscription(ros.msgs.ObjectEstimate, '/beo/estimates',
                                        self._on_estimate, 1000)
        self.pub = self.client.create_publisher(ros.PointCloud2, '/beo/input',
                                                ros.qos_profile_sensor_data)
        self.executor = ros.make_executor(self.ctx)  # the executor of beo-node
        self.executor.add_node(self.node)
        self.executor.add_node(self.client)
        threading.Thread(target=self.executor.spin, daemon=True).start()

    def _on_estimate(self, m):
        with self.cond:
            self.got[self.ros.ns_from_stamp(m.header.stamp)] = time.perf_counter()
            self.cond.notify_all()

    def send(self, j, stamp_ns):
        """Publish cloud ``j`` (cycling) stamped ``stamp_ns``; perf_counter when sent."""
        hdr = self.ros.Header(frame_id='camera', stamp=self.ros.stamp_from_ns(stamp_ns))
        msg = self.ros.xyz_to_cloud(self.clouds[j % len(self.clouds)], hdr)
        t = time.perf_counter()
        self.pub.publish(msg)
        return t

    def wait_first_estimate(self, timeout=60):
        """Warm-up / discovery: republish until the first estimate arrives."""
        end = time.monotonic() + timeout
        while time.monotonic() < end and not self.got:
            self.send(0, 1)
            with self.cond:
                self.cond.wait_for(lambda: bool(self.got), timeout=0.5)
        if not self.got:   # a node that answers nothing: a failure, not a skipped phase
            raise RuntimeError('no estimate from the node within 60 s')

    def settle(self, timeout=30.0):
        """Wait until the node has accounted for every cloud it received and is idle."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            c = self.node.counters()
            done = c['processed'] + c['dropped_stale'] + c['rejected'] + c['errors']
            backlog = self.node.backlog()
            if done == c['received'] and not backlog['waiting'] and backlog['in_flight'] == 0:
                time.sleep(0.3)  # clouds still in transit?
                if self.node.counters()['received'] == c['received']:
                    return
            time.sleep(0.02)

    def close(self):
        if self.executor is not None:
            self.executor.shutdown(timeout_sec=5.0)
        if self.client is not None:
            self.client.destroy_node()
        if self.node is not None:
            self.node.destroy_node()


def _replay_rate(bench, rate, args, bag_path, domain):
    """Open loop at one rate: the bag replayed by :func:`_replay_probe` in a process of its
    own; the row of ``rates`` in the result."""
    import subprocess
    bench.settle()
    with bench.cond:
        bench.got.clear()
    c0 = bench.node.counters()
    n_send = max(int(round(rate * args.node_duration)), 1)
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain),
               ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    cfg = json.dumps({'bag': str(bag_path), 'rate': rate, 'n': n_send,
                      'domain': domain})
    proc = subprocess.run(
        [sys.executable, '-c', 'from beo_ros.bench_node import _replay_probe; _replay_probe()',
         cfg], env=env, capture_output=True, text=True, timeout=120 + 2 * n_send / rate)
    if proc.returncode != 0:
        raise RuntimeError(f'bag player failed: {proc.stderr[-2000:]}')
    probe = json.loads(proc.stdout.strip().splitlines()[-1])
    bench.settle()
    c1 = bench.node.counters()
    d = {k: c1[k] - c0.get(k, 0) for k in c1}
    row = _rate_row(rate, probe, d, args.node_max_drop)
    log(f"[node] {rate:g} Hz: {row['estimates']}/{row['sent']} estimates, "
        f"{row['objects_per_s']:.2f} out/s, dropped {row['dropped_stale']}, "
        f"lost {row['lost']}, e2e p50 {_ms(row['e2e_p50_ms'])} ms "
        f"p95 {_ms(row['e2e_p95_ms'])} ms")
    return row


def _rate_row(rate, probe, d, max_drop):
    """One rate's row from the player's ``probe`` and the node's counter increments ``d``.

    The latency percentiles (ms) are NaN (n/a) with fewer than 2 estimates: one sample has
    no spread to summarize (``e2e_max_ms`` is the one measured)."""
    sent = {int(k): v for k, v in probe['sent'].items()}
    arrived = {int(k): v for k, v in probe['got'].items() if int(k) in sent}
    lat = np.array([arrived[k] - sent[k] for k in arrived]) * 1e3
    pct = lat if len(lat) >= 2 else lat[:0]   # one estimate: p50 = p95 = it, not a spread
    # output rate: estimates per second from the first to the last estimate
    span = (max(arrived.values()) - min(arrived.values())) if arrived else 0.0
    stats_wall = probe['wall_s']
    row = {
        'rate_hz': rate, 'sent': len(sent),
        'sent_per_s': (len(sent) - 1) / stats_wall if stats_wall > 0 else rate,
        'received': d['received'], 'estimates': len(arrived),
        'dropped_stale': d['dropped_stale'], 'rejected': d['rejected'],
        'errors': d['errors'], 'lost': len(sent) - d['received'],
        'missing_estimates': d['processed'] - len(arrived),
        'order_waits': d.get('order_waits', 0),
        'objects_per_s': (len(arrived) - 1) / span if span > 0 else 0.0,
        'e2e_p50_ms': _pct(pct, 50), 'e2e_p95_ms': _pct(pct, 95),
        'e2e_max_ms': float(lat.max()) if len(lat) else float('nan'),
    }
    row['sustained'] = bool(row['dropped_stale'] <= max_drop * row['sent']
                            and row['lost'] == 0 and row['rejected'] == 0
                            and row['errors'] == 0 and row['missing_estimates'] == 0)
    return row


def _closed_loop(bench, rounds):
    """Latency without queueing: the next cloud is published when the previous estimate
    arrived, ``rounds`` times over the clouds."""
    bench.settle()
    lat, lost, busy = [], 0, 0.0
    for j in range(len(bench.clouds) * rounds):
        stamp = 1000 + j
        t_sent = bench.send(j, stamp)
        with bench.cond:
            ok = bench.cond.wait_for(lambda: stamp in bench.got, timeout=30)
        if ok:  # time waiting for lost clouds is not counted in the rate
            lat.append(bench.got[stamp] - t_sent)
            busy += time.perf_counter() - t_sent
        else:
            lost += 1
    lat = np.asarray(lat) * 1e3
    return {'objects': int(len(lat)), 'lost': int(lost),
            'objects_per_s': float(len(lat) / max(busy, 1e-9)),
            'e2e_p50_ms': _pct(lat, 50), 'e2e_p95_ms': _pct(lat, 95)}


def _node_result(per_rate, closed, core, counters, workers, procs, clouds, rates, args):
    """The ``node`` entry of bench.json: the highest sustained rate, all rows, the closed loop
    and the node's stage latencies (``core``, s) and counters."""
    sustained = [r for r in per_rate if r['sustained']]
    best = max(sustained, key=lambda r: r['rate_hz']) if sustained else per_rate[0]
    return {
        # headline: the highest replay rate the node kept up with (no drops, nothing lost)
        'max_drop_fraction': float(args.node_max_drop),
        'objects_per_s': best['objects_per_s'], 'sustained_rate_hz': (
            best['rate_hz'] if sustained else None),
        'e2e_p50_ms': best['e2e_p50_ms'], 'e2e_p95_ms': best['e2e_p95_ms'],
        'objects': int(best['estimates']), 'lost': int(best['lost']),
        'dropped_stale': int(best['dropped_stale']),
        'max_objects_per_s': max(r['objects_per_s'] for r in per_rate),
        'rates': per_rate, 'closed_loop': closed, 'workers': workers,
        'worker_processes': procs,
        'duration_s': float(args.node_duration), 'clouds': len(clouds),
        'cloud_points_median': float(np.median([len(c) for c in clouds])),
        'node_stage_p50_ms': {k: v * 1e3 for k, v in core.items()},
        'node_counters': counters,
        'mode': (f'open loop: rosbag2 of {len(clouds)} rendered clouds replayed by a separate '
                 f'process (beo-replay\'s replay(), which also receives the estimates) at '
                 f'{", ".join(f"{r:g}" for r in rates)} Hz for {args.node_duration:g} s each '
                 f'into BeoNode (workers={workers}, worker_processes={procs}, '
                 f'SingleThreadedExecutor); sustained = stale '
                 f'drops <= {args.node_max_drop:g} of the clouds, nothing lost'),
    }


def node_bench(bank, X, n, idx, args, rng):
    """A real BeoNode fed by a rosbag2 replay (open loop) at fixed rates, plus a closed loop.

    Open loop (the sustained rate): for every rate in ``--node-rates`` the bench bag is replayed
    with :func:`beo_ros.ros.bag.replay` (real rclpy publisher, one cloud every 1/rate s, for
    ``--node-duration`` s) whatever the node does; estimates out per second, stale drops (the
    node keeps only the newest unprocessed cloud per topic), clouds lost in transport and
    publish -> ``~/estimates`` latency are measured per rate. A rate is sustained when at most
    ``--node-max-drop`` of its clouds were dropped as stale and none was lost, rejected or left
    without an estimate. Closed loop (latency without queueing): the next cloud is published
    when the previous estimate arrived.
    """
    # the bag player runs in its own process (like ros2 bag play), so discovery stays on the
    # local host, on a domain of our own
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    domain = bench_domain(os.getpid())
    try:
        import tempfile
        ros = _node_ros()
    except Exception as e:  # noqa: BLE001 - ROS, rosbags or interfaces missing
        return {'skipped': f'{type(e).__name__}: {e}'}

    spec = bank.spec   # a metric grid spans size * voxel_size metres: render at that scale
    size = spec.size * spec.voxel_size if spec.units == 'metric' else 1.0
    clouds = _node_clouds(X, n, idx, args.node_objects, rng, size=size)
    if not clouds:
        return {'skipped': 'no objects'}
    rates = sorted(float(r) for r in args.node_rates)
    n_msgs = int(math.ceil(max(rates) * args.node_duration)) + 1
    tmp = tempfile.TemporaryDirectory(prefix='beo_bench_bag_')
    bag_path = Path(tmp.name) / 'clouds'
    _write_node_bag(bag_path, clouds, n_msgs)

    ctx = ros.Context()
    ros.rclpy.init(args=[], context=ctx, domain_id=domain)
    bench = _BenchNode(ros, ctx, clouds)
    try:
        bench.start(bank, args)
        bench.wait_first_estimate()
        per_rate = [_replay_rate(bench, rate, args, bag_path, domain) for rate in rates]
        closed = _closed_loop(bench, args.node_rounds)
        core = bench.node.latency_p50()
        counters = bench.node.counters()
    finally:
        bench.close()
        ros.rclpy.try_shutdown(context=ctx)
        tmp.cleanup()
    return _node_result(per_rate, closed, core, counters, bench.workers, bench.procs, clouds,
                        rates, args)
