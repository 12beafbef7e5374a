"""Static checks of the packaging files: package.xml declares what beo_ros imports, setup.py
installs the model directories, launch/beo.launch.py and scripts/setup keep their fixes."""
import ast
import os
import pathlib
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]

# top-level import -> rosdep key in package.xml (ROS packages are their own key)
IMPORT_KEYS = {
    'numpy': 'python3-numpy',
    'scipy': 'python3-scipy',
    'sklearn': 'python3-sklearn',
    'open3d': 'python3-open3d-pip',
    'trimesh': 'python3-trimesh-pip',
    'rosbags': 'python3-rosbags-pip',
    'apsw': 'python3-rosbags-pip',    # rosbags' sqlite3 reader; bag/storage.py catches its errors
    'ruamel': 'python3-ruamel.yaml',  # bag/storage.py reads metadata.yaml with it
    'matplotlib': 'python3-matplotlib',
    'tqdm': 'python3-tqdm',
    # optional (blas_threads); not a confirmed rosdep key: it comes with python3-sklearn
    'threadpoolctl': 'python3-sklearn',
    'yaml': 'python3-yaml',
    'pytest': 'python3-pytest',
    'tf2_ros': 'tf2_ros_py',
}
# the package itself and the test modules (tests import helpers from each other)
OWN = {'beo_ros', 'conftest', 'test'} | {p.stem for p in (ROOT / 'test').glob('*.py')}


def _package():
    catkin_pkg = pytest.importorskip('catkin_pkg.package')
    pkg = catkin_pkg.parse_package(str(ROOT))
    pkg.validate()
    return pkg


def _top_level_imports(paths):
    """{module: first file importing it} for every absolute import in ``paths``."""
    found = {}
    for path in paths:
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            for name in names:
                found.setdefault(name.split('.')[0], path.relative_to(ROOT))
    return {m: p for m, p in found.items()
            if m not in sys.stdlib_module_names and m not in OWN}


def test_package_xml_is_valid_format3():
    pkg = _package()
    assert pkg.package_format == 3
    assert pkg.name == 'beo_ros'
    assert [e.content for e in pkg.exports if e.tagname == 'build_type'] == ['ament_python']


def test_package_xml_declares_every_import():
    pkg = _package()
    runtime = {d.name for d in pkg.exec_depends}
    tests = {d.name for d in pkg.test_depends} | runtime
    code = _top_level_imports(sorted((ROOT / 'beo_ros').rglob('*.py'))
                              + sorted((ROOT / 'launch').glob('*.py')))
    for module, where in code.items():
        key = IMPORT_KEYS.get(module, module)
        assert key in runtime, f'{where} imports {module}: add <exec_depend>{key}</exec_depend>'
    for module, where in _top_level_imports(sorted((ROOT / 'test').rglob('*.py'))).items():
        key = IMPORT_KEYS.get(module, module)
        assert key in tests, f'{where} imports {module}: add <test_depend>{key}</test_depend>'


def test_package_xml_tooling_deps():
    pkg = _package()
    runtime = {d.name for d in pkg.exec_depends}
    # the package ships a launch file: `ros2 launch` needs ros2launch, launch and launch_ros
    assert {'launch', 'launch_ros', 'ros2launch'} <= runtime
    # setup.cfg configures pytest-timeout (timeout = ..., timeout_method = ...)
    if 'timeout' in (ROOT / 'setup.cfg').read_text():
        assert 'python3-pytest-timeout' in {d.name for d in pkg.test_depends}


# --- setup.py installs the model directories, nested files included ----------------------

def _model_files(monkeypatch, cwd):
    """setup.py's model_files() run in ``cwd`` (without running setup() itself)."""
    tree = ast.parse((ROOT / 'setup.py').read_text())
    keep = [n for n in tree.body
            if (isinstance(n, (ast.Import, ast.ImportFrom)) and 'setuptools' not in ast.dump(n))
            or (isinstance(n, ast.Assign) and ast.unparse(n.targets[0]) == 'package_name')
            or (isinstance(n, ast.FunctionDef) and n.name == 'model_files')]
    ns = {}
    exec(compile(ast.Module(body=keep, type_ignores=[]), 'setup.py', 'exec'), ns)
    monkeypatch.chdir(cwd)
    return ns['model_files']()


