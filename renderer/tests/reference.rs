//! Statistical comparison with an independent renderer: Tessera's renders of its own scenes against
//! Mitsuba 3 (`scalar_rgb`) references made by `scenes/references/make_references.py`. Per pixel
//! z-test on luminance against the variance of both means, Šidák-corrected; at least 99.5 % of pixels
//! must be accepted (../shared/guide).

use renderer::film::Rect;
use renderer::image_io::{read_exr, VARIANCE_CHANNEL};
use renderer::stats::{lum, z_test};
use renderer::{render_tile, IntegratorKind, RenderSettings};
use std::path::{Path, PathBuf};

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

fn check(scene_name: &str, integrator: IntegratorKind, spp: u32) {
    check_blocks(scene_name, integrator, spp, 1);
}

/// As `check`, on the image averaged over `block × block` pixel blocks (means averaged, variances
/// of the mean summed / block⁴): for estimators whose per-pixel variance estimate is unreliable at
/// affordable sample counts (BSDF sampling of tiny lights), the test then sees enough samples per
/// cell that rare large contributions are not mistaken for zero variance.
fn check_blocks(scene_name: &str, integrator: IntegratorKind, spp: u32, block: u32) {
    check_with(scene_name, integrator, spp, block, renderer::light::LightSamplerKind::Power);
}

fn check_with(
    scene_name: &str,
    integrator: IntegratorKind,
    spp: u32,
    block: u32,
    light_sampler: renderer::light::LightSamplerKind,
) {
    let mut scene = renderer::gltf_loader::load(&root().join(format!("scenes/{scene_name}/{scene_name}.gltf")))
        .expect("scene loads");
    // The environment each scene is lit by (as in make_references.py's ENVIRONMENTS).
    let environment = match scene_name {
        "envlit" => renderer::environment::EnvironmentSettings {
            map: Some("scenes/env/sunset.exr".into()),
            ..Default::default()
        },
        _ => Default::default(),
    };
    scene.attach_environment(&environment, &root(), integrator == IntegratorKind::Mis).expect("environment loads");
    scene.set_light_sampler(light_sampler);
    let reference = read_exr(&root().join(format!("scenes/references/{scene_name}.exr"))).expect("reference EXR");
    let (w, h) = (reference.width, reference.height);
    let settings = RenderSettings {
        width: w,
        height: h,
        spp,
        integrator,
        seed: 1234,
        environment,
        light_sampler,
        ..RenderSettings::default()
    };
    let sums = render_tile(&scene, &settings, Rect { x0: 0, y0: 0, width: w, height: h }, 0..spp);
    let n = (w * h) as usize;
    let mean: Vec<f32> = (0..n).map(|i| lum(sums.mean(i))).collect();
    let var: Vec<f32> = (0..n).map(|i| sums.variance_of_mean(i)).collect();
    let (r, g, b) = (reference.channel("R").unwrap(), reference.channel("G").unwrap(), reference.channel("B").unwrap());
    let ref_lum: Vec<f32> = (0..n).map(|i| lum([r[i], g[i], b[i]])).collect();
    let ref_var = reference.channel(VARIANCE_CHANNEL).unwrap();
    let ref_var = ref_var.to_vec();
    let down = |v: &[f32], scale: f32| -> Vec<f32> {
        let (bw, bh) = (w / block, h / block);
        let mut out = vec![0.0f32; (bw * bh) as usize];
        for y in 0..bh * block {
            for x in 0..bw * block {
                out[((y / block) * bw + x / block) as usize] += v[(y * w + x) as usize] * scale;
            }
        }
        out
    };
    let k2 = (block * block) as f32;
    let (mean, var, ref_lum, ref_var) =
        (down(&mean, 1.0 / k2), down(&var, 1.0 / (k2 * k2)), down(&ref_lum, 1.0 / k2), down(&ref_var, 1.0 / (k2 * k2)));
    let (w, n) = (w / block, mean.len());
    let t = z_test(&mean, &var, &ref_lum, &ref_var);
    let (ours, theirs): (f64, f64) = (
        mean.iter().map(|&v| v as f64).sum::<f64>() / n as f64,
        ref_lum.iter().map(|&v| v as f64).sum::<f64>() / n as f64,
    );
    println!(
        "{scene_name} {integrator:?} {spp} spp, {block}x{block} blocks: {:.3}% of {} pixels accepted (α {:.2e}), worst z {:.2} at ({}, {}): ours {:.4} ref {:.4}; image mean ours {ours:.5} ref {theirs:.5}",
        100.0 * t.accepted_fraction(),
        t.pixels,
        t.per_pixel_alpha,
        t.worst_z,
        t.worst_pixel % w as usize,
        t.worst_pixel / w as usize,
        mean[t.worst_pixel],
        ref_lum[t.worst_pixel],
    );
    assert!(
        t.accepted_fraction() >= 0.995,
        "{scene_name} with {integrator:?}: only {:.3}% of pixels pass the z-test",
        100.0 * t.accepted_fraction()
    );
    // Region means too, the whole image and its lower half (the floor in most scenes, away from
    // directly seen emitters): a bias of a few percent everywhere (issue 10: NEE 8 % too dark under
    // a tessellated sphere light) can hide under per-pixel noise, never under a region mean's.
    let bh = mean.len() / w as usize;
    for (what, rows) in [("image", 0..bh), ("lower half", bh / 2..bh)] {
        let px = rows.start * w as usize..rows.end * w as usize;
        let k = px.len() as f64;
        let avg = |v: &[f32]| v[px.clone()].iter().map(|&x| x as f64).sum::<f64>() / k;
        let (a, b) = (avg(&mean), avg(&ref_lum));
        let se = ((avg(&var) + avg(&ref_var)) / k).sqrt();
        let z = (a - b) / se.max(1e-6 * b.abs());
        println!(
            "{scene_name} {integrator:?}: {what} mean ours {a:.6} ref {b:.6} ({:+.3} %, z = {z:.1})",
            100.0 * (a / b - 1.0)
        );
        assert!(z.abs() < 5.0, "{scene_name} with {integrator:?}: {what} mean {a:.6} vs {b:.6} (z = {z:.1})");
    }
}

