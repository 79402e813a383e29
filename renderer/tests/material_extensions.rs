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
