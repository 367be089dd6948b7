#!/usr/bin/env python3
"""Where the bit errors of one view come from (docs/RESULTS.md, "per-view loss").

    scripts/view-errors.py SPLATMARK REPORT.json ORIG_TRAIN/ MARKED_TRAIN/ ORIG_UNSEEN/ MARKED_UNSEEN/

REPORT is `splatmark embed --report`'s (message_hex, bits, reference_logits); the four folders
hold `splatmark render` PNGs of the original and the watermarked scene through the training and
the unseen cameras (same order). Every image is decoded alone (`splatmark decode`); per view v
and bit i, with m = ±1 the payload bit and r the asset reference:
    noise  n = m·(D(original_v) − r)    the unmarked asset's own view-to-view variation
    signal s = m·(D(marked_v) − D(original_v))    what the finetuning wrote into that view
and a bit decodes right when n + s > 0. Decoding goes through `decode --report`, as verification
does (reference subtracted, view projection applied when the report has them). Prints the per-view accuracy, the accuracy without the
noise (s > 0) and with the signal's mean over views (n + mean s > 0). Needs numpy.
"""
import json, subprocess, sys, os, glob
import numpy as np
sm = sys.argv.pop(1)
def logits(d, cache={}):
    out = []
    for f in sorted(glob.glob(d + '/*.png')):
        if f not in cache:
            r = subprocess.run([sm, 'decode', '--bits', str(BITS), '--report', REPORT, f], capture_output=True, text=True, check=True)
            cache[f] = json.loads(r.stdout)['logits']
        out.append(cache[f])
    return np.array(out)
REPORT = sys.argv[1]
rep = json.load(open(REPORT))
BITS = rep['bits']
msg = rep['message_hex']
bits = np.array([int(c) for c in ''.join(f'{int(h,16):04b}' for h in msg)]) if isinstance(msg, str) else np.array(msg)
m = 2 * bits - 1
# `decode --report` already decodes relative to the reference (and through the view
# projection) as verification does.
ref = np.zeros(BITS)
for name, o, k in [('train', sys.argv[2], sys.argv[3]), ('unseen', sys.argv[4], sys.argv[5])]:
    O, K = logits(o), logits(k)
    n = (O - ref) * m; s = (K - O) * m; t = n + s
    print(f'== {name}: {len(O)} views')
    print(f' acc per view {np.mean(t>0):.3f}  | acc if no view noise (s only) {np.mean(s>0):.3f} | acc with mean shift + noise {np.mean((n + s.mean(0))>0):.3f}')
    print(f' signal mean m*s {s.mean():.3f}, per-bit mean range [{s.mean(0).min():.3f},{s.mean(0).max():.3f}], std across views {s.std(0).mean():.3f}; noise std {n.std():.3f} (rms {np.sqrt((n**2).mean()):.3f})')
    print(f' acc avg logits {np.mean(t.mean(0)>0):.3f}; per view: ' + ' '.join(f'{a:.2f}' for a in (t>0).mean(1)))
    print(f' bits wrong on >1/2 views: {np.sum((t>0).mean(0)<0.5)}; bits with mean shift <0: {np.sum(s.mean(0)<0)}')
