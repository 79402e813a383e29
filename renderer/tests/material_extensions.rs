//! KHR_materials_volume (Beer–Lambert absorption inside transmissive meshes) and
//! KHR_materials_unlit, rendered: exact values where the transport is deterministic. The BSDF
//! lobes of clearcoat and sheen have their chi-square tests in `sampling_chi2.rs`, their furnace
//! tests in `furnace.rs` and their extremes in `extremes.rs`; loading is in `gltf_loading.rs`.

use renderer::film::Rect;
use renderer::material::Material;
use renderer::math::{Vec3, Vec4};
use renderer::testing::{emitter, SceneBuilder};
use renderer::{render_tile, IntegratorKind, RenderSettings};

/// A closed axis-aligned box of half-extents `h` centred at `c`, faces wound outward.
fn cube(b: &mut SceneBuilder, c: Vec3, h: Vec3, material: u32) {
    let p: Vec<Vec3> = (0..8)
        .map(|i| {
            c + Vec3::new(
                if i & 1 != 0 { h.x } else { -h.x },
                if i & 2 != 0 { h.y } else { -h.y },
                if i & 4 != 0 { h.z } else { -h.z },
            )
        })
        .collect();
    let tris = [
        [0, 2, 1],
        [1, 2, 3], // −z
        [4, 5, 6],
        [5, 7, 6], // +z
        [0, 1, 4],
        [1, 5, 4], // −y
        [2, 6, 3],
        [3, 6, 7], // +y
        [0, 4, 2],
        [2, 4, 6], // −x
        [1, 3, 5],
        [3, 7, 5], // +x
    ];
    b.triangles(&p, &tris, material);
}

fn clear_glass(absorption: Vec3) -> Material {
    Material {
        name: "absorbing glass".into(),
        base_color: Vec4::ONE,
        metallic: 0.0,
        roughness: 0.0,
        transmission: 1.0,
        // Index 1: no Fresnel reflection and no bending, so the only loss is absorption.
        ior: 1.0,
        absorption,
        ..Material::default()
    }
}

/// Mean of an 8×8 image of a narrow camera looking along −z through a unit-thick box at an emitter.
fn through_box(absorption: Vec3, integrator: IntegratorKind) -> Vec3 {
    let mut b = SceneBuilder::default();
    let e = b.material(emitter(Vec3::ONE));
    let g = b.material(clear_glass(absorption));
    b.quad(Vec3::new(0.0, 0.0, -3.0), Vec3::X * 10.0, Vec3::Y * 10.0, e);
    cube(&mut b, Vec3::new(0.0, 0.0, -1.0), Vec3::new(2.0, 2.0, 0.5), g);
    b.look_at(Vec3::new(0.0, 0.0, 2.0), Vec3::new(0.0, 0.0, -1.0), 2.0);
    let scene = b.build();
    let s = RenderSettings { width: 8, height: 8, spp: 4, integrator, max_depth: 16, ..RenderSettings::default() };
    let sums = render_tile(&scene, &s, Rect { x0: 0, y0: 0, width: 8, height: 8 }, 0..s.spp);
    let n = sums.rect.pixels();
    (0..n).map(|i| Vec3::from(sums.mean(i))).sum::<Vec3>() / n as f32
}

#[test]
fn absorption_follows_beer_lambert_over_the_real_path_length() {
    // attenuationColor c at attenuationDistance d: σ = −ln(c)/d; through thickness 1, exp(−σ).
    let (c, d) = (Vec3::new(0.5, 0.25, 1.0), 2.0f32);
    let sigma = Vec3::new(-c.x.ln(), -c.y.ln(), -c.z.ln()) / d;
    let expect = Vec3::new((-sigma.x).exp(), (-sigma.y).exp(), (-sigma.z).exp());
    for integrator in [IntegratorKind::Bsdf, IntegratorKind::Nee, IntegratorKind::Mis] {
        let clear = through_box(Vec3::ZERO, integrator);
        assert!((clear - Vec3::ONE).abs().max_element() < 1e-3, "{integrator:?} clear glass: {clear:?}");
        let got = through_box(sigma, integrator);
        // The camera's 2° field of view lengthens the off-axis paths by at most 1/cos(1°) − 1 = 0.015 %.
        assert!((got - expect).abs().max_element() < 2e-3, "{integrator:?}: {got:?}, expected {expect:?}");
    }
}

