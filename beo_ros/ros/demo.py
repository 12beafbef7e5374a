"""beo-demo: the whole pipeline end to end on data the package ships, no arguments needed.

1. Renders one partial view per class of the shipped model (the class mean shape at a random
   yaw, seen from a slightly raised elevation and from a random azimuth, or for a model learned
   from partial views from the side its training views saw; see ``render_inputs``) and writes
   the views as PointCloud2 messages into a rosbag2 bag in a temporary directory.
2. Starts the beo node in-process (its own rclpy context, discovery off) with that model.
3. Replays the bag into the node (``beo_ros.ros.bag.replay``), one cloud at a time, and collects
   ``~/estimates`` and ``~/completed``.
4. Prints a table (input, true class, label, probability, yaw, latency), writes ``results.json``
   and ``beo_demo.png`` (input points and completed object per input) to ``--out``.

Exit status 0 only if every input got an estimate. Needs neither /work/shared nor a ROS install.
"""
from __future__ import annotations

import json
import math
import os
import sqlite3
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from beo_ros.cli import ArgumentParser, count, interruptible, number

FRAME = 'sensor'  # z up, sensor at the origin (see render_inputs)
TOPIC = '/beo/input'


def _default_model_dir() -> str:
    """The node's default model; if it is not there, another shipped model next to it."""
    from beo_ros.core.bank import default_model_dir as shipped_model_dir
    from beo_ros.core.bank import shipped_models
    from beo_ros.ros.node import default_model_dir
    d = Path(default_model_dir())
    if (d / 'manifest.json').is_file():
        return str(d)
    others = shipped_models()
    if others:
        other = shipped_model_dir(others[0])
        print(f'beo-demo: default model {d} is missing; using {other}', file=sys.stderr)
        return str(other)
    return str(d)


def class_fields(bank) -> dict:
    """Class name -> (mean occupancy field float32 (N, N, N), level): the level keeps the
    mean's expected number of occupied voxels (its sum, clipped to [0, 1]) above it, so thin
    classes (chairs, tables) keep their legs instead of vanishing under a 0.5 threshold."""
    n = bank.spec.size
    fields = {}
    for m in bank.models:
        mean = np.asarray(m.mean, dtype=np.float32)
        keep = int(np.clip(round(float(mean.clip(0, 1).sum())), 1, mean.size))
        level = float(np.partition(mean, mean.size - keep)[mean.size - keep])
        fields[m.name] = (mean.reshape(n, n, n), level)
    return fields


def class_shapes(bank, fields: dict | None = None) -> dict:
    """Class name -> bool (N, N, N) occupancy: each class's mean field at its level
    (``fields``, default :func:`class_fields` of ``bank``)."""
    fields = class_fields(bank) if fields is None else fields
    return {name: f >= level for name, (f, level) in fields.items()}


def seen_from(bank, step_deg: float = 15.0, elevation_deg: float = 25.0,
              shapes: dict | None = None) -> dict:
    """Class name -> azimuth (radians, grid frame) from which the class's training views saw
    it, or None for a class seen from every side.

    A model learned from partial views in the viewer's frame (``beo-train --scans``: x from
    the camera toward the object) never saw the back of its objects: there the posterior
    variance of its mean (``mean_variance``) stays at the prior's, elsewhere the data shrank
    it. The azimuth is the one (every ``step_deg``) whose view of the class shape (``shapes``,
    default :func:`class_shapes`) hides the voxels of the highest mean variance. A model of
    complete shapes has the same variance everywhere: None.
    """
    from beo_ros.core.synthetic import partial_view
    n = bank.spec.size
    shapes = class_shapes(bank) if shapes is None else shapes
    out = {}
    for m in bank.models:
        var = np.asarray(m.mean_variance, dtype=np.float64).reshape(n, n, n)
        if var.max() - var.min() <= 1e-3 * var.max():
            out[m.name] = None
            continue
        azimuths = np.deg2rad(np.arange(0.0, 360.0, step_deg))
        hidden = []
        for az in azimuths:
            behind = partial_view(shapes[m.name], az, np.deg2rad(elevation_deg),
                                  ray_spacing=1.0) < 0
            hidden.append(var[behind].mean() if behind.any() else -np.inf)
        out[m.name] = float(azimuths[int(np.argmax(hidden))])
    return out


