"""Estimation in worker processes, each with its own copy of the model bank.

The node's estimates are numpy/BLAS plus a good deal of Python; in worker threads they share
the node's GIL with message conversion and the rclpy executor. Worker processes (spawned, so
they never inherit rclpy's threads and never import it) run estimates truly in parallel.
Everything here is picklable and ROS-free: the processes import only ``beo_ros.core``.
"""
from __future__ import annotations

import contextlib
import dataclasses
import multiprocessing
import os
import pickle
import signal
import threading
import time
from concurrent.futures import CancelledError, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from multiprocessing.connection import wait as wait_ready

import numpy as np

__all__ = ['BrokenProcessPool', 'EstimateTimeout', 'EstimatorPool', 'PoolRetired',
           'warm_up_points']

_bank = None         # this worker process's bank
_blas_limits = None  # kept alive: threadpoolctl restores the limits when it is collected


class PoolRetired(RuntimeError):
    """The estimate was not sent: the pool was shut down (model reload, node shutdown) or was
    already broken."""


class EstimateTimeout(TimeoutError):
    """An estimate took longer than its timeout: the pool's processes were killed (the pool is
    broken; estimates waiting on it get BrokenProcessPool)."""


def warm_up_points(spec=None) -> np.ndarray:
    """(400, 3) points on the face of a box 0.8 m ahead of a sensor at the origin, z up: 0.4 m
    across, or half the grid of a metric ``spec`` (a model's GridSpec) when that is smaller (a
    face larger than the grid has no point in it and the warm-up estimate is rejected)."""
    side = 0.4
    if spec is not None and spec.units == 'metric':
        side = min(side, 0.5 * spec.size * spec.voxel_size)
    rng = np.random.default_rng(0)
    pts = rng.uniform(-side / 2, side / 2, size=(400, 3)) + [1.0, 0.0, 0.0]
    pts[:, 0] = 0.8
    return pts


def _die_with(parent_pid):
    """End this process within a second of the node (``parent_pid``) ending, however it ends:
    a process the node had not registered yet when it was interrupted would otherwise wait
    for tasks for ever. (Not PR_SET_PDEATHSIG: that fires when the *thread* that spawned the
    process ends, and model reloads spawn from threads that end.)"""
    def watch():
        while os.getppid() == parent_pid:
            time.sleep(1.0)
        os._exit(0)

    threading.Thread(target=watch, name='beo_parent_watch', daemon=True).start()


def _exit_code(process, wait=1.0):
    """``process.exitcode`` of a process that has ended. It reads None while another thread
    reaps the process (the executor's, joining it: waitpid there, ECHILD here), so it is asked
    again for up to ``wait`` s."""
    end = time.monotonic() + wait
    while (code := process.exitcode) is None and time.monotonic() < end:
        time.sleep(0.005)
    return code


def _init(bank, blas_threads, parent_pid=None):
    """Process initializer: BLAS threads, the bank, one throw-away estimate."""
    global _bank, _blas_limits
    if parent_pid is not None:
        _die_with(parent_pid)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the node's: it shuts us down
    # spawned with SIGINT and SIGTERM blocked (see _spawning): a Ctrl-C meanwhile is dropped
    # now, a SIGTERM meanwhile ends the process now, after it has read all its start-up data
    signal.pthread_sigmask(signal.SIG_UNBLOCK, _START_SIGNALS)
    if blas_threads > 0:
        try:
            from threadpoolctl import threadpool_limits
            _blas_limits = threadpool_limits(limits=blas_threads, user_api='blas')
        except ImportError:
            pass
    _bank = bank
    try:  # the first estimate fills caches; no real cloud should pay for it
        _bank.estimate_points(warm_up_points(_bank.spec))
    except Exception:  # noqa: BLE001 - warm-up is best effort
        pass


_START_SIGNALS = {signal.SIGINT, signal.SIGTERM}


