"""The command-line tools: beo-replay, beo-record, beo-pcd2bag and beo-bag-recover."""
from __future__ import annotations

import contextlib
import json
import os
import signal
import sys
import threading
import time
from pathlib import Path

from beo_ros.cli import INTERRUPTED, TERMINATED, ArgumentParser, count, interruptible, number
from beo_ros.ros.bag.msgtypes import CLOUD_TYPE, check_node_name
from beo_ros.ros.bag.player import (ACK_TIMEOUT_S, BagReadError, ClockRangeError,
                                     TopicNameError, parse_remaps, replay)
from beo_ros.ros.bag.recorder import BagWriteError, parse_topic_specs, record
from beo_ros.ros.bag.recover import recover_bag
from beo_ros.ros.bag.scenes import (DEFAULT_FRAME, DEFAULT_INPUT_TOPIC, PLANE_TOPIC, UP_TOPIC,
                                    check_cloud_topic, pcd_to_bag)
from beo_ros.ros.bag.storage import STORAGES, bag_info, storage_errors
from beo_ros.ros.env import check_domain_id

MAX_PERIOD_S = 86_400.0            # --period / --object-period bound of beo-pcd2bag


class _Stop(threading.Event):
    """The stop event of a command-line tool; ``signum``: the signal that set it."""

    signum = None


def _install_sigint(stop: threading.Event, sigterm: bool = True):
    """SIGINT (and SIGTERM with ``sigterm``) sets ``stop``; a second one raises
    KeyboardInterrupt. Without ``sigterm``, SIGTERM keeps :func:`interruptible`'s handler
    (exit code 143)."""
    def handler(signum, frame):  # noqa: ARG001
        if stop.is_set():  # second Ctrl-C: give up immediately
            raise KeyboardInterrupt
        stop.signum = signum
        stop.set()
    signal.signal(signal.SIGINT, handler)
    if sigterm:
        signal.signal(signal.SIGTERM, handler)


def _ros_setup():
    try:
        from beo_ros.ros.env import ensure_ament_prefix
        ensure_ament_prefix()
    except Exception:  # noqa: BLE001 - only needed for beo_interfaces types
        pass


@contextlib.contextmanager
def _cli_node(name, sigterm_stops: bool = True, prog: str = 'beo'):
    """rclpy context and node for a command-line tool; yields (node, stop event set on
    SIGINT, and on SIGTERM with ``sigterm_stops``), and destroys the node and shuts rclpy down
    on the way out. If ROS does not start (a ROS_DOMAIN_ID that is not a number, ...): one
    line ``PROG: cannot start ROS: ...`` and exit code 1, as beo-node."""
    _ros_setup()
    import rclpy
    stop = _Stop()
    try:
        # no command-line arguments: rcl would take the tool's own ones (-r OLD:=NEW) as remap
        # rules
        rclpy.init(args=[], signal_handler_options=rclpy.signals.SignalHandlerOptions.NO)
        check_domain_id(rclpy.get_default_context())
        node = rclpy.create_node(name)
    except Exception as e:  # noqa: BLE001 - rclpy's RCLError and the like
        rclpy.try_shutdown()
        print(f'{prog}: cannot start ROS: {type(e).__name__}: {e}', file=sys.stderr)
        raise SystemExit(1) from None
    _install_sigint(stop, sigterm_stops)
    try:
        yield node, stop
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


def _output_problem(path) -> str | None:
    """Why a new bag cannot be made at ``path`` (it exists, or a parent is a file), or None."""
    p = Path(path)
    if p.exists() or p.is_symlink():
        return f'{path} exists already'
    for parent in p.parents:   # rosbags makes the missing ones
        if parent.exists():
            if not parent.is_dir():
                return f'cannot create {path}: {parent} is not a directory'
            break
    return None


def _refuse_output(p, path):
    """Exit with the parser's usage error (2) when a new bag cannot be made at ``path``."""
    problem = _output_problem(path)
    if problem:
        p.error(problem)