def test_model_files_flat_layout_unchanged(monkeypatch):
    """Today's flat models/<name>/* layout: one entry per model dir with its files."""
    import glob
    import os
    got = _model_files(monkeypatch, ROOT)
    want = []
    for d in sorted(glob.glob('models/*/')):
        files = sorted(f for f in glob.glob(os.path.join(d, '*')) if os.path.isfile(f))
        want.append((os.path.join('share', 'beo_ros', d.rstrip('/')), files))
    # the models/<name> entries are what the old top-level-only version gave; anything else
    # comes from subdirectories
    assert [e for e in got if e[0].count('/') == 3] == want
    assert any(d == 'share/beo_ros/models/tabletop_32' for d, _ in got)


def test_model_files_nested(monkeypatch, tmp_path):
    for rel in ('models/a/top.npz', 'models/a/sub/mid.json', 'models/a/sub/deep/low.npz',
                'models/a/.hidden/skip', 'models/a/.skip', 'models/b/only.npz'):
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text('x')
    (tmp_path / 'models' / 'empty').mkdir()
    (tmp_path / 'models' / 'README').write_text('not a model dir')
    got = _model_files(monkeypatch, tmp_path)
    assert got == [
        ('share/beo_ros/models/a', ['models/a/top.npz']),
        ('share/beo_ros/models/a/sub', ['models/a/sub/mid.json']),
        ('share/beo_ros/models/a/sub/deep', ['models/a/sub/deep/low.npz']),
        ('share/beo_ros/models/b', ['models/b/only.npz']),
        ('share/beo_ros/models/empty', []),
    ]


# --- launch/beo.launch.py, run against stand-ins for launch / launch_ros -----------------

def _fake_launch_modules(monkeypatch):
    """Minimal stand-ins recording how the launch file calls the launch/launch_ros API."""
    import types

    class Recorder:
        def __init__(self, *args, **kwargs):
            self.args, self.kwargs = args, kwargs

    class LaunchConfiguration(Recorder):
        def perform(self, context):
            return context[self.args[0]]

    mods = {name: types.ModuleType(name) for name in (
        'launch', 'launch.actions', 'launch.substitutions', 'launch_ros', 'launch_ros.actions',
        'launch_ros.parameter_descriptions')}
    mods['launch'].LaunchDescription = type('LaunchDescription', (Recorder,), {})
    mods['launch.actions'].DeclareLaunchArgument = type('DeclareLaunchArgument', (Recorder,), {})
    mods['launch.actions'].OpaqueFunction = type('OpaqueFunction', (Recorder,), {})
    mods['launch.substitutions'].LaunchConfiguration = LaunchConfiguration
    mods['launch_ros.actions'].Node = type('Node', (Recorder,), {})
    mods['launch_ros.parameter_descriptions'].ParameterValue = type('ParameterValue',
                                                                     (Recorder,), {})
    for name, mod in mods.items():
        monkeypatch.setitem(sys.modules, name, mod)


def _launch_node(monkeypatch, **context):
    _fake_launch_modules(monkeypatch)
    path = ROOT / 'launch' / 'beo.launch.py'
    ns = {'__file__': str(path), '__name__': 'beo_launch'}
    exec(compile(path.read_text(), str(path), 'exec'), ns)
    desc = ns['generate_launch_description']()
    entities = desc.args[0]
    declared = {e.args[0]: e.kwargs for e in entities
                if type(e).__name__ == 'DeclareLaunchArgument'}
    (opaque,) = [e for e in entities if type(e).__name__ == 'OpaqueFunction']
    ctx = {name: kw['default_value'] for name, kw in declared.items()}
    ctx.update(context)
    (node,) = opaque.kwargs['function'](ctx)
    return declared, node.kwargs


