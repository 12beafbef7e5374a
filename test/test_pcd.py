"""PCD reader/writer: round trips, LZF codec, malformed files, real OSD scans."""
import os
import re
import struct
from pathlib import Path

import numpy as np
import pytest

from beo_ros.core.pcd import PCDError, lzf_compress, lzf_decompress, read_pcd, write_pcd

DATA = Path(os.environ.get('BEO_DATA_DIR')
            or Path(__file__).resolve().parents[1].parent / 'shared' / 'data')
OSD = DATA / 'osd' / 'learn'


def sample_fields(n=12, seed=0):
    rng = np.random.default_rng(seed)
    xyz = rng.normal(size=(n, 3)).astype(np.float32)
    xyz[3] = np.nan
    return {
        'label': rng.integers(0, 60, n).astype(np.uint32),
        'x': xyz[:, 0], 'y': xyz[:, 1], 'z': xyz[:, 2],
        'rgba': rng.integers(0, 2 ** 32, n, dtype=np.uint64).astype(np.uint32),
        'normal': rng.normal(size=(n, 3)),  # float64, COUNT 3
        'i16': rng.integers(-300, 300, n).astype(np.int16),
    }


def assert_same(fields, pcd):
    assert list(pcd.fields) == list(fields)
    for k, v in fields.items():
        got = pcd[k]
        assert got.dtype == np.asarray(v).dtype, k
        np.testing.assert_array_equal(got, v, err_msg=k)


@pytest.mark.parametrize('kind', ['ascii', 'binary', 'binary_compressed'])
def test_round_trip(tmp_path, kind):
    fields = sample_fields()
    path = tmp_path / f'c_{kind}.pcd'
    write_pcd(path, fields, width=4, height=3, viewpoint=(1, 2, 3, 1, 0, 0, 0), data=kind)
    pcd = read_pcd(path)
    assert (pcd.width, pcd.height, pcd.n_points, pcd.data) == (4, 3, 12, kind)
    np.testing.assert_array_equal(pcd.viewpoint, [1, 2, 3, 1, 0, 0, 0])
    assert_same(fields, pcd)  # exact for ascii too: floats are written with repr()
    assert pcd.xyz().shape == (12, 3)


def test_empty_cloud_round_trip(tmp_path):
    write_pcd(tmp_path / 'e.pcd', {'x': np.zeros(0, np.float32)}, width=0, height=1)
    assert read_pcd(tmp_path / 'e.pcd')['x'].shape == (0,)


@pytest.mark.parametrize('data', [
    b'', b'a', b'abc' * 1000, bytes(range(256)) * 40, b'\x00' * 5000,
    np.random.default_rng(1).integers(0, 4, 20000).astype(np.uint8).tobytes(),
    np.random.default_rng(2).integers(0, 256, 3000).astype(np.uint8).tobytes()])
def test_lzf_round_trip(data):
    comp = lzf_compress(data)
    assert lzf_decompress(comp, len(data)) == data
    if len(data) > 1000 and len(set(data)) <= 3:  # highly repetitive
        assert len(comp) < len(data) / 2  # back references really are used


def test_lzf_literal_only_and_overlapping_reference():
    # literal 'ab' then a back reference (offset 2, length 7): overlapping copy repeats 'ab'
    stream = bytes([1]) + b'ab' + bytes([(5 << 5) | 0, 1])
    assert lzf_decompress(stream, 9) == b'ababababa'
    # long reference (length field 7 + extra byte): 'x' then copy offset 1, length 7+3+2 = 12
    stream = bytes([0]) + b'x' + bytes([(7 << 5), 3, 0])
    assert lzf_decompress(stream, 13) == b'x' * 13


@pytest.mark.parametrize('stream,size', [
    (bytes([5]) + b'ab', 6),            # literal run past the end
    (bytes([0]) + b'a' + bytes([0x20, 5]), 4),  # reference before the start
    (bytes([0]) + b'a' + bytes([0x20]), 4),     # truncated reference
    (bytes([1]) + b'ab', 3),           # size mismatch
])
def test_lzf_malformed(stream, size):
    with pytest.raises(PCDError):
        lzf_decompress(stream, size)


