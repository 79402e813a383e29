"""The light tracer's time at three ratios against the kernel's render of the same image, one
thread, runs alternating (the forty-fifth round's light-tracing prototype; built as
2026-12-01-zen3-r45-lt_var.py says, the default build at target/release).
"""
import os, subprocess, statistics
MAIN = '/work/main/target/release/tessera'
PROTO = '/tmp/proto-target/release/tessera'
args = ['render', '/work/main/scenes/glass/glass.gltf', '-o', '/tmp/lt_t.exr', '--spp', '256', '--width', '128',
        '--height', '96', '--threads', '1']
kernel, lt = [], {r: [] for r in ('0.1', '0.25', '1')}
for run in range(7):
    p = subprocess.run([MAIN, *args, '--seed', str(run)], check=True, stderr=subprocess.PIPE, text=True)
    kernel.append(float(p.stderr.split('rendered ')[1].split(' in ')[1].split('s ')[0]))
    for r in lt:
        env = dict(os.environ, TESSERA_PROTO_LT='1', TESSERA_PROTO_LT_OUT='/tmp/lt_t.bin', TESSERA_PROTO_LT_RATIO=r)
        p = subprocess.run([PROTO, *args, '--seed', str(run)], env=env, check=True,
                           stderr=subprocess.PIPE, text=True)
        lt[r].append(float(p.stderr.split('light tracing: ')[1].split(' in ')[1].split('s\n')[0]))
print('kernel render (default build), seconds:', ' '.join(f'{t:.3f}' for t in kernel), 'median', f'{statistics.median(kernel):.3f}')
for r, ts in lt.items():
    print(f'light tracer at {r} paths a camera sample, seconds:', ' '.join(f'{t:.3f}' for t in ts),
          'median', f'{statistics.median(ts):.3f}', f'({statistics.median(ts) / statistics.median(kernel):.3f} of the kernel render)')
