"""Glass relMSE and time: scalar baseline vs the connection prototype, seeds alternating.

The forty-fifth round's scratch measurement (docs/performance-journal.md), kept so it can be run
again: the prototype is 2026-12-01-zen3-r45-connection-prototype.diff, applied to f61b818 and built
with `CARGO_TARGET_DIR=/tmp/proto-target cargo build --release -p tessera-cli`. Its environment
variables: TESSERA_SCALAR=1 (the scalar path, no kernel: the baseline), TESSERA_PROTO_C=1 (the
connection, MIS-weighted; scalar too), and with it TESSERA_PROTO_C_ALONE=1 (the connection alone
takes every path it can make: a check of its estimator), passed here as PROTO_EXTRA.

    python3 2026-12-01-zen3-r45-proto_var.py [scene] [seeds] [spp]
"""
import os, subprocess, sys, statistics, numpy as np
sys.path.insert(0, '/work/main/scenes/references')
import mitsuba as mi
mi.set_variant('scalar_rgb')
from equal_time import rel_mse
EXTRA = dict(kv.split('=') for kv in os.environ.get('PROTO_EXTRA', '').split() if kv)
BIN = '/tmp/proto-target/release/tessera'
scene = sys.argv[1] if len(sys.argv) > 1 else 'glass'
seeds = int(sys.argv[2]) if len(sys.argv) > 2 else 4
spp = sys.argv[3] if len(sys.argv) > 3 else '256'
ref = np.array(mi.Bitmap(f'/work/main/scenes/references/{scene}.exr'), dtype=np.float64)[:, :, :3]
h, w = ref.shape[:2]
res = {'scalar': [], 'proto': []}
imgs = {'scalar': [], 'proto': []}
for s in range(seeds):
    for name, env in (('scalar', {'TESSERA_SCALAR': '1'}), ('proto', dict({'TESSERA_PROTO_C': '1'}, **EXTRA))):
        e = dict(os.environ, **env)
        out = f'/tmp/pv_{name}.exr'
        p = subprocess.run([BIN, 'render', f'/work/main/scenes/{scene}/{scene}.gltf', '-o', out, '--spp', spp,
                            '--width', str(w), '--height', str(h), '--seed', str(s), '--threads', '1'],
                           env=e, check=True, stderr=subprocess.PIPE, text=True)
        t = float(p.stderr.split(' in ')[1].split('s ')[0])
        img = np.array(mi.Bitmap(out), dtype=np.float64)[:, :, :3]
        res[name].append((t, rel_mse(img, ref)))
        imgs[name].append(img)
        print(name, s, f'{t:.3f}s', f'{res[name][-1][1]:.4e}', flush=True)
for name in res:
    ts = [t for t, _ in res[name]]; es = [e for _, e in res[name]]
    print(f'{name}: time median {statistics.median(ts):.3f}  relMSE mean {statistics.fmean(es):.4e}  median {statistics.median(es):.4e}')
A = np.mean(imgs['scalar'], axis=0); B = np.mean(imgs['proto'], axis=0)
sa = np.std(imgs['scalar'], axis=0, ddof=1) / np.sqrt(seeds); sb = np.std(imgs['proto'], axis=0, ddof=1) / np.sqrt(seeds)
print('mean image: scalar', A.mean(), 'proto', B.mean(), 'ref', ref.mean())
# Aggregate bias check over blocks of 8x8 pixels: z of the block-mean difference.
bh, bw = h // 8, w // 8
z = []
for i in range(bh):
    for j in range(bw):
        a = np.array([im[i*8:(i+1)*8, j*8:(j+1)*8].mean() for im in imgs['scalar']])
        b = np.array([im[i*8:(i+1)*8, j*8:(j+1)*8].mean() for im in imgs['proto']])
        se = np.sqrt(a.var(ddof=1) / seeds + b.var(ddof=1) / seeds)
        if se > 0:
            z.append((b.mean() - a.mean()) / se)
z = np.array(z)
print(f'block z-scores (proto - scalar): mean {z.mean():.3f} sd {z.std():.3f} max|z| {np.abs(z).max():.2f} n {len(z)}')
