"""beo_ros.cli: the argparse number types and the Ctrl-C wrapper shared by the commands."""
import argparse

import pytest

from beo_ros.cli import INTERRUPTED, count, interruptible, number


def _parser(kind):
    ap = argparse.ArgumentParser(prog='p')
    ap.add_argument('--x', type=kind)
    return ap


@pytest.mark.parametrize('text, why', [
    ('nan', "must be a finite number, got 'nan'"), ('inf', "must be a finite number, got 'inf'"),
    ('-inf', "must be a finite number, got '-inf'"), ('abc', "'abc' is not a number"),
    ('-1', 'must be in (0, 10], got -1'), ('0', 'must be in (0, 10], got 0')])
def test_number_refuses(text, why, capsys):
    # each refusal for its own reason: infinities refused by the bounds alone (no finite
    # check) read 'must be in (0, 10], got inf'
    with pytest.raises(SystemExit) as e:
        _parser(number(0, 10, lo_open=True)).parse_args([f'--x={text}'])
    assert e.value.code == 2
    assert capsys.readouterr().err.endswith(f'error: argument --x: {why}\n')


@pytest.mark.parametrize('text, value', [('0.5', 0.5), ('10', 10.0), ('1e-9', 1e-9)])
def test_number_accepts(text, value):
    assert _parser(number(0, 10, lo_open=True)).parse_args(['--x', text]).x == value


def test_number_unbounded_and_open_upper(capsys):
    assert _parser(number()).parse_args(['--x=-1e300']).x == -1e300
    with pytest.raises(SystemExit):
        _parser(number(0, 1, hi_open=True)).parse_args(['--x', '1'])
    assert 'argument --x: must be in [0, 1), got 1' in capsys.readouterr().err


@pytest.mark.parametrize('text, why', [
    ('-1', 'must be in [0, 100], got -1'), ('1.5', "'1.5' is not an integer"),
    ('x', "'x' is not an integer"), ('101', 'must be in [0, 100], got 101')])
def test_count_refuses(text, why, capsys):
    with pytest.raises(SystemExit) as e:
        _parser(count(0, 100)).parse_args([f'--x={text}'])
    assert e.value.code == 2
    assert capsys.readouterr().err.endswith(f'error: argument --x: {why}\n')


def test_count_accepts():
    assert _parser(count(1)).parse_args(['--x', '7']).x == 7


@pytest.mark.parametrize('kind, text', [(number(0, 1), '0'), (number(0, 1), '1'),
                                        (count(0, 100), '0'), (count(0, 100), '100')])
def test_closed_bounds_are_taken(kind, text):
    assert _parser(kind).parse_args(['--x', text]).x == float(text)


@pytest.mark.parametrize('kind, text, why', [
    (number(None, 5), '6', 'must be in (-inf, 5], got 6'),
    (number(2), '1', 'must be in [2, inf), got 1'),
    # an integer bound in full (:g wrote 2.14748e+09)
    (count(0, 2 ** 31 - 1), '2147483648', 'must be in [0, 2147483647], got 2147483648')])
def test_range_messages_of_open_and_integer_bounds(kind, text, why, capsys):
    with pytest.raises(SystemExit):
        _parser(kind).parse_args([f'--x={text}'])
    assert capsys.readouterr().err.endswith(f'error: argument --x: {why}\n')


def test_interruptible(capsys):
    @interruptible('beo-x')
    def main(argv=None):
        raise KeyboardInterrupt

    assert main() == INTERRUPTED
    assert capsys.readouterr().err.strip() == 'beo-x: interrupted'

    @interruptible('beo-x')
    def ok(argv=None):
        return 3
    assert ok() == 3


def test_interruptible_turns_sigterm_into_a_clean_exit(capsys):
    import os
    import signal
    import time

    from beo_ros.cli import TERMINATED
    before = signal.getsignal(signal.SIGTERM)
    cleaned = []

    @interruptible('beo-x')
    def main(argv=None):
        try:
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(5)   # the handler raises in the main thread at once
            return 0
        finally:
            cleaned.append(True)

    def mine(signum, frame):   # a handler of the caller's: a test run before may have left
        pass                   # the default in place of it had this test not set its own
    signal.signal(signal.SIGTERM, mine)
    try:
        t0 = time.monotonic()
        assert main() == TERMINATED and time.monotonic() - t0 < 4
        assert cleaned == [True]
        assert capsys.readouterr().err.strip() == 'beo-x: terminated'
        assert signal.getsignal(signal.SIGTERM) is mine   # restored
    finally:
        signal.signal(signal.SIGTERM, before)


