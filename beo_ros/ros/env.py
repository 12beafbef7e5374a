"""Runtime environment helpers for running beo_ros from the pip venv without sourcing ROS.

scripts/setup installs beo_interfaces (and beo_ros' share/ data) into the venv prefix
(``sys.prefix``). ament_index lookups only see prefixes listed in ``AMENT_PREFIX_PATH``,
which nobody sets when ``.venv/bin/beo-node`` is started directly: call
:func:`ensure_ament_prefix` before importing ``beo_interfaces`` or using
``ament_index_python``.
"""
import os
import sys

_MARKERS = ('beo_interfaces', 'beo_ros')


def _has_ament_packages(prefix):
    index = os.path.join(prefix, 'share', 'ament_index', 'resource_index', 'packages')
    return any(os.path.isfile(os.path.join(index, name)) for name in _MARKERS)


def ensure_ament_prefix(prefix=None):
    """Prepend ``prefix`` (default ``sys.prefix``) to ``AMENT_PREFIX_PATH`` when beo_interfaces
    (or beo_ros) is registered in that prefix's ament index and the variable lacks it (under
    any name: a symlinked path to a listed prefix is that prefix, and its place is kept, e.g.
    behind an overlay workspace listed first).

    Idempotent. Returns the resulting ``AMENT_PREFIX_PATH`` (possibly empty string).
    """
    prefix = os.path.abspath(prefix or sys.prefix)
    current = os.environ.get('AMENT_PREFIX_PATH', '')
    parts = [p for p in current.split(os.pathsep) if p]
    if _has_ament_packages(prefix) and not any(
            os.path.realpath(p) == os.path.realpath(prefix) for p in parts):
        parts.insert(0, prefix)
        os.environ['AMENT_PREFIX_PATH'] = os.pathsep.join(parts)
    return os.environ.get('AMENT_PREFIX_PATH', '')


# the largest ROS domain id whose DDS ports (7400 + 250 * id + ...) stay below 65536
MAX_DOMAIN_ID = 232


def check_domain_id(context):
    """``ValueError`` when the domain id of the initialised rclpy ``context`` (ROS_DOMAIN_ID)
    is over :data:`MAX_DOMAIN_ID`: rcl takes it, but Fast DDS then ends the process when the
    first node is created (exit 1, its own message on stdout, nothing on stderr)."""
    domain = context.get_domain_id()
    if domain > MAX_DOMAIN_ID:
        raise ValueError(f'ROS_DOMAIN_ID {domain} is over {MAX_DOMAIN_ID} (its DDS ports would '
                         'be past 65535)')
