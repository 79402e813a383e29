"""Glass relMSE and time: the scalar path tracer alone against it without E D S+ L plus the light
tracer's image of those paths (the forty-fifth round's light-tracing prototype), seeds alternating.

The prototype is 2026-12-01-zen3-r45-light-tracing-prototype.diff, applied to 4eb8ff3 and built
with `CARGO_TARGET_DIR=/tmp/proto-target cargo build --release -p tessera-cli`. Its environment
variables: TESSERA_SCALAR=1 (the scalar path, no kernel), TESSERA_PROTO_LT=1 (the path tracer
leaves E D S+ L to the light tracer), TESSERA_PROTO_LT_OUT=FILE (the light tracer's image, raw
f32 RGB) and TESSERA_PROTO_LT_RATIO=R (light paths a camera sample; LT_RATIO here).

    LT_RATIO=0.25 python3 2026-12-01-zen3-r45-lt_var.py [scene] [seeds] [spp]
"""
import os, subprocess, sys, statistics, numpy as np
sys.path.insert(0, '/work/main/scenes/references')
import mitsuba as mi
mi.set_variant('scalar_rgb')
from equal_time import rel_mse
BIN = '/tmp/proto-target/release/tessera'
scene = sys.argv[1] if len(sys.argv) > 1 else 'glass'
seeds = int(sys.argv[2]) if len(sys.argv) > 2 else 4
spp = sys.argv[3] if len(sys.argv) > 3 else '256'
ratio = os.environ.get('LT_RATIO', '1')
ref = np.array(mi.Bitmap(f'/work/main/scenes/references/{scene}.exr'), dtype=np.float64)[:, :, :3]
h, w = ref.shape[:2]
res = {'pt': [], 'pt+lt': [], 'pt-only-part': []}
imgs = {'pt': [], 'pt+lt': []}
for s in range(seeds):
    for name in ('pt', 'pt+lt'):
        env = dict(os.environ, TESSERA_SCALAR='1')
        if name == 'pt+lt':
            env.update(TESSERA_PROTO_LT='1', TESSERA_PROTO_LT_OUT='/tmp/lt.bin', TESSERA_PROTO_LT_RATIO=ratio)
        out = f'/tmp/lv_{name}.exr'
        p = subprocess.run([BIN, 'render', f'/work/main/scenes/{scene}/{scene}.gltf', '-o', out, '--spp', spp,
                            '--width', str(w), '--height', str(h), '--seed', str(s), '--threads', '1'],
                           env=env, check=True, stderr=subprocess.PIPE, text=True)
        t = float(p.stderr.split('rendered ')[1].split(' in ')[1].split('s ')[0])
        img = np.array(mi.Bitmap(out), dtype=np.float64)[:, :, :3]
        if name == 'pt+lt':
            t_lt = float(p.stderr.split('light tracing: ')[1].split(' in ')[1].split('s\n')[0])
            lt = np.fromfile('/tmp/lt.bin', dtype='<f4').reshape(h, w, 3).astype(np.float64)
            res['pt-only-part'].append((t, rel_mse(img, ref)))
            img = img + lt
            t += t_lt
        res[name].append((t, rel_mse(img, ref)))
        imgs[name].append(img)
        print(name, s, f'{t:.3f}s', f'{res[name][-1][1]:.4e}', flush=True)
for name in res:
    ts = [t for t, _ in res[name]]; es = [e for _, e in res[name]]
    print(f'{name}: time median {statistics.median(ts):.3f}  relMSE mean {statistics.fmean(es):.4e}  median {statistics.median(es):.4e}')
A = np.mean(imgs['pt'], axis=0); B = np.mean(imgs['pt+lt'], axis=0)
print('mean image: pt', A.mean(), 'pt+lt', B.mean(), 'ref', ref.mean())
bh, bw = h // 8, w // 8
z = []
for i in range(bh):
    for j in range(bw):
        a = np.array([im[i*8:(i+1)*8, j*8:(j+1)*8].mean() for im in imgs['pt']])
        b = np.array([im[i*8:(i+1)*8, j*8:(j+1)*8].mean() for im in imgs['pt+lt']])
        se = np.sqrt(a.var(ddof=1) / seeds + b.var(ddof=1) / seeds)
        if se > 0:
            z.append((b.mean() - a.mean()) / se)
z = np.array(z)
print(f'block z-scores (pt+lt - pt): mean {z.mean():.3f} sd {z.std():.3f} max|z| {np.abs(z).max():.2f} n {len(z)}')
# Against the reference, per 8x8 block of the seed-mean images, relative differences.
rel = lambda X: np.array([[X[i*8:(i+1)*8, j*8:(j+1)*8].mean() / max(ref[i*8:(i+1)*8, j*8:(j+1)*8].mean(), 1e-6) - 1 for j in range(bw)] for i in range(bh)])
print('block mean rel. diff vs ref: pt', np.abs(rel(A)).mean(), 'pt+lt', np.abs(rel(B)).mean())
k = int(np.argmax(np.abs(z)))
print('worst block index', k, 'row', k // bw, 'col', k % bw, 'z', z[k])