def _valid(p, check, *args):
    """``check(*args)``, its ValueError turned into the parser's usage error (exit 2)."""
    try:
        return check(*args)
    except ValueError as e:
        p.error(str(e))


def _one_line(exc) -> str:
    """An error's message on one line (a YAML error spans several: the bad line and a caret)."""
    return ' '.join(str(exc).split())


def _nothing_to_play(args, stats) -> str:
    """Why a replay sent nothing: its topics are empty, or the bag has none that matches."""
    if stats.topics:
        return 'no messages on ' + ', '.join(sorted(s.bag_topic for s in stats.topics.values()))
    if args.topics or args.all_topics:
        return 'no matching topics'
    try:
        others = sorted(bag_info(args.bag)['topics'])
    except Exception:  # noqa: BLE001 - only a hint
        others = []
    hint = f' (it has {", ".join(others)}: --all-topics plays them)' if others else ''
    return f'the bag has no {CLOUD_TYPE} topic{hint}'


@interruptible('beo-replay')
def replay_main(argv=None) -> int:
    p = ArgumentParser(
        prog='beo-replay', description='Play the PointCloud2 topics of a rosbag2 bag (sqlite3 or '
        'mcap) into the ROS 2 graph, timed by the bag timestamps.')
    p.add_argument('bag', help='bag directory (or a single .db3 / .mcap file)')
    p.add_argument('-r', '--remap', action='append', default=[], metavar='OLD:=NEW',
                   help='publish bag topic OLD on NEW (repeatable)')
    p.add_argument('--rate', type=number(0), default=1.0,
                   help='speed factor on the bag timing; 0 = as fast as possible (default 1)')
    p.add_argument('--loop', action='store_true', help='replay until interrupted')
    p.add_argument('--topics', nargs='+', metavar='TOPIC',
                   help='bag topics to play, any type (default: all PointCloud2 topics)')
    p.add_argument('--all-topics', action='store_true', help='play every topic of the bag')
    p.add_argument('--qos', choices=('reliable', 'best_effort'), default='reliable',
                   help='publisher reliability (default reliable; keep-last, volatile); '
                        'topics recorded from transient-local publishers (e.g. /tf_static) '
                        'are played reliable and transient-local, as recorded')
    # a DDS history depth is an int32 (rclpy's QoSProfile: a TypeError traceback beyond)
    p.add_argument('--depth', type=count(1, 2**31 - 1), default=10,
                   help='publisher history depth (default 10); a reliable publisher waits for '
                        'its subscribers to acknowledge every DEPTH messages')
    p.add_argument('--ack-timeout', type=number(0), default=ACK_TIMEOUT_S, metavar='S',
                   help='how long a reliable publisher waits for those acknowledgements before '
                        'it goes on and counts the messages as unacknowledged (maybe lost; '
                        f'default {ACK_TIMEOUT_S:g})')
    p.add_argument('--clock', type=number(0), nargs='?', const=40.0, default=0.0, metavar='HZ',
                   help='also publish the bag time on /clock, before every message and at HZ '
                        '(default 40) in between, for nodes run with use_sim_time:=true; '
                        'put it after BAG or write --clock=HZ (before BAG, "--clock BAG" '
                        'would read BAG as HZ); with --loop the clock goes back at each pass')
    p.add_argument('--wait-subscribers', type=count(0), default=0, metavar='N',
                   help='wait until every played topic has N matched subscribers')
    p.add_argument('--wait-timeout', type=number(0), default=10.0, metavar='S',
                   help='give up waiting for subscribers after S seconds (default 10; exit 3)')
    p.add_argument('--node-name', default='beo_replay')
    p.add_argument('--json', action='store_true', help='print the report as JSON')
    args = p.parse_args(argv)
    if args.topics and args.all_topics:
        p.error('--topics and --all-topics exclude each other')
    if args.wait_timeout != p.get_default('wait_timeout') and not args.wait_subscribers:
        p.error('--wait-timeout is for --wait-subscribers N (without it nothing is waited for)')
    remap = _valid(p, parse_remaps, args.remap)
    _valid(p, check_node_name, args.node_name)
    if not Path(args.bag).exists():
        p.error(f'no such bag: {args.bag}')
    code = 0
    # SIGTERM ends a replay with 143 (interruptible); SIGINT is how a --loop replay stops
    with _cli_node(args.node_name, sigterm_stops=False, prog='beo-replay') as (node, stop):
        try:
            stats = replay(args.bag, node, topics=args.topics, all_topics=args.all_topics,
                           remap=remap, rate=args.rate, loop=args.loop, qos=args.qos,
                           depth=args.depth, wait_subscribers=args.wait_subscribers,
                           wait_timeout=args.wait_timeout, stop=stop, clock_hz=args.clock,
                           ack_timeout=args.ack_timeout)
            time.sleep(0.2)  # let reliable transports drain before the publishers go away
            for topic, typ in stats.skipped.items():
                print(f'beo-replay: warning: skipping {topic}: message type {typ} is not '
                      'installed', file=sys.stderr)
            print(json.dumps(stats.to_dict(), indent=2) if args.json else stats.table())
            if stats.unacked:
                print(f'beo-replay: warning: {stats.unacked} message(s) were not acknowledged by '
                      f'every reliable subscriber within --ack-timeout {args.ack_timeout:g} s; '
                      'a slow or stalled subscriber may have lost them', file=sys.stderr)
            if stats.messages == 0 and not stats.interrupted:
                print(f'beo-replay: nothing to play: {_nothing_to_play(args, stats)}',
                      file=sys.stderr)
                code = 1
            # Ctrl-C is how a --loop replay ends once it plays; otherwise it cut the replay short
            if stats.interrupted and not (args.loop and stats.messages):
                print(f'beo-replay: interrupted after {stats.messages} message(s)',
                      file=sys.stderr)
                code = INTERRUPTED
        except BrokenPipeError:   # stdout's reader is gone, not the bag: cli.interruptible
            raise
        except TimeoutError as e:   # the usual causes: no subscriber yet, or another domain
            rng = os.environ.get('ROS_AUTOMATIC_DISCOVERY_RANGE') or 'unset'
            print(f'beo-replay: {e} (start the subscriber first, e.g. beo-node; it must run '
                  f'with the same ROS_DOMAIN_ID, here {node.context.get_domain_id()}, and '
                  f'ROS_AUTOMATIC_DISCOVERY_RANGE, here {rng})', file=sys.stderr)
            code = 3
        except KeyError as e:
            print(f'beo-replay: {e.args[0]}', file=sys.stderr)
            code = 2
        except ClockRangeError as e:   # a readable bag, refused with --clock
            print(f'beo-replay: {e}', file=sys.stderr)
            code = 2
        except TopicNameError as e:   # a readable bag, played once remapped
            print(f'beo-replay: {e}', file=sys.stderr)
            code = 2
        except BagReadError as e:   # corrupt part way: what was played before it
            if e.stats.messages:
                print(json.dumps(e.stats.to_dict(), indent=2) if args.json
                      else e.stats.table())
            print(f'beo-replay: cannot read {args.bag}: {_one_line(e)} (after {e.stats.messages} '
                  'message(s))', file=sys.stderr)
            code = 2
        except (ValueError, *storage_errors()) as e:   # not a bag, or a corrupt one
            print(f'beo-replay: cannot read {args.bag}: {_one_line(e)}', file=sys.stderr)
            code = 2
    return code


