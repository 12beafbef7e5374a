"""The beo_ros ROS 2 node: classify, orient and complete segmented object clouds.

Subscribes to every topic in ``input_topics`` (sensor_msgs/PointCloud2; sensor-data QoS, or
reliable with ``input_reliability``) and publishes, in the input cloud's frame:

- ``~/estimates`` beo_interfaces/ObjectEstimate (label, class probabilities, pose, dimensions),
- ``~/completed`` sensor_msgs/PointCloud2 (x y z probability) of the completed object,
- ``~/pose`` geometry_msgs/PoseStamped (object centre; orientation = the object frame, z up,
  x along the heading: a turn about up only in a frame whose z is up),
- ``~/markers`` visualization_msgs/MarkerArray (label text + box) for RViz, with a lifetime
  (``marker_lifetime``), deleted when the topic's cloud is rejected or fails,
- ``/diagnostics`` diagnostic_msgs/DiagnosticArray (rates, stage latencies, counters).

Services ``~/classify`` and ``~/complete`` take one cloud each. Each input topic keeps only its
latest unprocessed cloud; ``workers`` worker threads convert, estimate and publish, so services
stay responsive. With ``worker_processes`` N > 0 the threads hand the estimates to N spawned
processes, each with its own copy of the model bank, so N estimates run in parallel without
sharing the node's GIL (an embedding script then needs the ``if __name__ == '__main__':``
guard of multiprocessing's spawn). Results of one topic are published in the order its clouds
were received, even when several of its clouds are in flight on different workers.
"""
from __future__ import annotations

import collections
import contextlib
import os
import re
import signal
import sys
import threading
import time

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseStamped
from rcl_interfaces.msg import SetParametersResult
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.duration import Duration
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.exceptions import ParameterUninitializedException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import (HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_policy_name_from_kind,
                       qos_profile_sensor_data)
from rclpy.signals import SignalHandlerOptions
from rclpy.task import Future
from rclpy.time import Time
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header
from visualization_msgs.msg import MarkerArray

from beo_ros.core.bank import (TooFewPoints, format_class_prior, load_models,
                               parse_class_prior, resolve_model_dir, shipped_models)
from beo_ros.ros.conversions import (CloudFormatError, cloud_to_xyz, completed_cloud,
                                     estimate_to_msg, interfaces)
from beo_ros.ros.env import check_domain_id
from beo_ros.ros.markers import auto_lifetime, delete_all_markers, delete_markers, object_markers
from beo_ros.ros.params import (CHECKED_AT_START, declare, default_model_dir,
                                package_params_file, refusal, vector_reason)
from beo_ros.ros.procpool import (BrokenProcessPool, EstimateTimeout, EstimatorPool, PoolRetired,
                                  warm_up_points)

# the public names (default_model_dir: re-exported from beo_ros.ros.params)
__all__ = ['IN_PROCESS_BANK', 'BeoNode', 'InputRejected', 'StartupError', 'default_model_dir',
           'drain_executor', 'load_bank', 'main', 'make_executor', 'prior_text',
           'with_class_prior']

try:  # optional: TF gives the up vector when base_frame is set
    import tf2_ros
except ImportError:  # tf2_ros is not on PyPI; parameters are used instead
    tf2_ros = None

LOG_THROTTLE_SEC = 5.0
MARKER_ACK_WAIT = 1.0  # s a shutting-down node waits for its DELETEALL to be acknowledged
LATENCY_WINDOW = 200  # samples kept per stage for the p50 in diagnostics
# seconds destroy_node gives a spinning executor to take the answers of the calls it waited for
ANSWER_WAIT = 1.0
# a message-lost report of this many or more is garbage (seen from Fast DDS: 2^31 - 1, 2^64 - 1)
MAX_PLAUSIBLE_LOST = 2**31 - 1
# the counters of what becomes of a cloud or service call (the terms of the README's identity):
# a worker thread counts them as its cloud leaves in_flight, a service call when it is done
OUTCOMES = frozenset({'processed', 'rejected', 'rejected_format', 'rejected_too_few_points',
                      'errors', 'dropped_shutdown', 'service_failures'})
BASE_FRAME_WITHOUT_TF = ('base_frame is set but tf2_ros is not installed; using the '
                         'sensor_origin and up_vector parameters')
# what /diagnostics model_dir (and the logs) say of a bank passed to the constructor: no
# directory it came from is known, and the model_dir parameter was not loaded
IN_PROCESS_BANK = '<bank given in-process>'


def _main_lacks_guard() -> bool:
    """True when the program's ``__main__`` is a file without an ``if __name__ ==
    '__main__':`` test (or one that cannot be read): spawned worker processes run it again,
    so a script that creates the node unguarded breaks them. beo-node's script has the guard."""
    path = getattr(sys.modules.get('__main__'), '__file__', None)
    if not path:   # interactive: nothing to run again
        return False
    try:
        with open(path, encoding='utf-8', errors='replace') as f:
            source = f.read()
    except OSError:
        return True
    return re.search(r'''__name__\s*==\s*['"]__main__['"]''', source) is None


class _BlasCaps:
    """The BLAS thread caps (``blas_threads``) of this process's live nodes: the newest one
    applies, and the original limits come back once the last of them is destroyed. (Each node
    restored the limits it had found: destroying the first of two gave the second the library
    default, and destroying both in turn left the first one's cap in place.)"""

    def __init__(self):
        self._lock = threading.Lock()
        self._caps = []          # (token, threads) of the live nodes, oldest first
        self._original = None    # the first cap's limiter: it restores the original limits

    def add(self, n):
        """Cap the BLAS threads at ``n``; returns the token to ``remove`` it with."""
        from threadpoolctl import threadpool_limits
        token = object()
        with self._lock:
            limiter = threadpool_limits(limits=n, user_api='blas')
            if self._original is None:
                self._original = limiter
            self._caps.append((token, n))
        return token

    def remove(self, token):
        from threadpoolctl import threadpool_limits
        with self._lock:
            self._caps = [c for c in self._caps if c[0] is not token]
            if self._caps:
                threadpool_limits(limits=self._caps[-1][1], user_api='blas')
            elif self._original is not None:
                self._original.restore_original_limits()
                self._original = None


_BLAS_CAPS = _BlasCaps()


class StartupError(RuntimeError):
    """The node cannot start (bad model directory, bad parameters, interfaces not built)."""


class InputRejected(ValueError):
    """One input cloud or request cannot be estimated; ``kind`` names the counter."""

    def __init__(self, message: str, kind: str = 'rejected'):
        super().__init__(message)
        self.kind = kind


def _estimator_rejected(e: ValueError) -> InputRejected:
    """The InputRejected of the estimator's ValueError ``e``: too few points left after the
    outlier and cluster removal counts in ``rejected_too_few_points`` as well (it counted in
    ``rejected`` only, unlike a cloud with too few points as it came)."""
    kind = 'rejected_too_few_points' if isinstance(e, TooFewPoints) else 'rejected'
    return InputRejected(f'estimator rejected the cloud: {e}', kind)


def with_class_prior(bank, text: str):
    """``bank`` with the class prior of the ``class_prior`` parameter ('' keeps the bank's own);
    a copy sharing the models. Raises ValueError for a bad value (naming what is wrong)."""
    prior = parse_class_prior(text)
    return bank if prior is None else bank.with_class_prior(prior)


def prior_text(bank) -> str:
    """The bank's class prior as the ``class_prior`` parameter would write it."""
    prior = getattr(bank, 'class_prior', 'train')
    if isinstance(prior, str):
        return prior
    return format_class_prior(bank.classes, prior)   # names with a comma quoted


def load_bank(model_dir: str):
    """Load a model bank, turning every failure into a StartupError naming the path."""
    path = resolve_model_dir(model_dir)
    if not path.exists():
        raise StartupError(f"model_dir '{path}' does not exist (shipped models, by name: "
                           f"{', '.join(shipped_models()) or 'none'})")
    if not path.is_dir():
        raise StartupError(f"model_dir '{path}' is not a directory")
    try:
        return load_models(str(path))
    except Exception as e:  # ModelError names the bad file; anything else is wrapped
        raise StartupError(f"cannot load models from '{path}': {type(e).__name__}: {e}") from e


