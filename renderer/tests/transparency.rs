//! alphaMode MASK (cut-outs) and BLEND (stochastic transparency; shadow rays attenuated by 1 − alpha).

use renderer::film::Rect;
use renderer::material::AlphaMode;
use renderer::math::{Vec3, Vec4};
use renderer::testing::{emitter, lambert, SceneBuilder};
use renderer::{render_tile, IntegratorKind, RenderSettings};

/// A camera looking at an emitter of radiance 1 through a black quad with `alpha` and `mode`.
fn veil(mode: AlphaMode, alpha: f32) -> renderer::Scene {
    let mut b = SceneBuilder::default();
    let e = b.material(emitter(Vec3::ONE));
    let mut black = lambert(Vec3::ZERO);
    black.base_color = Vec4::new(0.0, 0.0, 0.0, alpha);
    black.alpha_mode = mode;
    let v = b.material(black);
    b.quad(Vec3::new(0.0, 0.0, -2.0), Vec3::X * 5.0, Vec3::Y * 5.0, e);
    b.quad(Vec3::new(0.0, 0.0, -1.0), Vec3::X * 5.0, Vec3::Y * 5.0, v);
    b.look_at(Vec3::new(0.0, 0.0, 1.0), Vec3::new(0.0, 0.0, -1.0), 20.0);
    b.build()
}

fn mean(scene: &renderer::Scene, spp: u32) -> (f32, f32) {
    let s = RenderSettings { width: 8, height: 8, spp, ..RenderSettings::default() };
    let sums = render_tile(scene, &s, Rect { x0: 0, y0: 0, width: 8, height: 8 }, 0..spp);
    let n = sums.rect.pixels();
    let m = (0..n).map(|i| sums.mean(i)[0]).sum::<f32>() / n as f32;
    let var = (0..n).map(|i| sums.variance_of_mean(i)).sum::<f32>() / (n * n) as f32;
    (m, var.sqrt())
}

#[test]
fn mask_cuts_out_below_the_cutoff() {
    assert_eq!(mean(&veil(AlphaMode::Mask(0.5), 0.2), 4).0, 1.0, "alpha 0.2 < 0.5: the veil is cut away");
    assert_eq!(mean(&veil(AlphaMode::Mask(0.5), 0.8), 4).0, 0.0, "alpha 0.8 ≥ 0.5: the veil blocks");
}

/// `layers` MASK veils (cutoff 0.5) one behind the other in front of the emitter: the ones in
/// `blocking` with alpha 0.8, the rest 0.2 (cut away).
fn veils(layers: usize, blocking: &[usize]) -> renderer::Scene {
    veils_of(AlphaMode::Mask(0.5), 0.2, 0.8, layers, blocking)
}

/// `layers` veils of `mode` in front of the emitter, of alpha `blocking_alpha` for the layers in
/// `blocking` and `alpha` for the rest.
fn veils_of(mode: AlphaMode, alpha: f32, blocking_alpha: f32, layers: usize, blocking: &[usize]) -> renderer::Scene {
    let mut b = SceneBuilder::default();
    let e = b.material(emitter(Vec3::ONE));
    b.quad(Vec3::new(0.0, 0.0, -2.0), Vec3::X * 5.0, Vec3::Y * 5.0, e);
    for k in 0..layers {
        let mut black = lambert(Vec3::ZERO);
        let a = if blocking.contains(&k) { blocking_alpha } else { alpha };
        black.base_color = Vec4::new(0.0, 0.0, 0.0, a);
        black.alpha_mode = mode;
        let v = b.material(black);
        b.quad(Vec3::new(0.0, 0.0, -0.5 - k as f32 / layers as f32), Vec3::X * 5.0, Vec3::Y * 5.0, v);
    }
    b.look_at(Vec3::new(0.0, 0.0, 1.0), Vec3::new(0.0, 0.0, -1.0), 20.0);
    b.build()
}

/// A ray passes any number of cut-outs (the walk per layer gave up after 256 and took the ray
/// as absorbed), and stops at the first surface that is not cut away, however deep.
#[test]
fn rays_pass_any_number_of_cutouts() {
    assert_eq!(mean(&veils(400, &[]), 4).0, 1.0, "400 cut-away veils: the emitter is seen");
    assert_eq!(mean(&veils(400, &[350]), 4).0, 0.0, "the 351st veil blocks");
    assert_eq!(mean(&veils(400, &[0]), 4).0, 0.0, "the nearest veil blocks");
    // Blended veils: alpha 0 passes every ray, alpha 1 stops every one, at any depth.
    assert_eq!(mean(&veils_of(AlphaMode::Blend, 0.0, 1.0, 400, &[]), 4).0, 1.0, "400 clear blended veils");
    assert_eq!(mean(&veils_of(AlphaMode::Blend, 0.0, 1.0, 400, &[300]), 4).0, 0.0, "the 301st blocks");
}