HEADER = ('VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n'
          'WIDTH 2\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 2\n')


@pytest.mark.parametrize('content,match', [
    (b'', 'no DATA'),
    (b'\xff\xfe\x00binary junk\n', 'ASCII'),
    (HEADER.replace('SIZE 4 4 4\n', '').encode() + b'DATA ascii\n1 2 3\n4 5 6\n', 'SIZE'),
    (HEADER.replace('SIZE 4 4 4', 'SIZE 4 4').encode() + b'DATA ascii\n', 'lengths'),
    (HEADER.replace('TYPE F F F', 'TYPE F F Q').encode() + b'DATA ascii\n', 'unsupported TYPE'),
    (HEADER.replace('POINTS 2', 'POINTS 3').encode() + b'DATA ascii\n', 'POINTS'),
    (HEADER.replace('WIDTH 2', 'WIDTH two').encode() + b'DATA ascii\n', 'non-numeric'),
    (HEADER.encode() + b'DATA zipped\n', 'unsupported DATA'),
    (HEADER.encode() + b'DATA ascii\n1 2 3\n', 'ascii data lines'),
    (HEADER.encode() + b'DATA ascii\n1 2 3\n4 5\n', 'numbers each'),
    (HEADER.encode() + b'DATA ascii\n1 2 3\n4 5 x\n', 'numbers each'),
    # integer fields: no silent wrapping (-1 -> 4294967295), truncation or overflow
    *[(HEADER.replace('TYPE F F F', 'TYPE F F U').encode() + b'DATA ascii\n1 2 3\n4 5 '
       + v + b'\n', "'z' .*not integers") for v in (b'-1', b'2.7', b'5e9', b'nan')],
    (HEADER.encode() + b'DATA binary\n' + b'\x00' * 20, 'expected 24'),
    (HEADER.encode() + b'DATA binary_compressed\n\x01', 'size header'),
    (HEADER.encode() + b'DATA binary_compressed\n' + struct.pack('<II', 4, 99) + b'abcd',
     'uncompressed size'),
    (HEADER.encode() + b'DATA binary_compressed\n' + struct.pack('<II', 40, 24) + b'abcd',
     r'compressed data truncated \(4 < 40 bytes\)'),
    # one byte short: 40 was short by more than the 8-byte size header, so a check that
    # counted that header as data passed it too
    (HEADER.encode() + b'DATA binary_compressed\n' + struct.pack('<II', 5, 24) + b'abcd',
     r'compressed data truncated \(4 < 5 bytes\)'),
    # a negative WIDTH or HEIGHT alone (POINTS agreeing with the product)
    (HEADER.replace('WIDTH 2', 'WIDTH -2').replace('POINTS 2', 'POINTS -2').encode()
     + b'DATA ascii\n', 'bad WIDTH -2 / HEIGHT 1'),
    (HEADER.replace('HEIGHT 1', 'HEIGHT -1').replace('POINTS 2', 'POINTS -2').encode()
     + b'DATA ascii\n', 'bad WIDTH 2 / HEIGHT -1'),
    (HEADER.encode() + b'DATA binary_compressed\n' + struct.pack('<II', 3, 24) + b'\x05ab',
     'LZF'),
])
def test_malformed_files(tmp_path, content, match):
    path = tmp_path / 'bad.pcd'
    path.write_bytes(content)
    with pytest.raises(PCDError, match=match) as e:
        read_pcd(path)
    # every message names the file (the LZF codec's did not: 'LZF: literal run past end ...')
    assert str(e.value).startswith(f'{path}: ')


