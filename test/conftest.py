"""Shared pytest fixtures. Append-only; ROS fixtures are prefixed ``ros_``."""
import faulthandler
import itertools
import os

import pytest

_ros_domain_counter = itertools.count()


def ros_beo_interfaces_built() -> bool:
    """True when the built beo_interfaces (not just its source folder) imports."""
    try:
        from beo_ros.ros.conversions import interfaces
        interfaces()
        import beo_interfaces.srv  # noqa: F401
        return True
    except ImportError:
        return False


@pytest.fixture
def ros_interfaces():
    """Skip the test when beo_interfaces is not built (run scripts/setup)."""
    if not ros_beo_interfaces_built():
        pytest.skip('beo_interfaces is not built; run scripts/setup')


@pytest.fixture
def ros_domain_id():
    """A DDS domain id unique to this pytest process and test (for subprocess tests)."""
    return 10 + (os.getpid() * 7 + next(_ros_domain_counter)) % 90


@pytest.fixture
def ros_context(monkeypatch, ros_domain_id):
    """An initialised rclpy Context of its own, discovery OFF (no traffic outside the process)
    and its own domain (no endpoints of an earlier test's context in its graph).

    Yields the context; shuts it down afterwards.
    """
    import rclpy
    from rclpy.context import Context

    monkeypatch.setenv('ROS_AUTOMATIC_DISCOVERY_RANGE', 'OFF')
    ctx = Context()
    rclpy.init(context=ctx, domain_id=ros_domain_id)
    try:
        yield ctx
    finally:
        rclpy.try_shutdown(context=ctx)


@pytest.fixture(scope='session')
def ros_tiny_model_dir(tmp_path_factory):
    """A tiny model bank trained on generated shapes (beo_ros.core.synthetic.make_tiny_bank).

    BEO_TEST_MODEL_DIR=<dir> uses that model directory instead (e.g. the shipped models).
    """
    if os.environ.get('BEO_TEST_MODEL_DIR'):
        return os.environ['BEO_TEST_MODEL_DIR']
    try:
        from beo_ros.core.synthetic import make_tiny_bank
    except ImportError as e:
        pytest.skip(f'beo_ros.core.synthetic.make_tiny_bank is not available: {e}')
    path = tmp_path_factory.mktemp('ros_tiny_bank')
    try:
        out = make_tiny_bank(path)
    except ImportError as e:  # the training code is not there yet
        pytest.skip(f'make_tiny_bank cannot train: {e}')
    return str(out if out is not None and not hasattr(out, 'estimate_points') else path)


EXIT_GRACE = 120.0   # seconds the interpreter may take to exit once the tests are done


def pytest_unconfigure(config):
    """A process that hangs on its way out (a thread joined at exit that never ends: CI
    2026-11-23, a wedged ProcessPoolExecutor thread) prints every thread's stack and fails
    within EXIT_GRACE s instead of holding CI until its own limit."""
    faulthandler.dump_traceback_later(EXIT_GRACE, exit=True)


@pytest.fixture
def ros_env_context(ros_domain_id):
    """An initialised rclpy Context on a domain of its own, discovery as the environment sets
    it (unlike ros_context); shut down afterwards."""
    import rclpy

    # a domain per test: a participant of the test before (its /clock subscriber) can linger in
    # the discovery graph of the next context of this process and would match its endpoints
    c = rclpy.Context()
    rclpy.init(context=c, domain_id=ros_domain_id)
    yield c
    rclpy.try_shutdown(context=c)


@pytest.fixture
def keep_signal_handlers():
    """The command-line tools install SIGINT/SIGTERM handlers: put pytest's back."""
    import signal
    saved = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    yield
    for s, h in saved.items():
        signal.signal(s, h)
