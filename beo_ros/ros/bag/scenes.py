"""beo-pcd2bag: labelled PCD scenes -> a bag of object clouds, up vectors and table planes."""
from __future__ import annotations

import math
import shutil
from pathlib import Path

from beo_ros.ros import MAX_STAMP_NS
from beo_ros.ros.bag.msgtypes import CLOUD_TYPE, check_topic_name
from beo_ros.ros.bag.storage import BagWriter

UP_TOPIC = '/beo/up'
PLANE_TOPIC = '/beo/table_plane'
DEFAULT_INPUT_TOPIC = '/beo/input'
DEFAULT_FRAME = 'camera'
T0_NS = 1_700_000_000_000_000_000  # first stamp written by pcd2bag (and the demo)
# the last stamp a header holds (builtin_interfaces/Time: int32 seconds, 2038-01-19); the bag's
# own int64 nanoseconds go further, but each message's header stamp equals its bag stamp
MAX_NS = MAX_STAMP_NS


class NoObjects(ValueError):
    """A scene without object labels (>= 20): nothing to segment, and no up vector worth writing."""


def scene_messages(scene_path, *, min_points: int = 50):
    """Segment one labelled scene -> ``(objects [(object_id, (n,3) points)], up (3,), plane (4,))``.

    Objects come from the OSD labels (``scans.segment_objects``), the up vector from a RANSAC fit
    of the table points (``scans.fit_table_plane``), oriented towards the sensor. A file without
    a label field is a ``PCDError``; one with no object label, :class:`NoObjects`.
    """
    import numpy as np

    from beo_ros.core import scans
    scene = scans.load_scene(scene_path)
    if not (scene.labels >= scans.FIRST_OBJECT_LABEL).any():
        raise NoObjects(f'{scene_path}: no objects (labels >= {scans.FIRST_OBJECT_LABEL})')
    objects = sorted(scans.segment_objects(scene, min_points=min_points).items())
    try:
        up, d = scans.fit_table_plane(scene)
    except ValueError as e:
        raise ValueError(f'{scene_path}: {e}') from e
    up = np.asarray(up, dtype=np.float64)
    norm = np.linalg.norm(up)
    up, d = up / norm, float(d) / norm
    return objects, up, np.array([up[0], up[1], up[2], d])


def _scene_stamps(counts, period: float, object_period: float, t0_ns: int) -> list:
    """Per scene (``counts``: its number of objects): ``(scene stamp, [object stamps])``."""
    step = int(round(object_period * 1e9))
    out, last = [], None
    for i, n in enumerate(counts):
        ns = int(t0_ns + round(i * period * 1e9))
        if last is not None:
            ns = max(ns, last + max(step, 1))
        objs = [ns + j * step if step else ns + j for j in range(n)]
        last = objs[-1] if objs else ns
        out.append((ns, objs))
    return out


def check_cloud_topic(topic: str) -> str:
    """``topic`` expanded (``check_topic_name``) as the object cloud topic of a pcd2bag bag;
    ``ValueError`` if it is not a valid name or is the up vector's or the plane's topic."""
    full = check_topic_name(topic)
    if full in (UP_TOPIC, PLANE_TOPIC):
        raise ValueError(f'the object cloud topic {topic!r} is the '
                         f"{'up vector' if full == UP_TOPIC else 'table plane'}'s topic "
                         f'{full}: give another')
    return full