@interruptible('beo-record')
def record_main(argv=None) -> int:
    p = ArgumentParser(
        prog='beo-record', description='Record ROS 2 topics to a new rosbag2 bag (sqlite3 or '
        'mcap) until Ctrl-C, --duration or --count.')
    p.add_argument('topics', nargs='+', metavar='TOPIC[:TYPE]',
                   help='topic, optionally with its type (e.g. /beo/estimates:'
                   'beo_interfaces/msg/ObjectEstimate); otherwise discovered from the graph')
    p.add_argument('-o', '--output', required=True, metavar='BAG', help='new bag directory')
    p.add_argument('--storage', choices=STORAGES, default='sqlite3',
                   help='bag storage (default %(default)s)')
    p.add_argument('--wait', type=number(0), default=10.0, metavar='S',
                   help='seconds to wait for publishers of untyped topics (default 10; exit 2)')
    p.add_argument('--duration', type=number(0, lo_open=True), metavar='S',
                   help='stop after S seconds')
    p.add_argument('--count', type=count(1), metavar='N',
                   help='stop after N messages (all topics)')
    p.add_argument('--node-name', default='beo_record')
    p.add_argument('--json', action='store_true', help='print the report as JSON')
    args = p.parse_args(argv)
    specs = _valid(p, parse_topic_specs, args.topics)
    _valid(p, check_node_name, args.node_name)
    _refuse_output(p, args.output)
    code = 0
    with _cli_node(args.node_name, prog='beo-record') as (node, stop):
        try:
            stats = record(node, args.output, specs, storage=args.storage, wait=args.wait,
                           duration=args.duration, count=args.count, stop=stop)
            print(json.dumps(stats.to_dict(), indent=2) if args.json else stats.table())
        except BrokenPipeError:   # stdout's reader is gone, not the bag: cli.interruptible
            raise
        except KeyError as e:
            print(f'beo-record: {e.args[0]}', file=sys.stderr)
            code = 2
        except ValueError as e:   # 'x' and '/x' given different types
            print(f'beo-record: {e}', file=sys.stderr)
            code = 2
        except BagWriteError as e:   # disk full, ...: what is left of the bag
            print(f'beo-record: {e}', file=sys.stderr)
            code = 2
        except OSError as e:
            print(f'beo-record: cannot write {args.output}: {e}', file=sys.stderr)
            code = 2
        except KeyboardInterrupt as e:   # before recording started (while waiting for types)
            why = e.args[0] if e.args else 'interrupted'
            code = INTERRUPTED
            if stop.signum == signal.SIGTERM:   # 143, as for SIGTERM anywhere else
                why, code = why.replace('interrupted', 'terminated', 1), TERMINATED
            print(f'beo-record: {why}', file=sys.stderr)
    return code


