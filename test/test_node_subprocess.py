"""The node as a separate process: stream -> ~/estimates, clean SIGINT exit, bad model_dir exit."""
import ast
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import yaml
from std_msgs.msg import Header

from beo_ros.ros.conversions import xyz_to_cloud

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / 'config' / 'beo.yaml'


def node_env(domain_id):
    env = dict(os.environ)
    env['ROS_DOMAIN_ID'] = str(domain_id)
    env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    env['PYTHONUNBUFFERED'] = '1'
    env['PYTHONPATH'] = os.pathsep.join([str(ROOT)] + [p for p in [env.get('PYTHONPATH')] if p])
    return env


def node_command():
    """The console script when installed next to this python, else ``python -m beo_ros.node``."""
    script = Path(sys.executable).parent / 'beo-node'
    return [str(script)] if script.exists() else [sys.executable, '-m', 'beo_ros.node']


@pytest.mark.usefixtures('ros_interfaces')
def test_missing_model_dir_exits_nonzero(tmp_path, ros_domain_id):
    missing = tmp_path / 'no_such_model_dir'
    for cmd in (node_command(), [sys.executable, '-m', 'beo_ros.node']):
        proc = subprocess.run(cmd + ['--ros-args', '-p', f'model_dir:={missing}'],
                              env=node_env(ros_domain_id), cwd=ROOT, capture_output=True,
                              text=True, timeout=60)
        assert proc.returncode != 0, proc
        assert str(missing) in proc.stderr
        assert 'Traceback' not in proc.stderr, proc.stderr


def _feed_until(done, proc, executor, pub, cloud, timeout=90.0):
    """Publish ``cloud`` every 0.5 s and spin ``executor`` until ``done()`` or ``timeout`` s;
    the node process ``proc`` must stay up meanwhile."""
    t0, last = time.monotonic(), float('-inf')
    while not done() and time.monotonic() - t0 < timeout:
        assert proc.poll() is None, proc.communicate()
        if time.monotonic() - last > 0.5:
            pub.publish(cloud)
            last = time.monotonic()
        executor.spin_once(timeout_sec=0.05)