def pcd_to_bag(scenes, bag_path, *, storage: str = 'sqlite3', topic: str = DEFAULT_INPUT_TOPIC,
               frame_id: str = DEFAULT_FRAME, period: float = 2.0, object_period: float = 0.25,
               min_points: int = 50, t0_ns: int = T0_NS) -> dict:
    """Write the segmented objects of labelled PCD scenes to a bag (see the package docstring).

    Scene ``i`` starts at ``t0 + i * period`` (or ``object_period`` after the previous scene's last
    object if that is later); its up vector and plane carry that stamp, its objects follow
    ``object_period`` apart (first one at the scene stamp), so every cloud has a unique stamp.
    Scenes without object labels are skipped (listed in ``'skipped'``); ``ValueError`` if none is
    left, for a bad scene or topic name (or ``topic`` :data:`UP_TOPIC` or :data:`PLANE_TOPIC`),
    or stamps past what a header stamp holds
    (:data:`MAX_NS`, 2038-01-19: its seconds are int32). No bag is left behind
    on any failure (Ctrl-C included).

    Returns ``{'bag', 'storage', 'scenes': [{'scene', 'stamp_ns', 'objects': [{'id', 'points',
    'centroid', 'stamp_ns'}], 'up', 'plane'}], 'skipped': [{'scene', 'reason'}],
    'topics': {topic: count}}``.
    """
    import numpy as np
    from geometry_msgs.msg import Vector3, Vector3Stamped
    from std_msgs.msg import Float64MultiArray, Header

    from beo_ros.ros.conversions import stamp_from_ns, xyz_to_cloud
    if not (math.isfinite(period) and math.isfinite(object_period)):
        raise ValueError('period and object_period must be finite numbers')
    if period < 0 or object_period < 0:
        raise ValueError('period and object_period must be >= 0')
    topic = check_cloud_topic(topic)
    summary = {'bag': str(bag_path), 'storage': storage, 'scenes': [], 'skipped': [],
               'topics': {}}
    # every scene is read before the bag is opened: a bad one leaves no half-written bag
    read = []
    for scene in scenes:
        try:
            read.append((scene, *scene_messages(scene, min_points=min_points)))
        except NoObjects as e:
            summary['skipped'].append({'scene': str(scene), 'reason': str(e)})
    if not read:
        raise ValueError('no scene with objects: ' + '; '.join(
            s['reason'] for s in summary['skipped']))
    if not any(objects for _, objects, _, _ in read):   # a bag without a single cloud
        raise ValueError(f'no object with at least {min_points} points (--min-points) in any '
                         'scene: no cloud to write, no bag written')
    stamps = _scene_stamps([len(objects) for _, objects, _, _ in read], period, object_period,
                           t0_ns)
    if max(max([ns, *objs]) for ns, objs in stamps) > MAX_NS:
        raise ValueError(f'--period {period:g} s / --object-period {object_period:g} s put the '
                         f'stamps of {len(read)} scene(s) past 2038-01-19, the last a header '
                         'stamp holds (int32 seconds)')
    existed = Path(bag_path).exists()
    try:
        with BagWriter(bag_path, storage) as w:
            w.add_topic(topic, CLOUD_TYPE)
            w.add_topic(UP_TOPIC, 'geometry_msgs/msg/Vector3Stamped')
            w.add_topic(PLANE_TOPIC, 'std_msgs/msg/Float64MultiArray')
            for (scene, objects, up, plane), (ns, obj_ns) in zip(read, stamps):
                header = Header(stamp=stamp_from_ns(ns), frame_id=frame_id)
                entry = {'scene': str(scene), 'stamp_ns': ns, 'objects': [],
                         'up': up.tolist(), 'plane': plane.tolist()}
                w.write(UP_TOPIC, Vector3Stamped(header=header, vector=Vector3(
                    x=float(up[0]), y=float(up[1]), z=float(up[2]))), ns)
                w.write(PLANE_TOPIC, Float64MultiArray(data=[float(v) for v in plane]), ns)
                for (obj_id, pts), t in zip(objects, obj_ns):
                    pts = np.asarray(pts, dtype=np.float32)
                    header = Header(stamp=stamp_from_ns(t), frame_id=frame_id)
                    w.write(topic, xyz_to_cloud(pts, header), t)
                    entry['objects'].append({'id': int(obj_id), 'points': int(len(pts)),
                                             'centroid': pts.mean(axis=0).tolist(),
                                             'stamp_ns': t})
                summary['scenes'].append(entry)
            summary['topics'] = dict(w.counts)
    except BaseException:
        if not existed:   # a half-written bag would only be refused by the next run
            shutil.rmtree(bag_path, ignore_errors=True)
        raise
    return summary