@contextlib.contextmanager
def _spawning():
    """Block SIGINT and SIGTERM in this thread while it spawns processes; they inherit the
    block until ``_init``.

    Why: the parent writes each new process its start-up data (the pickled bank, MBs) through
    a pipe whose read end it holds itself until the write is done (CPython 3.11
    ``popen_spawn_posix``), and the process reads it while it imports open3d (seconds). A
    Ctrl-C or SIGTERM to the process group (a terminal, ``docker stop``) killed the process
    half-way, and the parent then waited for ever in that write: the node never exited (and
    each process printed a KeyboardInterrupt traceback). The signal reaches the parent's
    other threads meanwhile (beo-node's handlers raise KeyboardInterrupt in its main thread
    once the block is lifted; rclpy's, in a process that embeds the node, shut the context
    down)."""
    old = signal.pthread_sigmask(signal.SIG_BLOCK, _START_SIGNALS)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


def _ready(delay):
    time.sleep(delay)  # long enough for a not yet ready sibling to take a task too
    return os.getpid()


def _estimate(points, origin, up, yaw_step_deg, threshold, cleaning, class_prior=None):
    """Estimate in this worker process -> (Estimate without its grids, class names).
    ``cleaning``: keyword arguments of ``estimate_points`` (outlier_mads, outlier_neighbors,
    cluster_tolerance). ``class_prior``: the node's current prior (None: the bank's own), so
    that changing it needs no new processes. An exception that would not unpickle in the
    parent (a class whose constructor wants other arguments than its ``args``) comes back as a
    RuntimeError naming it: unpickling it there broke the pool, killed the processes and was
    reported as a process that died, without the error. So does a SystemExit or
    KeyboardInterrupt."""
    if class_prior is not None:
        _bank.class_prior = class_prior
    try:
        est = _bank.estimate_points(points, sensor_origin=origin, up=up,
                                    yaw_step_deg=yaw_step_deg, threshold=threshold, **cleaning)
    except Exception as e:
        try:   # the parent rebuilds it as cls(*args): one that this fails for broke the pool
            pickle.loads(pickle.dumps(e))
        except Exception:   # noqa: BLE001 - any failure: send what it said instead
            raise RuntimeError(f'{type(e).__name__}: {e}') from None
        raise
    except BaseException as e:   # noqa: BLE001 - no Ctrl-C here (SIGINT is ignored): a
        # SystemExit or KeyboardInterrupt that a library raised came back to the caller as is
        # and ended its thread (or the embedding script)
        raise RuntimeError(f'{type(e).__name__}: {e}') from None
    if dataclasses.is_dataclass(est):
        # the node needs neither the (N,N,N) grids nor the features: ~0.3 MB less per result
        est = dataclasses.replace(est, completion=None, variance=None, grid=None, features=None)
    return est, list(_bank.classes)