#[test]
fn unlit_surfaces_show_their_color_to_every_integrator() {
    let color = Vec3::new(0.2, 0.5, 0.8);
    let unlit = Material { name: "unlit".into(), base_color: color.extend(1.0), unlit: true, ..Material::default() };
    let mut b = SceneBuilder::default();
    let u = b.material(unlit);
    b.quad(Vec3::new(0.0, 0.0, -1.0), Vec3::X * 5.0, Vec3::Y * 5.0, u);
    b.look_at(Vec3::new(0.0, 0.0, 1.0), Vec3::new(0.0, 0.0, -1.0), 20.0);
    let scene = b.build();
    for integrator in [IntegratorKind::Bsdf, IntegratorKind::Nee, IntegratorKind::Mis] {
        let s = RenderSettings { width: 4, height: 4, spp: 2, integrator, ..RenderSettings::default() };
        let sums = render_tile(&scene, &s, Rect { x0: 0, y0: 0, width: 4, height: 4 }, 0..s.spp);
        for i in 0..sums.rect.pixels() {
            let m = Vec3::from(sums.mean(i));
            assert!((m - color).abs().max_element() < 1e-6, "{integrator:?} pixel {i}: {m:?}");
        }
    }
}

/// Mean luminance and its standard error over a 16×16 image of a camera looking through a
/// unit-thick box of rough absorbing glass at a small lamp, rendered by `integrator` (the pixels
/// see the same thing, so their spread is the estimate's noise).
fn through_rough_box(absorption: Vec3, integrator: IntegratorKind, seed: u64) -> (f64, f64) {
    let mut b = SceneBuilder::default();
    let e = b.material(emitter(Vec3::splat(20.0)));
    let g = b.material(Material { roughness: 0.3, ior: 1.5, ..clear_glass(absorption) });
    // The lamp 2.5 behind the box's far face: a light sample from a vertex on that face (inside
    // the medium, the lamp outside) travels 2.5 in air and none in the glass.
    b.quad(Vec3::new(0.0, 0.0, -4.0), Vec3::X * 0.6, Vec3::Y * 0.6, e);
    cube(&mut b, Vec3::new(0.0, 0.0, -1.0), Vec3::new(3.0, 3.0, 0.5), g);
    b.look_at(Vec3::new(0.0, 0.0, 2.0), Vec3::new(0.0, 0.0, -1.0), 4.0);
    let scene = b.build();
    let s = RenderSettings { width: 16, height: 16, spp: 256, integrator, seed, max_depth: 12, ..Default::default() };
    let sums = render_tile(&scene, &s, Rect { x0: 0, y0: 0, width: 16, height: 16 }, 0..s.spp);
    let y: Vec<f64> =
        (0..sums.rect.pixels()).map(|i| renderer::math::luminance(Vec3::from(sums.mean(i))) as f64).collect();
    let n = y.len() as f64;
    let mean = y.iter().sum::<f64>() / n;
    let var = y.iter().map(|v| (v - mean) * (v - mean)).sum::<f64>() / (n - 1.0);
    (mean, (var / n).sqrt())
}

/// Light leaving an absorbing medium through a rough surface: next-event estimation at the
/// inside vertex of the far face reaches the lamp through that surface, in air, so the medium
/// must not attenuate it (it did, over the whole distance to the lamp: the medium of the side
/// the path arrived from was applied whatever side the light sample left by). NEE, MIS and BSDF
/// sampling alone estimate the same image, within their noise.
#[test]
fn light_samples_through_an_absorbing_surface_take_the_medium_of_their_side() {
    let sigma = Vec3::new(0.7, 1.4, 0.3);
    let (bsdf, bsdf_se) = through_rough_box(sigma, IntegratorKind::Bsdf, 1);
    assert!(bsdf > 0.01, "the lamp must be seen through the box: {bsdf}");
    for integrator in [IntegratorKind::Nee, IntegratorKind::Mis] {
        let (got, se) = through_rough_box(sigma, integrator, 2);
        let z = (got - bsdf) / (se * se + bsdf_se * bsdf_se).sqrt();
        assert!(z.abs() < 5.0, "{integrator:?}: {got} ± {se} against BSDF sampling's {bsdf} ± {bsdf_se} (z = {z:.1})");
    }
}