def test_launch_arguments(monkeypatch):
    declared, node = _launch_node(monkeypatch)
    assert set(declared) == {'params_file', 'namespace', 'log_level', 'input_topic',
                             'model_dir'}
    assert declared['model_dir']['default_value'] == ''
    desc = declared['input_topic']['description']
    assert '/beo/input' in desc and '~/input' in desc and 'input_topics' in desc
    assert node['package'] == 'beo_ros' and node['executable'] == 'beo_node'
    assert [(a, b.args[0]) for a, b in node['remappings']] == [('/beo/input', 'input_topic')]
    # the log level goes through ros_arguments (launch_ros adds --ros-args ... --)
    assert node['ros_arguments'][0] == '--log-level'
    assert node['ros_arguments'][1].args == ('log_level',)
    assert '--ros-args' not in [a for a in node.get('arguments', []) if isinstance(a, str)]


def test_launch_model_dir_override_only_when_given(monkeypatch):
    _, node = _launch_node(monkeypatch)
    (params_file,) = node['parameters']  # '' keeps the params file's model_dir
    assert params_file.args == ('params_file',)
    _, node = _launch_node(monkeypatch, model_dir='/data/models/2024')
    params_file, override = node['parameters']  # after the params file: it wins
    assert params_file.args == ('params_file',)
    value = override['model_dir']
    assert value.args == ('/data/models/2024',) and value.kwargs == {'value_type': str}


# --- scripts/setup: snippets run in a scratch tree ----------------------------------------

SETUP = ROOT / 'scripts' / 'setup'
PRELUDE = '''set -Eeuo pipefail
die() { printf '[setup] ERROR: %s\\n' "$*" >&2; exit 1; }
step() { :; }
'''


def _snippet(start, end):
    """Lines of scripts/setup from the one starting with ``start`` to the next one equal to
    ``end`` (both included)."""
    lines = SETUP.read_text().splitlines()
    i = next(n for n, ln in enumerate(lines) if ln.startswith(start))
    j = next(n for n in range(i, len(lines)) if lines[n] == end)
    return '\n'.join(lines[i:j + 1]) + '\n'


def _bash(script, **env):
    import shutil
    import subprocess
    bash = shutil.which('bash')
    if bash is None:
        pytest.skip('no bash')
    return subprocess.run([bash, '-c', PRELUDE + script], capture_output=True, text=True,
                          env={'PATH': os.environ.get('PATH', '/usr/bin:/bin'), **env},
                          timeout=60)


def _share_tree(tmp_path):
    root, venv = tmp_path / 'clone', tmp_path / 'venv'
    for rel in ('package.xml', 'config/beo.yaml', 'launch/beo.launch.py', 'models/m/a.npz'):
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_text(rel)
    share = venv / 'share' / 'beo_ros'
    share.mkdir(parents=True)
    script = (f'ROOT={root}\nSHARE={share}\n'
              + _snippet('for item in package.xml models config launch; do', 'done'))
    return root, share, script


def test_setup_share_links_idempotent(tmp_path):
    root, share, script = _share_tree(tmp_path)
    for _ in range(2):
        r = _bash(script)
        assert r.returncode == 0, r.stderr
        for item in ('package.xml', 'models', 'config', 'launch'):
            assert (share / item).is_symlink()
            assert os.readlink(share / item) == str(root / item)
        assert not (root / 'models' / 'models').exists()  # no link inside the target


def test_setup_share_replaces_installed_copy(tmp_path):
    import shutil
    root, share, script = _share_tree(tmp_path)
    shutil.copytree(root / 'models', share / 'models')  # what `pip install .` leaves
    (share / 'models' / 'm' / 'a.npz').write_text('older copy')
    r = _bash(script)
    assert r.returncode == 0, r.stderr
    assert (share / 'models').is_symlink()
    assert os.readlink(share / 'models') == str(root / 'models')
    assert (root / 'models' / 'm' / 'a.npz').read_text() == 'models/m/a.npz'