class BeoNode(Node):
    """Bayesian Eigenobjects estimator node (default name ``beo``).

    Args:
        node_name: ROS node name.
        bank: optional already-loaded model bank (skips ``model_dir`` loading; for embedding
            and tests). /diagnostics ``model_dir`` then reads IN_PROCESS_BANK, and setting
            ``model_dir`` loads that directory.
        **kwargs: passed to :class:`rclpy.node.Node` (context, namespace, parameter_overrides...).

    Raises:
        StartupError: the models cannot be loaded (message names the path/file), a parameter
            is invalid, or beo_interfaces is not built.
    """

    def __init__(self, node_name: str = 'beo', *, bank=None, **kwargs):
        super().__init__(node_name, **kwargs)
        self._workers = []
        self._blas_limits = None
        self._pool = None
        self._pool_lock = threading.Lock()  # the pool and the bank it serves; shutdown
        self._pool_cond = threading.Condition(self._pool_lock)
        self._replacing = None   # the broken pool being replaced (outside the lock)
        self._reload_gen = 0   # the latest model_dir reload (a newer one wins)
        self._reload_lock = threading.Lock()   # one reload starts processes at a time
        self._reload_threads = set()   # under _svc_threads_lock, as the service threads
        self._pool_closed = False
        self._destroyed = False       # destroy_node has begun
        self._rcl_destroyed = False   # ... and rclpy's part of it is done
        self._svc_threads = set()   # service calls being served (each in a thread of its own)
        self._svc_threads_lock = threading.Lock()
        self._svc_answers = set()   # answers handed to the executor, not yet taken (events)
        try:
            self._setup(bank)
        except BaseException:
            self._shutdown_worker()
            self._shutdown_pool()
            self._restore_blas()
            super().destroy_node()
            self._destroyed = self._rcl_destroyed = True
            raise

    # ------------------------------------------------------------------ setup
    def _setup(self, bank):
        """Everything the constructor does after the base class, in order (the constructor
        undoes it when this raises)."""
        srvs = self._import_interfaces()
        params, topics = self._read_parameters()
        self._setup_models(bank)
        self._setup_stats()
        self._setup_tf()
        sub_group = MutuallyExclusiveCallbackGroup()
        self._svc_group = ReentrantCallbackGroup()
        self._timer_group = MutuallyExclusiveCallbackGroup()
        self._create_publishers()
        self._setup_queue()
        # the throw-away estimate comes before the subscriptions: a node that listens is ready
        # (a bag replay that waits for the subscriber would otherwise see its first cloud wait
        # for the warm-up and the next replace it as stale)
        self._warm_up()
        self._subscribe(topics, params['input_reliability'], sub_group)
        self._create_services(srvs)
        self._diag_timer = self.create_timer(self.get_parameter('diagnostics_period').value,
                                             self._publish_diagnostics,
                                             callback_group=self._timer_group)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self._start_workers()

    def _import_interfaces(self):
        """The beo_interfaces service module (``self._msgs``: its messages)."""
        try:
            self._msgs = interfaces()
            import beo_interfaces.srv as srvs
        except ImportError as e:
            raise StartupError(f'beo_interfaces is not available ({e}); run scripts/setup') from e
        return srvs

    def _read_parameters(self):
        """Declare and check the parameters; (parameter values, resolved input topics)."""
        try:
            self._declare_parameters()
        except Exception as e:  # out-of-range / wrong-type overrides
            raise StartupError(f'invalid parameter: {type(e).__name__}: {e}') from e
        # a typo (-p yaw_stepdeg:=5.0) would otherwise be ignored unseen, and so would the
        # qos_overrides of ROS (no publisher or subscription of the node declares them)
        self.ignored_parameters = sorted(
            n for n in getattr(self, '_parameter_overrides', {}) if not self.has_parameter(n))
        if self.ignored_parameters:
            qos = any(n.startswith('qos_overrides.') for n in self.ignored_parameters)
            self.get_logger().warning(
                f"ignoring unknown parameter(s) {', '.join(self.ignored_parameters)} (see "
                'config/beo.yaml for the parameters'
                + ('; QoS overrides are not supported: input_reliability sets the QoS of the '
                   'input_topics' if qos else '') + ')')
        try:
            params = self._params()
            input_topics = self.get_parameter('input_topics').value
        except ParameterUninitializedException as e:
            # an empty array override ('[]') leaves the parameter without a type or value
            raise StartupError(f'invalid parameter: {e} (an empty array is not a value: give '
                               'at least one element)') from None
        reason = refusal(((name, params[name]) for name in CHECKED_AT_START), params)
        if reason:
            raise StartupError(f'invalid parameter: {reason}')
        return params, self._resolve_topics(input_topics)

    def _resolve_topics(self, input_topics) -> dict:
        """The ``input_topics`` without repeats: resolved name -> the entry to subscribe with
        (before the models load: a bad name fails fast). rcl remaps the name it subscribes
        with: given the resolved one, a remap of that (``-r /a:=/b -r /b:=/c``) applied too."""
        topics = {}
        for topic in input_topics:
            try:
                resolved = self.resolve_topic_name(topic)
            except Exception as e:  # rclpy raises RCLError / ValueError types of its own
                raise StartupError(f'invalid parameter: input_topics entry {topic!r}: {e}') from e
            if resolved in topics:
                self.get_logger().warning(f"input_topics lists '{resolved}' twice: one "
                                          'subscription')
                continue
            topics[resolved] = topic
        return topics

    def _setup_models(self, bank):
        """Worker counts, BLAS limits, the model bank (``bank`` or loaded from ``model_dir``)
        with the class prior, and the worker processes."""
        self._bank_lock = threading.Lock()  # serialises model reloads (the swap itself is atomic)
        self._n_procs = int(self.get_parameter('worker_processes').value)
        # each process is fed by a thread of its own
        self._n_workers = max(int(self.get_parameter('workers').value), self._n_procs)
        self._blas_limits = self._limit_blas_threads(int(self.get_parameter('blas_threads').value))
        # at most `workers` estimates run at once (worker threads and service calls together)
        self._est_slots = threading.Semaphore(self._n_workers)
        self._svc_waiting = 0
        self._svc_lock = threading.Lock()
        # the directory the models come from ('' or a shipped name resolved: diagnostics name
        # it), or IN_PROCESS_BANK (then any model_dir set loads that directory)
        if bank is None:
            self._serving_dir = str(resolve_model_dir(self.get_parameter('model_dir').value))
            bank = load_bank(self._serving_dir)
            self.get_logger().info(f"loaded models from '{self._serving_dir}': "
                                   f'classes {bank.classes}')
        else:
            self._serving_dir = IN_PROCESS_BANK
            self.get_logger().info(f'using the model bank given in-process (model_dir not '
                                   f'loaded): classes {bank.classes}')
        self._base_bank = bank  # as loaded: the class_prior parameter is applied to a copy
        self._serving_base = bank   # the models the estimates use now (a reload may be pending)
        try:
            bank = with_class_prior(bank, self.get_parameter('class_prior').value)
        except ValueError as e:
            raise StartupError(f'invalid parameter: {e}') from None
        self.get_logger().info(f'class prior: {prior_text(bank)}')
        self._bank = bank
        # the class_prior value in force (under _pool_lock): a reload that takes over applies
        # it (the parameter itself is stored only once _on_set_parameters has returned)
        self._prior = self.get_parameter('class_prior').value
        if self._n_procs:
            self._start_pool(bank)

    def _start_pool(self, bank):
        """Start the ``worker_processes`` (blocks for seconds)."""
        t0 = time.monotonic()
        try:
            self._pool = self._new_pool(bank)
        except Exception as e:
            if not self.context.ok():   # e.g. a SIGTERM to the group ended the processes
                raise ExternalShutdownException() from None
            hint = ("; a script that creates the node needs the if __name__ == '__main__': "
                    'guard' if _main_lacks_guard() else '')
            raise StartupError(f'cannot start {self._n_procs} worker process(es) '
                               f'({type(e).__name__}: {e}){hint}') from e
        if not self.context.ok():   # shut down by a signal during the seconds that took
            raise ExternalShutdownException()
        self.get_logger().info(f'{self._n_procs} worker process(es) ready in '
                               f'{time.monotonic() - t0:.1f} s')

    def _setup_stats(self):
        """The counters and the stage latency windows (all zero)."""
        self._stats_lock = threading.Lock()
        self._counters = collections.Counter({k: 0 for k in (
            'received', 'processed', 'dropped_stale', 'order_waits', 'rejected',
            'rejected_format',
            'rejected_too_few_points', 'errors', 'downsampled', 'nonfinite_points',
            'outlier_points', 'off_cluster_points', 'outside_grid_points',
            'service_calls', 'service_failures', 'worker_restarts', 'worker_timeouts',
            'reload_failures', 'dropped_shutdown', 'service_dropped_shutdown',
            'incompatible_publishers',
            'middleware_lost', 'middleware_lost_implausible', 'empty_frame_id')})
        self._latency = collections.defaultdict(lambda: collections.deque(maxlen=LATENCY_WINDOW))
        self._last_diag = (time.monotonic(), collections.Counter(self._counters))

    def _setup_tf(self):
        """The TF listener when ``base_frame`` is set (and tf2_ros installed)."""
        self._tf_buffer = None
        self._tf_listener = None
        self._tf_lock = threading.Lock()
        if self.get_parameter('base_frame').value and tf2_ros is None:
            self.get_logger().warning(BASE_FRAME_WITHOUT_TF)
        elif self.get_parameter('base_frame').value:
            # listening from the start: created on the first cloud, the buffer would still be
            # empty for it and the next few (rejected: no transform)
            self._tf_buffer = tf2_ros.Buffer()
            self._tf_listener = tf2_ros.TransformListener(self._tf_buffer, self)

    def _create_publishers(self):
        self._pub_estimate = self.create_publisher(self._msgs.ObjectEstimate, '~/estimates', 10)
        self._pub_completed = self.create_publisher(PointCloud2, '~/completed', 10)
        self._pub_pose = self.create_publisher(PoseStamped, '~/pose', 10)
        self._pub_markers = self.create_publisher(MarkerArray, '~/markers', 10)
        self._pub_diag = self.create_publisher(DiagnosticArray, '/diagnostics', 10)

    def _setup_queue(self):
        """The latest-cloud slots the worker threads take from, and the publish order."""
        self._cond = threading.Condition()
        self._slots = {}  # resolved topic -> (PointCloud2, receipt monotonic time)
        self._stop = False
        # per-topic publish order: a worker takes ticket n of its topic when it dequeues a
        # cloud and publishes (or gives up its turn) only once ticket n - 1 is done
        self._tickets = collections.Counter()   # topic -> next ticket to hand out
        self._turn = collections.Counter()      # topic -> ticket allowed to publish now
        self._turn_cond = threading.Condition()
        self._in_flight = 0
        # per topic, in its publish order: when its last markers went out (monotonic s), for
        # the automatic lifetime; topics whose markers may still be up
        self._marker_sent = {}
        self._marked = set()
        self._outcome = threading.local()   # .counts: the OUTCOMES counted so far, not yet added

    def _subscribe(self, topics, reliability, group):
        """One subscription per resolved topic (``topics``: resolved -> the entry;
        ``reliability``: input_reliability)."""
        self._topics = []
        qos = qos_profile_sensor_data
        if reliability == 'reliable':
            qos = QoSProfile(depth=qos_profile_sensor_data.depth, history=HistoryPolicy.KEEP_LAST,
                             reliability=ReliabilityPolicy.RELIABLE)
        for topic, entry in topics.items():
            events = SubscriptionEventCallbacks(
                incompatible_qos=lambda e, t=topic: self._on_incompatible_qos(e, t),
                message_lost=lambda e, t=topic: self._on_message_lost(e, t))
            self.create_subscription(
                PointCloud2, entry, lambda msg, t=topic: self._on_cloud(msg, t),
                qos, callback_group=group, event_callbacks=events)
            self._topics.append(topic)
        self._topic_index = {t: i for i, t in enumerate(self._topics)}

    def _create_services(self, srvs):
        # the default service QoS keeps the last 10 requests: of a burst of 40 calls the
        # middleware dropped 29 before the executor took them, unanswered and uncounted
        svc_qos = QoSProfile(history=HistoryPolicy.KEEP_ALL,
                             reliability=ReliabilityPolicy.RELIABLE)
        self._srv_classify = self.create_service(srvs.Classify, '~/classify', self._on_classify,
                                                 qos_profile=svc_qos,
                                                 callback_group=self._svc_group)
        self._srv_complete = self.create_service(srvs.Complete, '~/complete', self._on_complete,
                                                 qos_profile=svc_qos,
                                                 callback_group=self._svc_group)

    def _start_workers(self):
        self._workers = [threading.Thread(target=self._worker_loop, name=f'beo_worker_{i}',
                                          daemon=True)
                         for i in range(self._n_workers)]
        for w in self._workers:
            w.start()
        procs = f' and {self._n_procs} worker process(es)' if self._n_procs else ''
        self.get_logger().info(f'listening on {self._topics} with {self._n_workers} worker '
                               f'thread(s){procs}')

    def _new_pool(self, bank):
        """Worker processes with a copy of ``bank``, warmed up (blocks for a few seconds)."""
        return EstimatorPool(self._n_procs, bank, int(self.get_parameter('blas_threads').value))

    def _limit_blas_threads(self, n):
        """Cap the BLAS thread pools of the process at ``n`` threads (0: leave them).

        The workers already run estimates in parallel; a multi-threaded BLAS under each of them
        oversubscribes the cores, and OpenBLAS's spinning threads then slow every estimate down
        many times over when the machine is busy. Restored by destroy_node (the cap of another
        node of the process, if one lives on).
        """
        if n <= 0:
            return None
        try:
            return _BLAS_CAPS.add(n)
        except ImportError:
            self.get_logger().warning('threadpoolctl is not installed: blas_threads is ignored')
            return None

    def _restore_blas(self):
        token, self._blas_limits = self._blas_limits, None
        if token is not None:
            _BLAS_CAPS.remove(token)

    def _declare_parameters(self):
        # what _params reads: every parameter but input_topics (read once, at start-up)
        self._values = tuple(n for n in declare(self.declare_parameter) if n != 'input_topics')

    def _params(self) -> dict:
        return {p: self.get_parameter(p).value for p in self._values}

    def _on_set_parameters(self, params) -> SetParametersResult:
        merged = self._params()
        merged.update({p.name: p.value for p in params})
        reason = refusal(((p.name, p.value) for p in params), merged)
        if reason:
            return SetParametersResult(successful=False, reason=reason)
        new = {p.name: p.value for p in params}
        # against the models answering (a failed background reload leaves the old ones)
        want_dir = str(resolve_model_dir(new['model_dir'])) if 'model_dir' in new else None
        reload = want_dir is not None and want_dir != self._serving_dir
        reprior = ('class_prior' in new
                   and new['class_prior'] != self.get_parameter('class_prior').value)
        if ('model_dir' in new and not reload
                and new['model_dir'] != self.get_parameter('model_dir').value):
            # back to the models answering while a reload is starting (or after it failed):
            # that reload is cancelled
            try:
                with_class_prior(self._serving_base, merged['class_prior'])
            except ValueError as e:
                return SetParametersResult(successful=False, reason=str(e))
            with self._bank_lock:
                self._reload_gen += 1
                self._base_bank = self._serving_base
        if reload or reprior:
            try:
                base = load_bank(new['model_dir']) if reload else self._base_bank
                bank = with_class_prior(base, merged['class_prior'])
            except (StartupError, ValueError) as e:
                return SetParametersResult(successful=False, reason=str(e))
            with self._bank_lock:
                self._base_bank = base
                with self._pool_lock:
                    self._prior = merged['class_prior']
                if reload and self._n_procs:
                    # new processes take seconds to start: not on the executor thread (clouds
                    # and service calls would wait, and the middleware drop clouds uncounted);
                    # the old ones serve until the new ones are ready
                    self._reload_gen += 1
                    thread = threading.Thread(target=self._reload_pool, name='beo_reload',
                                              daemon=True,
                                              args=(base, self._reload_gen, want_dir))
                    with self._svc_threads_lock:
                        self._reload_threads.add(thread)
                    thread.start()
                else:   # worker processes get the prior with each estimate: no new ones
                    with self._pool_lock:   # a reload may switch the models meanwhile
                        serving = self._serving_base if self._n_procs else base
                        try:
                            self._bank = with_class_prior(serving, merged['class_prior'])
                            self._serving_base = serving
                        except ValueError:  # names the classes of a reload still starting:
                            pass            # it applies the prior when it switches
            if reload and not self._n_procs:
                self._serving_dir = want_dir
                self.get_logger().info(f"reloaded models from '{want_dir}'")
            self.get_logger().info(f'class prior: {prior_text(bank)}')
        if new.get('base_frame') and tf2_ros is None:
            self.get_logger().warning(BASE_FRAME_WITHOUT_TF)
        if 'diagnostics_period' in new:  # re-timing (not re-creating) is safe while spinning
            self._diag_timer.timer_period_ns = int(new['diagnostics_period'] * 1e9)
            self._diag_timer.reset()
        return SetParametersResult(successful=True)

    # ------------------------------------------------------------------ inputs
    def _count(self, key, n=1):
        pending = getattr(getattr(self, '_outcome', None), 'counts', None)
        if pending is not None and key in OUTCOMES:
            pending[key] += n   # added with the end of the cloud or call: see _one_outcome
            return
        with self._stats_lock:
            self._counters[key] += n

    @contextlib.contextmanager
    def _one_outcome(self, in_flight=False):
        """Count what becomes of one cloud (``in_flight``: as it leaves in_flight) or service
        call in one step when it is done, so that a diagnostics snapshot finds the counter
        identity holding (a cloud rejected behind another one of its topic was counted in
        rejected while it waited in_flight for its turn; a failed call in rejected before
        service_failures)."""
        self._outcome.counts = counts = collections.Counter()
        try:
            yield
        finally:
            self._outcome.counts = None
            with self._cond:
                with self._stats_lock:
                    self._counters.update(counts)
                if in_flight:
                    self._in_flight -= 1

    def _count_removed(self, est):
        """Count the points the estimator removed from an input cloud before the voxelization,
        and those outside a metric grid (not from the warm-up's synthetic one)."""
        with self._stats_lock:
            self._counters['outlier_points'] += est.n_outliers
            self._counters['off_cluster_points'] += est.n_off_cluster
            self._counters['outside_grid_points'] += est.n_outside_grid

    def _on_incompatible_qos(self, event, topic):
        """A publisher on ``topic`` whose QoS cannot match the subscription's (e.g. a
        best-effort one with input_reliability 'reliable'): none of its clouds arrive."""
        self._count('incompatible_publishers', max(int(event.total_count_change), 1))
        self.get_logger().warning(
            f"a publisher on '{topic}' offers QoS incompatible with the subscription "
            f"(input_reliability '{self.get_parameter('input_reliability').value}'; policy "
            f'{qos_policy_name_from_kind(event.last_policy_kind)}): its clouds are not '
            'received')

    def _on_message_lost(self, event, topic):
        """The middleware reports clouds on ``topic`` lost before they reached the node. Fast
        DDS sometimes reports 2^31 - 1 or 2^64 - 1 of them at once for large samples: such a
        report is counted in ``middleware_lost_implausible``, not added."""
        change = int(event.total_count_change)
        if 0 < change < MAX_PLAUSIBLE_LOST:
            self._count('middleware_lost', change)
            return
        self._count('middleware_lost_implausible')
        self.get_logger().warning(
            f"the middleware reported {change} clouds lost on '{topic}': implausible, not "
            "counted in middleware_lost", throttle_duration_sec=LOG_THROTTLE_SEC)

    def _on_cloud(self, msg, topic):
        """Subscription callback: keep only the latest cloud per topic."""
        with self._cond:
            self._count('received')
            if self._stop:   # destroy_node has begun: no worker takes it any more
                self._count('dropped_shutdown')
                return
            if topic in self._slots:
                self._count('dropped_stale')
            self._slots[topic] = (msg, time.monotonic())
            self._cond.notify()

    def _warm_up(self):
        """One throw-away estimate of a synthetic box so the first real cloud is not slow
        (worker processes warm themselves up before the pool reports ready)."""
        if self._n_procs:
            return
        t0 = time.monotonic()
        # without the point cleaning (nothing in it to warm up): a cluster_tolerance below the
        # synthetic face's point spacing (2 cm) left too few points, the estimate was rejected
        # and the first real cloud paid the warm-up
        p = dict(self._params(), outlier_mads=0.0, cluster_tolerance=0.0)
        try:
            self._estimate(warm_up_points(self._bank.spec), np.zeros(3),
                           np.array([0.0, 0.0, 1.0]), p, 0.5)
        except Exception as e:  # warm-up is best effort
            self.get_logger().debug(f'warm-up estimate failed: {type(e).__name__}: {e}')
        self._record('warm_up', time.monotonic() - t0)

    def _worker_loop(self):
        while True:
            with self._cond:
                while not self._slots and not self._stop:
                    self._cond.wait()
                if self._stop:
                    return   # clouds still waiting are counted by destroy_node
                topic = min(self._slots, key=lambda t: self._slots[t][1])  # oldest first
                msg, t_recv = self._slots.pop(topic)
                ticket = self._tickets[topic]
                self._tickets[topic] += 1
                self._in_flight += 1
            with self._one_outcome(in_flight=True):
                try:
                    self._process(topic, msg, t_recv, ticket)
                except BaseException as e:  # noqa: BLE001 - never let one cloud end the worker:
                    # a SystemExit or KeyboardInterrupt raised in an estimate (a library's
                    # sys.exit, or one sent back by a worker process) is no signal here (signals
                    # reach only the main thread); it ended the thread and the clouds waited
                    # unseen
                    if self._shutting_down():   # e.g. published after a signal shut rclpy down
                        self._count('dropped_shutdown')
                        continue
                    self._count('errors')
                    self.get_logger().error(f'estimation failed for a cloud on {topic}: '
                                            f'{type(e).__name__}: {e}',
                                            throttle_duration_sec=LOG_THROTTLE_SEC)

    def _shutting_down(self) -> bool:
        """destroy_node has begun, or the context was shut down (e.g. by a signal)."""
        return self._stop or not self.context.ok()

    def _wait_turn(self, topic, ticket) -> float:
        """Block until every earlier cloud of ``topic`` is published or given up; returns the
        seconds waited (counted in ``order_waits`` and the ``order_wait`` latency)."""
        if ticket is None:
            return 0.0
        with self._turn_cond:
            if self._turn[topic] == ticket:
                return 0.0
            t0 = time.monotonic()
            self._turn_cond.wait_for(lambda: self._turn[topic] == ticket)
            waited = time.monotonic() - t0
        self._count('order_waits')
        self._record('order_wait', waited)
        return waited

    def _end_turn(self, topic, ticket, unpublished=None):
        """Hand the publishing turn of ``topic`` to the next ticket (after our own turn came).
        ``unpublished``: the header of a cloud that was not published: the topic's markers
        are deleted in its turn first."""
        if ticket is not None:
            with self._turn_cond:
                self._turn_cond.wait_for(lambda: self._turn[topic] == ticket)
        if unpublished is not None:   # our turn: no other cloud of the topic publishes now
            self._unmark(topic, unpublished)
        if ticket is not None:
            with self._turn_cond:
                self._turn[topic] = ticket + 1
                self._turn_cond.notify_all()

    def _reject(self, where, err: InputRejected):
        self._count('rejected')
        if err.kind != 'rejected':
            self._count(err.kind)
        self.get_logger().warning(f'rejected input from {where}: {err}',
                                  throttle_duration_sec=LOG_THROTTLE_SEC)

    def _prepare(self, cloud, p, origin=None, up=None):
        """Cloud -> (points (n,3) float64, sensor origin (3,), up (3,)) in the cloud frame."""
        try:
            pts, n_bad = cloud_to_xyz(cloud)
        except CloudFormatError as e:
            raise InputRejected(f'malformed PointCloud2: {e}', 'rejected_format') from e
        if n_bad:
            self._count('nonfinite_points', n_bad)
        if len(pts) < p['min_points']:
            raise InputRejected(
                f'{len(pts)} finite points ({n_bad} non-finite dropped) < min_points '
                f"{p['min_points']}", 'rejected_too_few_points')
        if len(pts) > p['max_points']:
            keep = np.random.default_rng(0).choice(len(pts), p['max_points'], replace=False)
            pts = pts[np.sort(keep)]
            self._count('downsampled')
        if not cloud.header.frame_id:
            # estimated all the same (the cloud frame is implied), but no TF can place it
            self._count('empty_frame_id')
            self.get_logger().warning(
                "a cloud with an empty header.frame_id: its estimate is published in frame ''"
                + (", and up is up_vector, not TF's" if p['base_frame'] and up is None
                   else ''),   # (not when the service request gives up)
                throttle_duration_sec=LOG_THROTTLE_SEC)
        if up is None:
            up = self._tf_up(cloud.header.frame_id, p)
        if up is None:
            up = p['up_vector']
        if origin is None:
            origin = p['sensor_origin']
        for name, v, nz in (('sensor_origin', origin, False), ('up', up, True)):
            reason = vector_reason(name, v, nonzero=nz)
            if reason:
                raise InputRejected(reason)
        return pts, np.asarray(origin, dtype=np.float64), np.asarray(up, dtype=np.float64)

    def _tf_up(self, frame_id, p):
        """Up (+z of base_frame) in ``frame_id`` from TF, or None when TF is not used."""
        if not p['base_frame'] or tf2_ros is None or not frame_id:
            return None
        with self._tf_lock:  # several workers may get here first at once
            if self._tf_buffer is None:
                self._tf_buffer = tf2_ros.Buffer()
                self._tf_listener = tf2_ros.TransformListener(self._tf_buffer, self)
        try:
            tf = self._tf_buffer.lookup_transform(frame_id, p['base_frame'], Time())
        except Exception as e:
            raise InputRejected(f"no transform {p['base_frame']} -> {frame_id}: {e}") from e
        x, y, z, w = (tf.transform.rotation.x, tf.transform.rotation.y,
                      tf.transform.rotation.z, tf.transform.rotation.w)
        return [2 * (x * z + y * w), 2 * (y * z - x * w), 1 - 2 * (x * x + y * y)]

    def _estimate(self, pts, origin, up, p, threshold, priority=False):
        """Run the bank in one of the ``workers`` estimation slots (service calls go first),
        in this process or in a worker process; core ValueError -> InputRejected.
        ``ModelBank.estimate_points`` is safe to call from several threads (its caches only
        gain immutable entries; scratch buffers are thread-local)."""
        if priority:
            with self._svc_lock:
                self._svc_waiting += 1
            try:
                self._est_slots.acquire()
            finally:
                with self._svc_lock:
                    self._svc_waiting -= 1
        else:
            while self._svc_waiting > 0:  # let pending service calls go first
                time.sleep(0.001)
            self._est_slots.acquire()
        try:
            cleaning = dict(outlier_mads=p['outlier_mads'] or None,   # 0: off
                            outlier_neighbors=p['outlier_neighbors'],
                            cluster_tolerance=p['cluster_tolerance'] or None)
            if self._n_procs:
                try:
                    est, classes = self._pool_estimate(
                        pts, origin, up, p['yaw_step_deg'], threshold, cleaning,
                        timeout=p['estimate_timeout'] or None)
                except ValueError as e:
                    raise _estimator_rejected(e) from e
                return est, classes
            bank = self._bank  # one bank per estimate, even if model_dir is reloaded meanwhile
            try:
                est = bank.estimate_points(pts, sensor_origin=origin, up=up,
                                           yaw_step_deg=p['yaw_step_deg'], threshold=threshold,
                                           **cleaning)
            except ValueError as e:
                raise _estimator_rejected(e) from e
            return est, list(bank.classes)
        finally:
            self._est_slots.release()

    def _pool_estimate(self, *args, timeout=None):
        """Estimate in a worker process -> (Estimate, class names). A dead process breaks the
        pool: it is replaced and the cloud tried once more (it may not be the cloud's fault).
        No answer within ``timeout`` s: the processes are killed and replaced, and the cloud
        is not tried again (it may be what hangs them); counted in worker_timeouts."""
        retried = False
        for _ in range(8):
            with self._pool_lock:   # the pool and the prior of the bank it serves, together
                pool, prior = self._pool, self._bank.class_prior
            if pool is None:
                raise RuntimeError('the worker processes are shut down')
            try:
                return pool.estimate(*args, class_prior=prior, timeout=timeout)
            except EstimateTimeout as e:
                self._count('worker_timeouts')
                self._replace_broken_pool(pool, e)
                raise
            except PoolRetired as e:  # not sent: the pool broke earlier, or a reload replaced it
                if pool.broken:
                    self._replace_broken_pool(pool, e)
                elif self._pool is pool:
                    raise
            except BrokenProcessPool as e:  # a process died while this cloud was in the pool
                self._replace_broken_pool(pool, e)
                if retried:
                    raise
                retried = True
        raise RuntimeError('no usable worker process pool')

    def _replace_broken_pool(self, broken, err):
        """Replace ``broken`` (unless another worker already did, or is doing it: then wait
        for that); counted in worker_restarts. The new processes start outside the pool lock
        (seconds), so a class_prior change meanwhile does not stall the executor."""
        with self._pool_cond:
            if self._replacing is broken:
                self._pool_cond.wait_for(lambda: self._replacing is not broken)
                return
            # a signal to the process group also ends the worker processes: no restart then
            if self._pool is not broken or self._pool_closed or self._shutting_down():
                return
            self._replacing = broken
            self._count('worker_restarts')
            # the hung estimate's thread may come second: the pool knows why it was killed
            what = ('an estimate took longer than estimate_timeout' if isinstance(
                err, EstimateTimeout) or getattr(broken, 'timed_out', False)
                else 'a worker process died')
            self.get_logger().error(f'{what} ({err}); restarting the {self._n_procs} worker '
                                    'process(es)')
        new = None
        try:
            broken.shutdown(timeout=1.0)
            new = self._new_pool(self._bank)
        finally:
            with self._pool_cond:
                self._replacing = None
                if new is not None and self._pool is broken and not self._pool_closed:
                    self._pool, new = new, None
                self._pool_cond.notify_all()
            if new is not None:   # shut down or reloaded meanwhile
                new.shutdown(timeout=None)

    def _reload_pool(self, base, gen, model_dir):
        """Thread: start worker processes for the models ``base``, then switch to them (with the
        class prior of that moment) unless a newer reload came meanwhile; estimates already sent
        to the old processes finish there. A failure keeps the old processes (logged, counted
        in reload_failures). Reloads start their processes one at a time, and one superseded
        by a newer reload (or by shutdown) before its turn starts none."""
        try:
            with self._reload_lock:
                if self._pool_closed or gen != self._reload_gen:
                    self.get_logger().info(f"reload of '{model_dir}' skipped: "
                                           + ('shutting down' if self._pool_closed
                                              else 'model_dir changed again'))
                    return
                self._reload_now(base, gen, model_dir)
        finally:
            with self._svc_threads_lock:
                self._reload_threads.discard(threading.current_thread())

    def _reload_now(self, base, gen, model_dir):
        t0 = time.monotonic()
        try:
            new = self._new_pool(base)
        except Exception as e:  # noqa: BLE001 - reported, the old processes keep serving
            if self._pool_closed:   # shut down meanwhile: the failure is the shutdown's
                self.get_logger().info(f"reload of '{model_dir}' abandoned: shutting down")
                return
            self._count('reload_failures')   # not 'errors': those count clouds
            self.get_logger().error(f"worker processes cannot load the models of '{model_dir}' "
                                    f'({type(e).__name__}: {e}); the models of '
                                    f"'{self._serving_dir}' still answer (set model_dir again "
                                    'to retry)')
            with self._bank_lock:
                if gen == self._reload_gen and not self._pool_closed:
                    # class_prior is checked against _base_bank: the models answering again
                    self._base_bank = self._serving_base
                    self._prior_after_failed_reload(model_dir)
            return
        with self._pool_lock:
            closed = self._pool_closed
            if closed or gen != self._reload_gen:
                old = new    # shut down, or superseded by a newer reload
            else:
                try:
                    bank = with_class_prior(base, self._prior)
                except ValueError:   # checked against these models when it was set
                    bank = base
                old, self._pool, self._bank, self._serving_base = self._pool, new, bank, base
                self._serving_dir = model_dir
        if old is not None:   # at shutdown, gone before destroy_node returns
            old.shutdown(timeout=5.0 if closed else None)
        if old is not new:
            self.get_logger().info(f"reloaded models from '{model_dir}' "
                                   f'({self._n_procs} new worker process(es) in '
                                   f'{time.monotonic() - t0:.1f} s)')

    def _prior_after_failed_reload(self, model_dir):
        """Under _bank_lock, after the reload of ``model_dir`` failed: the class_prior value in
        force was checked against those models, and only applied when they take over (set
        with model_dir, or while they started). It is applied to the models answering if it
        fits them; if it names the failed models' classes, they keep the prior they have and
        that becomes the value in force. Logged either way (before, the prior answering and
        the value a later reload applies could differ from each other and the parameter,
        unseen)."""
        with self._pool_lock:
            before = prior_text(self._bank)
            try:
                self._bank = with_class_prior(self._serving_base, self._prior)
                unfit = None
            except ValueError as e:
                unfit = e
                self._prior = before
            after = prior_text(self._bank)
        if unfit is not None:
            self.get_logger().warning(
                f"class_prior does not fit the models answering ({unfit}): it was set for "
                f"those of '{model_dir}', which failed to load; the class prior stays {after} "
                '(set class_prior for the models answering)')
        elif after != before:
            self.get_logger().info(f'class prior: {after} (set with the failed reload of '
                                   f"'{model_dir}', now applied to the models answering)")

    def _record(self, stage, seconds):
        with self._stats_lock:
            self._latency[stage].append(float(seconds))

    @staticmethod
    def _status(est, threshold):
        if est.completed_points is None or len(est.completed_points) == 0:
            return f'no voxel reaches completion probability {threshold:g}'
        return 'ok'

    def _process(self, topic, msg, t_recv, ticket=None):
        """Estimate one cloud and publish the results; with a ``ticket`` the publishing waits
        until the earlier clouds of ``topic`` are published (or rejected). A cloud not
        published deletes the topic's markers (in the same order): its object is gone."""
        published = False
        try:
            t0 = time.monotonic()
            self._record('queue_wait', t0 - t_recv)
            p = self._params()
            try:
                pts, origin, up = self._prepare(msg, p)
                t1 = time.monotonic()
                self._record('convert', t1 - t0)
                est, classes = self._estimate(pts, origin, up, p, p['completion_threshold'])
            except InputRejected as e:
                self._reject(topic, e)
                return
            self._count_removed(est)
            t2 = time.monotonic()
            self._record('estimate', t2 - t1)
            for stage, sec in (est.timings or {}).items():
                self._record(f'core_{stage}', sec)
            header = msg.header
            status = self._status(est, p['completion_threshold'])
            completed = completed_cloud(est, header) if p['publish_completed'] else None
            waited = self._wait_turn(topic, ticket)
            if not self.context.ok():   # a signal shut rclpy down meanwhile: nothing to send on
                self._count('dropped_shutdown')
                return
            t3 = time.monotonic()
            out = estimate_to_msg(est, header, topic, t3 - t_recv, include_cloud=False,
                                  status=status, class_names=classes)
            self._pub_estimate.publish(out)
            self._pub_pose.publish(PoseStamped(header=header, pose=out.pose))
            if completed is not None:
                self._pub_completed.publish(completed)
            self._pub_markers.publish(self._markers(est, out, header, topic, up,
                                                    p['marker_lifetime']))
            published = True
            t4 = time.monotonic()
            self._record('publish', t4 - t2 - waited)
            self._record('end_to_end', t4 - t_recv)
            self._count('processed')
        finally:
            self._end_turn(topic, ticket, None if published else msg.header)

    def _markers(self, est, out, header, topic, up, lifetime) -> MarkerArray:
        """Label text above the object and its box, ids unique per input topic, living
        ``lifetime`` s (0: automatic, see ``auto_lifetime``)."""
        idx = self._topic_index.get(topic, len(self._topic_index))
        now = time.monotonic()
        last = self._marker_sent.get(topic)
        self._marker_sent[topic] = now
        self._marked.add(topic)
        if not lifetime:
            lifetime = auto_lifetime(None if last is None else now - last)
        return object_markers(est, out, header, idx, up, lifetime)

    def _unmark(self, topic, header):
        """Delete ``topic``'s markers, if up (a cloud of it was not published)."""
        if topic not in self._marked or not self.context.ok():
            return
        self._marked.discard(topic)
        try:
            self._pub_markers.publish(
                delete_markers(header, self._topic_index.get(topic, len(self._topic_index))))
        except Exception as e:  # noqa: BLE001 - never hide what became of the cloud
            self.get_logger().debug(f'markers of {topic} not deleted: {type(e).__name__}: {e}')

    # ------------------------------------------------------------------ services
    async def _on_classify(self, request, response):
        return await self._serve_aside(request, response, complete=False)

    async def _on_complete(self, request, response):
        return await self._serve_aside(request, response, complete=True)

    async def _serve_aside(self, request, response, complete):
        """Serve a call in a thread of its own while the executor goes on: the clouds that
        arrive meanwhile are taken (and counted, and dropped as stale by the node's own rule)
        instead of overflowing the subscription's queue unseen, and parameters stay settable.
        """
        executor = self.executor
        if executor is None:   # not spun by an executor
            return self._serve(request, response, complete)
        done = Future(executor=executor)
        # a done callback makes set_result wake the executor, which then resumes this call
        done.add_done_callback(lambda _: None)

        taken = threading.Event()   # the executor resumed this call: it sends the answer

        def run():
            try:
                result = self._serve(request, response, complete)
            except BaseException as e:  # noqa: BLE001 - _serve reports its own; not expected
                result = e
            finally:
                with self._svc_threads_lock:
                    self._svc_threads.discard(threading.current_thread())
                    self._svc_answers.add(taken)
            try:
                if isinstance(result, BaseException):
                    done.set_exception(result)
                else:
                    done.set_result(result)
            except Exception:  # the executor is shut down: nobody waits for the answer
                with self._svc_threads_lock:
                    self._svc_answers.discard(taken)
                self._count('service_dropped_shutdown')

        thread = threading.Thread(target=run, name='beo_service', daemon=True)
        with self._svc_threads_lock:
            if self._destroyed:   # a call cut short by the shutdown: counted as in _serve
                self._count('service_calls')
                self._count('service_dropped_shutdown')
                self._shutdown_logger().info(
                    f"~/{'complete' if complete else 'classify'}: call not served, the node "
                    'is shutting down')
                response.success = False
                response.message = 'the node is shutting down'
                return response
            self._svc_threads.add(thread)
        thread.start()
        try:
            return await done
        finally:
            with self._svc_threads_lock:
                self._svc_answers.discard(taken)
            taken.set()

    def _serve(self, request, response, complete):
        with self._one_outcome():
            return self._serve_now(request, response, complete)

    def _serve_now(self, request, response, complete):
        t0 = time.monotonic()
        name = self.resolve_service_name('~/complete' if complete else '~/classify')
        self._count('service_calls')
        p = self._params()
        try:
            threshold = p['completion_threshold']
            if complete and not request.threshold <= 0:   # NaN is refused below, not ignored
                threshold = float(request.threshold)
                if not threshold <= 1.0:
                    raise InputRejected(f'threshold must be in (0, 1], got {threshold}')
            origin = up = None
            if request.has_sensor_origin:
                o = request.sensor_origin
                origin = [o.x, o.y, o.z]
            if request.has_up:
                u = request.up
                up = [u.x, u.y, u.z]
            pts, origin, up = self._prepare(request.cloud, p, origin, up)
            est, classes = self._estimate(pts, origin, up, p, threshold, priority=True)
            self._count_removed(est)
            header = request.cloud.header
            response.estimate = estimate_to_msg(
                est, header, name, time.monotonic() - t0, include_cloud=False,
                status=self._status(est, threshold), class_names=classes)
            if complete:
                response.completed_cloud = completed_cloud(est, header)
            response.success = True
            response.message = 'ok'
            self._record('service', time.monotonic() - t0)
        except InputRejected as e:
            self._reject(name, e)
            self._count('service_failures')
            response.success = False
            response.message = str(e)
        except BaseException as e:  # noqa: BLE001 - report, never crash the executor: a
            # SystemExit raised in an estimate (a library's sys.exit, or one sent back by a
            # worker process) ended its spin, and the node with it
            if not isinstance(e, Exception) and (
                    threading.current_thread() is threading.main_thread()):
                raise   # a Ctrl-C (called without an executor, on the main thread)
            response.success = False
            if self._shutting_down():   # e.g. a signal ended the worker processes meanwhile
                # as the stream's clouds: not an error of the call
                self._count('service_dropped_shutdown')
                self._shutdown_logger().info(
                    f'{name}: call not completed, the node is shutting down '
                    f'({type(e).__name__}: {e})')
                response.message = 'the node is shutting down'
                return response
            self._count('errors')
            self._count('service_failures')
            self.get_logger().error(f'{name} failed: {type(e).__name__}: {e}',
                                    throttle_duration_sec=LOG_THROTTLE_SEC)
            response.message = f'internal error: {type(e).__name__}: {e}'
        return response

    def wait_ready(self, timeout: float | None = None) -> bool:  # noqa: ARG002 - API kept
        """True: the warm-up estimate runs in the constructor, before the node subscribes, so
        a constructed node is ready (kept for scripts written when it ran in the background)."""
        return True

    # ------------------------------------------------------------------ diagnostics
    def counters(self) -> dict:
        """Snapshot of the counters (received, processed, dropped_stale, rejected, ...)."""
        with self._stats_lock:
            return dict(self._counters)

    def latency_p50(self) -> dict:
        """Median seconds per stage over the last samples."""
        with self._stats_lock:
            return {k: float(np.median(v)) for k, v in self._latency.items() if v}

    @property
    def worker_threads(self) -> int:
        """Worker threads in use: the ``workers`` parameter, at least ``worker_processes``."""
        return self._n_workers

    def backlog(self) -> dict:
        """Clouds not yet published: ``waiting`` for a worker (at most one per topic) and
        ``in_flight`` (taken by a worker)."""
        with self._cond:
            return {'waiting': len(self._slots), 'in_flight': self._in_flight}

    def _publish_diagnostics(self):
        now = time.monotonic()
        with self._cond:   # one snapshot: the counters and the clouds they do not count yet
            counters = self.counters()
            waiting, in_flight = len(self._slots), self._in_flight
        t_prev, prev = self._last_diag
        self._last_diag = (now, collections.Counter(counters))
        dt = max(now - t_prev, 1e-6)
        delta = {k: counters[k] - prev.get(k, 0) for k in counters}
        level, message = DiagnosticStatus.OK, 'ok'
        if delta['errors']:
            level, message = DiagnosticStatus.ERROR, f"{delta['errors']} estimation errors"
        elif delta['reload_failures']:
            level, message = (DiagnosticStatus.ERROR,
                              f"{delta['reload_failures']} model reload(s) failed")
        elif delta['worker_restarts']:
            level, message = (DiagnosticStatus.ERROR,
                              f"worker processes restarted {delta['worker_restarts']}x")
        elif delta['rejected']:
            level, message = DiagnosticStatus.WARN, f"{delta['rejected']} inputs rejected"
        elif delta['dropped_stale']:
            level, message = (DiagnosticStatus.WARN,
                              f"{delta['dropped_stale']} stale clouds dropped "
                              '(input faster than processing)')
        elif delta['incompatible_publishers']:   # their clouds never arrive
            level, message = (DiagnosticStatus.WARN,
                              f"{delta['incompatible_publishers']} publisher(s) with an "
                              'incompatible QoS (see input_reliability)')
        elif delta['middleware_lost']:
            level, message = (DiagnosticStatus.WARN,
                              f"{delta['middleware_lost']} clouds lost in the middleware")
        values = [KeyValue(key='received_hz', value=f"{delta['received'] / dt:.2f}"),
                  KeyValue(key='processed_hz', value=f"{delta['processed'] / dt:.2f}")]
        values += [KeyValue(key=f'latency_p50_{k}_ms', value=f'{v * 1e3:.1f}')
                   for k, v in sorted(self.latency_p50().items())]
        values += [KeyValue(key=k, value=str(v)) for k, v in sorted(counters.items())]
        values.append(KeyValue(key='input_topics', value=','.join(self._topics)))
        values.append(KeyValue(key='workers', value=str(self._n_workers)))
        values.append(KeyValue(key='worker_processes', value=str(self._n_procs)))
        values.append(KeyValue(key='class_prior', value=prior_text(self._bank)))
        values.append(KeyValue(key='model_dir', value=str(self._serving_dir)))   # answering
        values.append(KeyValue(key='waiting', value=str(waiting)))
        values.append(KeyValue(key='in_flight', value=str(in_flight)))
        # with the namespace ('r1/beo'): beo nodes in /r1 and /r2 sent statuses of one name
        name = self.get_fully_qualified_name().lstrip('/')
        status = DiagnosticStatus(level=level, name=f'{name}: estimator',
                                  message=message, hardware_id='beo_ros', values=values)
        self._pub_diag.publish(DiagnosticArray(header=self._diag_header(), status=[status]))

    def _diag_header(self):
        return Header(stamp=self.get_clock().now().to_msg())

    # ------------------------------------------------------------------ teardown
    def _shutdown_worker(self):
        """Stop the worker threads; each finishes (and publishes) the cloud it is working on.
        Service calls being served are waited for too (within the same 30 s), and then the
        executor's taking their answers (within ANSWER_WAIT s)."""
        cond = getattr(self, '_cond', None)
        if cond is not None:
            with cond:
                self._stop = True
                cond.notify_all()
                waiting = len(self._slots)   # taken by no worker: they stop before the next
                self._slots.clear()
                self._count('dropped_shutdown', waiting)
        deadline = time.monotonic() + 30.0
        with self._svc_threads_lock:
            threads = list(self._workers) + list(self._svc_threads)
        for worker in threads:
            if worker.is_alive() and worker is not threading.current_thread():
                worker.join(timeout=max(deadline - time.monotonic(), 0.1))
        # an executor that still spins sends their answers once it takes them: before the
        # services are destroyed (destroyed first, the answers were lost, uncounted, and its
        # spin raised InvalidHandle); those it does not take in time are counted
        with self._svc_threads_lock:
            answers = list(self._svc_answers)
        deadline = time.monotonic() + ANSWER_WAIT
        for taken in answers:
            taken.wait(max(deadline - time.monotonic(), 0.0))
        with self._svc_threads_lock:
            lost, self._svc_answers = len(self._svc_answers), set()
        if lost:
            self._count('service_dropped_shutdown', lost)

    def _shutdown_pool(self):
        """Stop the worker processes (after the threads: their last estimates need them)."""
        with self._pool_lock:
            self._pool_closed = True
            pool, self._pool = self._pool, None
        if pool is not None:
            try:
                pool.shutdown(timeout=5.0)
            except KeyboardInterrupt:   # another Ctrl-C: do not wait for the processes to end
                pool.kill()

    def _delete_all_markers(self, log):
        """DELETEALL on ~/markers once the worker threads are done, if any are up: no object
        is published any more (not when a signal shut the context down: nothing to send on;
        ``main``'s handlers leave it up)."""
        if not getattr(self, '_marked', None) or not self.context.ok():
            return
        self._marked.clear()
        try:
            self._pub_markers.publish(delete_all_markers(self._diag_header()))
            # the node is about to go: without the acknowledgement, destroying the publisher
            # right away lost the DELETEALL about one time in five (beo-node on Ctrl-C)
            if not self._pub_markers.wait_for_all_acked(Duration(seconds=MARKER_ACK_WAIT)):
                log.debug(f'markers deleted, not acknowledged within {MARKER_ACK_WAIT:g} s')
        except Exception as e:  # noqa: BLE001 - best effort: they expire anyway
            log.debug(f'markers not deleted: {type(e).__name__}: {e}')

    def _shutdown_logger(self):
        """A logger for shutdown messages: not the node's, whose /rosout publisher may be gone
        with the context. Named after the node's logger ('r1.beo.shutdown' in /r1)."""
        return rclpy.logging.get_logger(f'{self.get_logger().name}.shutdown')

    def destroy_node(self):
        """Stop the worker threads and processes, then destroy the node. Idempotent; called
        again after a Ctrl-C cut it short (main does), it does what is left without waiting for
        the threads."""
        if self._rcl_destroyed:
            return
        log = self._shutdown_logger()
        if self._destroyed:
            self._shutdown_pool()
            self._restore_blas()
            self._destroy_rcl(log)
            return
        self._destroyed = True
        try:
            self._shutdown_worker()
        except KeyboardInterrupt:   # a second Ctrl-C: do not wait for the estimates in flight
            log.warning('interrupted again: not waiting for the estimates in flight')
        self._delete_all_markers(log)
        self._shutdown_pool()
        with self._svc_threads_lock:
            reloads = list(self._reload_threads)
        try:
            for thread in reloads:   # each shuts down the processes it was starting
                thread.join(timeout=30.0)
        except KeyboardInterrupt:   # daemon threads: they end with the process
            log.warning('interrupted again: not waiting for the model reloads')
        self._restore_blas()
        lost = self._counters['dropped_shutdown']
        if lost:
            log.info(f'{lost} cloud(s) received but not published: waiting for a worker or '
                     'estimated while shutting down')
        lost = self._counters['service_dropped_shutdown']
        if lost:
            log.info(f'{lost} service answer(s) not given: computed while shutting down, too '
                     'late to be sent, or the call came during the shutdown')
        self._destroy_rcl(log)

    def _destroy_rcl(self, log):
        """rclpy's destroy_node, to the end: a further Ctrl-C must not leave the node half
        destroyed (it can be called again: it destroys what is left)."""
        while True:
            try:
                super().destroy_node()
                break
            except KeyboardInterrupt:
                log.warning('interrupted again: destroying the node all the same')
        self._rcl_destroyed = True


