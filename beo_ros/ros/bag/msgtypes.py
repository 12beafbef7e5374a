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


def _msg_search_dirs(pkg: str, kind: str = 'msg') -> list:
    """Directories that may hold ``pkg``'s ``.msg`` files (``.srv`` files: ``kind`` 'srv'):
    ament prefixes, then this checkout."""
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
        dirs.append(Path(prefix) / 'share' / pkg / kind)
    try:  # next to the python package (some wheels ship the definitions there)
        mod = importlib.import_module(pkg)
        for p in getattr(mod, '__path__', []):
            dirs.append(Path(p) / kind)
    except Exception:  # noqa: BLE001
        pass
    dirs.append(Path(__file__).resolve().parents[3] / pkg / kind)  # source checkout
    return dirs


def _find_msg_file(msgtype: str) -> Path | None:
    pkg, kind, name = msgtype.split('/')
    for d in _msg_search_dirs(pkg, kind):
        f = d / f'{name}.{kind}'
        if f.is_file():
            return f
    return None


# the message types rosidl generates for a service pkg/srv/Type: its request and response
# (the two halves of Type.srv) and the event of service introspection (topic
# /<service>/_service_event), as in rosidl_parser's definition
_SRV_PART = re.compile(r'(.+)_(Request|Response|Event)')
_SRV_EVENT = ('service_msgs/ServiceEventInfo info\n'
              '{0}_Request[<=1] request\n'
              '{0}_Response[<=1] response\n')


def _definition(msgtype: str) -> str | None:
    """The .msg text of 'pkg/msg/Type' from its file, or of a type generated for a service
    ('pkg/srv/Type_Request', '_Response', '_Event') from its .srv file; None if not found."""
    pkg, kind, name = msgtype.split('/')
    m = _SRV_PART.fullmatch(name)
    if kind != 'srv' or not m:
        f = _find_msg_file(msgtype)
        return None if f is None else f.read_text()
    f = _find_msg_file(f'{pkg}/srv/{m.group(1)}')
    if f is None:
        return None
    if m.group(2) == 'Event':
        return _SRV_EVENT.format(f'{pkg}/srv/{m.group(1)}')
    halves = re.split(r'^---[ \t]*$', f.read_text(), maxsplit=1, flags=re.M)
    if len(halves) != 2:
        raise KeyError(f'{f}: no --- between request and response')
    return halves[0] if m.group(2) == 'Request' else halves[1]


def _srv_name(name: str) -> str:
    """A type name as rosbags' .msg parser leaves a service's: 'pkg/srv/msg/Type_Request'
    (it knows msg and action types only) -> 'pkg/srv/Type_Request', and a type a .srv
    file names relatively ('pkg/srv/msg/Type') -> 'pkg/msg/Type'."""
    m = re.fullmatch(r'([A-Za-z0-9_]+)/srv/msg/([A-Za-z0-9_]+)', name)
    if not m:
        return name
    return '/'.join((m.group(1), 'srv' if _SRV_PART.fullmatch(m.group(2)) else 'msg',
                     m.group(2)))


def _renamed(obj, rename):
    """A rosbags field definition with every string in it passed through ``rename``."""
    if isinstance(obj, str):
        return rename(obj)
    if isinstance(obj, (tuple, list)):
        return type(obj)(_renamed(x, rename) for x in obj)
    return obj


def types_from_msg(text: str, msgtype: str) -> dict:
    """rosbags' ``get_types_from_msg``, for service types too ('pkg/srv/Type_Event', the type of
    a service event topic, its request and response, and the types they name): rosbags alone
    files them under 'pkg/srv/msg/...' and cannot find them by their names."""
    from rosbags.typesys import get_types_from_msg
    types = get_types_from_msg(text, msgtype)
    return {_srv_name(k): _renamed(v, _srv_name) for k, v in types.items()}


def _referenced_types(obj) -> set:
    """Every 'pkg/msg/Type' (or 'pkg/srv/Type', ...) string nested anywhere in a rosbags field
    definition."""
    out = set()
    if isinstance(obj, str):
        if re.fullmatch(r'[A-Za-z0-9_]+/(msg|srv|action)/[A-Za-z0-9_]+', obj):
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
    directories, or this source checkout for ``beo_interfaces``), those of a service's request,
    response and event (``pkg/srv/Type_Event``) from its ``.srv`` file. Raises ``KeyError`` if
    a definition cannot be found.
    """
    global _TYPESTORE
    from rosbags.typesys import Stores
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
                text = _definition(t)
                if text is None:
                    raise KeyError(f'no message definition found for {t}')
                store.register(types_from_msg(text, t))
            todo.extend(_referenced_types(store.fielddefs[t]) - seen)
        return store


def _closure(store, msgtype: str) -> set:
    """``msgtype`` and every type its definition uses, nested ones included."""
    closure, todo = set(), [msgtype]
    while todo:
        t = todo.pop()
        if t not in closure:
            closure.add(t)
            todo.extend(_referenced_types(store.fielddefs[t]))
    return closure


def _char_as_uint8(obj):
    """A rosbags field definition with its ``char`` fields typed ``uint8``."""
    if obj == ('char', 0):
        return ('uint8', 0)
    if isinstance(obj, (tuple, list)):
        return type(obj)(_char_as_uint8(x) for x in obj)
    return obj


def hash_rihs01(store, msgtype: str) -> str:
    """The RIHS01 hash of a type of ``store`` as rosidl computes it: a .msg ``char`` is a
    ``uint8`` there (rosbags hashes it as a char: service_msgs/msg/ServiceEventInfo, in every
    service event, would get another hash than the publishers')."""
    from rosbags.typesys import Stores
    from rosbags.typesys import get_typestore as _get
    tmp = _get(Stores.EMPTY)
    tmp.fielddefs.update({t: _char_as_uint8(store.fielddefs[t])
                          for t in _closure(store, msgtype)})
    return tmp.hash_rihs01(msgtype)


def service_definition(msgtype: str) -> tuple[str, str]:
    """(ros2msg definition, RIHS01 hash) of a service's type 'pkg/srv/Type_Event' (or its
    _Request, _Response) as a bag stores them; ``KeyError`` if it has no definition.

    rosbags writes the definitions of msg types only: it is asked for that of the same types
    filed as 'pkg/msg/Type_Event', ..., and the names are put back."""
    from rosbags.typesys import Stores
    from rosbags.typesys import get_typestore as _get
    msgtype = normalize_msgtype(msgtype)
    store = get_typestore([msgtype])

    def as_msg(name):
        return re.sub(r'^([A-Za-z0-9_]+)/srv/', r'\1/msg/', name)

    tmp = _get(Stores.EMPTY)
    tmp.fielddefs.update({as_msg(t): _renamed(store.fielddefs[t], as_msg)
                          for t in _closure(store, msgtype)})
    msgdef = tmp.generate_msgdef(as_msg(msgtype), ros_version=2)[0]
    # 'pkg/Type_Request' (a field) and 'MSG: pkg/Type_Request' (a section): message names have
    # no underscore, these are the service's
    msgdef = re.sub(r'\b([A-Za-z0-9_]+)/(?:msg/)?([A-Za-z0-9]+_(?:Request|Response|Event))\b',
                    r'\1/srv/\2', msgdef)
    return msgdef, hash_rihs01(store, msgtype)