def test_setup_share_keeps_foreign_files(tmp_path):
    import shutil
    root, share, script = _share_tree(tmp_path)
    shutil.copytree(root / 'models', share / 'models')
    (share / 'models' / 'mine').mkdir()
    (share / 'models' / 'mine' / 'b.npz').write_text('user data')
    r = _bash(script)
    assert r.returncode != 0
    assert 'not in' in r.stderr and 'mine' in r.stderr
    assert (share / 'models' / 'mine' / 'b.npz').read_text() == 'user data'
    assert not (share / 'models').is_symlink()


def _functions():
    """The text of every function scripts/setup defines (step, die, ...)."""
    import re
    lines, out, i = SETUP.read_text().splitlines(), [], 0
    while i < len(lines):
        if re.match(r'[a-z_]+\(\) \{', lines[i]):
            j = i if lines[i].rstrip().endswith('}') else lines.index('}', i)
            out += lines[i:j + 1]
            i = j
        i += 1
    return '\n'.join(out) + '\n'


def test_setup_recreates_a_venv_without_pip(tmp_path):
    # Ctrl-C during `python -m venv` (while ensurepip runs) leaves .venv/bin/python without
    # pip: every re-run reused that venv and failed at `pip install -r requirements.txt`
    import subprocess
    venv = tmp_path / '.venv'
    subprocess.run([sys.executable, '-m', 'venv', '--without-pip', str(venv)], check=True)
    script = (f'VENV={venv}\nPY={sys.executable}\n' + _functions()
              + _snippet('step "python venv at .venv/"', 'VPY="$VENV/bin/python"'))
    r = _bash(script)
    assert r.returncode == 0, r.stderr
    assert 'recreating' in r.stdout
    pip = subprocess.run([str(venv / 'bin' / 'python'), '-m', 'pip', '--version'],
                         capture_output=True)
    assert pip.returncode == 0, pip.stderr
    r = _bash(script)   # a venv with pip is kept
    assert r.returncode == 0, r.stderr
    assert 'reusing' in r.stdout


def test_setup_recreates_a_venv_made_elsewhere(tmp_path):
    # a clone moved (or copied) with its .venv: the venv kept the old path in its scripts and
    # in the CMake files setup had rewritten, and every re-run failed in the interface build
    # ('includes non-existent path <old clone>/.venv/.../numpy/_core/include')
    import subprocess
    old, new = tmp_path / 'old' / '.venv', tmp_path / 'new' / '.venv'
    subprocess.run([sys.executable, '-m', 'venv', str(old)], check=True)
    old.parent.rename(new.parent)

    def run(venv):
        r = _bash(f'VENV={venv}\nPY={sys.executable}\n' + _functions()
                  + _snippet('step "python venv at .venv/"', 'VPY="$VENV/bin/python"'))
        assert r.returncode == 0, r.stderr
        return r.stdout

    assert 'recreating' in run(new)
    cfg = (new / 'pyvenv.cfg').read_text()
    assert f' -m venv {new}\n' in cfg, cfg
    assert 'reusing' in run(new)   # made here: kept
    (tmp_path / 'link').symlink_to(new.parent)   # the same clone through a symlinked path
    assert 'reusing' in run(tmp_path / 'link' / '.venv')


LDD_CHECK = ('# an unmatched glob must not pass', 'echo "    ok"')


def test_setup_ldd_check_fails_clearly_without_libraries(tmp_path):
    venv = tmp_path / 'venv'
    (venv / 'lib' / 'python3.11' / 'site-packages' / 'beo_interfaces').mkdir(parents=True)
    r = _bash(f'VENV={venv}\nLOG=/dev/null\n' + _snippet(*LDD_CHECK))
    assert r.returncode != 0
    assert 'libbeo_interfaces__*.so' in r.stderr


