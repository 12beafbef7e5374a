"""The core is ROS-free: no ROS imports under beo_ros/core, and ``import beo_ros`` loads no rclpy."""
import ast
import subprocess
import sys
from pathlib import Path

CORE = Path(__file__).resolve().parents[1] / 'beo_ros' / 'core'
FORBIDDEN_ROOTS = {'rclpy', 'rosbags', 'beo_interfaces', 'rosidl_runtime_py', 'launch_ros'}


def _imports(path, package='beo_ros.core'):
    """Absolute names of the modules ``path`` imports (relative imports resolved against
    ``package``, the package the file is in)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                yield a.name
        elif isinstance(node, ast.ImportFrom):
            base = package.split('.')
            base = base[:len(base) - node.level + 1] if node.level else []
            if node.module:
                yield '.'.join(base + [node.module])
            else:   # from . import x, y
                for a in node.names:
                    yield '.'.join(base + [a.name])


def _forbidden(name):
    """ROS runtime or message packages, and any part of beo_ros outside the core (the ROS layer
    and the commands build on the core, never the other way round). ament_index_python is a
    plain file lookup (bank.default_model_dir) and allowed."""
    root = name.split('.')[0]
    if root == 'beo_ros':
        return not (name == 'beo_ros.core' or name.startswith('beo_ros.core.'))
    return root in FORBIDDEN_ROOTS or root.endswith('_msgs')


def test_forbidden_detector():
    assert _forbidden('rclpy.node') and _forbidden('sensor_msgs.msg')
    assert _forbidden('beo_interfaces.srv') and _forbidden('rosbags.highlevel')
    assert _forbidden('beo_ros.ros.node') and _forbidden('beo_ros.evaluate')
    assert not _forbidden('numpy') and not _forbidden('scipy.ndimage')
    assert not _forbidden('beo_ros.core.grid') and not _forbidden('ament_index_python.packages')


def test_relative_imports_are_resolved(tmp_path):
    f = tmp_path / 'm.py'
    f.write_text('from .grid import x\nfrom ..ros import conversions\nfrom .. import cli\n'
                 'from . import bank\nimport numpy\n')
    assert list(_imports(f)) == ['beo_ros.core.grid', 'beo_ros.ros', 'beo_ros.cli',
                                 'beo_ros.core.bank', 'numpy']


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
