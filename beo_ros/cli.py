"""Pieces shared by the command lines (ROS-free): argparse number types, Ctrl-C handling and
output directories.

    ap.add_argument('--duration', type=number(0, None, lo_open=True), ...)

    @interruptible('beo-train')
    def main(argv=None): ...
"""
from __future__ import annotations

import argparse
import contextlib
import functools
import math
import os
import signal
import sys
import threading
import warnings
from pathlib import Path

import numpy as np

__all__ = ['ArgumentParser', 'BROKEN_PIPE', 'INTERRUPTED', 'TERMINATED', 'Terminated', 'count',
           'existing_parent', 'given_options', 'interruptible', 'json_safe', 'number',
           'out_dir_problem', 'output_dir', 'print_help', 'writable_dir']

INTERRUPTED = 130   # the shell's code for a process ended by SIGINT
TERMINATED = 143    # ... and by SIGTERM
BROKEN_PIPE = 141   # ... and by SIGPIPE


class Terminated(KeyboardInterrupt):
    """SIGTERM (``kill``, ``docker stop``) raised as an exception in the main thread, so that
    a command cleans up (temporary files, an empty output directory) as for Ctrl-C."""


class ArgumentParser(argparse.ArgumentParser):
    """argparse's parser for an :func:`interruptible` command: -h written to a stdout whose
    reader has gone raises BrokenPipeError (argparse drops it: ``beo-eval -h | head -0``
    ended in "Exception ignored ... BrokenPipeError", exit 120), so the command ends quietly
    with 141."""

    def print_help(self, file=None):
        file = sys.stdout if file is None else file
        if file is not None:   # None: no stdout at all (pythonw), as argparse
            file.write(self.format_help())
            file.flush()


_NOT_GIVEN = object()


def given_options(ap, argv=None):
    """The ``dest`` names of the options written in ``argv`` (None: ``sys.argv[1:]``) for
    parser ``ap``, given at their default value or not (a check that compares a value with
    its default cannot tell ``--paper-yaws 36`` from no ``--paper-yaws``). For store-type
    options (not append / count)."""
    # argparse fills in a default only for an attribute the namespace lacks
    ns = argparse.Namespace(**{a.dest: _NOT_GIVEN for a in ap._actions
                               if a.dest is not argparse.SUPPRESS})
    args, _ = ap.parse_known_args(argv, namespace=ns)
    return {name for name, value in vars(args).items() if value is not _NOT_GIVEN}


def print_help(text):
    """Print a command's help ``text`` on stdout -> 0, or :data:`BROKEN_PIPE` when stdout's
    reader has gone (``beo-node -h | head -0``), quietly, as :func:`interruptible` does."""
    try:
        print(text, flush=True)
    except BrokenPipeError:
        _stdout_to_devnull()
        return BROKEN_PIPE
    return 0


def _stdout_to_devnull():
    """stdout to /dev/null, or the flush at exit fails again on the closed pipe."""
    with contextlib.suppress(OSError, ValueError, AttributeError):
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())


def number(lo: float | None = None, hi: float | None = None, *, lo_open: bool = False,
           hi_open: bool = False):
    """argparse ``type``: a finite float in [lo, hi] (open ends with ``lo_open``/``hi_open``;
    None: unbounded). NaN and infinities are refused with a message naming the range."""
    def parse(text):
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f'{text!r} is not a number') from None
        if not math.isfinite(value):
            raise argparse.ArgumentTypeError(f'must be a finite number, got {text!r}')
        if ((lo is not None and (value < lo or (lo_open and value == lo)))
                or (hi is not None and (value > hi or (hi_open and value == hi)))):
            raise argparse.ArgumentTypeError(f'must be in {_range(lo, hi, lo_open, hi_open)}, '
                                             f'got {text}')
        return value
    parse.__name__ = 'number'   # argparse names the type in its messages
    return parse


def count(lo: int = 0, hi: int | None = None):
    """argparse ``type``: an integer in [lo, hi] (None: unbounded)."""
    def parse(text):
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f'{text!r} is not an integer') from None
        if value < lo or (hi is not None and value > hi):
            raise argparse.ArgumentTypeError(f'must be in {_range(lo, hi, False, False)}, '
                                             f'got {text}')
        return value
    parse.__name__ = 'integer'
    return parse


def _range(lo, hi, lo_open, hi_open):
    def fmt(v):   # an integer bound exactly (:g would print 2**31 - 1 as 2.14748e+09)
        return str(v) if isinstance(v, int) else f'{v:g}'
    left = '-inf' if lo is None else fmt(lo)
    right = 'inf' if hi is None else fmt(hi)
    return f"{'(' if lo_open or lo is None else '['}{left}, {right}{')' if hi_open or hi is None else ']'}"


def _raise_terminated(signum, frame):
    raise Terminated