/// Light through many blended veils: each ray passes each veil with probability 1 − alpha, so
/// the image's mean is (1 − alpha)^layers, with 300 veils too (past the 256 layers the walk per
/// layer stopped at).
#[test]
fn many_blended_layers_let_the_product_through() {
    let (alpha, layers) = (0.002f32, 300);
    let (m, sd) = mean(&veils_of(AlphaMode::Blend, alpha, alpha, layers, &[]), 512);
    let want = (1.0 - alpha).powi(layers as i32);
    assert!((m - want).abs() <= 5.0 * sd + 1e-6, "{m} ± {sd} against {want}");
}

/// One blended veil (alpha 1/2) placed twice in front of the emitter, as two instances of one
/// prototype: the copies decide apart, so (1 − 1/2)² of the light comes through. (Keyed by the
/// triangle alone, both copies took the same number, and half came through.)
#[test]
fn instances_of_a_blended_surface_decide_apart() {
    use renderer::mesh::{flags, Instance};
    let mut b = SceneBuilder::default();
    let e = b.material(emitter(Vec3::ONE));
    b.quad(Vec3::new(0.0, 0.0, -2.0), Vec3::X * 5.0, Vec3::Y * 5.0, e);
    let mut veil = lambert(Vec3::ZERO);
    veil.base_color = Vec4::new(0.0, 0.0, 0.0, 0.5);
    veil.alpha_mode = AlphaMode::Blend;
    let v = b.material(veil);
    let first = b.mesh.triangles.len() as u32;
    b.quad(Vec3::ZERO, Vec3::X * 5.0, Vec3::Y * 5.0, v);
    let end = b.mesh.triangles.len() as u32;
    for t in &mut b.mesh.triangles[first as usize..] {
        t.flags |= flags::OBJECT_SPACE;
    }
    b.mesh.prototypes.push(first..end);
    for z in [-0.5f32, -1.0] {
        b.mesh.instances.extend(Instance::new(0, renderer::math::Mat4::from_translation(Vec3::new(0.0, 0.0, z))));
    }
    assert_eq!(b.mesh.instances.len(), 2);
    b.look_at(Vec3::new(0.0, 0.0, 1.0), Vec3::new(0.0, 0.0, -1.0), 20.0);
    let (m, sd) = mean(&b.build(), 512);
    assert!((m - 0.25).abs() <= 5.0 * sd + 1e-6, "{m} ± {sd} against 0.25");
}

#[test]
fn blend_lets_one_minus_alpha_through() {
    for alpha in [0.0f32, 0.25, 0.9, 1.0] {
        let (m, sd) = mean(&veil(AlphaMode::Blend, alpha), 256);
        assert!((m - (1.0 - alpha)).abs() <= 5.0 * sd + 1e-6, "alpha {alpha}: {m} ± {sd}");
    }
}

#[test]
fn shadows_through_blend_surfaces_are_attenuated() {
    // A floor lit by an area light with a BLEND veil (alpha 0.6) between them: direct light × 0.4.
    let build = |veil: bool| {
        let mut b = SceneBuilder::default();
        let floor = b.material(lambert(Vec3::splat(0.5)));
        let e = b.material(emitter(Vec3::splat(4.0)));
        let mut v = lambert(Vec3::ZERO);
        v.base_color = Vec4::new(0.0, 0.0, 0.0, 0.6);
        v.alpha_mode = AlphaMode::Blend;
        let v = b.material(v);
        b.quad(Vec3::ZERO, Vec3::Z * 10.0, Vec3::X * 10.0, floor);
        b.quad(Vec3::new(0.0, 3.0, 0.0), Vec3::X * 0.5, Vec3::Z * 0.5, e);
        if veil {
            b.quad(Vec3::new(0.0, 1.5, 0.0), Vec3::X * 2.0, Vec3::Z * 2.0, v);
        }
        b.look_at(Vec3::new(0.0, 1.0, 0.001), Vec3::ZERO, 10.0);
        b.build()
    };
    let s = RenderSettings {
        width: 4,
        height: 4,
        spp: 64,
        max_depth: 1,
        integrator: IntegratorKind::Nee,
        ..RenderSettings::default()
    };
    let lit =
        |scene: &renderer::Scene| render_tile(scene, &s, Rect { x0: 1, y0: 1, width: 2, height: 2 }, 0..64).mean(0)[0];
    let (open, veiled) = (lit(&build(false)), lit(&build(true)));
    // The camera (at y = 1) is under the veil (y = 1.5), so only the shadow rays cross it, each
    // carrying exactly 1 − 0.6 of the light: with the same samples the ratio is 0.4.
    assert!(open > 0.0);
    let ratio = veiled / open;
    assert!((ratio - 0.4).abs() < 1e-4, "ratio {ratio}");
}
