//! `cargo bench -p tessera-renderer --bench light_tree`: nanoseconds per `LightTree::sample` and
//! `LightTree::pmf` call, for trees over the emissive triangles of one and of four sphere bulbs
//! (2208 and 4608 lights, as `scenes/sphere_light` and `scenes/sphere_lights`) seen from points on
//! a floor below them. Each walk's `u` depends on the walk before, as a path's would on its
//! previous bounce, so the figure is a walk's latency, not a pipelined throughput.
//!
//! A second line times walks that do not wait on each other: one `sample` call after another,
//! and [`LightTree::sample_batch`]'s sixteen interleaved, per walk.
//!
//! Prints the minimum and median over repetitions (the machine is shared: the minimum is the
//! figure least disturbed by other work; compare builds by running both in one session).

use renderer::light_tree::{LightBounds, LightTree, MAX_WALKS};
use renderer::math::Vec3;
use renderer::sampler::hash_unit;
use std::hint::black_box;
use std::time::Instant;

const CALLS: usize = 200_000;
const REPETITIONS: usize = 21;

/// Small one-sided triangle-sized lights on spheres (outward normals), `per_sphere` on each.
fn bulbs(centres: &[Vec3], per_sphere: u64) -> Vec<LightBounds> {
    let mut lights = Vec::new();
    for (s, &c) in centres.iter().enumerate() {
        for i in 0..per_sphere {
            let k = s as u64 * per_sphere + i;
            // A uniform direction (Archimedes: z uniform in [-1, 1], azimuth uniform).
            let z = 2.0 * hash_unit(3 * k) - 1.0;
            let phi = std::f32::consts::TAU * hash_unit(3 * k + 1);
            let r = (1.0 - z * z).max(0.0).sqrt();
            let n = Vec3::new(r * phi.cos(), z, r * phi.sin());
            let p = c + n * 0.5;
            lights.push(LightBounds {
                min: p - Vec3::splat(0.02),
                max: p + Vec3::splat(0.02),
                phi: 1.0 + hash_unit(3 * k + 2),
                w: n,
                cos_theta_o: 1.0,
                cos_theta_e: 0.0,
                two_sided: false,
            });
        }
    }
    lights
}

fn stats(mut ns: Vec<f64>) -> (f64, f64) {
    ns.sort_by(f64::total_cmp);
    (ns[0], ns[ns.len() / 2])
}

fn main() {
    let cases = [
        ("1 bulb, 2208 lights", vec![Vec3::new(0.0, 2.0, 0.0)], 2208u64),
        (
            "4 bulbs, 4608 lights",
            vec![
                Vec3::new(-1.5, 1.5, -1.5),
                Vec3::new(1.5, 1.5, -1.5),
                Vec3::new(-1.5, 2.5, 1.5),
                Vec3::new(1.5, 2.5, 1.5),
            ],
            1152,
        ),
    ];
    for (name, centres, per_sphere) in cases {
        let lights = bulbs(&centres, per_sphere);
        let Some(tree) = LightTree::build(&lights) else {
            eprintln!("{name}: no tree");
            continue;
        };
        let points: Vec<Vec3> = (0..4096u64)
            .map(|k| Vec3::new(hash_unit(100 + 2 * k) * 8.0 - 4.0, 0.0, hash_unit(101 + 2 * k) * 8.0 - 4.0))
            .collect();
        let n = Some(Vec3::Y);
        let (mut sample_ns, mut pmf_ns) = (Vec::new(), Vec::new());
        let (mut single_ns, mut batch_ns) = (Vec::new(), Vec::new());
        let us: Vec<f32> = (0..points.len() as u64).map(|k| hash_unit(9000 + k)).collect();
        let normals = [n; MAX_WALKS];
        let mut chosen = 0usize;
        for _ in 0..REPETITIONS {
            let start = Instant::now();
            let mut u = 0.3f32;
            for i in 0..CALLS {
                if let Some((light, pmf)) = tree.sample(black_box(points[i % points.len()]), n, u) {
                    chosen = chosen.wrapping_add(light);
                    u = (u + pmf * 7.77 + 0.618).fract();
                }
            }
            sample_ns.push(start.elapsed().as_nanos() as f64 / CALLS as f64);
            // Independent walks: one at a time, then sixteen interleaved (`sample_batch`), on
            // the same points and numbers.
            let start = Instant::now();
            for i in 0..CALLS {
                if let Some((light, _)) = tree.sample(black_box(points[i % points.len()]), n, us[i % us.len()]) {
                    chosen = chosen.wrapping_add(light);
                }
            }
            single_ns.push(start.elapsed().as_nanos() as f64 / CALLS as f64);
            let start = Instant::now();
            let mut out = [None; MAX_WALKS];
            for i in (0..CALLS).step_by(MAX_WALKS) {
                let at = i % points.len();
                tree.sample_batch(black_box(&points[at..at + MAX_WALKS]), &normals, &us[at..at + MAX_WALKS], &mut out);
                for (light, _) in out.iter().flatten() {
                    chosen = chosen.wrapping_add(*light);
                }
            }
            batch_ns.push(start.elapsed().as_nanos() as f64 / CALLS as f64);
            let start = Instant::now();
            let mut total = 0.0f32;
            for i in 0..CALLS {
                total += tree.pmf(black_box(points[i % points.len()]), n, (i * 7919) % lights.len());
            }
            black_box(total);
            pmf_ns.push(start.elapsed().as_nanos() as f64 / CALLS as f64);
        }
        black_box(chosen);
        // Levels a walk visits (family evaluations a walk), over one pass of the batch loop's
        // walks, counted outside the timed loops.
        let (mut level_sum, mut walks) = (0usize, 0usize);
        let mut out = [None; MAX_WALKS];
        for at in (0..points.len()).step_by(MAX_WALKS) {
            tree.sample_batch(&points[at..at + MAX_WALKS], &normals, &us[at..at + MAX_WALKS], &mut out);
            for (light, _) in out.iter().flatten() {
                level_sum += tree.levels(*light);
                walks += 1;
            }
        }
        let ((s_min, s_med), (p_min, p_med)) = (stats(sample_ns), stats(pmf_ns));
        let ((i_min, i_med), (b_min, b_med)) = (stats(single_ns), stats(batch_ns));
        println!(
            "{name}: sample {s_min:.1} ns min, {s_med:.1} median; pmf {p_min:.1} ns min, {p_med:.1} median \
             ({REPETITIONS} × {CALLS} calls)"
        );
        println!(
            "{name}: independent walks: one at a time {i_min:.1} ns min, {i_med:.1} median; \
             {MAX_WALKS} interleaved (sample_batch) {b_min:.1} ns min, {b_med:.1} median a walk; \
             {:.2} levels a walk",
            level_sum as f64 / walks.max(1) as f64
        );
    }
}
