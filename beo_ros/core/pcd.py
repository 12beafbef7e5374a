"""Read and write PCD (Point Cloud Data, PCL) files without PCL.

Supports ``DATA ascii``, ``binary`` and ``binary_compressed`` (LZF, decoded in pure Python) for
any field layout (TYPE I/U/F, SIZE 1/2/4/8, COUNT >= 1). Organized clouds keep their
``width``/``height``; arrays are flat in row-major order (index = row * width + col). Padding
fields named ``_`` (PCL's, possibly several) are read past but not returned. Data after the
points the header describes is refused in every kind (a wrong POINTS/WIDTH/HEIGHT would drop
points without a word), except padding: blank lines after ascii data, zero bytes and ASCII
whitespace after binary data (PCL's binary_compressed writers leave zero bytes there).

Packed colours (``rgb``/``rgba``, SIZE 4) keep their 32 bits whatever the TYPE. In ascii files
typed ``F`` they are read as float text ("4.2108e+06", the float whose bits are the colour) or,
when the whole column is plain unsigned integers, as the integer colour value ("16744455"): PCL's
ascii writers print the colour as that integer (since PCL 1.8 under ``TYPE U``, which needs no
special case), and files that keep the point type's ``F`` over that integer text exist. PCL's own
reader parses any ``F`` text as a float, which turns such integer text into another colour.
"""
from __future__ import annotations

import os
import struct
from dataclasses import dataclass, field

import numpy as np

DATA_KINDS = ('ascii', 'binary', 'binary_compressed')
_TYPES = {('I', 1): 'i1', ('I', 2): '<i2', ('I', 4): '<i4', ('I', 8): '<i8',
          ('U', 1): 'u1', ('U', 2): '<u2', ('U', 4): '<u4', ('U', 8): '<u8',
          ('F', 4): '<f4', ('F', 8): '<f8'}
_MAX_HEADER_LINES = 64   # keyword lines; comments and blank lines are not counted
_MAX_HEADER_BYTES = 1 << 20   # the whole header, comments included
MAX_COUNT = 1 << 16   # values per field and point (PCL descriptors have a few hundred)
PADDING = '_'   # PCL's name for padding fields; may repeat, never returned
COLOUR_FIELDS = ('rgb', 'rgba')   # packed 0xAARRGGBB colours, often typed F 4 (PCL's habit)


class PCDError(ValueError):
    """A PCD file (or the data given to :func:`write_pcd`) is malformed or unsupported."""


@dataclass
class PCDData:
    """Content of one PCD file.

    Attributes:
        fields: name -> array (n,) for COUNT 1 fields, (n, count) otherwise; dtype from TYPE/SIZE
            (padding fields ``_`` left out).
        width, height: cloud organisation (height 1 for unorganized clouds), n = width * height.
        viewpoint: (7,) float64 sensor pose ``tx ty tz qw qx qy qz``.
        data: 'ascii', 'binary' or 'binary_compressed' (how the file stored the points).
    """

    fields: dict
    width: int
    height: int
    viewpoint: np.ndarray = field(default_factory=lambda: np.array([0, 0, 0, 1, 0, 0, 0.0]))
    data: str = 'binary'

    def __getitem__(self, name: str) -> np.ndarray:
        return self.fields[name]

    def __contains__(self, name: str) -> bool:
        return name in self.fields

    @property
    def n_points(self) -> int:
        return self.width * self.height

    def xyz(self) -> np.ndarray:
        """(n, 3) float array of the x, y, z fields (float64 unless they are all F: integer
        coordinates would wrap in differences); PCDError unless each has COUNT 1."""
        for k in 'xyz':
            if k not in self.fields:
                raise PCDError(f'no {k!r} field')
            if self.fields[k].ndim != 1:
                raise PCDError(f'field {k!r} has COUNT {self.fields[k].shape[1]}, not 1')
        xyz = np.stack([self.fields[k] for k in 'xyz'], axis=1)
        return xyz if xyz.dtype.kind == 'f' else xyz.astype(np.float64)


# ----------------------------------------------------------------------------------- LZF codec