def render_inputs(bank, seed: int = 0, views_per_class: int = 1, size: float = 1.0) -> list:
    """One rendered partial view per class (and view) of the class's mean shape: list of dicts
    with 'name', 'true_class', 'true_yaw', 'azimuth', 'elevation', 'points' (n, 3) in the
    sensor frame and 'centre' (3,) (the grid centre).

    The shape is turned by a random yaw and seen from an elevation of 15-35 deg, from a random
    azimuth for a class seen from every side, else from within 10 deg of the side its training
    views saw (:func:`seen_from`; ``tabletop_32``'s mean box seen from elsewhere is no view it
    was taught, and was labelled a cylinder). A metric model is rendered as a depth sensor sees
    real objects: the smooth level surface of the mean field (:func:`class_fields`,
    ``render_surface_points``) from twice the grid's span ``size`` (1 m for ``tabletop_32``);
    its 'points' classifier reads surface normals, which the voxels of ``render_view_points``
    (jittered over whole voxels) do not have. A normalized model is rendered as before: the
    visible voxels of the class shape (:func:`class_shapes`), which they reproduce exactly
    (a smooth surface loses one-voxel chair legs in the voxelization). Depth noise: 0.2 % of
    ``size``.

    The sensor frame is the renderer's z-up world frame shifted so that the sensor sits at the
    origin: up is +z and the sensor origin is (0, 0, 0) for every view.
    """
    from beo_ros.core.synthetic import render_surface_points, render_view_points
    rng = np.random.default_rng(seed)
    fields = class_fields(bank)
    shapes = class_shapes(bank, fields)
    sides = seen_from(bank, shapes=shapes)
    metric = bank.spec.units == 'metric'
    inputs = []
    for cls, occ in shapes.items():
        for v in range(views_per_class):
            yaw = float(rng.uniform(0, 2 * math.pi))
            az = float(rng.uniform(0, 2 * math.pi))
            el = float(np.deg2rad(rng.uniform(15, 35)))
            if sides[cls] is not None:   # the side its training views saw, turned by the yaw
                az = float((yaw + sides[cls] + np.deg2rad(rng.uniform(-10, 10))) % (2 * math.pi))
            if metric:
                field, level = fields[cls]
                pts, origin = render_surface_points(field, level, yaw, az, el, distance=2.0 * size,
                                                    size=size, noise=0.002 * size, rng=rng)
            else:
                pts, origin = render_view_points(occ, yaw, az, el, distance=max(2.0, 2.0 * size),
                                                 size=size, noise=0.002 * size, rng=rng)
            pts = np.asarray(pts, dtype=np.float64) - np.asarray(origin, dtype=np.float64)
            pts = pts[np.isfinite(pts).all(axis=1)]
            inputs.append({'name': f'{cls}_{v}', 'true_class': cls, 'true_yaw': yaw,
                           'azimuth': az, 'elevation': el, 'points': pts,
                           'centre': -np.asarray(origin, dtype=np.float64)})
    return inputs


def write_bag(inputs, path, period: float = 0.5, storage: str = 'sqlite3') -> list:
    """One cloud per input on /beo/input, ``period`` s apart; sets ``input['stamp_ns']``."""
    from std_msgs.msg import Header

    from beo_ros.ros.bag import T0_NS, BagWriter
    from beo_ros.ros.conversions import stamp_from_ns, xyz_to_cloud
    with BagWriter(path, storage) as w:
        for i, inp in enumerate(inputs):
            ns = T0_NS + int(round(i * period * 1e9))
            header = Header(stamp=stamp_from_ns(ns), frame_id=FRAME)
            w.write(TOPIC, xyz_to_cloud(inp['points'], header), ns)
            inp['stamp_ns'] = ns
    return inputs


def run_node_on_bag(bag_path, model_dir, bank, up, origin, timeout: float = 120.0):
    """Start BeoNode in-process, replay the bag one cloud at a time; (estimates, completed, stats).

    ``estimates`` and ``completed`` map header stamps (ns) to messages.
    """
    # forced, not defaulted: with a user's LOCALHOST/SUBNET the demo would talk to other nodes
    # (its listener would take their estimates); the node's worker processes inherit it. Put
    # back afterwards: the caller's own contexts keep their setting
    saved_range = os.environ.get('ROS_AUTOMATIC_DISCOVERY_RANGE')
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'OFF'
    try:
        return _run_node_on_bag(bag_path, model_dir, bank, up, origin, timeout)
    finally:
        if saved_range is None:
            os.environ.pop('ROS_AUTOMATIC_DISCOVERY_RANGE', None)
        else:
            os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = saved_range


