"""beo-record: topics of the ROS 2 graph recorded to a new bag (:func:`record`)."""
from __future__ import annotations

import contextlib
import shutil
import threading
import time
from dataclasses import asdict, dataclass, field

from beo_ros.ros.bag.msgtypes import (check_topic_name, get_typestore, import_msg_class,
                                      normalize_msgtype)
from beo_ros.ros.bag.storage import BagWriter, storage_errors


COMMIT_PERIOD_S = 1.0   # beo-record commits its bag at least this often


class BagWriteError(Exception):
    """A bag could not be written (disk full, I/O error); the message says what is left."""


def _write_failure(writer, exc) -> str:
    """One line on a failed recording, after ``writer`` was aborted: the error, and what is
    left of the bag (its .db3 / .mcap file with the committed messages, or nothing: a bag with
    nothing committed is removed)."""
    reason = f'cannot write {writer.path}: {exc}'
    if not writer._opened:
        return reason
    if writer.storage == 'sqlite3':
        import sqlite3
        try:
            with contextlib.closing(sqlite3.connect(f'file:{writer.storage_file}?mode=ro',
                                                    uri=True)) as db:
                kept = db.execute('SELECT COUNT(*) FROM messages').fetchone()[0]
        except sqlite3.Error:
            kept = 0
    else:
        kept = writer.committed
    if kept:
        how = ('no metadata.yaml: play or read that file itself, or' if writer.storage ==
               'sqlite3' else 'no footer:')
        return (f'{reason}; {writer.storage_file} keeps the {kept} message(s) committed before '
                f'the error ({how} beo-bag-recover {writer.path} -o NEW makes a closed bag of '
                'them)')
    shutil.rmtree(writer.path, ignore_errors=True)
    return f'{reason}; the unfinished bag was removed (nothing in it was committed)'


@dataclass
class RecordStats:
    bag: str
    storage: str
    messages: int = 0
    wall_s: float = 0.0
    stopped_by: str = ''
    topics: dict = field(default_factory=dict)   # topic -> {'type', 'count'}

    def to_dict(self) -> dict:
        return asdict(self)

    def table(self) -> str:
        rows = [('topic', 'type', 'count')] + [(t, d['type'], str(d['count']))
                                               for t, d in self.topics.items()]
        widths = [max(len(r[i]) for r in rows) for i in range(3)]
        lines = ['  '.join(c.ljust(w) for c, w in zip(r, widths)).rstrip() for r in rows]
        lines.insert(1, '  '.join('-' * w for w in widths))
        lines.append(f'{self.messages} messages in {self.wall_s:.3f} s -> {self.bag} '
                     f'({self.storage}, stopped by {self.stopped_by})')
        return '\n'.join(lines)


def parse_topic_specs(specs) -> dict:
    """['/a', '/b:pkg/msg/T', ...] -> {'/a': None, '/b': 'pkg/msg/T'}.

    ``ValueError`` for a bad topic name or type, or a topic given twice with different types.
    """
    out = {}
    for s in specs:
        topic, sep, typ = s.partition(':')
        if not topic:
            raise ValueError(f'bad topic spec {s!r}')
        check_topic_name(topic)
        typ = normalize_msgtype(typ) if sep else None
        old = out.get(topic)
        if old and typ and old != typ:
            raise ValueError(f'{topic} is given twice, as {old} and as {typ}')
        out[topic] = typ or old
    return out


def resolve_topic_types(node, topics: dict, wait: float = 10.0,
                        stop: threading.Event | None = None) -> dict:
    """Fill in ``None`` types from the graph (waiting up to ``wait`` s); the given ones are
    normalized ('pkg/Type' -> 'pkg/msg/Type'). ``KeyError`` if not found, ``KeyboardInterrupt``
    if ``stop`` gets set first, ``ValueError`` for a bad type name or if two names of one topic
    ('x' and '/x') are given different types."""
    resolved = {}
    for t, typ in topics.items():
        name = node.resolve_topic_name(t)
        typ = normalize_msgtype(typ) if typ else None
        old = resolved.get(name)
        if old and typ and old != typ:
            raise ValueError(f'{name} is given twice, as {old} and as {typ}')
        resolved[name] = typ or old
    topics = resolved
    deadline = time.monotonic() + wait
    while True:
        missing = [t for t, typ in topics.items() if typ is None]
        if not missing:
            return topics
        graph = dict(node.get_topic_names_and_types())
        for t in missing:
            if graph.get(t):
                topics[t] = normalize_msgtype(graph[t][0])
        if all(typ is not None for typ in topics.values()):
            return topics
        if stop is not None and stop.is_set():
            raise KeyboardInterrupt('interrupted while waiting for publishers of: ' + ', '.join(
                t for t, typ in topics.items() if typ is None))
        if time.monotonic() > deadline:
            raise KeyError('no publisher found within {:g} s for: {}'.format(
                wait, ', '.join(t for t, typ in topics.items() if typ is None)))
        time.sleep(0.05)


