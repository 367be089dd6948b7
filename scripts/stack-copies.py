#!/usr/bin/env python3
"""Redundancy premise for small assets (docs/RESULTS.md, sixteenth session): every Gaussian of a
binary INRIA PLY (float properties only) replaced by K stacked copies of opacity
1 - (1 - o)^(1/K), which composite to the parent's opacity at its centre.

    scripts/stack-copies.py IN.ply OUT.ply K

Then `splatmark eval --message deadbeef --cameras CAMERAS OUT.ply OUT.ply` reports what removing,
cloning or perturbing a fifth of the copies costs the asset (`psnr_on_asset_vs_original` of the
model-attack rows), and `splatmark eval ... IN.ply OUT.ply` what stacking itself costs.
"""
import math
import struct
import sys

src, dst, k = sys.argv[1], sys.argv[2], int(sys.argv[3])
data = open(src, "rb").read()
end = data.index(b"end_header\n") + len(b"end_header\n")
header = data[:end].decode()
lines = header.splitlines()
props = [l.split()[-1] for l in lines if l.startswith("property")]
if any(l.split()[1] != "float" for l in lines if l.startswith("property")):
    sys.exit("only PLYs whose properties are all float32 are handled")
n = int(next(l for l in lines if l.startswith("element vertex")).split()[-1])
fmt = "<%df" % len(props)
rec = struct.calcsize(fmt)
oi = props.index("opacity")
out = bytearray()
for i in range(n):
    vals = list(struct.unpack(fmt, data[end + i * rec : end + (i + 1) * rec]))
    o = 1 / (1 + math.exp(-vals[oi]))
    oc = min(max(1 - (1 - o) ** (1.0 / k), 1e-6), 1 - 1e-6)
    vals[oi] = math.log(oc / (1 - oc))
    out += struct.pack(fmt, *vals) * k
head = header.replace("element vertex %d" % n, "element vertex %d" % (n * k))
open(dst, "wb").write(head.encode() + bytes(out))
print(n, "->", n * k)