@pytest.mark.parametrize('data', ['ascii', 'binary', 'binary_compressed'])
def test_data_after_the_points_is_refused_in_every_kind(tmp_path, data):
    """Before: a line after the ascii points was refused but bytes after binary points
    (POINTS too small, or a file appended) were read past without a word. Now every kind
    refuses them, saying how much trails; padding (blank lines, zero bytes such as PCL's
    binary_compressed writers leave, a line end) is still read past."""
    path = tmp_path / 'a.pcd'
    pts = np.arange(6, dtype=np.float32).reshape(2, 3)
    write_pcd(path, {'x': pts[:, 0], 'y': pts[:, 1], 'z': pts[:, 2]}, data=data)
    good = path.read_bytes()
    for pad in ((b'\n\n', b'  \n') if data == 'ascii' else (b'\x00' * 3889, b'\n')):
        path.write_bytes(good + pad)
        np.testing.assert_array_equal(read_pcd(path).xyz(), pts)
    extra = b'6 7 8\n9 10 11\n' if data == 'ascii' else np.ones(6, '<f4').tobytes()
    path.write_bytes(good + extra)
    what = '2 ascii data line(s)' if data == 'ascii' else '24 bytes of binary data'
    with pytest.raises(PCDError, match=re.escape(f'{path}: {what} after the 2 points')):
        read_pcd(path)


def test_header_comments_do_not_count_and_may_hold_any_bytes(tmp_path):
    # 70 comment lines (open3d reads this) and a UTF-8 comment were refused as 'no DATA line in
    # the first 64 header lines' / 'not a PCD file'; only keyword lines count toward the limit
    path = tmp_path / 'comments.pcd'
    path.write_bytes(b'# c\n' * 70 + '# Messung: Tisch \u00fcber Boden\n'.encode()
                     + HEADER.encode() + b'# \xff\xfe latin-1 bytes\nDATA ascii\n1 2 3\n4 5 6\n')
    np.testing.assert_array_equal(read_pcd(path).xyz(), [[1, 2, 3], [4, 5, 6]])
    # keyword lines stay bounded, and so does a header of comments without end
    path.write_bytes(b'VERSION 0.7\n' * 65 + HEADER.encode() + b'DATA ascii\n1 2 3\n4 5 6\n')
    with pytest.raises(PCDError, match='first 64 header lines'):
        read_pcd(path)
    path.write_bytes(b'#' * (1 << 20) + b'\n' + HEADER.encode() + b'DATA ascii\n')
    with pytest.raises(PCDError, match='no DATA line in the first 1048576 bytes'):
        read_pcd(path)
    # a keyword line with non-ASCII bytes is still not a PCD header
    path.write_bytes(HEADER.replace('VERSION 0.7', 'VERSION 0.7\u00fc').encode()
                     + b'DATA ascii\n1 2 3\n4 5 6\n')
    with pytest.raises(PCDError, match='not ASCII'):
        read_pcd(path)


@pytest.mark.parametrize('name', ['rgb', 'rgba'])
def test_ascii_packed_colour_typed_f_as_integer_or_float_text(tmp_path, name):
    # 'rgb F 4' holding the integer colour ("16744455" = 0xFF8007) was parsed as the float
    # 16744455.0, whose bits read back as [127, 128, 7] instead of [255, 128, 7]
    colours = np.array([0xFF8007, 0xFF000000 | 0x102030, 0], dtype=np.uint32)
    as_float = colours.view(np.float32)
    head = (f'FIELDS x {name}\nSIZE 4 4\nTYPE F {{t}}\nCOUNT 1 1\nWIDTH 4\nHEIGHT 1\n'
            'DATA ascii\n')
    path = tmp_path / 'c.pcd'
    for t, texts in (('F', [str(int(v)) for v in colours]),            # integer text under F
                     ('U', [str(int(v)) for v in colours]),            # PCL >= 1.8: TYPE U
                     ('F', [repr(float(v)) for v in as_float])):       # packed float text
        path.write_text(head.format(t=t) + ''.join(f'{i} {c}\n' for i, c in
                                                   enumerate(texts + [texts[0]])))
        got = read_pcd(path)[name]
        assert got.dtype == np.dtype('<f4' if t == 'F' else '<u4')
        np.testing.assert_array_equal(got.view(np.uint32), np.r_[colours, colours[0]])
    # a float-text column stays floats, also with an integral-looking cell and nan
    path.write_text(head.format(t='F') + '0 4.2108e+06\n1 nan\n2 3\n3 1.5\n')
    np.testing.assert_array_equal(read_pcd(path)[name], np.float32([4.2108e6, np.nan, 3, 1.5]))
    path.write_text(head.format(t='F') + '0 1.5\n1 3\n2 3\n3 3\n')   # without a nan too
    np.testing.assert_array_equal(read_pcd(path)[name], np.float32([1.5, 3, 3, 3]))
    # integer text with a nan cell is still integer text: nan there, the colours' bits elsewhere
    path.write_text(head.format(t='F') + ''.join(
        f'{i} {c}\n' for i, c in enumerate([str(int(v)) for v in colours] + ['nan'])))
    got = read_pcd(path)[name]
    np.testing.assert_array_equal(got[:3].view(np.uint32), colours)
    assert np.isnan(got[3])
    # the integer text is only special for colour fields: elsewhere F text is a float
    path.write_text(head.replace(name, 'intensity').format(t='F') + '0 16744455\n' * 4)
    np.testing.assert_array_equal(read_pcd(path)['intensity'], np.float32([16744455.0] * 4))