@interruptible('beo-pcd2bag')
def pcd2bag_main(argv=None) -> int:
    p = ArgumentParser(
        prog='beo-pcd2bag', description='Labelled organized PCD scenes (OSD format) -> rosbag2 bag '
        f'with one PointCloud2 per segmented object, the table-implied up vector on {UP_TOPIC} '
        f'(geometry_msgs/Vector3Stamped) and the table plane a,b,c,d on {PLANE_TOPIC} '
        '(std_msgs/Float64MultiArray), all in the camera frame.')
    p.add_argument('scenes', nargs='+', metavar='SCENE.pcd')
    p.add_argument('-o', '--output', required=True, metavar='BAG', help='new bag directory')
    p.add_argument('--storage', choices=STORAGES, default='sqlite3',
                   help='bag storage (default %(default)s)')
    p.add_argument('--topic', default=DEFAULT_INPUT_TOPIC,
                   help=f'object cloud topic (default {DEFAULT_INPUT_TOPIC})')
    p.add_argument('--frame', default=DEFAULT_FRAME, help=f'frame id (default {DEFAULT_FRAME})')
    p.add_argument('--period', type=number(0, MAX_PERIOD_S), default=2.0, metavar='S',
                   help=f'seconds between scenes (default 2, at most {MAX_PERIOD_S:g})')
    p.add_argument('--object-period', type=number(0, MAX_PERIOD_S), default=0.25, metavar='S',
                   help='seconds between the objects of one scene (default 0.25, at most '
                   f'{MAX_PERIOD_S:g})')
    p.add_argument('--min-points', type=count(0), default=50,
                   help='skip objects with fewer points (default 50)')
    p.add_argument('--json', action='store_true', help='print the summary as JSON')
    args = p.parse_args(argv)
    folders = [s for s in args.scenes if Path(s).is_dir()]
    if folders:
        p.error(f'a directory, not a PCD file: {", ".join(folders)}')
    missing = [s for s in args.scenes if not Path(s).is_file()]
    if missing:
        p.error(f'no such file: {", ".join(missing)}')
    _valid(p, check_cloud_topic, args.topic)
    _refuse_output(p, args.output)
    try:
        summary = pcd_to_bag(args.scenes, args.output, storage=args.storage, topic=args.topic,
                             frame_id=args.frame, period=args.period,
                             object_period=args.object_period, min_points=args.min_points)
    except ValueError as e:   # PCDError and bad scenes (no table plane, ...) are ValueErrors
        print(f'beo-pcd2bag: {e}', file=sys.stderr)
        return 2
    except storage_errors() as e:   # a full disk: OSError, or sqlite3's own error
        print(f'beo-pcd2bag: cannot write {args.output}: {e}', file=sys.stderr)
        return 2
    for s in summary['skipped']:
        print(f'beo-pcd2bag: warning: skipped {s["reason"]}', file=sys.stderr)
    for s in summary['scenes']:
        if not s['objects']:
            print(f'beo-pcd2bag: warning: {s["scene"]}: no object with at least '
                  f'{args.min_points} points (--min-points); only its up vector and plane are '
                  'written', file=sys.stderr)
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        for s in summary['scenes']:
            up = ', '.join(f'{v:+.3f}' for v in s['up'])
            pts = (f' ({", ".join(str(o["points"]) for o in s["objects"])} points)'
                   if s['objects'] else '')
            print(f'{Path(s["scene"]).name}: {len(s["objects"])} object(s){pts}, up ({up})')
        print(' '.join(f'{t}: {n}' for t, n in summary['topics'].items()) + f' -> {args.output} '
              f'({args.storage})')
    return 0