def lzf_decompress(data: bytes, expected_size: int) -> bytes:
    """Decode a raw LZF stream (liblzf format, as PCL writes it) of ``expected_size`` bytes."""
    src = memoryview(bytes(data))
    n = len(src)
    out = bytearray()
    i = 0
    try:
        while i < n:
            c = src[i]
            i += 1
            if c < 32:  # literal run of c + 1 bytes
                j = i + c + 1
                if j > n:
                    raise PCDError('LZF: literal run past end of input')
                out += src[i:j]
                i = j
                continue
            length = c >> 5
            if length == 7:
                length += src[i]
                i += 1
            length += 2
            off = ((c & 0x1F) << 8 | src[i]) + 1
            i += 1
            start = len(out) - off
            if start < 0:
                raise PCDError('LZF: back reference before start of output')
            if off >= length:
                out += out[start:start + length]
            else:  # overlapping copy repeats the last `off` bytes
                pattern = out[start:]
                reps = -(-length // off)
                out += (pattern * reps)[:length]
    except IndexError:
        raise PCDError('LZF: truncated input') from None
    if len(out) != expected_size:
        raise PCDError(f'LZF: decoded {len(out)} bytes, header says {expected_size}')
    return bytes(out)


def lzf_compress(data: bytes) -> bytes:
    """Encode ``data`` as a valid raw LZF stream (greedy, 3-byte hash; pure Python, for fixtures).

    Slow (about 1 MB/s); meant for test fixtures and small clouds, not for bulk data.
    """
    data = bytes(data)
    n = len(data)
    out = bytearray()
    lit = bytearray()
    table = {}

    def flush():
        for k in range(0, len(lit), 32):
            chunk = lit[k:k + 32]
            out.append(len(chunk) - 1)
            out.extend(chunk)
        lit.clear()

    i = 0
    while i < n:
        ref = -1
        if i + 2 < n:
            key = data[i:i + 3]
            ref = table.get(key, -1)
            table[key] = i
        off = i - ref - 1
        if ref >= 0 and off < 8192:
            maxlen = min(264, n - i)
            length = 3
            while length < maxlen and data[ref + length] == data[i + length]:
                length += 1
            flush()
            L = length - 2
            if L < 7:
                out.append((L << 5) | (off >> 8))
            else:
                out.append((7 << 5) | (off >> 8))
                out.append(L - 7)
            out.append(off & 0xFF)
            i += length
        else:
            lit.append(data[i])
            i += 1
    flush()
    return bytes(out)


# ----------------------------------------------------------------------------------- reading

def _parse_header(f, path) -> tuple:
    header = {}
    n_keys = n_bytes = 0
    while True:
        raw = f.readline(_MAX_HEADER_BYTES - n_bytes + 1)
        if not raw:
            raise PCDError(f'{path}: end of file inside the header (no DATA line)')
        n_bytes += len(raw)
        if n_bytes > _MAX_HEADER_BYTES:
            raise PCDError(f'{path}: no DATA line in the first {_MAX_HEADER_BYTES} bytes (not a '
                           'PCD file?)')
        stripped = raw.strip()
        if not stripped or stripped.startswith(b'#'):
            continue   # blank lines and comments (any bytes, as PCL skips them) do not count
        try:
            line = raw.decode('ascii').strip()
        except UnicodeDecodeError:
            raise PCDError(f'{path}: header is not ASCII text (not a PCD file?)') from None
        n_keys += 1
        if n_keys > _MAX_HEADER_LINES:
            raise PCDError(f'{path}: no DATA line in the first {_MAX_HEADER_LINES} header lines')
        key, *rest = line.split()   # spaces or tabs, as PCL reads it
        header[key.upper()] = rest
        if key.upper() == 'DATA':
            return header


def _layout(header: dict, path) -> tuple:
    """-> (names, numpy dtypes, counts, width, height, viewpoint, data kind)."""
    for k in ('FIELDS', 'SIZE', 'TYPE', 'WIDTH', 'HEIGHT', 'DATA'):
        if k not in header:
            raise PCDError(f'{path}: header misses {k}')
    names = header['FIELDS']
    nf = len(names)
    try:
        sizes = [int(s) for s in header['SIZE']]
        counts = [int(s) for s in header.get('COUNT', ['1'] * nf)]
        width, height = int(header['WIDTH'][0]), int(header['HEIGHT'][0])
        viewpoint = np.array([float(v) for v in header.get('VIEWPOINT', '0 0 0 1 0 0 0'.split())])
        points = int(header['POINTS'][0]) if 'POINTS' in header else width * height
    except (ValueError, IndexError):
        raise PCDError(f'{path}: non-numeric SIZE/COUNT/WIDTH/HEIGHT/VIEWPOINT/POINTS') from None
    types = [t.upper() for t in header['TYPE']]
    if nf == 0 or not (len(sizes) == len(types) == len(counts) == nf):
        raise PCDError(f'{path}: FIELDS/SIZE/TYPE/COUNT lengths differ '
                       f'({nf}, {len(sizes)}, {len(types)}, {len(counts)})')
    real = [nm for nm in names if nm != PADDING]
    if len(set(real)) != len(real):
        raise PCDError(f'{path}: duplicate field names {names}')
    dtypes = []
    for name, t, s, c in zip(names, types, sizes, counts):
        if (t, s) not in _TYPES:
            raise PCDError(f'{path}: field {name!r} has unsupported TYPE {t} SIZE {s}')
        if not 1 <= c <= MAX_COUNT:
            raise PCDError(f'{path}: field {name!r} has COUNT {c}, not in [1, {MAX_COUNT}]')
        dtypes.append(np.dtype(_TYPES[(t, s)]))
    if width < 0 or height < 0:
        raise PCDError(f'{path}: bad WIDTH {width} / HEIGHT {height}')
    if points != width * height:
        raise PCDError(f'{path}: POINTS {points} != WIDTH*HEIGHT {width * height}')
    if viewpoint.shape != (7,):
        raise PCDError(f'{path}: VIEWPOINT needs 7 numbers, got {viewpoint.size}')
    kind = header['DATA'][0].lower() if header['DATA'] else ''
    if kind not in DATA_KINDS:
        raise PCDError(f'{path}: unsupported DATA {kind!r} (expected one of {DATA_KINDS})')
    return names, dtypes, counts, width, height, viewpoint, kind


def _shape(arr: np.ndarray, count: int) -> np.ndarray:
    return arr if count == 1 else arr.reshape(-1, count)


def _ascii_values(cells, dt, name, path, ncol) -> np.ndarray:
    """Text cells (k,) of one ascii field -> (k,) array of dtype ``dt``; integers exactly
    (64-bit ones would lose digits through float64), never wrapped or truncated."""
    dt = np.dtype(dt)
    try:
        if dt.kind == 'f':
            return cells.astype(np.float64).astype(dt)
        try:
            ints = [int(v) for v in cells]
        except ValueError:   # written as floats ('3.0', '1e3'): integral values only
            floats = cells.astype(np.float64)
            if not (np.isfinite(floats) & (floats == np.round(floats))).all():
                ints = None
            else:
                ints = [int(v) for v in floats]
    except ValueError:
        raise PCDError(f'{path}: ascii data rows are not {ncol} numbers each') from None
    info = np.iinfo(dt)
    if ints is None or (ints and not (info.min <= min(ints) and max(ints) <= info.max)):
        raise PCDError(f'{path}: ascii field {name!r} ({dt.name}) has values that are not '
                       f'integers in [{info.min}, {info.max}]')
    return np.array(ints, dtype=dt)


def _ascii_packed_colour(cells) -> np.ndarray | None:
    """Cells of an ascii ``rgb``/``rgba`` field typed ``F 4`` whose text is the packed colour as
    an unsigned integer ("16744455" for 0xFF8007) -> float32 array holding those bits, or None
    when the column is float text (a packed float such as "4.2108e+06" or "2.35e-38", which the
    float parse keeps). Parsed as a float, "16744455" became 16744455.0, whose bits are another
    colour ([127, 128, 7] for [255, 128, 7]). Only a column of plain digits (and "nan") in
    [0, 2^32) is taken as integers: a packed float is printed with a '.', an exponent, or is
    "nan", unless its alpha byte is 0x4b or more, which the writers of float colours (alpha 0
    or 255) do not produce."""
    digits = np.char.isdigit(cells)
    nan = np.char.lower(cells) == 'nan'
    if not digits.any() or not (digits | nan).all():
        return None
    ints = [int(v) for v in cells[digits]]
    if max(ints) > 0xFFFFFFFF:
        return None
    out = np.full(len(cells), np.nan, dtype=np.float32)
    out[digits] = np.array(ints, dtype=np.uint32).view(np.float32)
    return out


def _refuse_trailing(path, n, what):
    raise PCDError(f'{path}: {what} after the {n} points the header describes (POINTS, WIDTH '
                   'or HEIGHT wrong, or another file appended?)')


def _check_binary_tail(path, n, tail: bytes):
    """PCDError for bytes after the binary points other than padding (zero bytes, whitespace)."""
    if tail.strip(b'\0 \t\r\n'):
        _refuse_trailing(path, n, f'{len(tail)} bytes of binary data')


def read_pcd(path) -> PCDData:
    """Read a PCD file (ascii, binary or binary_compressed). Raises :class:`PCDError`."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise PCDError(f'{path}: ' + ('a directory, not a PCD file' if os.path.isdir(path)
                                      else 'no such file'))
    with open(path, 'rb') as f:
        header = _parse_header(f, path)
        body = f.read()
    names, dtypes, counts, width, height, viewpoint, kind = _layout(header, path)
    n = width * height
    fields = {}
    if kind == 'ascii':
        lines = [ln for ln in body.decode('ascii', errors='replace').splitlines() if ln.strip()]
        ncol = sum(counts)
        if len(lines) > n:
            _refuse_trailing(path, n, f'{len(lines) - n} ascii data line(s)')
        if len(lines) != n:
            raise PCDError(f'{path}: {len(lines)} ascii data lines, expected {n}')
        try:   # text cells: integer fields are parsed exactly, not through float64
            table = np.array([ln.split() for ln in lines], dtype=str) if n else \
                np.zeros((0, ncol), dtype=str)
        except ValueError:
            raise PCDError(f'{path}: ascii data rows are not {ncol} numbers each') from None
        if table.ndim != 2 or table.shape[1] != ncol:
            raise PCDError(f'{path}: ascii data rows are not {ncol} numbers each')
        col = 0
        for name, dt, c in zip(names, dtypes, counts):
            if name != PADDING:
                cells = table[:, col:col + c].ravel()
                values = _ascii_packed_colour(cells) if name in COLOUR_FIELDS and \
                    dt == np.dtype('<f4') else None
                if values is None:
                    values = _ascii_values(cells, dt, name, path, ncol)
                fields[name] = _shape(values, c)
            col += c
    elif kind == 'binary':
        try:
            rec = np.dtype([(f'f{i}', dt, (c,)) for i, (dt, c) in enumerate(zip(dtypes, counts))])
        except (ValueError, OverflowError) as e:   # a point record beyond numpy's limits
            raise PCDError(f'{path}: the header describes points numpy cannot hold: {e}') \
                from None
        need = rec.itemsize * n
        if len(body) < need:
            raise PCDError(f'{path}: binary data has {len(body)} bytes, expected {need}')
        _check_binary_tail(path, n, body[need:])
        arr = np.frombuffer(body, dtype=rec, count=n)
        for i, (name, c) in enumerate(zip(names, counts)):
            if name != PADDING:
                fields[name] = _shape(np.ascontiguousarray(arr[f'f{i}']).ravel(), c)
    else:
        if len(body) < 8:
            raise PCDError(f'{path}: binary_compressed data misses its size header')
        csize, usize = struct.unpack('<II', body[:8])
        need = sum(dt.itemsize * c for dt, c in zip(dtypes, counts)) * n
        if usize != need:
            raise PCDError(f'{path}: uncompressed size {usize} != {need} expected from the header')
        if len(body) - 8 < csize:
            raise PCDError(f'{path}: compressed data truncated ({len(body) - 8} < {csize} bytes)')
        _check_binary_tail(path, n, body[8 + csize:])
        try:
            raw = lzf_decompress(body[8:8 + csize], usize) if usize else b''
        except PCDError as e:   # the codec does not know the file: name it like the others
            raise PCDError(f'{path}: {e}') from None
        pos = 0  # structure of arrays: all values of field 0, then field 1, ...
        for name, dt, c in zip(names, dtypes, counts):
            nbytes = dt.itemsize * c * n
            if name != PADDING:
                fields[name] = _shape(np.frombuffer(raw, dtype=dt, count=c * n,
                                                    offset=pos).copy(), c)
            pos += nbytes
    return PCDData(fields=fields, width=width, height=height, viewpoint=viewpoint, data=kind)


# ----------------------------------------------------------------------------------- writing

def _pcd_type(dt: np.dtype) -> tuple:
    dt = np.dtype(dt)
    if dt.kind == 'f' and dt.itemsize in (4, 8):
        return 'F', dt.itemsize
    if dt.kind == 'i' and dt.itemsize in (1, 2, 4, 8):
        return 'I', dt.itemsize
    if dt.kind in 'ub' and dt.itemsize in (1, 2, 4, 8):
        return 'U', dt.itemsize
    raise PCDError(f'unsupported dtype {dt} for PCD')


def write_pcd(path, fields: dict, width: int | None = None, height: int = 1,
              viewpoint=(0, 0, 0, 1, 0, 0, 0), data: str = 'binary') -> None:
    """Write ``fields`` (name -> (n,) or (n, count) array) as a PCD v0.7 file.

    ``width * height`` must equal n (``width`` defaults to n / height). ``data`` is 'binary'
    (default), 'ascii' or 'binary_compressed' (pure-Python LZF; slow for big clouds). In ascii,
    a packed colour (``rgb``/``rgba``) typed F 4 is written as its integer, as PCL writes it.
    """
    if not fields:
        raise PCDError('write_pcd needs at least one field')
    if data not in DATA_KINDS:
        raise PCDError(f'data must be one of {DATA_KINDS}, got {data!r}')
    for v in (width, height):   # read_pcd refuses a negative or non-integer WIDTH/HEIGHT
        if v is not None and (isinstance(v, bool) or not isinstance(v, (int, np.integer))
                              or v < 0):
            raise PCDError(f'width and height must be integers >= 0, got {width!r}, {height!r}')
    try:
        vp = np.asarray(viewpoint, dtype=np.float64)
    except (TypeError, ValueError):
        vp = None
    if vp is None or vp.shape != (7,):
        raise PCDError(f'viewpoint must be 7 numbers tx ty tz qw qx qy qz, got {viewpoint!r}')
    arrays = []
    for name, a in fields.items():
        a = np.asarray(a)
        if a.dtype == bool:
            a = a.astype(np.uint8)
        if a.ndim == 1:
            a = a[:, None]
        if a.ndim != 2 or not str(name) or not str(name).isascii() \
                or any(ch.isspace() for ch in str(name)):
            raise PCDError(f'field {name!r} must be a non-blank ASCII name (the header is ASCII) '
                           'with a (n,) or (n, c) array')
        if not 1 <= a.shape[1] <= MAX_COUNT:
            raise PCDError(f'field {name!r} has {a.shape[1]} values per point, not in '
                           f'[1, {MAX_COUNT}]')
        arrays.append((str(name), a))
    names = [nm for nm, _ in arrays]
    if PADDING in names:
        raise PCDError(f'field name {PADDING!r} is padding (read_pcd skips it)')
    if len(set(names)) != len(names):
        raise PCDError(f'duplicate field names {names}')
    n = arrays[0][1].shape[0]
    if any(a.shape[0] != n for _, a in arrays):
        raise PCDError('all fields must have the same number of points')
    if width is None:
        width = n // height if height else 0
    if width * height != n:
        raise PCDError(f'width*height = {width}*{height} != {n} points')
    types = [_pcd_type(a.dtype) for _, a in arrays]
    vp = ' '.join(repr(float(v)) for v in vp)   # exact, not 6 digits
    header = ('# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\n'
              f'FIELDS {" ".join(nm for nm, _ in arrays)}\n'
              f'SIZE {" ".join(str(s) for _, s in types)}\n'
              f'TYPE {" ".join(t for t, _ in types)}\n'
              f'COUNT {" ".join(str(a.shape[1]) for _, a in arrays)}\n'
              f'WIDTH {width}\nHEIGHT {height}\nVIEWPOINT {vp}\nPOINTS {n}\nDATA {data}\n')
    dts = [np.dtype(_TYPES[t]) for t in types]
    header = header.encode('ascii')   # before the file is opened (and emptied)
    with open(path, 'wb') as f:
        f.write(header)
        if data == 'ascii':
            cols = []
            for (name, a), (t, s), dt in zip(arrays, types, dts):
                if name in COLOUR_FIELDS and (t, s) == ('F', 4):
                    # the colour as its integer, as PCL writes it: the float with the bits of
                    # an opaque colour whose red is >= 128 is a NaN, printed 'nan' (lost)
                    a, t = a.astype(dt).view(np.uint32), 'U'
                for j in range(a.shape[1]):
                    v = a[:, j]
                    cols.append([repr(float(x)) if t == 'F' else str(int(x)) for x in v])
            f.write(''.join(' '.join(row) + '\n' for row in zip(*cols)).encode('ascii'))
        elif data == 'binary':
            rec = np.dtype([(f'f{i}', dt, (a.shape[1],)) for i, (dt, (_, a))
                            in enumerate(zip(dts, arrays))])
            out = np.empty(n, dtype=rec)
            for i, (dt, (_, a)) in enumerate(zip(dts, arrays)):
                out[f'f{i}'] = a.astype(dt)
            f.write(out.tobytes())
        else:
            raw = b''.join(a.astype(dt).tobytes() for dt, (_, a) in zip(dts, arrays))
            comp = lzf_compress(raw)
            f.write(struct.pack('<II', len(comp), len(raw)))
            f.write(comp)