def _subscription_qos(node, topic: str, depth: int = 100):
    """Reliable/transient-local only if every current publisher offers it (as ros2 bag does)."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    infos = node.get_publishers_info_by_topic(topic)
    reliable = bool(infos) and all(i.qos_profile.reliability == ReliabilityPolicy.RELIABLE
                                   for i in infos)
    latched = bool(infos) and all(i.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL
                                  for i in infos)
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                      reliability=ReliabilityPolicy.RELIABLE if reliable
                      else ReliabilityPolicy.BEST_EFFORT,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL if latched
                      else DurabilityPolicy.VOLATILE)


class _Recorder:
    """Subscribes ``topics`` ({topic: msgtype}) as their publishers appear, spinning ``node`` with
    ``executor`` (added to it and shut down if ``own_exec``), and writes what they receive to the
    open ``writer`` in batches, counted in ``stats``, as :func:`record` describes."""

    def __init__(self, node, writer: BagWriter, topics: dict, stats: RecordStats, *, executor,
                 own_exec: bool, commit_every: float):
        self.node, self.writer, self.topics, self.stats = node, writer, topics, stats
        self.executor, self.own_exec, self.commit_every = executor, own_exec, commit_every
        self.subs = []
        self.unsubscribed = dict(topics)
        self._pending = []   # (topic, stamp ns, raw CDR) received and not yet written
        self._lock = threading.Lock()
        self._t0 = self._t_poll = self._t_commit = time.monotonic()
        self._uncommitted = False
        self._added = False   # the node is in our own executor

    def start(self, ready: threading.Event | None) -> None:
        """List the topics, subscribe those with publishers, then signal ``ready``."""
        for topic, typ in self.topics.items():
            self.stats.topics[topic] = {'type': typ, 'count': 0}
        self._subscribe_new()
        if self.own_exec:
            self.executor.add_node(self.node)
            self._added = True
        if ready is not None:
            ready.set()
        self._t0 = self._t_poll = self._t_commit = time.monotonic()

    def run(self, count: int | None, duration: float | None, stop: threading.Event) -> None:
        """Spin, subscribe, write and commit until ``count`` messages, ``duration`` s or
        ``stop``; ``stats.stopped_by`` says which."""
        while True:
            self.executor.spin_once(timeout_sec=0.05)
            if self.unsubscribed and time.monotonic() - self._t_poll > 0.05:
                self._t_poll = time.monotonic()
                self._subscribe_new()
            self._write_pending(count)
            self._commit_if_due()
            stopped_by = self._stop_reason(count, duration, stop)
            if stopped_by:
                self.stats.stopped_by = stopped_by
                break

    def finish(self) -> None:
        """Take the wall time, list the never-published topics in the bag (empty, unless the
        writer failed), drop the subscriptions and the executor if it is ours: also after a
        failure part-way through :meth:`start`, or one of these writes."""
        self.stats.wall_s = time.monotonic() - self._t0
        try:
            if not self.writer.failed:
                for topic, typ in self.unsubscribed.items():   # never published: listed, empty
                    self.writer.add_topic(topic, typ, reliable=False)
        finally:
            for s in self.subs:
                self.node.destroy_subscription(s)
            if self.own_exec:
                if self._added:
                    self.executor.remove_node(self.node)
                self.executor.shutdown()

    def _callback_for(self, topic: str):
        """A raw subscription callback queueing the message of ``topic``, stamped at receipt."""
        def cb(raw):
            with self._lock:
                self._pending.append((topic, self.node.get_clock().now().nanoseconds,
                                      bytes(raw)))
        return cb

    def _subscribe_new(self) -> None:
        """Subscribe to topics that now have publishers, with QoS adapted to their offers."""
        node = self.node
        for topic, typ in list(self.unsubscribed.items()):
            infos = node.get_publishers_info_by_topic(topic)
            if not infos:
                continue
            others = sorted({normalize_msgtype(i.topic_type) for i in infos} - {typ})
            if others:   # a subscription of one type gets nothing of theirs
                node.get_logger().warning(
                    f'{topic} has publishers of {", ".join(others)}: their messages are not '
                    f'recorded (the topic is recorded as {typ})')
            qos = _subscription_qos(node, topic)
            # the bag's offered QoS is that of the publishers matched now (a latched
            # publisher that appears after the recording started is replayed latched)
            self.writer.add_topic(topic, typ, reliable=qos.reliability.name == 'RELIABLE',
                                  transient_local=qos.durability.name == 'TRANSIENT_LOCAL')
            self.subs.append(node.create_subscription(import_msg_class(typ), topic,
                                                      self._callback_for(topic), qos, raw=True))
            del self.unsubscribed[topic]

    def _write_pending(self, count: int | None) -> None:
        """Write the messages received so far (none beyond ``count`` in total)."""
        with self._lock:
            batch, self._pending[:] = list(self._pending), []
        for topic, t, raw in batch:
            if count is not None and self.stats.messages >= count:
                break
            self.writer.write(topic, raw, t, self.topics[topic])
            self.stats.topics[topic]['count'] += 1
            self.stats.messages += 1
            self._uncommitted = True

    def _commit_if_due(self) -> None:
        """Commit what is written if ``commit_every`` s passed since the last commit."""
        # also when nothing new came: a burst followed by quiet is committed too
        if self._uncommitted and time.monotonic() - self._t_commit >= self.commit_every:
            self._t_commit = time.monotonic()
            self.writer.commit()
            self._uncommitted = False

    def _stop_reason(self, count: int | None, duration: float | None,
                     stop: threading.Event) -> str:
        """'count', 'duration' or 'interrupt' when the recording is to end, else ''."""
        if count is not None and self.stats.messages >= count:
            return 'count'
        if duration is not None and time.monotonic() - self._t0 >= duration:
            return 'duration'
        if stop.is_set():
            return 'interrupt'
        return ''


def record(node, bag_path, topics, *, storage: str = 'sqlite3', wait: float = 10.0,
           duration: float | None = None, count: int | None = None,
           stop: threading.Event | None = None, ready: threading.Event | None = None,
           executor=None, commit_every: float | None = None) -> RecordStats:
    """Record ``topics`` to a new bag at ``bag_path``, spinning ``node`` in the calling thread.

    Args:
        node: rclpy Node that only this call spins (its context must be initialized).
        topics: ``{topic: msgtype or None}`` / list of ``'TOPIC[:TYPE]'``; ``None`` types are
            discovered from the graph within ``wait`` s.
        duration: stop after this many seconds of recording; ``count``: after this many messages
            in total; ``stop``: an Event to end the recording (e.g. set by SIGINT).
        ready: set once all subscriptions exist (useful to start publishers in tests).
        commit_every: commit the messages written at least every this many seconds (default
            ``COMMIT_PERIOD_S``, 1 s), so that a crash or SIGKILL keeps them: a .db3 file then
            reads on its own (there is no metadata.yaml), an mcap file through
            :func:`recover_bag` (it has no footer).
    Messages are stored as received (raw CDR), stamped with the node clock at receipt. A topic is
    subscribed once it has a publisher (typed topics may have none yet), with reliability and
    durability adapted to what its publishers offer. ``KeyError``, before the bag is created,
    for a type without a definition or Python module; ``KeyboardInterrupt``, with no bag, if
    ``stop`` is set while untyped topics wait for a publisher. :class:`BagWriteError` when the
    bag cannot be written (disk full, ...): its message says what is left of the bag; no
    metadata.yaml is written then, a bag with nothing readable in it is removed.
    """
    from rclpy.executors import SingleThreadedExecutor
    if isinstance(topics, (list, tuple)):
        topics = parse_topic_specs(topics)
    stop = stop or threading.Event()
    topics = resolve_topic_types(node, dict(topics), wait, stop)
    for typ in set(topics.values()):   # before the bag exists: a bad type leaves no bag
        get_typestore([typ])
        import_msg_class(typ)
    stats = RecordStats(bag=str(bag_path), storage=storage)
    commit_every = COMMIT_PERIOD_S if commit_every is None else commit_every
    writer = BagWriter(bag_path, storage)
    own_exec = executor is None
    executor = executor or SingleThreadedExecutor(context=node.context)
    recorder = _Recorder(node, writer, topics, stats, executor=executor, own_exec=own_exec,
                         commit_every=commit_every)
    try:
        with writer:
            try:
                recorder.start(ready)
                recorder.run(count, duration, stop)
            finally:
                recorder.finish()
    except storage_errors() as e:
        raise BagWriteError(_write_failure(writer, e)) from None
    return stats
