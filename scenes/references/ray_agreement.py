"""Whether two ray engines found the same hits, as bench_embree.py and bench_mitsuba_rays.py check it.

A ray agrees when both engines miss it, or both hit it with closest distances within 1e-4 relative
(an absolute floor of 1e-7 below t = 1e-3, where rounding alone differs by that much). More than one
ray in 10^4 disagreeing fails the script.
"""
import sys

import numpy as np


def disagreeing(hit_ref, t_ref, t_tess):
    """Mask of the rays where the reference (hit flags `hit_ref`, distances `t_ref`) and Tessera
    (distances `t_tess`, infinite for a miss) disagree."""
    tess_hit = np.isfinite(t_tess)
    with np.errstate(invalid="ignore"):  # inf − inf where both miss; those are masked out by `hit_ref`
        far = np.abs(t_ref - t_tess) > 1e-4 * np.maximum(t_ref, 1e-3)
    return (hit_ref != tess_hit) | (hit_ref & far)


def finish(bad, t_ref, t_tess, name):
    """Prints the first five disagreeing rays and exits 1 when more than one ray in 10^4 disagrees."""
    if bad.sum() > 0:
        i = np.flatnonzero(bad)[:5]
        print(f"disagreeing rays (index, {name} t, tessera t):",
              [(int(k), float(t_ref[k]), float(t_tess[k])) for k in i])
    if bad.sum() > len(bad) // 10_000:
        sys.exit(1)