@pytest.mark.usefixtures('ros_interfaces')
def test_node_process_streams_and_stops_on_sigint(ros_tiny_model_dir, ros_domain_id,
                                                  monkeypatch):
    import rclpy
    from beo_interfaces.msg import ObjectEstimate
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import PointCloud2
    from _shapes import box_view

    # in a namespace: the parameter file must still apply (its key is /**/beo)
    proc = subprocess.Popen(
        node_command() + ['--ros-args', '--params-file', str(CONFIG), '-r', '__ns:=/robot1',
                          '-p', f'model_dir:={ros_tiny_model_dir}'],
        env=node_env(ros_domain_id), cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        text=True)
    monkeypatch.setenv('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    ctx = Context()
    rclpy.init(context=ctx, domain_id=ros_domain_id)
    node = rclpy.create_node('beo_subprocess_client', context=ctx)
    got = threading.Event()
    estimates = []

    def on_estimate(msg):
        estimates.append(msg)
        got.set()

    try:
        node.create_subscription(ObjectEstimate, '/robot1/beo/estimates', on_estimate, 10)
        pub = node.create_publisher(PointCloud2, '/beo/input', qos_profile_sensor_data)
        cloud = xyz_to_cloud(box_view(), Header(frame_id='camera'))
        executor = SingleThreadedExecutor(context=ctx)
        executor.add_node(node)
        t0 = time.monotonic()
        _feed_until(got.is_set, proc, executor, pub, cloud)
        if not got.is_set():
            proc.send_signal(signal.SIGINT)
            out, err = proc.communicate(timeout=30)
            pytest.fail(f'no estimate from the node process in {time.monotonic() - t0:.0f} s; '
                        f'rc {proc.returncode}, stderr:\n{err}')
        print(f'first estimate {time.monotonic() - t0:.2f} s after start, '
              f'label {estimates[0].label}, latency {estimates[0].latency * 1e3:.1f} ms')
        assert estimates[0].header.frame_id == 'camera'
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
        try:
            out, err = proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            out, err = proc.communicate()
            pytest.fail(f'node did not exit on SIGINT:\n{err}')
    assert proc.returncode == 0, err
    assert 'Traceback' not in err and 'never retrieved' not in err, err
    assert '2 worker process(es)' in err, err     # config/beo.yaml's workers, namespaced


@pytest.mark.usefixtures('ros_interfaces')
@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGTERM], ids=['SIGINT', 'SIGTERM'])
def test_a_signal_deletes_the_markers_before_the_node_exits(ros_tiny_model_dir, ros_domain_id,
                                                            monkeypatch, sig):
    """Ctrl-C (or the SIGTERM of ros2 launch or docker stop) to beo-node: a DELETEALL on
    ~/markers, the last of them, before it exits 0, and at once (not at the next tick of its
    diagnostics timer, 60 s here). rclpy's own signal handlers shut the ROS context down
    first: nothing was left to send the DELETEALL on, and the objects stayed up in RViz for
    their marker lifetime (up to an hour)."""
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import PointCloud2
    from visualization_msgs.msg import Marker, MarkerArray
    from _shapes import box_view

    proc = subprocess.Popen(
        node_command() + ['--ros-args', '-p', f'model_dir:={ros_tiny_model_dir}',
                          '-p', 'diagnostics_period:=60.0'],
        env=node_env(ros_domain_id), cwd=ROOT, stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE, text=True)
    monkeypatch.setenv('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    ctx = Context()
    rclpy.init(context=ctx, domain_id=ros_domain_id)
    node = rclpy.create_node('beo_marker_client', context=ctx)
    actions = []
    try:
        node.create_subscription(MarkerArray, '/beo/markers',
                                 lambda msg: actions.extend(m.action for m in msg.markers), 10)
        pub = node.create_publisher(PointCloud2, '/beo/input', qos_profile_sensor_data)
        cloud = xyz_to_cloud(box_view(), Header(frame_id='camera'))
        executor = SingleThreadedExecutor(context=ctx)
        executor.add_node(node)
        _feed_until(lambda: Marker.ADD in actions, proc, executor, pub, cloud)
        assert Marker.ADD in actions, 'no markers from the node process'
        proc.send_signal(sig)
        end = time.monotonic() + 30
        while proc.poll() is None and time.monotonic() < end:
            executor.spin_once(timeout_sec=0.05)
        end = time.monotonic() + 5   # what it sent last may still be on its way
        while proc.poll() is not None and Marker.DELETEALL not in actions and \
                time.monotonic() < end:
            executor.spin_once(timeout_sec=0.05)
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
        if proc.poll() is None:
            proc.kill()
            pytest.fail(f'node did not exit within 30 s of the signal:\n{proc.communicate()[1]}')
    err = proc.communicate()[1]
    assert proc.returncode == 0, err
    assert 'Traceback' not in err, err
    assert actions[-1] == Marker.DELETEALL, actions


@pytest.mark.usefixtures('ros_interfaces')
@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGTERM], ids=['SIGINT', 'SIGTERM'])
def test_signal_to_the_group_while_worker_processes_start(ros_domain_id, sig):
    """Ctrl-C (or docker stop's SIGTERM) reaches the whole process group while the worker
    processes import and read their copy of the models: the node exits, quietly. (They died
    half-way through reading, and the node waited for ever writing the rest of the models.)
    The shipped model: its pickle is larger than a pipe's buffer, the tiny one's is not."""
    proc = subprocess.Popen(
        node_command() + ['--ros-args', '--params-file', str(CONFIG)],
        env=node_env(ros_domain_id), cwd=ROOT, stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE, text=True, start_new_session=True)
    lines = []
    spawning = threading.Event()

    def read():
        for line in proc.stderr:
            lines.append(line)
            if 'class prior' in line:   # the next step spawns the processes
                spawning.set()

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    try:
        assert spawning.wait(60), ''.join(lines)
        time.sleep(0.5)   # the processes are importing (seconds)
        assert proc.poll() is None, ''.join(lines)
        os.killpg(proc.pid, sig)
        rc = proc.wait(timeout=30)
    except subprocess.TimeoutExpired:
        pytest.fail('the node did not exit:\n' + ''.join(lines))
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    reader.join(timeout=5)
    err = ''.join(lines)
    assert rc == 0, err
    assert 'Traceback' not in err, err
    assert 'worker process(es) ready' not in err   # it was stopped while they started
    end = time.monotonic() + 10
    while time.monotonic() < end:   # the processes go with it
        try:
            os.killpg(proc.pid, 0)
        except ProcessLookupError:
            break
        time.sleep(0.1)
    else:
        ps = subprocess.run(['ps', '-o', 'pid,stat,etime,args', '-g', str(proc.pid)],
                            capture_output=True, text=True).stdout
        pytest.fail(f'processes of the node outlived it:\n{ps}')


def test_config_lists_every_parameter_with_its_default():
    cfg = yaml.safe_load(CONFIG.read_text())['/**/beo']['ros__parameters']
    src = (ROOT / 'beo_ros' / 'ros' / 'params.py').read_text()
    declared = {}
    for call in ast.walk(ast.parse(src)):
        if (isinstance(call, ast.Call) and isinstance(call.func, ast.Name)
                and call.func.id == 'd' and isinstance(call.args[0], ast.Constant)):
            try:
                declared[call.args[0].value] = ast.literal_eval(call.args[1])
            except ValueError:  # computed default (model_dir)
                declared[call.args[0].value] = None
    assert set(cfg) == set(declared)
    # the deployment file runs the estimates in 2 processes (the node's built-in default, for
    # embedding, is none); every other value is the node's default
    deployment = {'workers': 2, 'worker_processes': 2}
    for k, v in declared.items():
        if v is not None:
            want = deployment.get(k, v)
            assert cfg[k] == want and type(cfg[k]) is type(v), k


def test_launch_file_is_valid_python():
    path = ROOT / 'launch' / 'beo.launch.py'
    code = compile(path.read_text(), str(path), 'exec')
    ns = {'__file__': str(path), '__name__': 'beo_launch'}
    exec(code, ns)
    assert callable(ns['generate_launch_description'])
    assert Path(ns['default_params_file']()).resolve() == CONFIG.resolve() or \
        Path(ns['default_params_file']()).name == 'beo.yaml'
    try:
        import launch_ros  # noqa: F401
    except ImportError:
        with pytest.raises(RuntimeError, match='launch'):
            ns['generate_launch_description']()
    else:
        assert ns['generate_launch_description']() is not None