// Test sample counts: the per-pixel tests need each pixel's sample variance to describe its error,
// which holds for MIS and NEE at modest spp. BSDF-only sampling finds a small light in a few paths
// out of thousands, so most pixels see zero or one hit and the per-pixel variance estimate is
// meaningless at any affordable spp (that is the point of the Veach scene); those tests run on
// block-averaged images, where each cell pools enough samples. Measured acceptance (this machine):
// cornell mis/nee 64 spp 99.99 %, bsdf 4×4 @ 256 spp 99.8 %; veach mis 256 spp 99.9 %,
// nee 8×8 @ 256 spp 100 %, bsdf 32×32 @ 1024 spp 100 % (12 cells).

#[test]
fn cornell_mis_matches_mitsuba() {
    check("cornell", IntegratorKind::Mis, 64);
}

#[test]
fn cornell_nee_matches_mitsuba() {
    check("cornell", IntegratorKind::Nee, 64);
}

#[test]
fn cornell_bsdf_matches_mitsuba() {
    check_blocks("cornell", IntegratorKind::Bsdf, 256, 4);
}

#[test]
fn veach_mis_matches_mitsuba() {
    check("veach", IntegratorKind::Mis, 256);
}

#[test]
fn veach_nee_matches_mitsuba() {
    // Light sampling alone has heavy tails here: the glossy plates reflect the bulbs, and a
    // plate point's estimate is large only where a light sample lands in its narrow lobe. At 256
    // spp and 8×8 blocks a block whose rare large samples had not come up read as a confident
    // miss: the same test by hand (`tessera render --integrator nee --light-sampler power`,
    // seeds 0–9, this test's z-test on 8×8 blocks) failed 8 of 10 seeds before bulbs were one
    // light and 8 of 10 after, at 1024 spp 4 and 2, and at 1024 spp in 16×16 blocks none of
    // either. A bias of the technique would show in every block: the mean over the image.
    check_blocks("veach", IntegratorKind::Nee, 1024, 16);
}

#[test]
fn veach_bsdf_matches_mitsuba() {
    check_blocks("veach", IntegratorKind::Bsdf, 1024, 32);
}

#[test]
fn envlit_mis_matches_mitsuba() {
    check("envlit", IntegratorKind::Mis, 64);
}

/// relMSE (`noise::rel_mse_against`: luminance, the metric of the noise estimates) of a 64-spp MIS
/// render of envlit against the Mitsuba reference, with or without MIS compensation of the
/// environment's sampling.
fn envlit_rel_mse(mis_compensation: bool) -> f64 {
    let mut scene = renderer::gltf_loader::load(&root().join("scenes/envlit/envlit.gltf")).expect("scene loads");
    let environment =
        renderer::environment::EnvironmentSettings { map: Some("scenes/env/sunset.exr".into()), ..Default::default() };
    scene.attach_environment(&environment, &root(), mis_compensation).expect("environment loads");
    let reference = read_exr(&root().join("scenes/references/envlit.exr")).expect("reference EXR");
    let (w, h) = (reference.width, reference.height);
    let settings = RenderSettings { width: w, height: h, spp: 64, seed: 7, environment, ..RenderSettings::default() };
    let sums = render_tile(&scene, &settings, Rect { x0: 0, y0: 0, width: w, height: h }, 0..64);
    let [r, g, b] = ["R", "G", "B"].map(|c| reference.channel(c).expect("RGB reference"));
    let reference: Vec<[f32; 3]> = (0..r.len()).map(|i| [r[i], g[i], b[i]]).collect();
    let image: Vec<[f32; 3]> = (0..reference.len()).map(|i| sums.mean(i)).collect();
    renderer::noise::rel_mse_against(&image, &reference).expect("same size")
}

