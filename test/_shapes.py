"""ROS-free shape fixtures shared by several test modules (no test module imports another)."""
import numpy as np

N = 16   # grid size of asymmetric_shapes (test_bank's too)


def box_view(centre=(2.0, 0.3, 0.4), size=(0.5, 0.35, 0.8), n=3000, seed=0):
    """Points (n', 3) on the faces of a box visible from the origin (one partial view, z up)."""
    rng = np.random.default_rng(seed)
    c, h = np.asarray(centre, float), np.asarray(size, float) / 2
    pts = []
    for axis in range(3):
        for sign in (-1, 1):
            normal = np.zeros(3)
            normal[axis] = sign
            face_c = c + normal * h
            if normal @ (-face_c) <= 0:  # faces turned away from the sensor are not seen
                continue
            p = rng.uniform(-1, 1, size=(n // 3, 3)) * h + c
            p[:, axis] = face_c[axis]
            pts.append(p)
    return np.concatenate(pts)


def box_off(path, sx, sy, sz):
    """An axis-aligned box mesh centred at the origin, as an OFF file."""
    v = [(x * sx, y * sy, z * sz) for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    tris = [t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))]
    path.write_text('OFF\n8 12 0\n' + ''.join(f'{x} {y} {z}\n' for x, y, z in v)
                    + ''.join(f'3 {a} {b} {c}\n' for a, b, c in tris))


def asymmetric_shapes(count, rng, N=N):
    """Two classes whose shapes have no yaw symmetry: 'ell' (a bar with an arm at one end) and
    'step' (a low slab with a tall block in one quadrant), on an (N, N, N) grid."""
    c = (N - 1) / 2
    ii, jj, kk = np.meshgrid(*(np.arange(N) - c,) * 3, indexing='ij')
    X, y = [], []
    for _ in range(count):
        L, w, h, a = rng.uniform(5, 6.5), rng.uniform(1.5, 2.2), rng.uniform(3, 5), rng.uniform(3, 5)
        o = (np.abs(ii) <= L) & (np.abs(jj + 2) <= w) & (np.abs(kk) <= h)
        o |= (ii >= L - 2 * w) & (ii <= L) & (jj >= -2) & (jj <= -2 + a + w) & (np.abs(kk) <= h)
        X.append(o.ravel())
        y.append(0)
        L, b, h = rng.uniform(5, 6.5), rng.uniform(3, 4.5), rng.uniform(2, 3)
        o = (np.abs(ii) <= L) & (np.abs(jj) <= b) & (kk <= -h) & (kk >= -6)
        o |= (ii >= 1) & (ii <= L) & (jj >= -b) & (jj <= 0) & (kk >= -6) & (kk <= 6)
        X.append(o.ravel())
        y.append(1)
    return np.array(X, dtype=np.float32), np.array(y)