class EstimatorPool:
    """``n`` spawned processes, each estimating with its own copy of ``bank``.

    The constructor returns once every process has loaded the bank and run its warm-up
    estimate. A process that dies breaks the whole pool (pending estimates raise
    BrokenProcessPool); the owner replaces it.

    Args:
        n: number of processes.
        bank: the bank to copy (it must pickle; a ModelBank pickles as its constructor
            arguments).
        blas_threads: BLAS threads per process (0: library default).
        timeout: seconds to wait for the processes to be ready.

    Raises:
        BrokenProcessPool (a RuntimeError): the processes did not start;
        TimeoutError: not within ``timeout``.
    """

    def __init__(self, n: int, bank, blas_threads: int = 1, timeout: float = 120.0):
        self.n = int(n)
        self._closed = False
        self._killed = False   # kill() ran: the pool is broken, or about to be
        self.timed_out = False   # ... because an estimate timed out (not a death)
        self._kill_lock = threading.Lock()
        # estimates handed to the processes: at most one per process, so that the timeout of
        # each runs from when a process is free to take it (queued behind others, a cloud
        # ran out of time without any process hanging, and the healthy ones were killed)
        self._sent = threading.BoundedSemaphore(self.n)
        self.waiting = 0   # estimates waiting for a free process
        self._procs = None   # the processes, once all are ready (see _processes)
        self._pool = ProcessPoolExecutor(
            self.n, mp_context=multiprocessing.get_context('spawn'), initializer=_init,
            initargs=(bank, int(blas_threads), os.getpid()))
        try:
            self.pids = self._wait_ready(timeout)
        except BaseException:
            self.shutdown(timeout=1.0)
            raise
        procs = self._procs = list(self._pool._processes.values())
        # taken now: ProcessPoolExecutor.shutdown drops its result queue, and a pool shut down
        # right after a process died mid-send left the watchdog nothing to close
        writer = getattr(getattr(self._pool, '_result_queue', None), '_writer', None)
        self._watchdog = threading.Thread(target=self._watch, args=(procs, writer), daemon=True,
                                          name='beo_pool_watchdog')
        self._watchdog.start()

    def _watch(self, procs, writer):
        """Thread: a process that dies (ends before the pool is shut down, or after it with a
        non-zero exit code) takes its siblings with it; once all are gone, the parent's copy of
        the result pipe's write end (``writer``, taken when the pool started) is closed.

        Why: ProcessPoolExecutor (CPython 3.11) reads a result to its end before it looks at
        the processes again, and the parent keeps a write end of that pipe open. A process
        killed half-way through sending a result (the OOM killer, say) leaves the executor's
        thread waiting for the rest for ever: the estimate never ends, the pool is never
        marked broken, and the interpreter hangs at exit joining that thread. A sibling may
        also wait for ever on the queue lock the dead process held. With every process gone
        and the last write end closed, the read ends in EOF and the executor breaks the pool
        as for any other death. Also after shutdown(timeout=None) (a reload's old processes):
        the siblings, idle, would otherwise wait for ever for the executor's thread to tell
        them to end.
        """
        pending = {p.sentinel: p for p in procs}
        while pending:
            ended = [pending.pop(s) for s in wait_ready(list(pending))]
            # exit code 0: ended by the executor's shutdown, which ends the processes only once
            # every estimate sent is answered (a code still unknown counts as a death: a kill
            # is harmless then)
            if pending and (not self._closed or any(_exit_code(p) != 0 for p in ended)):
                self.kill()   # the pool is broken anyway
        if writer is not None:
            try:
                writer.close()
            except OSError:
                pass

    def _wait_ready(self, timeout):
        """Pids of the processes once each has run a task (so its initializer is done)."""
        deadline = time.monotonic() + timeout
        pids = set()
        while len(pids) < self.n:
            # the first n submissions spawn the n processes (spawned on demand, one per task
            # while none is idle); a process answers only after its initializer
            with _spawning():
                futures = [self._pool.submit(_ready, 0.05) for _ in range(self.n)]
            for f in futures:
                pids.add(f.result(timeout=max(deadline - time.monotonic(), 0.01)))
        return sorted(pids)

    def estimate(self, points, origin, up, yaw_step_deg, threshold, cleaning=None,
                 class_prior=None, timeout=None):
        """Estimate one cloud in a worker process (blocks) -> (Estimate, class names);
        ``cleaning``: keyword arguments of ``ModelBank.estimate_points`` (outlier_mads,
        outlier_neighbors, cluster_tolerance; None: its defaults); ``class_prior`` as for
        ``ModelBank.class_prior`` (None: the bank's own).

        Raises ValueError from the core as is, BrokenProcessPool when a process died while the
        estimate was queued or running (or the pool was shut down with it queued), PoolRetired
        when it could not be sent, EstimateTimeout when no answer came within ``timeout``
        seconds (None: no limit): a process that hangs (e.g. stopped, or deadlocked in a
        library) would otherwise hold the calling thread forever, so all processes are killed.
        The estimate waits (without a limit) until a process is free before it is sent; the
        timeout runs from then (a pool shut down or killed meanwhile: BrokenProcessPool).
        Only the first estimate to time out in a pool raises EstimateTimeout; others whose
        time runs out once the processes were killed raise BrokenProcessPool (one hang, one
        timeout; the other clouds were only waiting).
        """
        if not self._sent.acquire(blocking=False):   # every process is busy
            with self._kill_lock:
                self.waiting += 1
            try:
                self._sent.acquire()
            finally:
                with self._kill_lock:
                    self.waiting -= 1
            if self._closed or self._killed:   # as for an estimate queued in the executor
                self._sent.release()
                raise BrokenProcessPool('the worker processes were shut down or killed while '
                                        'the estimate waited for one')
        try:
            return self._estimate(points, origin, up, yaw_step_deg, threshold, cleaning,
                                  class_prior, timeout)
        finally:
            self._sent.release()

    def _estimate(self, points, origin, up, yaw_step_deg, threshold, cleaning, class_prior,
                  timeout):
        try:
            future = self._pool.submit(_estimate, np.ascontiguousarray(points, np.float64),
                                       np.asarray(origin, np.float64), np.asarray(up, np.float64),
                                       float(yaw_step_deg), float(threshold),
                                       dict(cleaning or {}), class_prior)
        except BrokenProcessPool as e:
            raise PoolRetired('the estimator pool is broken') from e
        except RuntimeError as e:
            if self._closed:
                raise PoolRetired('the estimator pool was shut down') from e
            raise
        try:
            try:
                return future.result(timeout=timeout)
            except TimeoutError:
                if future.done():   # finished right at the deadline
                    return future.result()
                with self._kill_lock:
                    first, self._killed = not self._killed, True
                    self.timed_out = self.timed_out or first
                if not first:
                    # another estimate's timeout (or a death) killed the processes before the
                    # executor failed this one: a hang is reported once, this cloud is retried
                    raise BrokenProcessPool('the worker processes were killed while the '
                                            'estimate waited') from None
                self.kill()
                raise EstimateTimeout(f'no answer from the worker processes within {timeout:g} '
                                      's; they were killed') from None
        except CancelledError:
            # still queued when the pool was shut down (replaced after another estimate's
            # crash or timeout): not this cloud's fault, so the caller retries it as for a crash
            raise BrokenProcessPool('the estimate was cancelled: its pool was shut down') \
                from None

    def _processes(self):
        """The worker processes: those of the ready pool (they are never replaced), else the
        executor's so far. Why not always the executor's: ProcessPoolExecutor.shutdown forgets
        them, so a kill() after shutdown(timeout=None) (the timeout of an estimate a reload's
        old processes still had) killed none, and a hung process kept the executor's thread,
        joined at interpreter exit, waiting for ever."""
        if self._procs is not None:
            return self._procs
        return list((getattr(self._pool, '_processes', None) or {}).values())

    def kill(self):
        """Kill the processes at once (SIGKILL: also ends a stopped or hung process), also after
        a shutdown; the pool is broken afterwards."""
        self._killed = True
        for p in self._processes():
            if p.is_alive():
                p.kill()

    @property
    def broken(self) -> bool:
        return bool(getattr(self._pool, '_broken', False))

    def shutdown(self, timeout: float | None = 5.0):
        """Stop the processes. Estimates still waiting for a free process raise
        BrokenProcessPool; those handed to the processes finish there.

        ``timeout`` None returns at once and cancels nothing: the pool winds down in the
        background once the processes have answered what they were sent (a model reload's old
        processes, say). Otherwise estimates not yet taken by a process are cancelled
        (BrokenProcessPool), and processes still alive after ``timeout`` seconds are
        terminated, and killed if that does not end them within 1 s (a stopped process keeps
        SIGTERM pending); their estimates raise BrokenProcessPool.
        """
        self._closed = True
        procs = self._processes()
        self._pool.shutdown(wait=False, cancel_futures=timeout is not None)
        if timeout is None:
            return
        deadline = time.monotonic() + timeout
        for p in procs:
            p.join(max(deadline - time.monotonic(), 0.0))
            if p.is_alive():
                p.terminate()
                p.join(1.0)
            if p.is_alive():
                p.kill()
                p.join(1.0)