@pytest.mark.parametrize('kind', ['ascii', 'binary', 'binary_compressed'])
def test_packed_colour_typed_f_round_trips_whatever_its_bits(tmp_path, kind):
    # an opaque colour whose red is >= 128 (white: 0xFFFFFFFF) has the bits of a float NaN:
    # the ascii writer printed 'nan' and the colour read back as 0x7fc00000
    colours = np.array([0xFFFFFFFF, 0xFF8007, 0xFF802030, 0x7F800001, 0], dtype=np.uint32)
    path = tmp_path / 'c.pcd'
    write_pcd(path, {'x': np.zeros(5, np.float32), 'rgb': colours.view(np.float32)}, data=kind)
    got = read_pcd(path)['rgb']
    assert got.dtype == np.float32
    np.testing.assert_array_equal(got.view(np.uint32), colours)


def test_tab_separated_header_is_read(tmp_path):
    # PCL splits header lines on any whitespace
    path = tmp_path / 'tabs.pcd'
    path.write_bytes(HEADER.replace(' ', '\t').encode() + b'DATA\tascii\n1 2 3\n4 5 6\n')
    np.testing.assert_array_equal(read_pcd(path).xyz(), [[1, 2, 3], [4, 5, 6]])


@pytest.mark.parametrize('count', ['100000000000', '65537', '0', '-1'])
def test_implausible_count_is_named(tmp_path, count):
    # COUNT 1e11 made numpy raise "dimension does not fit into a C int"
    path = tmp_path / 'count.pcd'
    path.write_bytes(HEADER.replace('COUNT 1 1 1', f'COUNT {count} 1 1').encode()
                     + b'DATA binary\n' + b'\x00' * 24)
    with pytest.raises(PCDError, match="field 'x' has COUNT"):
        read_pcd(path)


def test_xyz_of_a_field_with_count_2_is_named(tmp_path):
    path = tmp_path / 'c2.pcd'
    path.write_bytes(HEADER.replace('COUNT 1 1 1', 'COUNT 2 1 1').encode()
                     + b'DATA ascii\n1 1 2 3\n4 4 5 6\n')
    pcd = read_pcd(path)
    assert pcd['x'].shape == (2, 2)
    with pytest.raises(PCDError, match="'x' has COUNT 2"):
        pcd.xyz()


def test_missing_file_and_bad_write(tmp_path):
    with pytest.raises(PCDError, match='no such file'):
        read_pcd(tmp_path / 'nope.pcd')
    with pytest.raises(PCDError):
        write_pcd(tmp_path / 'a.pcd', {'x': np.zeros(3), 'y': np.zeros(4)})
    with pytest.raises(PCDError):
        write_pcd(tmp_path / 'a.pcd', {'x': np.zeros(4)}, width=3, height=1)
    with pytest.raises(PCDError):
        write_pcd(tmp_path / 'a.pcd', {'x': np.zeros(4, complex)})
    with pytest.raises(PCDError):
        write_pcd(tmp_path / 'a.pcd', {})
    assert issubclass(PCDError, ValueError)


