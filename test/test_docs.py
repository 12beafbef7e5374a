"""The README and docs/*.md against the code: console scripts, their options, the node's
parameters and the interface fields they name (stale docs fail here, not in a user's shell)."""
import ast
import re
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / 'README.md'
DOCS = [README] + sorted((ROOT / 'docs').glob('*.md'))
# a command name as the docs write it: beo-eval, beo_node (not beo_ros, beo_demo_out, ...)
COMMAND = re.compile(r'(?<![\w.-])(beo-[a-z][a-z0-9-]*|beo_node)(?![\w.-])')
OPTION = re.compile(r'(?<![\w-])--[a-z][a-z0-9-]*')
# where a command's own arguments end on a line: a code span's end, a comment, a shell
# separator, an opening parenthesis (prose about it) or the next command
ARGS_END = re.compile(r'`|\s#\s|;|\||&&|\(|(?<![\w/.-])beo[-_][a-z]')


def console_scripts():
    """{name: 'module:function'} of setup.py's console_scripts."""
    tree = ast.parse((ROOT / 'setup.py').read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.Dict):
            for k, v in zip(node.keys, node.values):
                if isinstance(k, ast.Constant) and k.value == 'console_scripts':
                    entries = ast.literal_eval(v)
                    return dict(tuple(s.strip() for s in e.split('=')) for e in entries)
    raise AssertionError('setup.py has no console_scripts')


def _run_help(target, prog):
    """``prog --help`` through its entry point ``module:function`` (no console script
    needed) -> (exit code, stdout + stderr)."""
    module, func = target.split(':')
    code = (f'import sys; sys.argv[0] = {prog!r}; from {module} import {func} as main; '
            'sys.exit(main())')
    proc = subprocess.run([sys.executable, '-c', code, '--help'], capture_output=True,
                          text=True, timeout=120, cwd=ROOT)
    return proc.returncode, proc.stdout + proc.stderr


@pytest.fixture(scope='module')
def helps():
    """{console script: its --help text}; beo-eval's includes beo-eval --scans' options,
    which it hands to scan_eval."""
    out = {}
    for name, target in console_scripts().items():
        rc, text = _run_help(target, name)
        out[name] = (rc, text)
    rc, text = _run_help('beo_ros.scan_eval:main', 'beo-eval --scans')
    assert rc == 0, text
    out['beo-eval'] = (out['beo-eval'][0], out['beo-eval'][1] + text)
    return out


def doc_lines():
    """(file name, line number, line) of the docs, a code block's continued lines (``\\``)
    joined into the first."""
    for path in DOCS:
        lines = path.read_text().split('\n')
        i = 0
        while i < len(lines):
            line, n = lines[i], i + 1
            while line.rstrip().endswith('\\') and i + 1 < len(lines):
                i += 1
                line = line.rstrip()[:-1] + ' ' + lines[i].strip()
            yield path.name, n, line
            i += 1


def test_every_console_script_has_a_help_and_is_in_the_readme(helps):
    readme = README.read_text()
    for name, (rc, text) in helps.items():
        assert rc == 0 and 'Traceback' not in text, f'{name} --help:\n{text}'
        assert text.startswith('usage: '), f'{name}:\n{text}'
        assert re.search(rf'(?<![\w/.-]){re.escape(name)}(?![\w.-])', readme), \
            f'{name} not in README.md'


def test_every_command_the_docs_name_is_a_console_script():
    scripts = console_scripts()
    unknown = [f'{f}:{n}: {m}' for f, n, line in doc_lines()
               for m in COMMAND.findall(line) if m not in scripts]
    assert not unknown, unknown


def test_every_option_the_docs_give_a_command_exists(helps):
    """An option written after a command (``beo-eval --data X --cv 5``) is one of its own."""
    wrong = []
    for f, n, line in doc_lines():
        for m in COMMAND.finditer(line):
            text = helps.get(m.group(1), (0, ''))[1]
            args = ARGS_END.split(line[m.end():])[0]
            for opt in OPTION.findall(args):
                # beo-node's ROS arguments are rcl's, after --ros-args
                if opt in ('--ros-args', '--params-file') and m.group(1) in ('beo-node',
                                                                            'beo_node'):
                    continue
                if not re.search(re.escape(opt) + r'(?![\w-])', text):
                    wrong.append(f'{f}:{n}: {m.group(1)} {opt}')
    assert not wrong, wrong


OTHER_TOOLS_OPTIONS = {'--no-deps', '--from-paths', '--ignore-src', '--skip-keys',   # pip, rosdep
                       '--base-paths', '--show-args'}                          # colcon, ros2