def test_setup_ldd_check_reports_missing_dependency(tmp_path):
    import shutil
    if shutil.which('ldd') is None:
        pytest.skip('no ldd')
    venv = tmp_path / 'venv'
    pkg = venv / 'lib' / 'python3.11' / 'site-packages' / 'beo_interfaces'
    pkg.mkdir(parents=True)
    # stand-in libraries: copies of a real shared library, one with a fake ldd result
    libc_user = next((p for p in map(pathlib.Path, ('/usr/lib/x86_64-linux-gnu/libz.so.1',
                                                     '/lib/x86_64-linux-gnu/libz.so.1'))
                      if p.exists()), None)
    if libc_user is None:
        pytest.skip('no libz.so.1 to stand in for a library')
    shutil.copy(libc_user, venv / 'lib' / 'libbeo_interfaces__a.so')
    shutil.copy(libc_user, pkg / 'ext.so')
    ok = _bash(f'VENV={venv}\nLOG=/dev/null\n' + _snippet(*LDD_CHECK))
    assert ok.returncode == 0, ok.stderr
    # an ldd that reports a missing library first and then writes on: with `ldd | grep -q`
    # under pipefail, grep's early exit kills ldd with SIGPIPE and the miss went unreported
    fake = tmp_path / 'bin'
    fake.mkdir()
    (fake / 'ldd').write_text('#!/bin/sh\necho "\tlibmissing.so.1 => not found"\n'
                              'for i in $(seq 1 50000); do echo "\tlibok$i.so => /x"; done\n')
    (fake / 'ldd').chmod(0o755)
    r = _bash(f'PATH={fake}:$PATH\nVENV={venv}\nLOG=/dev/null\n' + _snippet(*LDD_CHECK))
    assert r.returncode != 0
    assert 'libmissing.so.1' in r.stderr and 'unresolved shared libraries' in r.stderr


def _apt_pkgs():
    line = next(ln for ln in SETUP.read_text().splitlines() if ln.startswith('APT_PKGS=('))
    return set(line[len('APT_PKGS=('):line.index(')')].split())


def test_setup_apt_packages_cover_open3d_libraries():
    """Every system library that open3d's libOpen3D.so needs (readelf NEEDED) comes from a
    package scripts/setup installs (or from the base system)."""
    import shutil
    import subprocess
    pkgs = _apt_pkgs()
    assert {'libegl1', 'libgl1', 'libx11-6', 'libusb-1.0-0', 'libudev1', 'libidn2-0',
            'cmake', 'g++', 'make'} <= pkgs
    if not all(shutil.which(t) for t in ('readelf', 'ldd', 'dpkg')):
        pytest.skip('needs readelf, ldd and dpkg')
    try:
        import importlib.util
        spec = importlib.util.find_spec('open3d')
    except ImportError:
        spec = None
    if spec is None or not spec.submodule_search_locations:
        pytest.skip('open3d not installed')
    libs = sorted(pathlib.Path(spec.submodule_search_locations[0]).glob('libOpen3D.so*'))
    if not libs:
        pytest.skip('no libOpen3D.so in the open3d package')
    base = {'libc6', 'libgcc-s1', 'libstdc++6', 'zlib1g'}  # base system / pulled in by g++
    needed = set()
    for lib in libs:
        out = subprocess.run(['readelf', '-d', str(lib)], capture_output=True, text=True).stdout
        needed |= {ln.split('[')[1].rstrip(']') for ln in out.splitlines() if '(NEEDED)' in ln}
        resolved = subprocess.run(['ldd', str(lib)], capture_output=True, text=True).stdout
        for ln in resolved.splitlines():
            parts = ln.split()
            if len(parts) >= 3 and parts[0] in needed and parts[1] == '=>':
                path = os.path.realpath(parts[2])
                if not path.startswith(('/lib', '/usr/lib')):
                    continue  # shipped inside the wheel
                owner = None
                for cand in (path, path.replace('/usr/lib/', '/lib/', 1),
                             path.replace('/lib/', '/usr/lib/', 1)):
                    q = subprocess.run(['dpkg', '-S', cand], capture_output=True, text=True)
                    if q.returncode == 0:
                        owner = q.stdout.split(':')[0]
                        break
                assert owner is not None, f'{parts[0]} ({path}) belongs to no package'
                assert owner in pkgs | base, (
                    f'{lib.name} needs {parts[0]} from {owner}: add it to APT_PKGS')


