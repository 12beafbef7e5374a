"""The core is ROS-free: no ROS imports under beo_ros/core, and ``import beo_ros`` loads no rclpy."""
import ast
import subprocess
import sys
from pathlib import Path

CORE = Path(__file__).resolve().parents[1] / 'beo_ros' / 'core'
FORBIDDEN_ROOTS = {'rclpy', 'rosbags', 'beo_interfaces', 'rosidl_runtime_py', 'launch_ros'}


def _imports(path):
    tree = ast.parse(path.read_text(), filename=str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                yield a.name
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            yield node.module


def _forbidden(name):
    root = name.split('.')[0]
    return root in FORBIDDEN_ROOTS or root.endswith('_msgs')


def test_forbidden_detector():
    assert _forbidden('rclpy.node') and _forbidden('sensor_msgs.msg')
    assert _forbidden('beo_interfaces.srv') and _forbidden('rosbags.highlevel')
    assert not _forbidden('numpy') and not _forbidden('scipy.ndimage')


def test_core_modules_do_not_import_ros():
    files = sorted(CORE.glob('*.py'))
    assert len(files) >= 8, files
    bad = [(f.name, m) for f in files for m in _imports(f) if _forbidden(m)]
    assert not bad, f'ROS imports in beo_ros/core: {bad}'


def test_import_beo_ros_does_not_load_rclpy():
    code = ('import sys, beo_ros, beo_ros.core.bank, beo_ros.core.training, '
            'beo_ros.core.synthetic\n'
            'bad = sorted(m for m in sys.modules if m.split(".")[0] in '
            '("rclpy", "rosbags", "beo_interfaces") or m.split(".")[0].endswith("_msgs"))\n'
            'print(bad)\n'
            'assert not bad, bad\n')
    r = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, timeout=120,
                       cwd=str(CORE.parents[1]))
    assert r.returncode == 0, r.stdout + r.stderr
    assert r.stdout.strip() == '[]'
