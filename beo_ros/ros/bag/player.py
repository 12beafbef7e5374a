"""beo-replay: a bag's messages published into the ROS 2 graph (:func:`replay`)."""
from __future__ import annotations

import functools
import math
import threading
import time
import weakref
from dataclasses import asdict, dataclass, field
from pathlib import Path

from beo_ros.ros.bag.msgtypes import (CLOUD_TYPE, check_topic_name, import_msg_class,
                                      normalize_msgtype)
from beo_ros.ros.bag.scenes import MAX_NS
from beo_ros.ros.bag.storage import (_check_readable, _open_reader, _topic_set, cdr_payload,
                                     detect_storage, recorded_latched, storage_errors)


@dataclass
class TopicStats:
    topic: str            # topic published on (after remapping)
    bag_topic: str        # topic in the bag
    msgtype: str
    count: int = 0
    bytes: int = 0
    subscribers: int = 0  # matched subscriptions when replay ended


@dataclass
class ReplayStats:
    """What :func:`replay` sent."""

    bag: str
    storage: str
    rate: float
    loops: int = 0                      # completed passes over the bag
    messages: int = 0
    bytes: int = 0
    wall_s: float = 0.0                 # from the first to the last publish
    bag_span_s: float = 0.0             # bag timestamp span of the messages sent in a pass
    waited_s: float = 0.0               # time spent in --wait-subscribers
    interrupted: bool = False
    topics: dict = field(default_factory=dict)   # published topic -> TopicStats
    skipped: dict = field(default_factory=dict)  # bag topic -> type not installed (all_topics)
    latched: list = field(default_factory=list)  # published topics played transient-local
    clock_messages: int = 0                      # /clock messages published (clock_hz)
    # messages published before an acknowledgement wait that timed out (reliable publishers):
    # a reliable subscriber may have lost up to this many (``ack_timeout`` of :func:`replay`)
    unacked: int = 0

    @property
    def messages_per_s(self) -> float:
        return self.messages / self.wall_s if self.wall_s > 0 else float('inf')

    def to_dict(self) -> dict:
        d = asdict(self)
        d['messages_per_s'] = round(self.messages_per_s, 3) if self.wall_s > 0 else None
        d['mbytes_per_s'] = (round(self.bytes / 1e6 / self.wall_s, 3) if self.wall_s > 0
                             else None)
        return d

    def table(self) -> str:
        rows = [('topic', 'bag topic', 'type', 'count', 'MB', 'subs')]
        for s in self.topics.values():
            rows.append((s.topic, s.bag_topic, s.msgtype, str(s.count), f'{s.bytes / 1e6:.2f}',
                         str(s.subscribers)))
        widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
        lines = ['  '.join(c.ljust(w) for c, w in zip(r, widths)).rstrip() for r in rows]
        lines.insert(1, '  '.join('-' * w for w in widths))
        rate = 'max' if self.rate == 0 else f'{self.rate:g}x'
        lines.append(f'{self.messages} messages, {self.bytes / 1e6:.2f} MB in {self.wall_s:.3f} s '
                     f'(bag span {self.bag_span_s:.3f} s, rate {rate}, {self.loops} pass(es)'
                     f'{", interrupted" if self.interrupted else ""})')
        if self.clock_messages:
            lines.append(f'{self.clock_messages} /clock messages')
        if self.latched:
            lines.append('played transient-local, as recorded: ' + ', '.join(self.latched))
        if self.unacked:
            lines.append(f'{self.unacked} message(s) not acknowledged by every reliable '
                         'subscriber in time (maybe lost)')
        if self.skipped:
            lines.append(f'{len(self.skipped)} topic(s) skipped, type not installed: '
                         + ', '.join(f'{t} ({m})' for t, m in self.skipped.items()))
        return '\n'.join(lines)


def parse_remaps(remaps) -> dict:
    """['OLD:=NEW', ...] -> {OLD: NEW}; ``ValueError`` if NEW is not a valid topic name or OLD is
    remapped twice."""
    out = {}
    for r in remaps or ():
        if ':=' not in r:
            raise ValueError(f'remap must be OLD:=NEW, got {r!r}')
        old, new = r.split(':=', 1)
        if not old or not new:
            raise ValueError(f'remap must be OLD:=NEW, got {r!r}')
        check_topic_name(new)
        if out.get(old, new) != new:
            raise ValueError(f'{old} is remapped twice: to {out[old]} and to {new}')
        out[old] = new
    return out