def test_header_comments_and_defaults(tmp_path):
    # no COUNT / VIEWPOINT / POINTS lines: defaults apply
    path = tmp_path / 'min.pcd'
    path.write_bytes(b'# comment\nVERSION .7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\n'
                     b'WIDTH 2\nHEIGHT 1\nDATA ascii\n1 2 3\nnan 5 6\n')
    pcd = read_pcd(path)
    np.testing.assert_array_equal(pcd.xyz(), [[1, 2, 3], [np.nan, 5, 6]])
    np.testing.assert_array_equal(pcd.viewpoint, [0, 0, 0, 1, 0, 0, 0])


def test_real_osd_scan():
    path = OSD / 'learn0.pcd'
    if not path.is_file():
        pytest.skip(f'shared data not found at {DATA}')
    pcd = read_pcd(path)
    assert (pcd.width, pcd.height, pcd.data) == (640, 480, 'binary_compressed')
    assert list(pcd.fields) == ['label', 'x', 'y', 'z', 'rgba']
    assert pcd['label'].dtype == np.uint32 and pcd['x'].dtype == np.float32
    xyz = pcd.xyz()
    ok = np.isfinite(xyz).all(axis=1)
    assert 0.3 < ok.mean() < 1.0
    assert np.all(xyz[ok, 2] > 0.3) and np.all(xyz[ok, 2] < 3)  # in front of the camera
    assert set(np.unique(pcd['label'])) >= {1, 20, 30}


@pytest.mark.parametrize('kind', ['ascii', 'binary', 'binary_compressed'])
def test_repeated_padding_fields_are_read_past(tmp_path, kind):
    # PCL pads with fields named '_' (several of them): FIELDS x y z _ rgb _
    rng = np.random.default_rng(4)
    n = 5
    xyz = rng.normal(size=(n, 3)).astype(np.float32)
    rgb = rng.integers(0, 2 ** 32, n, dtype=np.uint64).astype(np.uint32)
    pad1, pad2 = np.zeros((n, 4), np.uint8), np.zeros((n, 12), np.uint8)
    header = ('VERSION 0.7\nFIELDS x y z _ rgb _\nSIZE 4 4 4 1 4 1\nTYPE F F F U U U\n'
              f'COUNT 1 1 1 4 1 12\nWIDTH {n}\nHEIGHT 1\nPOINTS {n}\nDATA {kind}\n').encode()
    cols = [xyz[:, 0], xyz[:, 1], xyz[:, 2], pad1, rgb, pad2]
    if kind == 'ascii':
        body = ''.join(' '.join([*(repr(float(v)) for v in xyz[i]), *map(str, pad1[i]),
                                 str(rgb[i]), *map(str, pad2[i])]) + '\n'
                       for i in range(n)).encode()
    elif kind == 'binary':
        rec = np.dtype([('x', '<f4'), ('y', '<f4'), ('z', '<f4'), ('p1', 'u1', (4,)),
                        ('rgb', '<u4'), ('p2', 'u1', (12,))])
        arr = np.empty(n, rec)
        for k, v in zip(rec.names, cols):
            arr[k] = v
        body = arr.tobytes()
    else:
        raw = b''.join(np.ascontiguousarray(v).tobytes() for v in cols)
        comp = lzf_compress(raw)
        body = struct.pack('<II', len(comp), len(raw)) + comp
    (tmp_path / 'pad.pcd').write_bytes(header + body)
    pcd = read_pcd(tmp_path / 'pad.pcd')
    assert list(pcd.fields) == ['x', 'y', 'z', 'rgb']
    np.testing.assert_array_equal(pcd.xyz(), xyz)
    np.testing.assert_array_equal(pcd['rgb'], rgb)
    # other repeated names are still refused
    (tmp_path / 'dup.pcd').write_bytes(header.replace(b'x y z _ rgb _', b'x y z _ x _'))
    with pytest.raises(PCDError, match='duplicate field names'):
        read_pcd(tmp_path / 'dup.pcd')