def test_setup_failure_is_reported_once_and_names_the_pip_command(tmp_path):
    # before: a failing $(...) printed 'FAILED ... during step' twice (set -E gives the
    # subshell the trap too), and a failing pip was reported as 'line N: pipfilter'
    script = _functions() + 'trap on_err ERR\nstep "a step"\nX="$(false; echo hi)"\n'
    r = _bash(script)
    assert r.returncode == 1
    assert r.stderr.count('FAILED (exit 1) during step: a step') == 1, r.stderr
    fake = tmp_path / 'python'
    fake.write_text('#!/bin/sh\necho "ERROR: No matching distribution" >&2\nexit 1\n')
    fake.chmod(0o755)
    r = _bash(_functions() + f'trap on_err ERR\nVPY={fake}\nstep "pip"\n'
              'pip_install -r requirements.txt\necho not reached\n')
    assert r.returncode == 1 and 'not reached' not in r.stdout
    assert 'No matching distribution' in r.stdout + r.stderr
    assert 'ERROR: pip install -r requirements.txt failed' in r.stderr, r.stderr


def _section(start):
    """Lines of scripts/setup from the one starting with ``start`` up to the next '# ---'
    separator (excluded)."""
    lines = SETUP.read_text().splitlines()
    i = next(n for n, ln in enumerate(lines) if ln.startswith(start))
    j = next((n for n in range(i + 1, len(lines)) if lines[n].startswith('# ---')), len(lines))
    return '\n'.join(lines[i:j]) + '\n'


def test_setup_activate_deactivate_restores_ament_prefix_path(tmp_path):
    # `source .venv/bin/activate` put the venv into AMENT_PREFIX_PATH and `deactivate` left
    # it there (and did not give back a previous value)
    import subprocess
    venv = tmp_path / 'venv'
    subprocess.run([sys.executable, '-m', 'venv', '--without-pip', str(venv)], check=True)
    act = venv / 'bin' / 'activate'
    # an activate patched by an older scripts/setup: its block is replaced, not doubled
    with act.open('a') as f:
        f.write('# >>> beo_ros >>> (added by scripts/setup)\n'
                'export AMENT_PREFIX_PATH="$VIRTUAL_ENV${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}"\n'
                '# <<< beo_ros <<<\n')
    patch = f'VENV={venv}\n' + _section('step "runtime environment in .venv/bin/activate"')
    r = _bash(patch)
    assert r.returncode == 0, r.stderr
    once = act.read_text()
    r = _bash(patch)   # idempotent
    assert r.returncode == 0, r.stderr
    assert act.read_text() == once
    assert once.count('# >>> beo_ros >>>') == 2   # the restore in deactivate, the export

    show = ('printf "%s|%s\\n" "${AMENT_PREFIX_PATH-<unset>}" '
            '"$(printenv AMENT_PREFIX_PATH || echo "<unexported>")"\n')
    script = (f'source {act}\n' + show + 'deactivate\n' + show
              + f'source {act}\nsource {act}\n' + show + 'deactivate\n' + show
              + 'set | grep -c "^_BEO_OLD" || true\n')
    venv_s = str(venv)
    for before, env in (('<unset>', {}),
                        ('/opt/ros/jazzy', {'AMENT_PREFIX_PATH': '/opt/ros/jazzy'}),
                        ('', {'AMENT_PREFIX_PATH': ''}),
                        (f'{venv_s}:/opt/ros/jazzy',
                         {'AMENT_PREFIX_PATH': f'{venv_s}:/opt/ros/jazzy'})):
        r = _bash(script, **env)
        assert r.returncode == 0, r.stderr
        out = r.stdout.splitlines()
        active = venv_s if before in ('<unset>', '') else (
            before if before.startswith(venv_s) else f'{venv_s}:{before}')
        restored = '<unset>|<unexported>' if before == '<unset>' else f'{before}|{before}'
        assert out[0] == f'{active}|{active}', (before, out)
        assert out[1] == restored, (before, out)
        assert out[2] == f'{active}|{active}', (before, out)   # activated twice
        assert out[3] == restored, (before, out)
        assert out[4] == '0', (before, out)   # no helper variables left behind


