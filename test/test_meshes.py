"""Mesh loading and ModelNet-convention voxelization."""
import os
from pathlib import Path

import numpy as np
import pytest
import trimesh

from beo_ros.core.meshes import MeshError, load_mesh, mesh_to_grid_transform, voxelize_mesh

from _shapes import box_off

DATA = Path(os.environ.get('BEO_DATA_DIR')
            or Path(__file__).resolve().parents[1].parent / 'shared' / 'data')
MESHES = sorted((DATA / 'meshes').glob('*.off')) if (DATA / 'meshes').is_dir() else []


def bbox(grid):
    a = np.argwhere(grid)
    return a.min(axis=0), a.max(axis=0)


@pytest.mark.parametrize('extents', [(1, 2, 4), (4, 1, 1), (3, 3, 3), (2.0, 1.0, 0.5)])
def test_box_fills_grid_with_aspect(extents):
    mesh = trimesh.creation.box(extents)
    mesh.apply_translation([10, -3, 7])  # placement in mesh coords does not matter
    g = voxelize_mesh(mesh, size=32)
    assert g.shape == (32, 32, 32) and g.dtype == bool
    lo, hi = bbox(g)
    size = hi - lo + 1
    np.testing.assert_array_equal(size, np.round(32 * np.asarray(extents) / max(extents)))
    np.testing.assert_allclose((lo + hi) / 2, 15.5, atol=0.5)  # centred
    assert g.sum() == np.prod(size)  # solid: every voxel of the box is filled
    assert voxelize_mesh(mesh, fill=False).sum() < g.sum()