def test_interruptible_unwraps_an_import_cut_short_by_ctrl_c(capsys):
    # pybind11 turns a KeyboardInterrupt during a module's init into an ImportError
    @interruptible('beo-x')
    def main(argv=None):
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as e:
            raise ImportError('initialization failed') from e

    assert main() == INTERRUPTED
    assert capsys.readouterr().err.strip() == 'beo-x: interrupted'

    @interruptible('beo-x')
    def other(argv=None):
        raise ImportError('no module named x') from OSError('libx.so: cannot open')
    with pytest.raises(ImportError, match='no module'):
        other()


def test_interruptible_shows_a_warning_as_one_line(capsys):
    # before: Python's 'FILE:LINE: UserWarning: ...' and the source line of the warn call
    import warnings

    @interruptible('beo-x')
    def main(argv=None):
        warnings.warn('learn0.pcd: left out 1 object(s)', UserWarning, stacklevel=2)
        return 0

    with warnings.catch_warnings():   # (which restores showwarning itself on exit)
        show = warnings.showwarning
        warnings.simplefilter('always')
        assert main() == 0
        assert warnings.showwarning is show   # restored for whatever runs after the command
    assert capsys.readouterr().err == 'beo-x: warning: learn0.pcd: left out 1 object(s)\n'


def test_interruptible_restores_the_default_for_a_handler_not_set_from_python(monkeypatch):
    # signal.signal returns None for a handler that C code set: it cannot be set back, and
    # the default is (signal.signal(SIGTERM, None) is a TypeError)
    import signal
    calls = []

    def fake(signum, handler):
        calls.append((signum, handler))
        return None
    monkeypatch.setattr(signal, 'signal', fake)
    assert interruptible('beo-x')(lambda: 4)() == 4
    assert calls[-1] == (signal.SIGTERM, signal.SIG_DFL)


def test_json_safe():
    import numpy as np

    from beo_ros.cli import json_safe
    got = json_safe({'a': (np.float64('nan'), np.int64(3), float('inf'), -float('inf'), 0.5),
                     'b': [np.float32(0.25), {'c': np.float32('inf')}], 'd': 'x'})
    assert got == {'a': [None, 3, None, None, 0.5], 'b': [0.25, {'c': None}], 'd': 'x'}
    assert type(got['a'][1]) is int and type(got['b'][0]) is float


def test_complete_files_renames_what_was_written_and_only_when_the_block_completes(tmp_path):
    from beo_ros.cli import complete_files
    with complete_files(tmp_path, ('a.json', 'b.png')) as tmp:
        assert tmp['b.png'].suffix == '.png' and tmp['a.json'].parent == tmp_path
        tmp['a.json'].write_text('{}')
    assert sorted(p.name for p in tmp_path.iterdir()) == ['a.json']
    with pytest.raises(KeyboardInterrupt):
        with complete_files(tmp_path, ('a.json', 'b.png')) as tmp:
            tmp['a.json'].write_text('[1]')
            tmp['b.png'].write_text('png')
            raise KeyboardInterrupt
    assert sorted(p.name for p in tmp_path.iterdir()) == ['a.json']   # no .partial. left
    assert (tmp_path / 'a.json').read_text() == '{}'


def test_out_dir_problem(tmp_path, monkeypatch):
    import os

    from beo_ros.cli import existing_parent, out_dir_problem
    (tmp_path / 'file').write_text('x')
    (tmp_path / 'link').symlink_to(tmp_path / 'nothing')
    (tmp_path / 'dir').mkdir()
    (tmp_path / 'good_link').symlink_to(tmp_path / 'dir')
    assert out_dir_problem(tmp_path / 'dir') is None
    assert out_dir_problem(tmp_path / 'dir' / 'new' / 'sub') is None
    assert out_dir_problem(tmp_path / 'good_link' / 'new') is None   # a link to a directory
    assert out_dir_problem(tmp_path / 'file') == 'exists and is not a directory'
    assert out_dir_problem(tmp_path / 'file' / 'sub') == (
        f"cannot make the output directory ({tmp_path / 'file'} is not a directory)")
    for out in (tmp_path / 'link', tmp_path / 'link' / 'sub'):
        assert out_dir_problem(out) == (
            f"cannot make the output directory ({tmp_path / 'link'} is a broken symbolic "
            f"link, to {tmp_path / 'nothing'})")
    assert existing_parent(tmp_path / 'dir') == tmp_path   # above the path, even if it exists
    assert existing_parent(tmp_path / 'dir' / 'a' / 'b') == tmp_path / 'dir'
    # (root may write anywhere: os.access stands in for a directory of another user)
    real = os.access
    monkeypatch.setattr(os, 'access', lambda p, mode: real(p, mode) and
                        os.fspath(p) != os.fspath(tmp_path / 'dir'))
    assert out_dir_problem(tmp_path / 'dir') == 'the output directory is not writable'
    assert out_dir_problem(tmp_path / 'dir' / 'new') == (
        f"cannot make the output directory ({tmp_path / 'dir'} is not writable)")