#[test]
fn mis_compensation_lowers_envlit_error() {
    // Issue 15: sampling (luminance − mean) instead of luminance leaves the sunset map's dim sky
    // to BSDF sampling; measured with bench_peers.py (5 seeds): relMSE 4.70e-3 → 1.76e-3 at 64 spp,
    // 8.03e-4 → 5.42e-4 at 256, at the same speed. Unbiasedness is the Mitsuba z-tests' job
    // (envlit_mis_matches_mitsuba); this checks the gain is there, on one seed.
    let (plain, compensated) = (envlit_rel_mse(false), envlit_rel_mse(true));
    println!("envlit 64 spp relMSE: plain {plain:.3e}, compensated {compensated:.3e}");
    assert!(compensated < 0.75 * plain, "compensated {compensated:.3e} vs plain {plain:.3e}");
}

#[test]
fn envlit_nee_matches_mitsuba() {
    // NEE alone on the rough metal sphere meets the 6e3 sun only through rare samples: blocks.
    check_blocks("envlit", IntegratorKind::Nee, 256, 32);
}

#[test]
fn envlit_bsdf_matches_mitsuba() {
    // BSDF sampling finds the sun (6e3, 0.3° wide) in a handful of paths per block: heavy tails.
    check_blocks("envlit", IntegratorKind::Bsdf, 1024, 32);
}

// Glass: light reaches the floor and wall through the smooth sphere only by BSDF sampling (a
// caustic NEE cannot connect), so every integrator has heavy tails there: blocks.
#[test]
fn glass_mis_matches_mitsuba() {
    check_blocks("glass", IntegratorKind::Mis, 256, 16);
}

#[test]
fn glass_bsdf_matches_mitsuba() {
    check_blocks("glass", IntegratorKind::Bsdf, 256, 16);
}

// The same spheres absorbing inside (KHR_materials_volume), against Mitsuba's `volpath` with a
// homogeneous absorbing interior: Beer–Lambert along the paths inside, on the light samples taken
// at the rough sphere's inner surface (which leave through it into air), and in the kernel.
#[test]
fn absorbing_glass_matches_mitsuba() {
    check_blocks("glass_absorb", IntegratorKind::Mis, 256, 16);
    check_blocks("glass_absorb", IntegratorKind::Nee, 256, 16);
}

#[test]
fn the_light_tree_and_uniform_selection_agree_with_mitsuba() {
    use renderer::light::LightSamplerKind::{Tree, Uniform};
    check_with("veach", IntegratorKind::Mis, 256, 1, Tree);
    check_with("veach", IntegratorKind::Mis, 256, 1, Uniform);
    check_with("envlit", IntegratorKind::Mis, 64, 1, Tree);
}

#[test]
fn many_lights_match_mitsuba_with_every_light_sampler() {
    use renderer::light::LightSamplerKind::{Power, Tree, Uniform};
    check_with("many_lights", IntegratorKind::Mis, 64, 1, Tree);
    // Uniform and power selection find the few nearby lights rarely: heavy tails, so blocks.
    check_with("many_lights", IntegratorKind::Mis, 64, 8, Power);
    check_with("many_lights", IntegratorKind::Mis, 64, 8, Uniform);
}

/// Issue 10's case: a 48 × 24 UV-sphere bulb over a floor. NEE and MIS were 8 % too dark here
/// (shadow rays found the bulb's own triangles); the image-mean test catches that at once.
#[test]
fn sphere_light_matches_mitsuba() {
    check("sphere_light", IntegratorKind::Nee, 64);
    check("sphere_light", IntegratorKind::Mis, 64);
    check_blocks("sphere_light", IntegratorKind::Bsdf, 256, 8);
}

#[test]
fn sphere_lights_match_mitsuba_with_every_light_sampler() {
    use renderer::light::LightSamplerKind::{Auto, Power, Tree, Uniform};
    for ls in [Auto, Power, Tree, Uniform] {
        check_with("sphere_lights", IntegratorKind::Mis, 64, 1, ls);
    }
}
