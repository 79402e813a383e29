#!/usr/bin/env python3
"""How much a render would gain from spreading its samples by noise, read off its variance channel.

    tessera render scenes/glass/glass.gltf -o glass.exr --width 128 --height 96 --spp 1024
    python3 scenes/references/allocation_gain.py glass.exr [--pilot pilot.exr]

The image's relMSE is the mean over pixels of v_i / n_i, where v_i is pixel i's per-sample variance
over (luminance² + 0.01) (the metric `bench_peers.py` uses) and n_i its sample count. At a fixed total,
the uniform n_i = N gives mean(v) / N; n_i ∝ √v_i gives mean(√v)² / N, the least any allocation can
give (Cauchy–Schwarz). Their ratio, mean(v) / mean(√v)², is the efficiency an allocation with perfect
knowledge of v gains, at equal cost per sample (an expensive noisy pixel gains less). It is printed for
blocks of 1, 2, 4, 8, 16 and 32 pixels a side (one count per block: each block's mean v), and for
`budget::tile_needs_more`'s rule (stop each 32×32 tile at the same error), which at a fixed total
gives mean(v) / N — the uniform figure, whatever v is: equal error everywhere bounds the worst tile,
not the mean.

With `--pilot P.exr` (a render of the same scene at few samples, another seed), the allocation is
made from the pilot's variance channel instead (smoothed over a 5×5 box, every pixel kept at a quarter
of the uniform count or more), and the gain is that allocation's relMSE against the uniform one's
under the first image's v: what a two-stage adaptive sampler would gain, before its own costs.

The render's variance channel is the variance of the pixel's mean; times the render's spp it is the
per-sample variance. Numbers are estimates from a finite render: a 1024-spp render's v is itself
noisy, which biases the per-pixel figure up a little (√ of a noisy v is smaller on average).
"""
import argparse

import numpy as np

try:
    import mitsuba as mi
except ImportError:  # pragma: no cover
    raise SystemExit("needs mitsuba (pip install mitsuba) to read the EXR's channels")


def per_sample_rel_variance(path):
    bitmap = mi.Bitmap(path)
    names = [bitmap.struct_()[i].name for i in range(bitmap.channel_count())]
    x = np.array(bitmap, dtype=np.float64)
    lum = 0.2126 * x[:, :, 0] + 0.7152 * x[:, :, 1] + 0.0722 * x[:, :, 2]
    spp = x[:, :, names.index("spp")]
    var = np.maximum(x[:, :, names.index("variance")], 0.0) * spp
    return var / (lum ** 2 + 0.01), spp


def blocks(v, side):
    h, w = v.shape[0] // side * side, v.shape[1] // side * side
    return v[:h, :w].reshape(h // side, side, w // side, side).mean(axis=(1, 3))


def main():
    mi.set_variant("scalar_rgb")
    ap = argparse.ArgumentParser()
    ap.add_argument("image")
    ap.add_argument("--pilot", help="a low-spp render of the same scene (another seed)")
    a = ap.parse_args()
    v, spp = per_sample_rel_variance(a.image)
    print(f"{a.image}: {v.shape[1]}x{v.shape[0]}, {spp.mean():.0f} spp; "
          f"relMSE at 256 spp (uniform) {v.mean() / 256:.3e}")
    print("block side  optimal gain (n ∝ √v per block)")
    for side in (1, 2, 4, 8, 16, 32):
        b = blocks(v, side)
        print(f"{side:>10}  {b.mean() / np.sqrt(b).mean() ** 2:.2f}")
    print(f"{'equal error per 32x32 tile':>26}: 1.00 (at a fixed total, the uniform figure)")
    if a.pilot:
        from scipy.ndimage import uniform_filter
        vp, pilot_spp = per_sample_rel_variance(a.pilot)
        s = np.sqrt(np.maximum(uniform_filter(vp, 5, mode="nearest"), 0.0))
        n_pilot = pilot_spp.mean()
        for total in (64, 256, 1024):
            rest = max(total - n_pilot, 1.0)
            floor = 0.25 * rest
            n = n_pilot + floor + (rest - floor) * v.size * s / s.sum()
            print(f"two-stage from a {n_pilot:.0f}-spp pilot, {total} spp in all: "
                  f"gain {(v / total).mean() / (v / n).mean():.2f}")


if __name__ == "__main__":
    main()