def make_qos(kind: str = 'reliable', depth: int = 10, latched: bool = False):
    """Keep-last ``depth``, ``kind`` reliability, volatile; ``latched``: reliable and
    transient-local whatever ``kind`` (what a latched topic's subscribers ask for)."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    if kind not in ('reliable', 'best_effort'):
        raise ValueError(f'qos must be reliable or best_effort, got {kind!r}')
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                      reliability=ReliabilityPolicy.RELIABLE if kind == 'reliable' or latched
                      else ReliabilityPolicy.BEST_EFFORT,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL if latched
                      else DurabilityPolicy.VOLATILE)


def _sleep_until(deadline: float, stop: threading.Event | None, tick=None,
                 period: float = 0.05) -> bool:
    """Sleep until time.monotonic() >= deadline; False if ``stop`` got set first. ``tick()``
    is called with time.monotonic() every ``period`` s while sleeping (a replay's /clock)."""
    next_tick = time.monotonic() + period
    while True:
        now = time.monotonic()
        left = deadline - now
        if stop is not None and stop.is_set():
            return False
        if left <= 0:
            return True
        if tick is not None and now >= next_tick:
            tick(now)
            next_tick += period * max(1, math.ceil((now - next_tick) / period))
            continue   # the tick took time: look at the clock again
        # here now < next_tick whenever there is a tick
        time.sleep(min(left, 0.05, next_tick - now if tick is not None else left))


_PUBLISHERS = weakref.WeakKeyDictionary()   # node -> {(topic, type, qos, depth, latched): pub}


def _publisher(node, msgtype: str, topic: str, qos: str, depth: int, latched: bool = False):
    """A publisher of ``node``, reused across replays (destroying one right after the last
    publish could drop reliable messages still in flight, creating one per replay piles up)."""
    cache = _PUBLISHERS.setdefault(node, {})
    key = (topic, msgtype, qos, depth, latched)
    if key not in cache:
        cache[key] = node.create_publisher(import_msg_class(msgtype), topic,
                                           make_qos(qos, depth, latched))
    return cache[key]


# how long a reliable publisher waits for its subscribers to acknowledge what it has sent
# before its keep-last history would overwrite a message not yet delivered
ACK_TIMEOUT_S = 5.0


class _AckGate:
    """Keeps a reliable keep-last publisher from overwriting messages its subscribers have not
    acknowledged: after every ``depth`` publishes since the last complete acknowledgement,
    :meth:`published` waits (``Publisher.wait_for_all_acked``, in 0.1 s steps so that ``stop``
    is seen) until they are all acknowledged or ``timeout`` s pass. Those that were not are
    counted in ``stats.unacked``. Best-effort publishers are not gated (nothing acknowledges)."""

    def __init__(self, timeout: float, stats, stop: threading.Event | None):
        self.timeout, self.stats, self.stop = timeout, stats, stop
        self._sent = {}   # id(publisher) -> [publisher, depth, publishes since the last wait]

    def published(self, pub) -> None:
        entry = self._sent.get(id(pub))
        if entry is None:
            from rclpy.qos import ReliabilityPolicy
            q = pub.qos_profile
            if q.reliability != ReliabilityPolicy.RELIABLE:
                return
            entry = self._sent[id(pub)] = [pub, max(1, int(q.depth)), 0]
        entry[2] += 1
        if entry[2] >= entry[1]:
            self._wait(entry)

    def flush(self) -> None:
        """Wait for the acknowledgement of everything sent (the end of a replay)."""
        for entry in self._sent.values():
            if entry[2]:
                self._wait(entry)

    def _wait(self, entry) -> None:
        from rclpy.duration import Duration
        pub, _, n = entry
        deadline = time.monotonic() + self.timeout
        while True:
            left = deadline - time.monotonic()
            if pub.wait_for_all_acked(Duration(nanoseconds=int(max(0.0, min(left, 0.1)) * 1e9))):
                break
            if left <= 0 or (self.stop is not None and self.stop.is_set()):
                self.stats.unacked += n
                break
        entry[2] = 0


def _publish_clock(pub, stamp_ns: int, stats) -> None:
    from rosgraph_msgs.msg import Clock
    from beo_ros.ros.conversions import stamp_from_ns
    msg = Clock(clock=stamp_from_ns(stamp_ns))
    pub.publish(msg)
    stats.clock_messages += 1


# with wait_subscribers and clock_hz: how long to wait for a /clock subscriber once the data
# topics have theirs (a use_sim_time node subscribes to /clock when it starts; without one,
# nothing needs /clock and the replay starts after this pause)
CLOCK_GRACE_S = 1.0


def _clock_tick(pub, stats, t_start: float, bag_t0: int, rate: float, t_next: int,
                now: float) -> None:
    """Publish the bag time at monotonic time ``now`` of a replay that started at ``t_start``,
    never past ``t_next``, the stamp of the message about to be sent (/clock must not step
    back when that message's own clock follows)."""
    _publish_clock(pub, min(bag_t0 + round((now - t_start) * rate * 1e9), t_next), stats)


def _check_output_types(node, conns, remap) -> None:
    """``KeyError`` if two bag topics of different types would be published on one topic (by
    remapping), or a published topic has another type in the graph already (rcl refuses the
    publisher). Topics are compared by their full names, as the publishers resolve them
    (bag topic 'x' is played on /x)."""
    outs = {}
    for c in conns:
        out = node.resolve_topic_name(remap.get(c.topic, c.topic))
        if outs.setdefault(out, (c.msgtype, c.topic))[0] != c.msgtype:
            typ, first = outs[out]
            if first == c.topic:   # two channels of one mcap topic: a remap cannot part them
                raise KeyError(f'{c.topic} was recorded in two types ({typ}, {c.msgtype}) and '
                               'one topic plays in one type: leave it out of the topics played')
            raise KeyError(f'{first} ({typ}) and {c.topic} ({c.msgtype}) would both be played '
                           f'on {out}: one topic has one type; remap one of them elsewhere')
    graph = dict(node.get_topic_names_and_types())
    for out, (typ, bag_topic) in outs.items():
        others = sorted({normalize_msgtype(t) for t in graph.get(out, ())} - {typ})
        if others:
            raise KeyError(f'{out} has type {others[0]} in the ROS graph; cannot play '
                           f'{bag_topic} ({typ}) on it')


class ClockRangeError(ValueError):
    """The bag's stamps go beyond what ``/clock`` holds (int32 seconds, 2038): a readable bag
    that cannot be played with the clock."""


class TopicNameError(ValueError):
    """A bag topic to play is not a valid ROS topic name (and is not remapped to one)."""


class BagReadError(ValueError):
    """A bag turned out unreadable (corrupt database, truncated file) during :func:`replay`;
    ``stats``: what was played before."""

    def __init__(self, message: str, stats: ReplayStats):
        super().__init__(message)
        self.stats = stats


def _replay_connections(reader, bag_path, topics, all_topics: bool, remap: dict) -> list:
    """The connections of the open bag ``reader`` to play: those of ``topics``, all of them
    (``all_topics``) or the PointCloud2 ones. ``KeyError`` for a topic in ``topics`` or a
    remapped topic that is not in the bag, :class:`TopicNameError` for a topic to play that
    is not a valid ROS topic name and is not remapped."""
    if topics:
        wanted = _topic_set(topics)
        missing = wanted - {c.topic for c in reader.connections}
        if missing:
            raise KeyError(f'topics not in bag {bag_path}: {sorted(missing)}')
        conns = [c for c in reader.connections if c.topic in wanted]
    elif all_topics:
        conns = list(reader.connections)
        for c in conns:   # a damaged channel or schema record: no valid type name
            normalize_msgtype(c.msgtype)
    else:
        conns = [c for c in reader.connections if c.msgtype == CLOUD_TYPE]
    unknown = set(remap) - {c.topic for c in reader.connections}
    if unknown:   # a typo would otherwise play on the old name
        raise KeyError(f'remapped topics not in bag {bag_path}: {sorted(unknown)}')
    for c in conns:   # rclpy would refuse its publisher with a multi-line exception
        if c.topic not in remap:
            try:
                check_topic_name(c.topic)
            except ValueError as e:
                why = str(e).removeprefix(f'bad topic name {c.topic!r}: ')
                raise TopicNameError(f'{bag_path}: topic {c.topic!r} is not a valid ROS topic '
                                     f'name ({why}): remap it to one (--remap OLD:=NEW) to '
                                     'play it') from None
    return conns


def _replay_publishers(node, conns, remap: dict, stats: ReplayStats, qos: str, depth: int,
                       strict: bool) -> tuple[list, dict, dict]:
    """Publishers for the connections to play -> (the connections kept, {bag topic: publisher},
    {published topic: its first publisher}); adds their topics to ``stats.topics`` (and
    ``stats.latched``). A topic of a type not installed raises ``KeyError`` if ``strict`` (it
    was asked for), else it is left out and listed in ``stats.skipped``."""
    kept, pubs, pub_by_out = [], {}, {}
    for c in conns:
        out = remap.get(c.topic, c.topic)
        if c.topic in stats.skipped:
            continue
        if c.topic not in pubs:
            try:
                latched = recorded_latched(c)
                # keep every latched message for late subscribers (one per static
                # broadcaster on /tf_static), not only the last ``depth``
                pubs[c.topic] = _publisher(node, c.msgtype, out, qos,
                                           max(depth, int(getattr(c, 'msgcount', 0) or 0))
                                           if latched else depth, latched)
                if latched:
                    stats.latched.append(out)
            except KeyError:   # type not installed: fatal only for a topic asked for
                if strict:
                    raise
                stats.skipped[c.topic] = c.msgtype
                continue
            pub_by_out.setdefault(out, pubs[c.topic])
            stats.topics.setdefault(out, TopicStats(out, c.topic, c.msgtype))
        kept.append(c)
    return kept, pubs, pub_by_out


def _wait_for_subscribers(pubs: dict, clock, wait_subscribers: int, wait_timeout: float,
                          stop: threading.Event | None, stats: ReplayStats) -> bool:
    """Wait until every publisher of ``pubs`` has ``wait_subscribers`` matched subscriptions
    and ``clock`` (if any) one, or ``CLOCK_GRACE_S`` more; ``TimeoutError`` after
    ``wait_timeout`` s. False if ``stop`` got set first (``stats.interrupted``); the time
    waited goes to ``stats.waited_s``."""
    t_wait = time.monotonic()
    deadline = t_wait + wait_timeout
    clock_grace = None   # once the data topics match, up to 1 s more for /clock
    while True:
        counts = {p.topic_name: p.get_subscription_count() for p in pubs.values()}
        short = {t: c for t, c in counts.items() if c < wait_subscribers}
        if not short:
            if clock is None or clock.get_subscription_count() > 0:
                break
            clock_grace = clock_grace or time.monotonic() + CLOCK_GRACE_S
            if time.monotonic() >= clock_grace:
                break
        if stop is not None and stop.is_set():
            stats.interrupted = True
            return False
        if short and time.monotonic() > deadline:
            raise TimeoutError(f'waited {wait_timeout:g} s for {wait_subscribers} '
                               f'subscriber(s); matched: {short}')
        time.sleep(0.02)
    stats.waited_s = time.monotonic() - t_wait
    return True


class _Player:
    """Sends the messages of ``conns`` of an open bag with ``pubs`` ({bag topic: publisher}),
    timed as :func:`replay` describes, and counts them in ``stats``."""

    def __init__(self, reader, conns, pubs: dict, remap: dict, stats: ReplayStats, *,
                 rate: float, clock, clock_hz: float, stop: threading.Event | None,
                 on_publish, ack_timeout: float):
        self.reader, self.conns, self.pubs, self.remap = reader, conns, pubs, remap
        self.stats, self.rate, self.clock, self.clock_hz = stats, rate, clock, clock_hz
        self.stop, self.on_publish = stop, on_publish
        self.acks = _AckGate(ack_timeout, stats, stop)
        self._t_first = None   # monotonic time of the first publish
        self._t_start = None   # monotonic time of the pass's first message (rate > 0)

    def play(self, n_passes: int | None) -> None:
        """Pass after pass over the bag, ``n_passes`` times (None: until stopped), then wait
        for the acknowledgement of what was sent."""
        while n_passes is None or self.stats.loops < n_passes:
            bag_t0 = self._play_pass()
            if self.stats.interrupted:
                break
            self.stats.loops += 1
            if bag_t0 is None:  # nothing to play: don't spin forever with --loop
                break
        self.acks.flush()

    def _play_pass(self) -> int | None:
        """One pass over the bag -> the stamp of its first message (None: it has none)."""
        self._t_start = None
        bag_t0 = None            # stamp of the pass's first message: the timing's origin
        sent_t0 = sent_t1 = None  # stamps of the first and last message sent
        for conn, t, raw in self.reader.messages(connections=self.conns):
            if bag_t0 is None:
                bag_t0 = t
            if not self._wait_until_due(t, bag_t0):
                self.stats.interrupted = True
                break
            if self.clock is not None:
                _publish_clock(self.clock, t, self.stats)
            self._send(conn, t, raw)
            sent_t0 = t if sent_t0 is None else sent_t0
            sent_t1 = t
        if sent_t0 is not None:   # not the message an interrupt kept from being sent
            self.stats.bag_span_s = (sent_t1 - sent_t0) / 1e9
        return bag_t0

    def _wait_until_due(self, t: int, bag_t0: int) -> bool:
        """Wait until the message stamped ``t`` is due (publishing /clock in between); False
        if ``stop`` got set first."""
        if self.rate > 0:
            if self._t_start is None:
                self._t_start = time.monotonic()
            tick = None if self.clock is None else functools.partial(
                _clock_tick, self.clock, self.stats, self._t_start, bag_t0, self.rate, t)
            return _sleep_until(self._t_start + (t - bag_t0) / 1e9 / self.rate, self.stop, tick,
                                1.0 / self.clock_hz if self.clock_hz > 0 else 0.05)
        return not (self.stop is not None and self.stop.is_set())

    def _send(self, conn, t: int, raw) -> None:
        """Publish one message of the bag and count it."""
        data = cdr_payload(raw)
        pub = self.pubs[conn.topic]
        pub.publish(data)
        self.acks.published(pub)
        now = time.monotonic()
        self._t_first = now if self._t_first is None else self._t_first
        # from the first to the last publish, kept current for a BagReadError's stats
        self.stats.wall_s = now - self._t_first
        ts = self.stats.topics[self.remap.get(conn.topic, conn.topic)]
        ts.count += 1
        ts.bytes += len(data)
        self.stats.messages += 1
        self.stats.bytes += len(data)
        if self.on_publish is not None:
            self.on_publish(ts.topic, data, t)


def replay(bag_path, node, *, topics=None, all_topics: bool = False, remap=None,
           rate: float = 1.0, loop: bool = False, loops: int | None = None,
           qos: str = 'reliable', depth: int = 10, wait_subscribers: int = 0,
           wait_timeout: float = 10.0, stop: threading.Event | None = None,
           on_publish=None, clock_hz: float = 0.0,
           ack_timeout: float = ACK_TIMEOUT_S) -> ReplayStats:
    """Publish the messages of a bag with ``node``'s publishers; returns what was sent.

    Args:
        bag_path: rosbag2 directory (sqlite3 or mcap) or a single ``.db3``/``.mcap`` file.
        node: an rclpy Node; it need not be spun (publishing does not need an executor). Its
            publishers are created on first use and reused by later replays with that node.
        topics: bag topics to play, one name or several (any type; ``KeyError`` if one's
            type is not installed); default: every PointCloud2 topic, or every topic with
            ``all_topics`` (topics of types not installed are then skipped, listed in
            ``stats.skipped``).
        remap: ``{bag_topic: published_topic}`` or a list of ``'OLD:=NEW'`` strings.
        rate: timing factor: a message is sent at ``t0 + (stamp - first_stamp) / rate``; ``0``
            publishes as fast as possible.
        loop: repeat until ``stop`` is set; ``loops`` caps the number of passes (default 1).
        qos: 'reliable' or 'best_effort' (history keep-last ``depth``, volatile). A reliable
            publisher waits for its subscribers' acknowledgements after every ``depth``
            messages (at most ``ack_timeout`` s; what was not acknowledged by then is counted in
            ``stats.unacked``) and at the end, so that a fast replay (``rate=0``) does not
            overwrite undelivered messages in its history; best-effort subscribers can still
            miss messages (nothing tells the publisher). A topic
            recorded from transient-local publishers only (``recorded_latched``, e.g.
            /tf_static) is played reliable and transient-local, as recorded, so that late and
            transient-local subscribers (tf2's static listener) get it; ``stats.latched``
            lists such topics.
        wait_subscribers: before sending, wait until every played topic has at least this many
            matched subscriptions, at most ``wait_timeout`` s (then raise ``TimeoutError``).
        stop: set it (e.g. from a signal handler) to end early; ``stats.interrupted`` is then True.
        on_publish: ``callable(published_topic, raw_bytes, bag_stamp_ns)`` after every publish.
        clock_hz: > 0: also publish the bag time on /clock (``rosgraph_msgs/Clock``, best
            effort, depth 1, as ``ros2 bag play --clock``) before every message and at this
            rate in between, for nodes with ``use_sim_time``; ``stats.clock_messages``.
    """
    if not (math.isfinite(rate) and rate >= 0):
        raise ValueError(f'rate must be a finite number >= 0, got {rate}')
    if not (math.isfinite(clock_hz) and clock_hz >= 0):
        raise ValueError(f'clock_hz must be a finite number >= 0, got {clock_hz}')
    remap = parse_remaps(remap) if isinstance(remap, (list, tuple)) else dict(remap or {})
    # as the publishers will: 'x' is /x (of the node's namespace), for the checks of one type
    # per topic
    remap = {old: node.resolve_topic_name(new) for old, new in remap.items()}
    bag_path = Path(bag_path)
    n_passes = loops if loops is not None else (None if loop else 1)
    stats = ReplayStats(bag=str(bag_path), storage=detect_storage(bag_path), rate=float(rate))
    _check_readable(bag_path)
    try:
        with _open_reader(bag_path) as reader:
            conns = _replay_connections(reader, bag_path, topics, all_topics, remap)
            _check_output_types(node, conns, remap)
            conns, pubs, pub_by_out = _replay_publishers(node, conns, remap, stats, qos, depth,
                                                         strict=bool(topics))
            if not conns:
                return stats
            # rosbags' end_time is one past the last stamp: 2**63, beyond an int64, for a
            # last stamp of 2**63 - 1
            last_ns = reader.end_time - 1
            if clock_hz > 0 and last_ns > MAX_NS:
                raise ClockRangeError(f'{bag_path}: its stamps go past 2038 ({last_ns} ns), '
                                      'beyond what /clock (int32 seconds) holds: play it '
                                      'without the clock')
            # made before the wait, so that discovery matches /clock with the data topics
            # best effort, depth 1, volatile: rclcpp's ClockQoS
            clock = (_publisher(node, 'rosgraph_msgs/msg/Clock', '/clock', 'best_effort', 1)
                     if clock_hz > 0 else None)
            if wait_subscribers > 0 and not _wait_for_subscribers(
                    pubs, clock, wait_subscribers, wait_timeout, stop, stats):
                return stats
            _Player(reader, conns, pubs, remap, stats, rate=rate, clock=clock, clock_hz=clock_hz,
                    stop=stop, on_publish=on_publish, ack_timeout=ack_timeout).play(n_passes)
            for out, ts in stats.topics.items():
                ts.subscribers = pub_by_out[out].get_subscription_count()
    except TimeoutError:   # --wait-subscribers (an OSError too)
        raise
    except storage_errors() as e:   # a corrupt database, a truncated file
        raise BagReadError(str(e) or type(e).__name__, stats) from e
    return stats