def interruptible(prog: str):
    """Decorator for a command's ``main``: Ctrl-C ends it with one line on stderr and exit
    code 130 instead of a traceback, SIGTERM likewise with exit code 143 (the command cleans
    up in its own ``finally`` blocks; while it runs, SIGTERM raises :class:`Terminated`), and
    a stdout whose reader has gone (a closed pipe) quietly with 141, as SIGPIPE would.
    While it runs, a warning (a scan's left-out objects, a fit that did not converge) is one
    line ``PROG: warning: ...``, not Python's file, line number and source line."""
    def wrap(main):
        @functools.wraps(main)
        def run(*args, **kwargs):
            main_thread = threading.current_thread() is threading.main_thread()
            if main_thread:
                old = signal.signal(signal.SIGTERM, _raise_terminated)
            show = warnings.showwarning
            warnings.showwarning = functools.partial(_warning_line, prog)
            try:
                try:
                    return main(*args, **kwargs)
                except ImportError as e:
                    # interrupted while a compiled module initialised (open3d's, seconds):
                    # pybind11 reports it as "ImportError: initialization failed"
                    if isinstance(e.__cause__, KeyboardInterrupt):
                        raise e.__cause__ from None
                    raise
            except BrokenPipeError:
                # stdout's reader went away (beo-eval ... | head -1): stop quietly, as a command
                # that SIGPIPE ends
                _stdout_to_devnull()
                return BROKEN_PIPE
            except Terminated:
                print(f'{prog}: terminated', file=sys.stderr)
                return TERMINATED
            except KeyboardInterrupt:
                print(f'{prog}: interrupted', file=sys.stderr)
                return INTERRUPTED
            finally:
                warnings.showwarning = show
                if main_thread:   # None: a handler not set from Python; the default then
                    signal.signal(signal.SIGTERM, signal.SIG_DFL if old is None else old)
        return run
    return wrap


def _warning_line(prog, message, category, filename, lineno, file=None, line=None):  # noqa: ARG001
    """``warnings.showwarning`` of a command: ``PROG: warning: MESSAGE`` on stderr."""
    print(f'{prog}: warning: {message}', file=file or sys.stderr)


def json_safe(obj):
    """``obj`` with every non-finite float (NaN: nothing to average) as None and numpy scalars
    as Python numbers, for strict JSON."""
    if isinstance(obj, dict):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, (np.floating, np.integer)):
        return json_safe(obj.item())
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


@contextlib.contextmanager
def complete_files(out, names):
    """Yield {name: temporary path} in directory ``out`` for the files ``names``; when the block
    completes, those written are renamed to ``out/name`` together, and on a failure or Ctrl-C
    none is: no result set without some of its files. The temporary names keep the extension
    (matplotlib's savefig reads it)."""
    tmp = {name: out / f'.partial.{name}' for name in names}
    try:
        yield tmp
        for name in names:
            if tmp[name].exists():
                os.replace(tmp[name], out / name)
    finally:
        for path in tmp.values():
            path.unlink(missing_ok=True)


def out_dir_problem(out):
    """Why ``out`` cannot be the output directory, or None; creates nothing."""
    # a symbolic link to nothing exists for mkdir ('File exists' once the inputs had loaded)
    broken = next((d for d in (out, *out.absolute().parents)
                   if d.is_symlink() and not d.exists()), None)
    if broken is not None:
        return (f'cannot make the output directory ({broken} is a broken symbolic link, to '
                f'{os.readlink(broken)})')
    if out.exists():
        if not out.is_dir():
            return 'exists and is not a directory'
        return None if writable_dir(out) else 'the output directory is not writable'
    parent = existing_parent(out)
    if not parent.is_dir():
        return f'cannot make the output directory ({parent} is not a directory)'
    if not writable_dir(parent):
        return f'cannot make the output directory ({parent} is not writable)'
    return None


def existing_parent(path) -> Path:
    """The nearest folder above ``path`` (made absolute) that exists (it may be a file)."""
    return next(d for d in Path(path).absolute().parents if d.exists())


def writable_dir(path) -> bool:
    """True when ``path`` is a directory this process may create files in."""
    path = Path(path)
    return path.is_dir() and os.access(path, os.W_OK | os.X_OK)


@contextlib.contextmanager
def output_dir(out):
    """Make the directory ``out`` (and missing parents) for the block; if the block fails
    (an exception, Ctrl-C included), remove the directories it made that are still empty
    (never one that existed before or holds files)."""
    out = Path(out)
    made = [d for d in (out, *out.absolute().parents) if not d.exists()]
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OSError(f'--out {out}: cannot make the output directory ({e.strerror or e})') \
            from None
    try:
        yield out
    except BaseException:
        for d in made:   # deepest first
            try:
                d.rmdir()
            except OSError:
                break
        raise
