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

    t0 = time.monotonic()
    assert main() == TERMINATED and time.monotonic() - t0 < 4
    assert cleaned == [True]
    assert capsys.readouterr().err.strip() == 'beo-x: terminated'
    assert signal.getsignal(signal.SIGTERM) is before   # restored


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
        raise ImportError('no module named x')
    with pytest.raises(ImportError, match='no module'):
        other()


def test_interruptible_shows_a_warning_as_one_line(capsys):
    # before: Python's 'FILE:LINE: UserWarning: ...' and the source line of the warn call
    import warnings

    @interruptible('beo-x')
    def main(argv=None):
        warnings.warn('learn0.pcd: left out 1 object(s)', UserWarning, stacklevel=2)
        return 0

    show = warnings.showwarning
    with warnings.catch_warnings():
        warnings.simplefilter('always')
        assert main() == 0
    assert capsys.readouterr().err == 'beo-x: warning: learn0.pcd: left out 1 object(s)\n'
    assert warnings.showwarning is show   # restored for whatever runs after the command
