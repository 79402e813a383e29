#!/usr/bin/env python3
"""Where a scene's noise comes from, by path depth and image region, read off Tessera's variance channel.

    cargo build --release
    python3 scenes/references/variance_by_depth.py [--scene glass] [--spp 1024] [--depths 1 2 3 4 8 64]

Renders the scene at 128x96 with `--max-depth D` for each D and prints the relMSE at 256 spp that each
render's variance channel predicts (per-sample variance / 256 over (reference luminance² + 0.01), the
metric of `bench_peers.py`), in all and split by region. The increase from one depth to the next is
the noise the extra bounces add (the variance of a sum is not the sum of variances, so this is a
guide, not a decomposition). For `glass` the regions are the two balls as the camera sees them
(discs placed by eye on the error map: centres (88, 51) and (35, 51), radius 20 px), the wall (rows
above 40 but for the balls) and the rest (floor); for other scenes, the whole image only.
"""
import argparse
import os
import subprocess
import tempfile

import numpy as np

import make_references as mr

try:
    import mitsuba as mi
except ImportError:  # pragma: no cover
    raise SystemExit("needs mitsuba (pip install mitsuba) to read the EXRs")

TESSERA = os.path.join(os.path.dirname(mr.ROOT), "target", "release", "tessera")


def main():
    mi.set_variant("scalar_rgb")
    ap = argparse.ArgumentParser()
    ap.add_argument("--scene", default="glass")
    ap.add_argument("--spp", type=int, default=1024)
    ap.add_argument("--depths", type=int, nargs="+", default=[1, 2, 3, 4, 8, 64])
    a = ap.parse_args()
    ref = np.array(mi.Bitmap(os.path.join(mr.HERE, f"{a.scene}.exr")), dtype=np.float64)
    lum = 0.2126 * ref[:, :, 0] + 0.7152 * ref[:, :, 1] + 0.0722 * ref[:, :, 2]
    h, w = lum.shape
    yy, xx = np.mgrid[0:h, 0:w]
    regions = {"all": np.ones_like(lum, dtype=bool)}
    if a.scene == "glass" and (w, h) == (128, 96):
        rough = (xx - 88) ** 2 + (yy - 51) ** 2 < 400
        smooth = (xx - 35) ** 2 + (yy - 51) ** 2 < 400
        wall = (yy < 40) & ~rough & ~smooth
        regions.update(rough=rough, smooth=smooth, wall=wall, floor=~(rough | smooth | wall))
    env = ["--env", os.path.join(mr.ROOT, "env", "sunset.exr"), "--env-rotate", "0.0"] if a.scene == "envlit" else []
    print(f"{a.scene}, {w}x{h}, {a.spp} spp a render: relMSE at 256 spp its variance predicts "
          "(each region's share of the image's mean)")
    print(f"{'max depth':>9}  " + "  ".join(f"{r:>9}" for r in regions))
    with tempfile.TemporaryDirectory() as tmp:
        out = os.path.join(tmp, "d.exr")
        for d in a.depths:
            subprocess.run([TESSERA, "render", os.path.join(mr.ROOT, a.scene, f"{a.scene}.gltf"), "-o", out,
                            "--width", str(w), "--height", str(h), "--spp", str(a.spp), "--max-depth", str(d), *env],
                           check=True, capture_output=True)
            bitmap = mi.Bitmap(out)
            names = [bitmap.struct_()[i].name for i in range(bitmap.channel_count())]
            x = np.array(bitmap, dtype=np.float64)
            v = np.maximum(x[:, :, names.index("variance")], 0.0) * x[:, :, names.index("spp")] / (lum ** 2 + 0.01) / 256
            print(f"{d:>9}  " + "  ".join(f"{v[m].sum() / v.size:>9.2e}" for m in regions.values()))


if __name__ == "__main__":
    main()
