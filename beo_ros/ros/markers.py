"""RViz markers of one estimate: the object's box and its label above it."""
from __future__ import annotations

import numpy as np
from visualization_msgs.msg import Marker, MarkerArray

from beo_ros.ros.conversions import object_dimensions


def object_markers(est, out, header, idx, up) -> MarkerArray:
    """Box (id ``2 idx``) and label text (id ``2 idx + 1``; ns 'beo') of the estimate ``est``,
    published as the ObjectEstimate ``out``, in the frame of ``header``; the text floats above
    the completed points along ``up`` (3,)."""
    up = np.asarray(up, dtype=np.float64)
    up = up / np.linalg.norm(up)
    centre = np.array([out.pose.position.x, out.pose.position.y, out.pose.position.z])
    d = object_dimensions(est)
    if est.completed_points is not None and len(est.completed_points):
        height = float(np.max((np.asarray(est.completed_points) - centre) @ up))
    else:
        height = 0.0
    box = Marker(header=header, ns='beo', id=2 * idx, type=Marker.CUBE, action=Marker.ADD)
    box.pose = out.pose
    box.scale.x, box.scale.y, box.scale.z = (max(float(v), 0.01) for v in d)
    box.color.r, box.color.g, box.color.b, box.color.a = 0.1, 0.8, 0.3, 0.35
    text = Marker(header=header, ns='beo', id=2 * idx + 1, type=Marker.TEXT_VIEW_FACING,
                  action=Marker.ADD)
    pos = centre + up * (max(height, 0.0) + 0.08)
    text.pose.position.x, text.pose.position.y, text.pose.position.z = (float(v) for v in pos)
    text.pose.orientation.w = 1.0
    text.scale.z = 0.08
    text.color.r = text.color.g = text.color.b = text.color.a = 1.0
    text.text = f'{out.label} {out.probability:.0%}'
    return MarkerArray(markers=[box, text])
