"""Helpers shared by the bag test modules (test_bag.py, test_bag_tools.py): generated clouds
and bags, a labelled PCD scene, and running the command-line tools in subprocesses."""
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from builtin_interfaces.msg import Time
from std_msgs.msg import Header, String

from beo_ros.ros import bag
from beo_ros.ros.conversions import xyz_to_cloud

REPO = Path(__file__).resolve().parents[1]
T0 = 1_700_000_000_000_000_000


def stamp(ns):
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def make_cloud(i, n=50, frame='camera', ns=None):
    rng = np.random.default_rng(i)
    pts = rng.normal(size=(n, 3)).astype(np.float32) * 0.1 + np.float32(i)
    return pts, xyz_to_cloud(pts, Header(stamp=stamp(ns if ns is not None else T0 + i),
                                         frame_id=frame))


def write_test_bag(path, storage, n=10, period_ns=10_000_000, extra_topic=True):
    """n clouds on /beo/input (stamps T0 + i*period), and a String every 2nd step on /chatter."""
    clouds = []
    with bag.BagWriter(path, storage) as w:
        for i in range(n):
            ns = T0 + i * period_ns
            pts, msg = make_cloud(i, ns=ns)
            clouds.append(pts)
            w.write('/beo/input', msg, ns)
            if extra_topic and i % 2 == 0:
                w.write('/chatter', String(data=f'hello {i}'), ns + 1)
    return clouds


def write_scene_pcd(path, labels=True, objects=True):
    """A labelled organized scene as the OSD ones: a table 0.3 m below the camera (label 1) and
    a box on it (label 20, or 1 with objects=False); no label field with labels=False."""
    from beo_ros.core.pcd import write_pcd
    rng = np.random.default_rng(0)
    m, k = 600, 300
    table = np.c_[rng.uniform(-0.4, 0.4, m), np.full(m, 0.3), rng.uniform(0.6, 1.4, m)]
    box = np.c_[rng.uniform(-0.05, 0.05, k), rng.uniform(0.2, 0.3, k), rng.uniform(0.95, 1.05, k)]
    pts = np.r_[table, box].astype(np.float32)
    fields = {'x': pts[:, 0], 'y': pts[:, 1], 'z': pts[:, 2]}
    if labels:
        fields['label'] = np.r_[np.ones(m), np.full(k, 20 if objects else 1)].astype(np.uint32)
    write_pcd(path, fields, width=(m + k) // 3, height=3)
    return path


def cli_env(domain):
    env = dict(os.environ)
    env['ROS_DOMAIN_ID'] = str(domain)
    env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    env['PYTHONPATH'] = str(REPO) + os.pathsep + env.get('PYTHONPATH', '')
    return env


def wait_for_nodes(domain, names, timeout=60.0):
    """Block until nodes ``names`` (of other processes) are in domain ``domain``'s graph."""
    import rclpy
    from rclpy.context import Context
    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain)
    try:
        node = rclpy.create_node('beo_test_watcher', context=ctx)
        end = time.monotonic() + timeout
        while not names <= set(node.get_node_names()) and time.monotonic() < end:
            time.sleep(0.1)
        assert names <= set(node.get_node_names()), f'{names} never appeared'
        node.destroy_node()
    finally:
        ctx.try_shutdown()


def signal_loop_replay(tmp_path, ros_domain_id, sig, settle=0.0):
    """Run ``beo-replay BAG --loop`` in a subprocess, send it ``sig`` once its node is up (and
    ``settle`` s later); -> (exit code, stdout, stderr)."""
    write_test_bag(tmp_path / 'b', 'sqlite3', n=3)
    code = 'import sys; from beo_ros.ros.bag import replay_main; sys.exit(replay_main(sys.argv[1:]))'
    p = subprocess.Popen([sys.executable, '-c', code, str(tmp_path / 'b'), '--loop'],
                         env=cli_env(ros_domain_id), stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    try:
        wait_for_nodes(ros_domain_id, {'beo_replay'})
        time.sleep(settle)
        p.send_signal(sig)
        out, err = p.communicate(timeout=30)
    finally:
        if p.poll() is None:
            p.kill()
    return p.returncode, out, err
