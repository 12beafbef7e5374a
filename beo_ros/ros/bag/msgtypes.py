"""Topic and node names, message types and the rosbags typestore of the bag tools."""
from __future__ import annotations

import importlib
import os
import re
import sys
import threading
from pathlib import Path

CLOUD_TYPE = 'sensor_msgs/msg/PointCloud2'


# ---------------------------------------------------------------------------------------------
# names
# ---------------------------------------------------------------------------------------------

def _name_reason(exc) -> str:
    """rcl's reason from a name validation error, on one line."""
    first = (str(exc).splitlines() or [type(exc).__name__])[0]
    first = re.sub(r', at \S+:\d+$', '', first).rstrip(': ')
    m = re.search(r'(?:is invalid|Invalid \w+ name): (.*)', first)
    return m.group(1) if m else first


def check_topic_name(name: str, node_name: str = 'beo') -> str:
    """``name`` expanded as a topic of node ``node_name`` in namespace ``/`` ('x' -> '/x');
    ``ValueError`` with rcl's reason if it is not a valid ROS 2 topic name."""
    from rclpy.expand_topic_name import expand_topic_name
    from rclpy.validate_full_topic_name import validate_full_topic_name
    try:
        full = expand_topic_name(name, node_name, '/')
        validate_full_topic_name(full)
    except Exception as e:  # noqa: BLE001 - rcl raises ValueError or NameValidationException
        raise ValueError(f'bad topic name {name!r}: {_name_reason(e)}') from None
    return full


def check_node_name(name: str) -> str:
    """``name`` if it is a valid ROS 2 node name, else ``ValueError`` with rcl's reason."""
    from rclpy.validate_node_name import validate_node_name
    try:
        validate_node_name(name)
    except Exception as e:  # noqa: BLE001
        raise ValueError(f'bad node name {name!r}: {_name_reason(e)}') from None
    return name


# ---------------------------------------------------------------------------------------------
# message types
# ---------------------------------------------------------------------------------------------

# interface kinds whose types are published on topics: messages, and the service event
# (pkg/srv/Type_Event, ros2 bag record --all-services) and action feedback
# (pkg/action/Type_FeedbackMessage) topics of services and actions
_KINDS = ('msg', 'srv', 'action')


def normalize_msgtype(name: str) -> str:
    """'pkg/Type', 'pkg/msg/Type' or 'pkg.msg.Type' -> 'pkg/msg/Type' ('pkg/srv/Type' and
    'pkg/action/Type', the types of service event and action feedback topics, likewise)."""
    parts = [p for p in re.split(r'[/.]', name.strip()) if p]
    if len(parts) == 2:
        parts = [parts[0], 'msg', parts[1]]
    if len(parts) != 3 or parts[1] not in _KINDS:
        raise ValueError(f'not a message type name: {name!r} (expected pkg/msg/Type)')
    return '/'.join(parts)


def import_msg_class(msgtype: str):
    """The rclpy message class of 'pkg/msg/Type'; ``KeyError`` naming it if not installed."""
    pkg, kind, name = normalize_msgtype(msgtype).split('/')
    if pkg == 'beo_interfaces':
        from beo_ros.ros.env import ensure_ament_prefix
        ensure_ament_prefix()
    try:
        return getattr(importlib.import_module(f'{pkg}.{kind}'), name)
    except (ImportError, AttributeError):
        raise KeyError(f'message type {pkg}/{kind}/{name} is not installed (no Python module '
                       f'{pkg}.{kind} with {name})') from None


def msgtype_of(msg) -> str:
    """'pkg/msg/Type' of an rclpy message instance or class ('pkg/srv/Type' for a service's
    event message, ...)."""
    cls = msg if isinstance(msg, type) else type(msg)
    parts = cls.__module__.split('.')
    kind = parts[1] if len(parts) > 1 and parts[1] in _KINDS else 'msg'
    return f'{parts[0]}/{kind}/{cls.__name__}'


def _msg_search_dirs(pkg: str) -> list:
    """Directories that may hold ``pkg``'s ``.msg`` files: ament prefixes, then this checkout."""
    dirs = []
    prefixes = os.environ.get('AMENT_PREFIX_PATH', '')
    if pkg == 'beo_interfaces':
        try:
            from beo_ros.ros.env import ensure_ament_prefix
            ensure_ament_prefix()
            prefixes = os.environ.get('AMENT_PREFIX_PATH', '')
        except Exception:  # noqa: BLE001 - the source checkout below still works
            pass
    for prefix in [p for p in prefixes.split(os.pathsep) if p] + [sys.prefix]:
        dirs.append(Path(prefix) / 'share' / pkg / 'msg')
    try:  # next to the python package (some wheels ship the definitions there)
        mod = importlib.import_module(pkg)
        for p in getattr(mod, '__path__', []):
            dirs.append(Path(p) / 'msg')
    except Exception:  # noqa: BLE001
        pass
    dirs.append(Path(__file__).resolve().parents[3] / pkg / 'msg')  # source checkout
    return dirs


def _find_msg_file(msgtype: str) -> Path | None:
    pkg, _, name = msgtype.split('/')
    for d in _msg_search_dirs(pkg):
        f = d / f'{name}.msg'
        if f.is_file():
            return f
    return None


def _referenced_types(obj) -> set:
    """Every 'pkg/msg/Type' string nested anywhere in a rosbags field definition."""
    out = set()
    if isinstance(obj, str):
        if re.fullmatch(r'[A-Za-z0-9_]+/msg/[A-Za-z0-9_]+', obj):
            out.add(obj)
    elif isinstance(obj, (tuple, list)):
        for x in obj:
            out |= _referenced_types(x)
    return out


_TYPESTORE = None
_TYPESTORE_LOCK = threading.Lock()


def get_typestore(msgtypes=()):
    """The rosbags ROS 2 Jazzy typestore with ``msgtypes`` (and what they use) registered.

    Types missing from the stock store are parsed from their ``.msg`` files (ament share
    directories, or this source checkout for ``beo_interfaces``). Raises ``KeyError`` if a
    definition cannot be found.
    """
    global _TYPESTORE
    from rosbags.typesys import Stores, get_types_from_msg
    from rosbags.typesys import get_typestore as _get

    with _TYPESTORE_LOCK:
        if _TYPESTORE is None:
            _TYPESTORE = _get(Stores.ROS2_JAZZY)
        store = _TYPESTORE
        todo = [normalize_msgtype(t) for t in msgtypes]
        seen = set()
        while todo:
            t = todo.pop()
            if t in seen:
                continue
            seen.add(t)
            if t not in store.fielddefs:
                f = _find_msg_file(t)
                if f is None:
                    raise KeyError(f'no message definition found for {t}')
                store.register(get_types_from_msg(f.read_text(), t))
            todo.extend(_referenced_types(store.fielddefs[t]) - seen)
        return store