# --- scripts/test: its arguments reach pytest (run in a scratch clone, fake python) --------

def _scripts_test(tmp_path, cwd, *args):
    """The pytest arguments scripts/test passes, run in ``cwd`` of a scratch clone (its
    .venv/bin/python records its working directory and arguments)."""
    import shutil
    import subprocess
    bash = shutil.which('bash')
    if bash is None:
        pytest.skip('no bash')
    root = tmp_path / 'clone'
    (root / 'scripts').mkdir(parents=True, exist_ok=True)
    (root / 'test').mkdir(exist_ok=True)
    (root / 'test' / 'test_a.py').write_text('')
    (root / '.venv' / 'bin').mkdir(parents=True, exist_ok=True)
    shutil.copy(ROOT / 'scripts' / 'test', root / 'scripts' / 'test')
    py = root / '.venv' / 'bin' / 'python'
    py.write_text('#!/bin/sh\npwd\nfor a in "$@"; do echo "$a"; done\n')
    py.chmod(0o755)
    r = subprocess.run([bash, str(root / 'scripts' / 'test'), *args], cwd=root / cwd,
                       capture_output=True, text=True, timeout=60,
                       env={'PATH': os.environ.get('PATH', '/usr/bin:/bin')})
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    assert lines[0] == str(root) and lines[1:4] == ['-m', 'pytest', '-q'], lines
    return root, lines[4:]


def test_scripts_test_paths_relative_to_the_caller(tmp_path):
    # from inside test/, `../scripts/test test_a.py` ran pytest in the clone with
    # 'test test_a.py': file or directory not found
    root, args = _scripts_test(tmp_path, 'test', 'test_a.py', '-x')
    assert args == [f'{root}/test/test_a.py', '-x']
    root, args = _scripts_test(tmp_path, 'test', 'test_a.py::test_b')
    assert args == [f'{root}/test/test_a.py::test_b']
    # from the clone and with paths relative to it: as before
    root, args = _scripts_test(tmp_path, '.', 'test/test_a.py', '-k', 'b')
    assert args == [f'{root}/test/test_a.py', '-k', 'b']
    root, args = _scripts_test(tmp_path, '.')
    assert args == ['test']
    # a -k expression that names an existing directory is no path
    root, args = _scripts_test(tmp_path, '.', '-k', 'test')
    assert args == ['test', '-k', 'test']


def test_ci_run_resolves_a_relative_data_dir_from_the_callers_directory(tmp_path):
    # .ci/run changed into the clone first: BEO_DATA_DIR=data from the directory holding
    # data/ was called 'no directory' and ../shared/data was used instead
    import shutil
    import subprocess
    bash = shutil.which('bash')
    if bash is None:
        pytest.skip('no bash')
    root = tmp_path / 'clone'
    for d in (root / '.ci', root / 'scripts', tmp_path / 'data', tmp_path / 'shared' / 'data'):
        d.mkdir(parents=True)
    shutil.copy(ROOT / '.ci' / 'run', root / '.ci' / 'run')
    for name in ('setup', 'test'):   # stand-ins that report what they were given
        (root / 'scripts' / name).write_text(f'#!/bin/sh\necho "{name}: $BEO_DATA_DIR"\n')
        (root / 'scripts' / name).chmod(0o755)

    def run(data_dir, cwd):
        env = {'PATH': os.environ.get('PATH', '/usr/bin:/bin'), 'BEO_DATA_DIR': data_dir}
        r = subprocess.run([bash, str(root / '.ci' / 'run')], cwd=cwd, env=env,
                           capture_output=True, text=True, timeout=60)
        assert r.returncode == 0, r.stderr
        return r.stdout

    out = run('data', tmp_path)
    assert f'setup: {tmp_path}/data\n' in out and f'test: {tmp_path}/data\n' in out, out
    out = run('missing', tmp_path)   # no such directory: the one next to the clone
    assert 'is no directory' in out and f'test: {tmp_path}/shared/data\n' in out, out