def make_executor(context=None):
    """The executor ``main`` spins the node with: single-threaded.

    The node's own worker threads (and processes) do the heavy work; the executor only hands
    over clouds, sets parameters and starts each service call in a thread of its own (which
    waits for an estimation slot), resuming it when the thread is done.
    rclpy's MultiThreadedExecutor took ~0.7 of a core of Python at 20 clouds/s in the node
    bench, starving the estimates and delaying the clouds until the DDS queue dropped them.
    """
    return SingleThreadedExecutor(context=context)


def drain_executor(executor):
    """Let callbacks already handed to the executor's thread pool finish, then shut it down.

    (rclpy 7.1 ``Executor.shutdown`` destroys its guard condition without waiting for them.)
    """
    pool = getattr(executor, '_executor', None)
    if pool is not None:
        try:
            pool.shutdown(wait=True)
        except KeyboardInterrupt:   # a further Ctrl-C: stop waiting for them
            pool.shutdown(wait=False)
    executor.shutdown(timeout_sec=5.0)


def _shut_down(executor, node):
    """main's last steps: drain the executor, destroy the node, shut rclpy down. A further
    Ctrl-C meanwhile cuts the waits short (see ``BeoNode.destroy_node``) but every step still
    runs: before, one that came during the last steps ended the process with a traceback
    (1 of 15 double Ctrl-Cs with service calls in flight)."""
    steps = ([lambda: drain_executor(executor)] if executor is not None else []) + (
        [node.destroy_node] if node is not None else []) + [rclpy.try_shutdown]
    for step in steps:
        for _ in range(100):   # each step can run again and gets further on every try
            try:
                step()
                break
            except KeyboardInterrupt:
                rclpy.logging.get_logger('beo.shutdown').warning(
                    'interrupted again: shutting down all the same')