def _run_node_on_bag(bag_path, model_dir, bank, up, origin, timeout):
    import rclpy
    from rclpy.executors import MultiThreadedExecutor
    from rclpy.parameter import Parameter
    from rclpy.qos import QoSProfile
    from sensor_msgs.msg import PointCloud2

    from beo_ros.ros import bag
    from beo_ros.ros.conversions import interfaces, ns_from_stamp
    from beo_ros.ros.env import check_domain_id
    from beo_ros.ros.node import BeoNode, StartupError, drain_executor
    msgs = interfaces()
    ctx = rclpy.Context()
    try:
        rclpy.init(args=[], context=ctx)   # not sys.argv: no remap rules from the command line
        check_domain_id(ctx)
    except Exception as e:  # noqa: BLE001 - rclpy's RCLError: a ROS_DOMAIN_ID that is no number
        ctx.try_shutdown()
        raise StartupError(f'cannot start ROS: {type(e).__name__}: {e}') from None
    estimates, completed = {}, {}
    lock = threading.Lock()
    got = threading.Condition(lock)
    ex = node = listener = player = spinner = None
    stop_spin = threading.Event()
    try:
        node = BeoNode(context=ctx, bank=bank, parameter_overrides=[
            Parameter('model_dir', value=str(model_dir)),
            Parameter('up_vector', value=[float(v) for v in up]),
            Parameter('sensor_origin', value=[float(v) for v in origin])])
        listener = rclpy.create_node('beo_demo_listener', context=ctx)
        player = rclpy.create_node('beo_demo_player', context=ctx)

        def keep(store, m):
            with got:
                store[ns_from_stamp(m.header.stamp)] = m
                got.notify_all()
        listener.create_subscription(msgs.ObjectEstimate, '/beo/estimates',
                                     lambda m: keep(estimates, m), QoSProfile(depth=100))
        listener.create_subscription(PointCloud2, '/beo/completed',
                                     lambda m: keep(completed, m), QoSProfile(depth=100))
        ex = MultiThreadedExecutor(num_threads=4, context=ctx)
        ex.add_node(node)
        ex.add_node(listener)

        def spin():
            while not stop_spin.is_set():
                ex.spin_once(timeout_sec=0.05)
        spinner = threading.Thread(target=spin, daemon=True)
        spinner.start()

        def failures():
            c = node.counters()
            return c['rejected'] + c['errors']
        seen = {'failures': failures()}

        def wait_for_estimate(topic, raw, stamp):
            """on_publish: one cloud at a time, so the latest-only node drops none."""
            deadline = time.monotonic() + timeout
            with got:
                while not (stamp in estimates and stamp in completed):
                    if failures() > seen['failures']:   # rejected: no estimate will come
                        seen['failures'] += 1
                        return
                    left = deadline - time.monotonic()
                    if left <= 0:
                        return
                    got.wait(min(left, 0.1))
        # the latency column is the steady state's: the first cloud would wait for the
        # node's warm-up estimate (about 0.5-1 s) otherwise (a node stuck in it shows as
        # estimates that never come)
        node.wait_ready(timeout)
        stats = bag.replay(bag_path, player, rate=0, wait_subscribers=1, wait_timeout=10.0,
                           on_publish=wait_for_estimate)
    finally:
        stop_spin.set()
        if spinner is not None:
            spinner.join(10)
        if ex is not None:
            drain_executor(ex)
        for n in (node, listener, player):
            if n is not None:
                n.destroy_node()
        rclpy.try_shutdown(context=ctx)
    # once destroy_node has waited for its workers: a worker counts a cloud 'processed' after
    # publishing it, so a snapshot taken as the last estimate arrived could lack it (9 of 10)
    return estimates, completed, stats, node.counters()


def results_table(rows) -> str:
    head = ('input', 'true class', 'label', 'prob', 'yaw deg', 'true yaw', 'same turned by',
            'latency ms', 'points')
    lines = [head]
    for r in rows:
        lines.append((r['input'], r['true_class'], r['label'] or '-',
                      '-' if r['probability'] is None else f"{r['probability']:.2f}",
                      '-' if r['yaw'] is None else f"{math.degrees(r['yaw']):.0f}",
                      f"{math.degrees(r['true_yaw']):.0f}",
                      '/'.join(map(str, r['symmetric_turns_deg'])) or '-',
                      '-' if r['latency'] is None else f"{r['latency'] * 1e3:.0f}",
                      str(r['points'])))
    widths = [max(len(str(x[i])) for x in lines) for i in range(len(head))]
    out = ['  '.join(str(c).ljust(w) for c, w in zip(x, widths)).rstrip() for x in lines]
    out.insert(1, '  '.join('-' * w for w in widths))
    return '\n'.join(out)


