#!/usr/bin/env python3
"""Region means of EXRs against a reference, with standard errors from their variance channels.

    python3 scenes/references/compare_regions.py REFERENCE.exr IMAGE.exr [IMAGE.exr ...] [--rows 0.5:1]

Prints, per image, the mean luminance over the region (default: the lower half), its standard error
(from the `variance` channel, the variance of each pixel's mean luminance) and the ratio to the
reference with the z-score of the difference. Used for issue 10's before/after table.
"""
import argparse

import numpy as np


def load(path):
    import mitsuba as mi
    mi.set_variant("scalar_rgb")
    b = mi.Bitmap(path)
    names = [f.name for f in b.struct_()]
    a = np.array(b, dtype=np.float64)
    rgb = a[:, :, [names.index(c) for c in "RGB"]]
    lum = rgb @ np.array([0.2126, 0.7152, 0.0722])
    var = a[:, :, names.index("variance")] if "variance" in names else np.zeros_like(lum)
    return lum, var


def region(lum, var, rows):
    h = lum.shape[0]
    r0, r1 = int(rows[0] * h), int(rows[1] * h)
    l, v = lum[r0:r1], var[r0:r1]
    return l.mean(), np.sqrt(v.sum()) / l.size


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("reference")
    ap.add_argument("images", nargs="+")
    ap.add_argument("--rows", default="0.5:1", help="fraction of the image height, from:to (0 = top)")
    a = ap.parse_args()
    rows = tuple(float(x) for x in a.rows.split(":"))
    rm, rse = region(*load(a.reference), rows)
    print(f"{'reference':40s} {rm:.6f} ± {rse:.6f}")
    for p in a.images:
        m, se = region(*load(p), rows)
        z = (m - rm) / max(np.hypot(se, rse), 1e-12)
        print(f"{p:40s} {m:.6f} ± {se:.6f}  ratio {m / rm:.4f}  ({100 * (m / rm - 1):+.2f} %, z = {z:+.1f})")


if __name__ == "__main__":
    main()