def _interrupt(signum, frame):  # noqa: ARG001 - signal handler signature
    """SIGTERM (ros2 launch, docker stop) ends beo-node as a Ctrl-C does."""
    raise KeyboardInterrupt(signal.Signals(signum).name)


class _Interrupts:
    """main's Ctrl-C and SIGTERM: each raises KeyboardInterrupt in the main thread with the ROS
    context still up, so that destroy_node can publish its DELETEALL on ~/markers (rclpy's own
    handlers shut the context down first: ros2/rclpy#1287).

    Python runs a signal handler only once the main thread is back in Python, and a spinning
    executor waits in C until its next timer or message (seconds): a thread reads the signal's
    byte from the wakeup fd and wakes ``executor``, whose spin then returns to Python. Main
    thread only; ``close`` restores the handlers found."""

    def __init__(self):
        self.executor = None
        self._read, self._write = os.pipe()
        os.set_blocking(self._write, False)   # the C handler writes: it must never block
        self._old = {sig: signal.signal(sig, handler) for sig, handler in (
            (signal.SIGINT, signal.default_int_handler), (signal.SIGTERM, _interrupt))}
        self._old_fd = signal.set_wakeup_fd(self._write, warn_on_full_buffer=False)
        threading.Thread(target=self._wake, name='beo_signal_wake', daemon=True).start()

    def _wake(self):
        try:
            while os.read(self._read, 512):
                executor = self.executor
                if executor is not None:
                    try:
                        executor.wake()
                    except Exception:  # noqa: BLE001 - shut down meanwhile: nothing to wake
                        pass
        finally:   # the write end was closed
            os.close(self._read)

    def close(self):
        self.executor = None
        signal.set_wakeup_fd(self._old_fd)
        for sig, handler in self._old.items():   # None: one not set from Python
            signal.signal(sig, signal.SIG_DFL if handler is None else handler)
        os.close(self._write)