def plot(inputs, rows, completed_pts, path):
    """One 3D panel per input: input points (blue) and completed object (orange)."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    n = len(inputs)
    cols = min(5, n)
    nrows = math.ceil(n / cols)
    fig = plt.figure(figsize=(3.2 * cols, 3.4 * nrows))
    for k, (inp, r) in enumerate(zip(inputs, rows)):
        ax = fig.add_subplot(nrows, cols, k + 1, projection='3d')
        comp = completed_pts.get(inp['stamp_ns'])
        if comp is not None and len(comp):
            ax.scatter(comp[:, 0], comp[:, 1], comp[:, 2], s=7, c='tab:orange', alpha=0.35,
                       linewidths=0, label='completed', depthshade=False)
        p = inp['points']
        if len(p) > 3000:
            p = p[np.random.default_rng(0).choice(len(p), 3000, replace=False)]
        ax.scatter(p[:, 0], p[:, 1], p[:, 2], s=2.5, c='tab:blue', linewidths=0, label='input',
                   depthshade=False)
        allp = np.concatenate([x for x in (inp['points'], comp) if x is not None and len(x)])
        lo, hi = allp.min(axis=0), allp.max(axis=0)
        c, half = (lo + hi) / 2, max((hi - lo).max() / 2, 1e-3)
        ax.set_xlim(c[0] - half, c[0] + half)
        ax.set_ylim(c[1] - half, c[1] + half)
        ax.set_zlim(c[2] - half, c[2] + half)
        ax.set_xticklabels([])
        ax.set_yticklabels([])
        ax.set_zticklabels([])
        ok = r['label'] == r['true_class']
        label = r['label'] or 'no estimate'
        prob = '' if r['probability'] is None else f' {r["probability"]:.2f}'
        ax.set_title(f'{inp["true_class"]}\n-> {label}{prob}', fontsize=9,
                     color='black' if ok else 'tab:red', parse_math=False)   # '$' in a name
    fig.suptitle('beo-demo: input view (blue), completed object (orange)', fontsize=11)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


@interruptible('beo-demo')
def main(argv=None) -> int:
    p = ArgumentParser(
        prog='beo-demo', description='Render partial views of every class of the model (the '
        'shipped one by default), replay them as a rosbag2 bag into an in-process beo node, '
        'print the estimates and plot them. Exit 0 only if every input got an estimate.')
    p.add_argument('--out', default='./beo_demo_out', metavar='DIR',
                   help='output directory for results.json and beo_demo.png '
                        '(default ./beo_demo_out)')
    p.add_argument('--model', metavar='DIR', help='model bank directory (default: the shipped '
                   'model, as the node resolves it)')
    p.add_argument('--seed', type=count(0), default=0,
                   help='random yaws/viewpoints (default 0)')
    p.add_argument('--views-per-class', type=count(1), default=1,
                   help='rendered views per class (default 1)')
    p.add_argument('--storage', choices=('sqlite3', 'mcap'), default='mcap',
                   help='bag storage of the demo bag (default mcap)')
    p.add_argument('--keep-bag', action='store_true',
                   help='copy the demo bag into --out/demo_bag (replacing an earlier one)')
    p.add_argument('--timeout', type=number(0, None, lo_open=True), default=120.0,
                   help='seconds to wait for each estimate (default 120)')
    args = p.parse_args(argv)
    from beo_ros.cli import out_dir_problem, output_dir
    problem = out_dir_problem(Path(args.out))
    if problem:
        p.error(f'--out {args.out}: {problem}')
    t_start = time.monotonic()
    from beo_ros.ros.env import ensure_ament_prefix
    ensure_ament_prefix()

    from beo_ros.ros.node import StartupError, load_bank
    model_dir = args.model or _default_model_dir()
    try:
        bank = load_bank(model_dir)
    except StartupError as e:
        print(f'beo-demo: {e}', file=sys.stderr)
        return 2
    print(f'model: {model_dir} ({len(bank.classes)} classes: {", ".join(bank.classes)})')
    try:
        # a failure or Ctrl-C before anything is written leaves no empty --out behind
        with output_dir(args.out) as out:
            return _demo(args, bank, model_dir, out, t_start)
    except StartupError as e:   # ROS or the node did not start: as beo-node, exit code 1
        print(f'beo-demo: {e}', file=sys.stderr)
        return 1
    except BrokenPipeError:   # stdout's reader is gone: see cli.interruptible
        raise
    except (OSError, sqlite3.Error) as e:   # a full disk (the demo bag: sqlite3's own error)
        print(f'beo-demo: error: {e}', file=sys.stderr)
        return 2


def _demo(args, bank, model_dir, out, t_start) -> int:
    """Steps 1-4 of the module docstring into the output directory ``out``; exit code."""
    spec = bank.spec   # render at the model's scale: a metric grid spans size * voxel_size
    size = spec.size * spec.voxel_size if spec.units == 'metric' else 1.0
    inputs = render_inputs(bank, seed=args.seed, views_per_class=args.views_per_class, size=size)
    up, origin = (0.0, 0.0, 1.0), (0.0, 0.0, 0.0)   # render_inputs' sensor frame
    with tempfile.TemporaryDirectory(prefix='beo_demo_') as tmp:
        bag_path = Path(tmp) / 'demo_bag'
        write_bag(inputs, bag_path, storage=args.storage)
        print(f'demo bag: {len(inputs)} clouds on {TOPIC} ({args.storage})')
        t_node = time.monotonic()
        estimates, completed, stats, counters = run_node_on_bag(
            bag_path, model_dir, bank, up, origin, timeout=args.timeout)
        node_s = time.monotonic() - t_node
        kept_bag = None
        if args.keep_bag:
            import shutil
            kept = out / 'demo_bag'
            # an earlier run's bag (maybe the other storage: demo_bag.mcap beside a new .db3)
            if kept.is_dir() and not kept.is_symlink():
                shutil.rmtree(kept)
            elif kept.exists() or kept.is_symlink():
                kept.unlink()
            shutil.copytree(bag_path, kept)
            # its storage file (demo_bag.mcap or .db3), which beo-replay takes as well
            kept_bag = next(f for f in sorted(kept.iterdir()) if f.suffix in ('.db3', '.mcap'))

    from beo_ros.ros.conversions import cloud_to_xyz, quaternion_to_rotation
    rows, completed_pts = [], {}
    for inp in inputs:
        e = estimates.get(inp['stamp_ns'])
        c = completed.get(inp['stamp_ns'])
        if c is not None:
            completed_pts[inp['stamp_ns']] = cloud_to_xyz(c)[0]
        yaw, turns = None, []
        if e is not None:   # object yaw about +z (the sensor frame's up) from the pose
            o = e.pose.orientation
            r = quaternion_to_rotation([o.x, o.y, o.z, o.w])
            yaw = float(math.atan2(r[1, 0], r[0, 0])) % (2 * math.pi)
            if len(e.hypotheses):   # the first hypothesis holds the estimate's own yaw
                turns = sorted(round(math.degrees(s - e.hypotheses[0].yaw)) % 360
                               for s in e.symmetric_yaws)
        rows.append({'input': inp['name'], 'true_class': inp['true_class'],
                     'true_yaw': inp['true_yaw'], 'points': int(len(inp['points'])),
                     'label': e.label if e is not None else None,
                     'probability': float(e.probability) if e is not None else None,
                     'yaw': yaw, 'symmetric_turns_deg': turns,
                     'latency': float(e.latency) if e is not None else None,
                     'status': e.status if e is not None else 'no estimate',
                     'completed_points': int(len(completed_pts.get(inp['stamp_ns'], [])))})
    print(results_table(rows))
    n_est = sum(r['label'] is not None for r in rows)
    n_ok = sum(r['label'] == r['true_class'] for r in rows)
    png = out / 'beo_demo.png'
    plot(inputs, rows, completed_pts, png)
    total_s = time.monotonic() - t_start
    summary = {'model': str(model_dir), 'bag': None if kept_bag is None else str(kept_bag),
               'inputs': len(rows), 'estimated': n_est,
               'correct': n_ok, 'node_and_replay_s': round(node_s, 3),
               'total_s': round(total_s, 3), 'replay': stats.to_dict(), 'node_counters': counters,
               'results': rows}
    (out / 'results.json').write_text(json.dumps(summary, indent=2))
    print(f'{n_est}/{len(rows)} inputs estimated, {n_ok} correctly labelled; '
          f'{total_s:.1f} s total ({node_s:.1f} s node + replay)')
    print(f'wrote {png} and {out / "results.json"}')
    if n_est < len(rows):
        print(f'beo-demo: {len(rows) - n_est} input(s) got no estimate', file=sys.stderr)
        return 1
    return 0


if __name__ == '__main__':
    sys.exit(main())