def test_every_option_the_docs_name_exists(helps):
    """Any ``--option`` in the docs, also in prose (``--views-per-class 4``), is one of a
    console script's, of a measurement script's (scripts/*.py) or of the ROS tools'."""
    known = ''.join(text for _, text in helps.values())
    known += ''.join(p.read_text() for p in (ROOT / 'scripts').glob('*.py'))
    wrong = []
    for f, n, line in doc_lines():
        for opt in OPTION.findall(line):
            if opt in OTHER_TOOLS_OPTIONS:
                continue
            # '--node-*' stands for every option starting so
            tail = '' if opt.endswith('-') else r'(?![\w-])'
            if not re.search(re.escape(opt) + tail, known):
                wrong.append(f'{f}:{n}: {opt}')
    assert not wrong, wrong


def declared_parameters():
    """{name: (default, ParameterDescriptor)} as the node declares them."""
    from beo_ros.ros import params
    out = {}
    params.declare(lambda name, value, descriptor: out.__setitem__(name, (value, descriptor)))
    return out


def readme_parameter_rows():
    """{name: default cell} of the README's parameter table (``a`` / ``b`` rows split)."""
    text = README.read_text()
    table = text[text.index('| parameter | default | meaning |'):]
    rows = {}
    for line in table.split('\n')[2:]:
        if not line.startswith('|'):
            break
        names_cell, default_cell = [c.strip() for c in line.split('|')[1:3]]
        names = re.findall(r'`([a-z_]+)`', names_cell)
        defaults = re.findall(r'`([^`]*)`', default_cell)
        for i, name in enumerate(names):
            rows[name] = f'`{defaults[i]}`' if len(names) > 1 else default_cell
    return rows


def test_readme_parameter_table_lists_every_parameter_with_its_default():
    declared = declared_parameters()
    rows = readme_parameter_rows()
    assert sorted(rows) == sorted(declared)
    for name, (value, _) in declared.items():
        if name == 'model_dir':   # computed (the shipped model's path): described in words
            continue
        first = re.match(r'`([^`]*)`', rows[name].strip())
        assert first, (name, rows[name])
        assert yaml.safe_load(first.group(1)) == value, (name, rows[name], value)


def test_config_defaults_are_the_nodes_outside_the_deployment_settings():
    """config/beo.yaml: every declared parameter with the node's default (the computed ones
    too, which an AST reading of params.py cannot see), except what the file deploys."""
    cfg = yaml.safe_load((ROOT / 'config' / 'beo.yaml').read_text())['/**/beo'][
        'ros__parameters']
    declared = declared_parameters()
    assert list(cfg) == list(declared)
    deployment = {'workers': 2, 'worker_processes': 2, 'model_dir': ''}
    for name, (value, _) in declared.items():
        want = deployment.get(name, value)
        assert cfg[name] == want and type(cfg[name]) is type(want), name


def _fields(path):
    return {ln.split()[1] for ln in path.read_text().split('\n')
            if ln.strip() and not ln.lstrip().startswith(('#', '---'))}


def test_interface_fields_the_readme_names_exist():
    iface = ROOT / 'beo_interfaces'
    estimate = _fields(iface / 'msg' / 'ObjectEstimate.msg')
    requests = _fields(iface / 'srv' / 'Classify.srv') | _fields(iface / 'srv' / 'Complete.srv')
    text = README.read_text()
    row = next(ln for ln in text.split('\n') if ln.startswith('| pub | `~/estimates`'))
    named = set(re.findall(r'`([a-z_]+)`', row.split('|')[3]))
    assert named and named <= estimate, named - estimate
    has = set(re.findall(r'`(has_[a-z_]+)`', text))
    assert has and has <= requests, has - requests


def test_readme_layout_names_every_module_script_and_doc():
    text = README.read_text()
    layout = text[text.index('## Repository layout'):]
    # beo_ros/{train,evaluate}.py names train.py and evaluate.py
    layout = re.sub(r'\{([\w,]+)\}\.py',
                    lambda m: ' '.join(f'{n}.py' for n in m.group(1).split(',')), layout)
    files = [p for p in (ROOT / 'beo_ros').rglob('*.py')
             if p.name not in ('__init__.py', '__main__.py')]
    files += list((ROOT / 'scripts').glob('*.py')) + list((ROOT / 'docs').glob('*.md'))
    missing = sorted(str(p.relative_to(ROOT)) for p in files
                     if not re.search(rf'(?<![\w.]){re.escape(p.name)}\b', layout))
    assert not missing, missing