USAGE = """usage: beo-node [-h] [--ros-args (-p NAME:=VALUE | --params-file FILE) ...]

Runs the beo node (node name 'beo') until Ctrl-C. Parameters, with their defaults and
ranges: config/beo.yaml of the package (e.g. beo-node --ros-args --params-file
config/beo.yaml); arrays of doubles need decimal points (-p up_vector:="[0.0, -1.0, 0.0]").
"""


def _params_files(argv) -> list:
    """The files of the ``--params-file FILE`` arguments after ``--ros-args`` in ``argv``."""
    ros = argv[argv.index('--ros-args') + 1:] if '--ros-args' in argv else []
    return [ros[i + 1] for i, a in enumerate(ros[:-1]) if a == '--params-file']


def main(args=None):
    """Run the node until Ctrl-C, SIGTERM or shutdown (then it deletes its markers); exits with
    status 1 if it cannot start."""
    argv = sys.argv[1:] if args is None else list(args)
    own = argv[:argv.index('--ros-args')] if '--ros-args' in argv else argv
    if '-h' in own or '--help' in own:
        from beo_ros.cli import print_help
        where = package_params_file()
        where = f"The package's config/beo.yaml: {where}\n" if where else ''
        return print_help(USAGE + where + '\n' + __doc__)   # 141, quietly, into a closed pipe
    if own:   # e.g. '-p model_dir:=...' without --ros-args would be ignored unseen
        print(f"{USAGE}\nbeo-node: error: unrecognized arguments: {' '.join(own)} (ROS "
              'arguments go after --ros-args)', file=sys.stderr)
        sys.exit(2)
    try:
        # not rclpy's signal handlers: they shut the context down before destroy_node runs
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
        check_domain_id(rclpy.get_default_context())
    except Exception as e:  # e.g. --params-file of a missing or malformed file
        rclpy.try_shutdown()
        missing = [f for f in _params_files(argv) if not os.path.isfile(f)]
        if missing:   # rcl's 'Error opening YAML file' names neither the cause nor the remedy
            where = package_params_file()
            print(f'beo-node: cannot start: --params-file {missing[0]}: no such file'
                  + (f" (the package's config/beo.yaml is {where})" if where else ''),
                  file=sys.stderr)
        else:
            print(f'beo-node: cannot start: {type(e).__name__}: {e}', file=sys.stderr)
        sys.exit(1)
    interrupts = _Interrupts()
    node = None
    executor = None
    failed = False
    try:
        node = BeoNode()
        executor = make_executor()
        interrupts.executor = executor
        executor.add_node(node)
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except StartupError as e:
        rclpy.logging.get_logger('beo').fatal(f'cannot start: {e}')
        failed = True
    except Exception:
        if rclpy.ok():
            raise
        # rclpy was shut down while the node was starting (e.g. creating a publisher on the
        # dead context; not by a signal since main's own handlers, which leave it up): a
        # normal shutdown
    finally:
        interrupts.executor = None   # not spinning any more: nothing to wake
        try:
            _shut_down(executor, node)
        finally:
            interrupts.close()
    if failed:
        sys.exit(1)


if __name__ == '__main__':
    sys.exit(main())
