#!/usr/bin/env python3
"""What removing a fifth of an asset's Gaussians does to each bit's logit (docs/RESULTS.md,
twenty-seventh session): per view, the clean margins m·z (m = ±1 the message's sign, z the
logit in the matched head's noise units) and, over DRAWS copies with a random 20 % of the
Gaussians removed, the bit accuracy and the shift of the margins (mean and spread); then, per
bit, the clean margin on every view and the errors over the draws.

    scripts/removal-margins.py SPLATMARK ASSET.ply REPORT.json WEIGHTS.bpk CAMERAS.json DRAWS [OUT]

SPLATMARK the binary, ASSET and REPORT a kept embedding (`bench quality --assets DIR`),
WEIGHTS the decoder its report names (`weights/decoder-32.coarse.bpk` for a switched asset),
CAMERAS the scene's cameras (every one is rendered; views that show none of the asset are
listed and left out of the per-bit table). Draw k removes the Gaussians Python's
`random.Random(k)` shuffles first, so a run is reproducible; the asset itself is draw −1. The
unmarked original with the same REPORT gives the removal's shift without a message (its mean
≈ 0). Needs only the standard library; OUT (default: a temporary folder) keeps the logits.
"""
import json
import os
import random
import statistics as st
import subprocess
import sys
import tempfile


def read_ply(path):
    data = open(path, "rb").read()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    lines = data[:end].decode().splitlines()
    if any(l.split()[1] != "float" for l in lines if l.startswith("property")):
        sys.exit("only PLYs whose properties are all float32 are handled")
    rec = 4 * sum(1 for l in lines if l.startswith("property"))
    n = int(next(l for l in lines if l.startswith("element vertex")).split()[-1])
    return lines, [data[end + i * rec : end + (i + 1) * rec] for i in range(n)]


def write_ply(path, lines, rows):
    head = [("element vertex %d" % len(rows)) if l.startswith("element vertex") else l for l in lines]
    with open(path, "wb") as f:
        f.write(("\n".join(head) + "\n").encode())
        f.write(b"".join(rows))


def main():
    if len(sys.argv) < 7:
        sys.exit(__doc__)
    exe, asset, report, weights, cameras, draws = sys.argv[1:7]
    draws = int(draws)
    out = sys.argv[7] if len(sys.argv) > 7 else tempfile.mkdtemp(prefix="removal-margins.")
    os.makedirs(out, exist_ok=True)
    msg = json.load(open(report))["message_hex"]
    bits = len(msg) * 4
    sign = [1 if c == "1" else -1 for c in bin(int(msg, 16))[2:].zfill(bits)]
    lines, rows = read_ply(asset)
    env = dict(os.environ, RAYON_NUM_THREADS=os.environ.get("RAYON_NUM_THREADS", "1"))
    margins = {}  # view -> draw -> [m·z]
    for k in range(-1, draws):
        scene = asset
        if k >= 0:
            idx = list(range(len(rows)))
            random.Random(k).shuffle(idx)
            keep = sorted(idx[int(round(0.2 * len(rows))) :])
            scene = os.path.join(out, "removed.ply")
            write_ply(scene, lines, [rows[i] for i in keep])
        img = os.path.join(out, "img%d" % k)
        subprocess.run([exe, "render", scene, "--cameras", cameras, "--device", "cpu", "--out", img,
                        "--progress", "none"], check=True, env=env, capture_output=True)
        for name in sorted(os.listdir(img)):
            r = subprocess.run([exe, "decode", "--bits", str(bits), "--weights", weights, "--report",
                                report, os.path.join(img, name), "--progress", "none"],
                               check=True, env=env, capture_output=True)
            z = json.loads(r.stdout)["logits"]
            margins.setdefault(name, {})[k] = [s * x for s, x in zip(sign, z)]
            os.remove(os.path.join(img, name))
        os.rmdir(img)
    json.dump(margins, open(os.path.join(out, "margins.json"), "w"))
    shown = []
    print("view | clean: bits, mean margin, least | removed: bit accuracy, margin shift mean, sd")
    for v, d in sorted(margins.items()):
        c = d[-1]
        ds = [d[k] for k in range(draws)]
        shift = [x[i] - c[i] for x in ds for i in range(bits)]
        acc = sum(x > 0 for m in ds for x in m) / (bits * max(draws, 1))
        if st.pstdev(shift) > 0:
            shown.append(v)
        print("%s | %.3f, %.2f, %.2f | %.3f, %+.2f, %.2f" % (
            v, sum(x > 0 for x in c) / bits, st.mean(c), min(c), acc, st.mean(shift), st.pstdev(shift)))
    print("\nbit | clean margin per view (%s) | errors over %d views x %d draws" % (
        ", ".join(v.split(".")[0] for v in shown), len(shown), draws))
    for i in range(bits):
        errs = sum(margins[v][k][i] <= 0 for v in shown for k in range(draws))
        print("%2d | %s | %d" % (i, " ".join("%.2f" % margins[v][-1][i] for v in shown), errs))
    print("\nlogits kept in", out)


if __name__ == "__main__":
    main()