@interruptible('beo-bag-recover')
def recover_main(argv=None) -> int:
    p = ArgumentParser(
        prog='beo-bag-recover', description='Copy the intact messages of a bag that was never '
        'closed (a recording ended by SIGKILL, a crash or a full disk: no metadata.yaml, or an '
        'mcap file without its footer) into a new, closed bag.')
    p.add_argument('bag', help='bag directory, or its .db3 / .mcap file')
    p.add_argument('-o', '--output', required=True, metavar='BAG', help='new bag directory')
    p.add_argument('--storage', choices=STORAGES,
                   help="the new bag's storage (default: the old one's)")
    p.add_argument('--json', action='store_true', help='print the summary as JSON')
    args = p.parse_args(argv)
    _refuse_output(p, args.output)
    try:
        summary = recover_bag(args.bag, args.output, storage=args.storage)
    except (ValueError, KeyError) as e:   # not a bag, nothing intact, a type without a definition
        print(f'beo-bag-recover: {e.args[0] if isinstance(e, KeyError) else e}',
              file=sys.stderr)
        return 2
    except BagWriteError as e:   # a full disk, ...
        print(f'beo-bag-recover: {e}', file=sys.stderr)
        return 2
    except storage_errors() as e:
        print(f'beo-bag-recover: {args.bag}: {e}', file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        topics = ' '.join(f'{t}: {n}' for t, n in summary['topics'].items()) or 'no topics'
        lost = (f'; {summary["lost_bytes"]} bytes after the last intact record were left '
                'out' if summary['lost_bytes'] else '')
        print(f'{summary["messages"]} message(s) ({topics}) -> {args.output} '
              f'({summary["storage"]}){lost}')
    return 0