def test_ascii_64_bit_integers_round_trip_exactly(tmp_path):
    fields = {'u': np.array([2 ** 64 - 1, 0, 2 ** 53 + 1], dtype=np.uint64),
              'i': np.array([2 ** 62 + 1, -2 ** 63, 2 ** 63 - 1], dtype=np.int64)}
    write_pcd(tmp_path / 'big.pcd', fields, data='ascii')
    assert_same(fields, read_pcd(tmp_path / 'big.pcd'))
    # integral values written as floats are still accepted
    (tmp_path / 'f.pcd').write_bytes(b'FIELDS a\nSIZE 4\nTYPE I\nWIDTH 2\nHEIGHT 1\n'
                                     b'DATA ascii\n3.0\n-1e3\n')
    np.testing.assert_array_equal(read_pcd(tmp_path / 'f.pcd')['a'], [3, -1000])


def test_a_directory_is_called_so(tmp_path):
    with pytest.raises(PCDError, match='a directory, not a PCD file'):
        read_pcd(tmp_path)


def test_non_ascii_field_name_is_refused_and_leaves_the_file_alone(tmp_path):
    path = tmp_path / 'a.pcd'
    write_pcd(path, {'x': np.arange(3, dtype=np.float32)})
    before = path.read_bytes()
    with pytest.raises(PCDError, match="'tempé' must be a non-blank ASCII name"):
        write_pcd(path, {'tempé': np.zeros(3, np.float32)})
    assert path.read_bytes() == before   # was emptied by a UnicodeEncodeError mid-write


@pytest.mark.parametrize('kw, match', [
    (dict(height=-1), 'width and height must be integers >= 0'),
    (dict(width=-2, height=-2), 'width and height must be integers >= 0'),
    (dict(width=2.0, height=2), 'width and height must be integers >= 0'),
    (dict(extra={'e': np.zeros((4, 0))}), "'e' has 0 values per point"),
    (dict(viewpoint=(0, 0, 0)), 'viewpoint must be 7 numbers'),
    (dict(extra={1: np.zeros(4), '1': np.zeros(4)}), 'duplicate field names'),
    (dict(extra={'_': np.ones(4)}), "'_' is padding"),
])
def test_write_refuses_what_read_would_refuse_or_drop(tmp_path, kw, match):
    # each was written: read_pcd then refused the file (or left the '_' field out)
    extra = kw.pop('extra', {})
    with pytest.raises(PCDError, match=match):
        write_pcd(tmp_path / 'a.pcd', {'x': np.zeros(4, np.float32), **extra}, **kw)
    write_pcd(tmp_path / 'b.pcd', {'x': np.zeros(4, np.float32)}, width=np.int64(2), height=2,
              viewpoint=np.array([1, 2, 3, 1, 0, 0, 0]))
    assert read_pcd(tmp_path / 'b.pcd').height == 2


def test_xyz_of_integer_fields_is_float(tmp_path):
    # I/U typed coordinates (a depth camera's millimetres) came back as uint16: p0 - p1 wrapped
    write_pcd(tmp_path / 'mm.pcd', {'x': np.array([10, 20], np.uint16),
                                    'y': np.array([5, 5], np.int16),
                                    'z': np.array([1000, 1200], np.uint16)})
    xyz = read_pcd(tmp_path / 'mm.pcd').xyz()
    assert xyz.dtype == np.float64
    np.testing.assert_array_equal(xyz[0] - xyz[1], [-10, 0, -200])
    write_pcd(tmp_path / 'f.pcd', {k: np.zeros(2, np.float32) for k in 'xyz'})
    assert read_pcd(tmp_path / 'f.pcd').xyz().dtype == np.float32   # float fields as they are
