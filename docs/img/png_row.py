# Puts PNG images side by side (same height; RGB or RGBA, 8-bit, non-interlaced), composited on
# white, with a 4-pixel white gap: how docs/img/color_correction.png was drawn from a run's
# renders and the scene's photos. Pure Python 3, no packages.
# Usage: python3 png_row.py out.png a.png b.png ...
import struct, sys, zlib


def read_png(path):
    data = open(path, 'rb').read()
    assert data[:8] == b'\x89PNG\r\n\x1a\n', f'{path}: not a PNG'
    pos, idat, w = 8, b'', None
    while pos < len(data):
        n, = struct.unpack('>I', data[pos:pos + 4])
        kind, body = data[pos + 4:pos + 8], data[pos + 8:pos + 8 + n]
        if kind == b'IHDR':
            w, h, depth, ctype, _, _, interlace = struct.unpack('>IIBBBBB', body)
            assert depth == 8 and ctype in (2, 6) and interlace == 0, f'{path}: only 8-bit RGB(A), not interlaced'
            ch = 3 if ctype == 2 else 4
        elif kind == b'IDAT':
            idat += body
        pos += 12 + n
    raw, stride = zlib.decompress(idat), w * ch
    rows, prev = [], bytearray(stride)
    for y in range(h):
        f, line = raw[y * (stride + 1)], bytearray(raw[y * (stride + 1) + 1:(y + 1) * (stride + 1)])
        for i in range(stride):
            a = line[i - ch] if i >= ch else 0
            b = prev[i]
            c = prev[i - ch] if i >= ch else 0
            if f == 1: line[i] = (line[i] + a) & 255
            elif f == 2: line[i] = (line[i] + b) & 255
            elif f == 3: line[i] = (line[i] + (a + b) // 2) & 255
            elif f == 4:
                p = a + b - c
                pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
                line[i] = (line[i] + (a if pa <= pb and pa <= pc else b if pb <= pc else c)) & 255
        rows.append(line)
        prev = line
    # Composite on white.
    out = []
    for line in rows:
        px = bytearray()
        for x in range(w):
            r, g, b = line[x * ch:x * ch + 3]
            al = line[x * ch + 3] if ch == 4 else 255
            px += bytes(round((v * al + 255 * (255 - al)) / 255) for v in (r, g, b))
        out.append(px)
    return w, h, out


def chunk(t, d):
    return struct.pack('>I', len(d)) + t + d + struct.pack('>I', zlib.crc32(t + d) & 0xffffffff)


out, paths = sys.argv[1], sys.argv[2:]
imgs = [read_png(p) for p in paths]
h = imgs[0][1]
assert all(i[1] == h for i in imgs), 'images must share a height'
gap = 4
width = sum(i[0] for i in imgs) + gap * (len(imgs) - 1)
raw = bytearray()
for y in range(h):
    raw.append(0)
    for k, (w, _, rows) in enumerate(imgs):
        if k:
            raw += b'\xff' * (3 * gap)
        raw += rows[y]
png = b'\x89PNG\r\n\x1a\n' + chunk(b'IHDR', struct.pack('>IIBBBBB', width, h, 8, 2, 0, 0, 0))
png += chunk(b'IDAT', zlib.compress(bytes(raw), 9)) + chunk(b'IEND', b'')
open(out, 'wb').write(png)
print(f'{len(imgs)} images -> {out} ({width}x{h})')