def test_z_up_and_odd_size():
    # a tetrahedron that is wide at the bottom (z low) and pointed at the top
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 2.0]])
    tet = trimesh.Trimesh(v, [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    g = voxelize_mesh(tet, size=17)
    assert g.shape == (17, 17, 17)
    per_layer = g.sum(axis=(0, 1))
    assert per_layer[0] > per_layer[8] > per_layer[16] >= 1  # mesh +z is grid k
    assert bbox(g)[0][2] == 0 and bbox(g)[1][2] == 16
    t = mesh_to_grid_transform(tet, 17)
    np.testing.assert_allclose(t[:3, :3] @ [0, 0, 2.0], [0, 0, 17])
    # a whole float is an integer size (a TypeError in np.zeros before); bool and 16.5 are not
    np.testing.assert_array_equal(voxelize_mesh(tet, 17.0), g)
    for bad in (True, 16.5, float('nan'), '16', 1):
        with pytest.raises(ValueError, match='size must be an integer'):
            voxelize_mesh(tet, bad)


def test_load_mesh_formats_and_errors(tmp_path):
    box = trimesh.creation.box((1, 2, 3))
    for ext in ('off', 'obj', 'stl', 'ply'):
        path = tmp_path / f'box.{ext}'
        box.export(path)
        m = load_mesh(path)
        assert len(m.faces) == 12
        np.testing.assert_allclose(np.ptp(m.vertices, axis=0), [1, 2, 3])
        lo, hi = bbox(voxelize_mesh(path))
        np.testing.assert_allclose(hi - lo + 1, 32 * np.array([1, 2, 3]) / 3, atol=1.5)
    with pytest.raises(MeshError, match='no such'):
        load_mesh(tmp_path / 'missing.off')
    (tmp_path / 'junk.off').write_text('OFF\n3 1 0\n0 0 0\nthis is not a number\n')
    with pytest.raises(MeshError, match='junk.off: cannot parse mesh'):
        load_mesh(tmp_path / 'junk.off')
    (tmp_path / 'empty.stl').write_bytes(b'')   # shorter than a binary STL header
    with pytest.raises(MeshError, match='empty.stl: mesh has no triangles'):
        load_mesh(tmp_path / 'empty.stl')
    (tmp_path / 'x.xyz').write_text('1 2 3\n')
    with pytest.raises(MeshError, match='unsupported'):
        load_mesh(tmp_path / 'x.xyz')
    flat = trimesh.Trimesh([[0, 0, 0], [0, 0, 0], [0, 0, 0]], [[0, 1, 2]], process=False)
    with pytest.raises(MeshError, match='zero or non-finite extent'):
        voxelize_mesh(flat)
    (tmp_path / 'point.off').write_text('OFF\n3 1 0\n1 2 3\n1 2 3\n1 2 3\n3 0 1 2\n')
    with pytest.raises(MeshError, match=r'point\.off: mesh is degenerate \(zero extent\)'):
        load_mesh(tmp_path / 'point.off')
    # the extension's case does not matter
    box.export(tmp_path / 'BOX.OFF', file_type='off')
    assert len(load_mesh(tmp_path / 'BOX.OFF').faces) == 12
    assert issubclass(MeshError, ValueError)


def test_vertices_no_triangle_uses_do_not_count(tmp_path):
    # many ModelNet OFF files keep such vertices; one far away shrank the object to 2 voxels
    box = trimesh.creation.box((1, 2, 4))
    ref = voxelize_mesh(box)
    with_far = trimesh.Trimesh(np.r_[box.vertices, [[1e9, 1e9, 1e9]]], box.faces, process=False)
    np.testing.assert_array_equal(voxelize_mesh(with_far), ref)
    np.testing.assert_allclose(mesh_to_grid_transform(with_far), mesh_to_grid_transform(box))
    path = tmp_path / 'far.off'
    with_far.export(path)
    m = load_mesh(path)
    assert len(m.vertices) == 8
    np.testing.assert_array_equal(voxelize_mesh(m), ref)
    # a NaN vertex that no triangle uses does not matter either; a used one is refused
    path.write_text('OFF\n4 1 0\n0 0 0\n1 0 0\n0 1 1\nnan nan nan\n3 0 1 2\n')
    assert len(load_mesh(path).vertices) == 3
    path.write_text('OFF\n3 1 0\n0 0 0\n1 0 0\nnan 1 1\n3 0 1 2\n')
    with pytest.raises(MeshError, match='non-finite'):
        load_mesh(path)



def test_huge_coordinates(tmp_path):
    # a box far out near the float64 limit: its centre (lo + hi) / 2 overflowed to inf and
    # the voxelization failed with "cannot convert float NaN to integer"
    box = trimesh.creation.box((1, 2, 4))
    far = trimesh.Trimesh((box.vertices + 2) * 1e307 + 1e308, box.faces, process=False)
    np.testing.assert_array_equal(voxelize_mesh(far), voxelize_mesh(box))
    # an extent that overflows cannot be voxelized: refused naming the file (the error from
    # the voxelization named nothing)
    wide = trimesh.Trimesh(np.sign(box.vertices) * 1e308, box.faces, process=False)
    path = tmp_path / 'wide.off'
    wide.export(path)
    with pytest.raises(MeshError, match='wide.off: mesh extent overflows'):
        load_mesh(path)

def test_the_surface_gets_the_samples_its_density_asks_for(monkeypatch):
    # the samples were capped at 4M: a 256^3 grid of bathtub_0001 (23.5M samples wanted) got
    # 5 per square voxel, its surface had holes, the fill leaked and 34 % of the solid was
    # missing; they are drawn in chunks of at most SAMPLE_CHUNK instead
    from beo_ros.core import meshes
    real = trimesh.sample.sample_surface
    counts = []

    def counting(mesh, count, seed=None):
        counts.append(count)
        return real(mesh, min(count, 1000), seed=seed)   # the points need not be many here

    monkeypatch.setattr(trimesh.sample, 'sample_surface', counting)
    box = trimesh.creation.box((1, 1, 1))
    voxelize_mesh(box, 16, density=2000.0)
    assert abs(sum(counts) - 6 * 16 ** 2 * 2000.0) <= 1   # 3.07M
    counts.clear()
    voxelize_mesh(box, 64, density=200.0)
    assert abs(sum(counts) - 6 * 64 ** 2 * 200.0) <= 1    # 4.9M
    assert max(counts) <= meshes.SAMPLE_CHUNK and len(counts) == 2


@pytest.mark.parametrize('kw', [dict(density=float('nan')), dict(density=-1.0), dict(density=0),
                                dict(density='32'), dict(seed='a'), dict(seed=1.5)])
def test_voxelize_mesh_names_bad_density_and_seed(kw):
    with pytest.raises(ValueError, match=next(iter(kw)) + ' must be'):
        voxelize_mesh(trimesh.creation.box((1, 1, 1)), 16, **kw)


@pytest.mark.skipif(not MESHES, reason=f'shared meshes not found under {DATA}')
@pytest.mark.parametrize('path', MESHES, ids=[p.stem for p in MESHES])
def test_modelnet_meshes(path):
    g = voxelize_mesh(load_mesh(path))
    lo, hi = bbox(g)
    assert (hi - lo).max() == 31  # the largest extent spans the grid
    np.testing.assert_allclose((lo + hi) / 2, 15.5, atol=1.0)
    assert 500 < g.sum() < 32 ** 3 // 2
    np.testing.assert_array_equal(g, voxelize_mesh(load_mesh(path)))  # deterministic


@pytest.mark.skipif(not MESHES, reason=f'shared meshes not found under {DATA}')
def test_matches_training_grid_statistics():
    npz = DATA / 'modelnet10' / 'modelnet10_vox32_train.npz'
    if not npz.is_file():
        pytest.skip('ModelNet10 grids not found')
    z = np.load(npz)
    vox = np.unpackbits(z['voxels'][:300], axis=1).reshape(-1, 32, 32, 32).astype(bool)
    ext = np.array([np.ptp(np.argwhere(g), axis=0).max() for g in vox])
    # the training grids follow the same convention: the largest extent spans all 32 voxels
    assert np.mean(ext == 31) > 0.8
    toilet = [p for p in MESHES if p.stem.startswith('toilet')]
    if toilet:
        g = voxelize_mesh(load_mesh(toilet[0]))
        sel = z['labels'] == list(z['classes']).index('toilet')
        train = np.unpackbits(z['voxels'][sel], axis=1).reshape(-1, 32, 32, 32) > 0
        iou = (train & g).sum(axis=(1, 2, 3)) / (train | g).sum(axis=(1, 2, 3))
        assert iou.max() > 0.5  # a similar toilet exists among the training grids


def test_a_directory_is_called_so(tmp_path):
    with pytest.raises(MeshError, match='a directory, not a mesh file'):
        load_mesh(tmp_path)


def test_a_subnormal_extent_is_refused_naming_the_file(tmp_path):
    # a box 3e-310 wide: the scale size / extent overflowed to inf and the voxelization
    # failed with numpy's 'index -9223372036854775808 is out of bounds for axis 0'
    from beo_ros.core.datasets import load_meshes
    box = trimesh.creation.box((1, 2, 3))
    tiny = trimesh.Trimesh(box.vertices * 1e-310, box.faces, process=False)
    with pytest.raises(MeshError, match='too small to scale to 32 voxels'):
        voxelize_mesh(tiny)
    path = tmp_path / 'chair_0001.off'
    path.write_text(f'OFF\n8 {len(box.faces)} 0\n'
                    + ''.join(' '.join(repr(float(c)) for c in v) + '\n'
                              for v in tiny.vertices)
                    + ''.join('3 ' + ' '.join(map(str, f)) + '\n' for f in box.faces))
    with pytest.raises(MeshError, match='chair_0001.off: mesh extent .* too small'):
        load_meshes([path], 32)
    # 1e-300 still scales: the same grid as the unit box
    np.testing.assert_array_equal(voxelize_mesh(trimesh.Trimesh(
        box.vertices * 1e-300, box.faces, process=False)), voxelize_mesh(box))


@pytest.mark.parametrize('header', ['OFF\n8 12 0\n', 'OFF 8 12 0\n', 'OFF8 12 0\n',
                                    'COFF\n8 12 0\n'])
def test_a_truncated_off_file_is_refused(tmp_path, header):
    # trimesh reads the faces a cut-off download still has without a word: 6 of a box's 12
    # triangles made a hollow grid of 1287 voxels instead of 8448
    full = tmp_path / 'full.off'
    box_off(full, 1, 2, 3)
    body = full.read_text().split('\n', 2)[2]
    (tmp_path / 'whole.off').write_text(header + body)
    assert len(load_mesh(tmp_path / 'whole.off').faces) == 12
    cut = tmp_path / 'cut.off'
    cut.write_text(header + ''.join(body.splitlines(keepends=True)[:8 + 6]))
    with pytest.raises(MeshError, match=r'cut.off: truncated OFF file: its header declares 12 '
                                        r'faces, it ends after 6'):
        load_mesh(cut)
    cut.write_text(header + ''.join(body.splitlines(keepends=True)[:8 + 11]))   # one face short
    with pytest.raises(MeshError, match=r'ends after 11'):
        load_mesh(cut)


@pytest.mark.parametrize('index', [9, 4, -1])
def test_a_ply_face_index_outside_the_vertices_is_refused(tmp_path, index):
    # past the end was a raw IndexError out of load_mesh (a traceback from beo-train), a
    # negative index wrapped around to another vertex without a word
    faces = [[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, index]]
    path = tmp_path / 'tet.ply'
    path.write_text('ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\n'
                    'property float z\nelement face 4\nproperty list uchar int vertex_indices\n'
                    'end_header\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n'
                    + ''.join('3 ' + ' '.join(map(str, f)) + '\n' for f in faces))
    with pytest.raises(MeshError, match=f'tet.ply: a face refers to vertex {index}, the mesh '
                                        r'has 4 vertices \(0..3\)'):
        load_mesh(path)


def test_an_obj_vertex_line_of_two_numbers_is_refused_naming_the_file(tmp_path):
    # trimesh then reads every vertex as 2-D: the voxelization failed with numpy's 'could not
    # broadcast input array from shape (2,) into shape (3,)', naming no file
    path = tmp_path / 'tet.obj'
    path.write_text('v 0 0 0\nv 1 0 0\nv 0 1\nv 0 0 1\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n')
    with pytest.raises(MeshError, match=r'tet.obj: vertices must have 3 coordinates'):
        voxelize_mesh(path)


@pytest.mark.parametrize('material', [False, True])
def test_an_obj_file_with_a_utf8_byte_order_mark_is_loaded(tmp_path, material):
    # as Windows editors save UTF-8: trimesh took the BOM for part of the first 'v' keyword,
    # dropped that vertex and failed with 'cannot parse mesh (IndexError: index 3 is out of
    # bounds ...)'; its material file is still found next to it
    body = ('v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\n'
            + ('mtllib tet.mtl\nusemtl red\n' if material else '')
            + 'f 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n')
    (tmp_path / 'tet.mtl').write_text('newmtl red\nKd 1 0 0\n')
    (tmp_path / 'plain.obj').write_text(body)
    (tmp_path / 'bom.obj').write_bytes(b'\xef\xbb\xbf' + body.encode())
    plain, bom = load_mesh(tmp_path / 'plain.obj'), load_mesh(tmp_path / 'bom.obj')
    np.testing.assert_array_equal(bom.vertices, plain.vertices)
    np.testing.assert_array_equal(bom.faces, plain.faces)
    assert len(bom.vertices) == 4
    if material:
        assert list(bom.visual.material.main_color) == [255, 0, 0, 255]
    np.testing.assert_array_equal(voxelize_mesh(tmp_path / 'bom.obj', size=8),
                                  voxelize_mesh(tmp_path / 'plain.obj', size=8))


@pytest.mark.parametrize('solid_header', [False, True])
@pytest.mark.parametrize('cut', [-30, 10])
def test_a_binary_stl_of_the_wrong_length_is_called_so(tmp_path, cut, solid_header):
    # trimesh refuses a truncated (or padded) binary STL and then reads it as ASCII: the
    # error said 'mesh has no triangles' of a file that declares 12 (still so when the binary
    # header starts with 'solid', as SolidWorks writes it)
    data = trimesh.exchange.stl.export_stl(trimesh.creation.box((1, 2, 3)))
    if solid_header:
        data = b'solid part1'.ljust(80) + data[80:]
        assert len(load_mesh_bytes(tmp_path, data).faces) == 12   # whole: it loads
    path = tmp_path / 'box.stl'
    path.write_bytes(data[:cut] if cut < 0 else data + bytes(cut))
    with pytest.raises(MeshError, match=f'box.stl: binary STL of {len(data) + cut} bytes, its '
                                        r'header declares 12 triangles \(684 bytes\)'):
        load_mesh(path)


def load_mesh_bytes(tmp_path, data, name='whole.stl'):
    (tmp_path / name).write_bytes(data)
    return load_mesh(tmp_path / name)


def test_an_ascii_stl_without_triangles_has_none(tmp_path):
    with pytest.raises(MeshError, match='empty.stl: mesh has no triangles'):
        load_mesh_bytes(tmp_path, b'solid empty'.ljust(84) + b'\nendsolid empty\n', 'empty.stl')


def test_an_off_file_with_faces_of_five_corners_loads(tmp_path):
    # trimesh's OFF reader fails on faces of more than 4 corners ("The 'out' kwarg is
    # necessary when using the string multiply ufunc"): a closed pentagonal prism (legal OFF)
    # was refused as 'cannot parse mesh'
    a = np.linspace(0, 2 * np.pi, 6)[:-1]
    v = [(np.cos(t), np.sin(t), z) for z in (0, 1) for t in a]
    faces = ['5 0 1 2 3 4', '5 9 8 7 6 5'] + [f'4 {i} {5 + i} {5 + (i + 1) % 5} {(i + 1) % 5}'
                                              for i in range(5)]
    path = tmp_path / 'prism.off'
    path.write_text('OFF\n10 7 0\n' + ''.join(f'{x} {y} {z}\n' for x, y, z in np.array(v))
                    + '\n'.join(faces) + '\n')
    mesh = load_mesh(path)
    assert len(mesh.faces) == 2 * 3 + 5 * 2 and mesh.is_watertight
    np.testing.assert_allclose(abs(mesh.volume), 5 / 2 * np.sin(2 * np.pi / 5))
    # a face line cut short is still refused
    path.write_text(path.read_text().replace('5 9 8 7 6 5', '5 9 8 7'))
    with pytest.raises(MeshError, match='prism.off: cannot parse mesh'):
        load_mesh(path)


# ---------------------------------------------------------------- mutation audit
def _no_samples(monkeypatch, counts=None):
    def sample(mesh, count, seed=None):
        if counts is not None:
            counts.append(count)
        return np.zeros((0, 3)), np.zeros(0, np.int64)
    monkeypatch.setattr(trimesh.sample, 'sample_surface', sample)


def test_the_vertices_are_marked_besides_the_samples(monkeypatch):
    _no_samples(monkeypatch)
    g = voxelize_mesh(trimesh.creation.box((1, 2, 4)), 32, fill=False)
    # the 8 corners of a box 8 x 16 x 32 voxels, centred
    want = {(x, y, z) for x in (12, 19) for y in (8, 23) for z in (0, 31)}
    assert set(map(tuple, np.argwhere(g))) == want


def test_at_least_1000_samples_however_low_the_density(monkeypatch):
    counts = []
    _no_samples(monkeypatch, counts)
    voxelize_mesh(trimesh.creation.box((1, 1, 1)), 16, density=0.1)   # 154 asked for
    assert counts == [1000]


def test_the_seed_chooses_the_samples():
    box = trimesh.creation.box((1, 1, 1))
    a, b = (voxelize_mesh(box, 32, fill=False, density=0.5, seed=s) for s in (0, 1))
    assert (a != b).any()
    np.testing.assert_array_equal(voxelize_mesh(box, 32, fill=False, density=0.5, seed=0), a)
    assert voxelize_mesh(box, 16, seed=None).sum() == 16 ** 3   # None: fresh samples, accepted
