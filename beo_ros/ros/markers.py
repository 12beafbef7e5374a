"""RViz markers of one estimate: the object's box and its label above it."""
from __future__ import annotations

import math

import numpy as np
from builtin_interfaces.msg import Duration
from visualization_msgs.msg import Marker, MarkerArray

from beo_ros.ros.conversions import object_dimensions

NS = 'beo'
AUTO_LIFETIME_INTERVALS = 3.0   # automatic lifetime: this many intervals between estimates
MIN_AUTO_LIFETIME = 1.0         # s; also the first estimate's (no interval yet)


def auto_lifetime(interval: float | None) -> float:
    """Seconds a topic's markers live with ``marker_lifetime`` 0 (automatic): a few of the
    ``interval`` seconds since its previous estimate (None: none yet), at least
    MIN_AUTO_LIFETIME, so that they stay up until the next estimate replaces them."""
    if interval is None or not math.isfinite(interval):
        return MIN_AUTO_LIFETIME
    return max(MIN_AUTO_LIFETIME, AUTO_LIFETIME_INTERVALS * interval)


def _duration(seconds: float) -> Duration:
    ns = int(round(seconds * 1e9))
    return Duration(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def object_markers(est, out, header, idx, up, lifetime: float = 0.0) -> MarkerArray:
    """Box (id ``2 idx``) and label text (id ``2 idx + 1``; ns 'beo') of the estimate ``est``,
    published as the ObjectEstimate ``out``, in the frame of ``header``; the text floats above
    the completed points along ``up`` (3,). RViz removes them ``lifetime`` seconds after they
    arrive (0: never)."""
    up = np.asarray(up, dtype=np.float64)
    up = up / np.linalg.norm(up)
    centre = np.array([out.pose.position.x, out.pose.position.y, out.pose.position.z])
    d = object_dimensions(est)
    if est.completed_points is not None and len(est.completed_points):
        height = float(np.max((np.asarray(est.completed_points) - centre) @ up))
    else:
        height = 0.0
    box = Marker(header=header, ns=NS, id=2 * idx, type=Marker.CUBE, action=Marker.ADD)
    box.pose = out.pose
    box.scale.x, box.scale.y, box.scale.z = (max(float(v), 0.01) for v in d)
    box.color.r, box.color.g, box.color.b, box.color.a = 0.1, 0.8, 0.3, 0.35
    text = Marker(header=header, ns=NS, id=2 * idx + 1, type=Marker.TEXT_VIEW_FACING,
                  action=Marker.ADD)
    pos = centre + up * (max(height, 0.0) + 0.08)
    text.pose.position.x, text.pose.position.y, text.pose.position.z = (float(v) for v in pos)
    text.pose.orientation.w = 1.0
    text.scale.z = 0.08
    text.color.r = text.color.g = text.color.b = text.color.a = 1.0
    text.text = f'{out.label} {out.probability:.0%}'
    box.lifetime = text.lifetime = _duration(lifetime)
    return MarkerArray(markers=[box, text])


def delete_markers(header, idx) -> MarkerArray:
    """DELETE of the box and label of ``object_markers(..., idx, ...)``: that input's object
    is no longer published (its last cloud was rejected or failed)."""
    return MarkerArray(markers=[Marker(header=header, ns=NS, id=i, action=Marker.DELETE)
                                for i in (2 * idx, 2 * idx + 1)])


def delete_all_markers(header) -> MarkerArray:
    """DELETEALL: the node publishes no object any more (it is shutting down)."""
    return MarkerArray(markers=[Marker(header=header, ns=NS, action=Marker.DELETEALL)])
