"""rosbag2 tools for beo_ros, without ros2cli or rosbag2: replay, record and PCD-scene conversion.

Bags are read and written with the pure-Python ``rosbags`` library (sqlite3 ``.db3`` and ``.mcap``
storage, detected from the bag's metadata), and messages cross into rclpy as raw CDR bytes
(``rclpy.serialization``) -- the same wire format, so nothing is converted on the way.

Console entry points:

``beo-replay BAG``
    Plays the ``sensor_msgs/PointCloud2`` topics of a bag (all topics with ``--all-topics``, or the
    ones named with ``--topics``) into the live graph, timed by the bag's receive timestamps divided
    by ``--rate`` (``--rate 0``: as fast as possible). Header stamps are left as recorded. Reports
    per-topic counts and the wall duration as a table (``--json`` for machine-readable output).
    Exit code 130 when Ctrl-C cuts it short (0 for a ``--loop`` replay that played), 143 on
    SIGTERM.
    In-process use: :func:`replay`.

``beo-record TOPIC[:TYPE] ... -o BAG``
    Records topics to a new bag until SIGINT or SIGTERM (either closes the bag, exit code 0),
    ``--duration`` or ``--count``. Types are discovered
    from the graph or given as ``TOPIC:pkg/msg/Type``. Message definitions of types that the
    rosbags Jazzy typestore lacks (e.g. ``beo_interfaces/msg/ObjectEstimate``) are parsed from the
    package's ``.msg`` files, so the bag is self-describing. In-process use: :func:`record`.

``beo-pcd2bag SCENE.pcd ... -o BAG``
    Labelled organized tabletop scenes (OSD format) -> one bag with, per scene (scenes ``--period``
    apart):

    - ``--topic`` (default ``/beo/input``), ``sensor_msgs/PointCloud2``: one cloud per segmented
      object (points x y z float32, frame ``camera``, sensor at the origin); objects with fewer
      than ``--min-points`` points are skipped. The objects of a scene follow each other
      ``--object-period`` apart (first at the scene stamp) so that each has a unique stamp and a
      node that keeps only the latest cloud gets time to process each one;
    - ``/beo/up``, ``geometry_msgs/Vector3Stamped``: unit up vector (table normal pointing towards
      the camera side, from an open3d RANSAC fit of the table points), frame ``camera``, scene
      stamp;
    - ``/beo/table_plane``, ``std_msgs/Float64MultiArray``: plane ``[a, b, c, d]`` with
      ``a x + b y + c z + d = 0``, ``(a, b, c)`` the up vector above (camera frame), scene stamp.

    Each message's bag (receive) timestamp equals its header stamp. A file without a label field
    is refused; a scene without object labels (>= 20) is skipped with a warning.

Bad arguments (numbers out of range, invalid topic or node names, an output that exists) exit 2
with one line; Ctrl-C, one line and exit code 130, SIGTERM 143 (beo-record: both stop the
recording and close the bag, exit code 0), leaving no partial pcd2bag bag.

Modules: ``msgtypes`` (topic and node names, message types, the typestore), ``storage``
(:class:`BagWriter`, :func:`read_bag`, :func:`bag_info`, the QoS a bag stores), ``recover``
(:func:`recover_bag`), ``player`` (:func:`replay`), ``recorder`` (:func:`record`), ``scenes``
(:func:`pcd_to_bag`) and ``cli`` (the ``*_main`` entry points); this package re-exports their
names. Patch a name (``monkeypatch.setattr``) or change a setting such as ``COMMIT_PERIOD_S``
in the module that defines it: the copies here are not what the code looks up.
"""
from beo_ros.ros.bag.cli import (MAX_PERIOD_S, _cli_node, pcd2bag_main, record_main,
                                 recover_main, replay_main)
from beo_ros.ros.bag.msgtypes import (CLOUD_TYPE, check_node_name, check_topic_name,
                                      get_typestore, import_msg_class, msgtype_of,
                                      normalize_msgtype)
from beo_ros.ros.bag.player import (ACK_TIMEOUT_S, CLOCK_GRACE_S, BagReadError, ReplayStats,
                                    TopicNameError, TopicStats, _clock_tick, _sleep_until,
                                    make_qos, parse_remaps, replay)
from beo_ros.ros.bag.recorder import (COMMIT_PERIOD_S, BagWriteError, RecordStats,
                                      parse_topic_specs, record, resolve_topic_types)
from beo_ros.ros.bag.recover import MCAP_MAGIC, _bag_file, recover_bag
from beo_ros.ros.bag.scenes import (DEFAULT_FRAME, DEFAULT_INPUT_TOPIC, MAX_NS, PLANE_TOPIC,
                                    T0_NS, UP_TOPIC, NoObjects, pcd_to_bag, scene_messages)
from beo_ros.ros.bag.storage import (STORAGES, BagWriter, bag_info, cdr_payload,
                                     detect_storage, hot_journal, read_bag, read_messages,
                                     recorded_latched, recorded_reliable, storage_errors)

__all__ = [
    # msgtypes
    'CLOUD_TYPE', 'check_node_name', 'check_topic_name', 'get_typestore', 'import_msg_class',
    'msgtype_of', 'normalize_msgtype',
    # storage
    'STORAGES', 'BagWriter', 'bag_info', 'cdr_payload', 'detect_storage', 'hot_journal',
    'read_bag',
    'read_messages', 'recorded_latched', 'recorded_reliable', 'storage_errors',
    # recover
    'MCAP_MAGIC', 'recover_bag',
    # player
    'ACK_TIMEOUT_S', 'CLOCK_GRACE_S', 'BagReadError', 'ReplayStats', 'TopicNameError',
    'TopicStats', 'make_qos', 'parse_remaps', 'replay',
    # recorder
    'COMMIT_PERIOD_S', 'BagWriteError', 'RecordStats', 'parse_topic_specs', 'record',
    'resolve_topic_types',
    # scenes
    'DEFAULT_FRAME', 'DEFAULT_INPUT_TOPIC', 'MAX_NS', 'PLANE_TOPIC', 'T0_NS', 'UP_TOPIC',
    'NoObjects', 'pcd_to_bag', 'scene_messages',
    # cli
    'MAX_PERIOD_S', 'pcd2bag_main', 'record_main', 'recover_main', 'replay_main',
    # private helpers the tests use
    '_bag_file', '_cli_node', '_clock_tick', '_sleep_until',
]
