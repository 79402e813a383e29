//! KHR_lights_punctual: loading, units and the radiance they deliver.

use renderer::film::Rect;
use renderer::math::Vec3;
use renderer::punctual::{PunctualKind, PunctualLight};
use renderer::testing::{lambert, SceneBuilder};
use renderer::{render_tile, IntegratorKind, RenderSettings};

fn floor_scene(light: PunctualLight) -> renderer::Scene {
    let mut b = SceneBuilder::default();
    let m = b.material(lambert(Vec3::splat(0.5)));
    b.quad(Vec3::ZERO, Vec3::new(0.0, 0.0, 50.0), Vec3::new(50.0, 0.0, 0.0), m);
    b.look_at(Vec3::new(0.0, 3.0, 0.001), Vec3::ZERO, 10.0);
    let mut s = b.build();
    s.set_punctual(vec![light]);
    s
}

fn centre_radiance(scene: &renderer::Scene, integrator: IntegratorKind) -> f32 {
    let s = RenderSettings { width: 9, height: 9, spp: 16, max_depth: 1, integrator, ..RenderSettings::default() };
    render_tile(scene, &s, Rect { x0: 4, y0: 4, width: 1, height: 1 }, 0..16).mean(0)[0]
}

#[test]
fn directional_and_point_lights_deliver_their_irradiance() {
    // Lambert ρ = 0.5 under irradiance E reflects L = ρ E / π.
    let sun = PunctualLight {
        kind: PunctualKind::Directional,
        intensity: Vec3::splat(3.0),
        position: Vec3::ZERO,
        direction: Vec3::new(0.0, -1.0, 1.0).normalize(),
    };
    let expect = 0.5 * 3.0 * (45f32).to_radians().cos() / std::f32::consts::PI;
    let point = PunctualLight {
        kind: PunctualKind::Point,
        intensity: Vec3::splat(8.0),
        position: Vec3::new(0.0, 2.0, 0.0),
        direction: -Vec3::Y,
    };
    let expect_point = 0.5 * 8.0 / 4.0 / std::f32::consts::PI;
    for integrator in [IntegratorKind::Mis, IntegratorKind::Nee] {
        let got = centre_radiance(&floor_scene(sun), integrator);
        assert!((got - expect).abs() < 1e-3 * expect, "{integrator:?} directional: {got} vs {expect}");
        let got = centre_radiance(&floor_scene(point), integrator);
        assert!((got - expect_point).abs() < 0.01 * expect_point, "{integrator:?} point: {got} vs {expect_point}");
    }
    // BSDF sampling cannot hit a delta light: it sees nothing, as it should.
    assert_eq!(centre_radiance(&floor_scene(point), IntegratorKind::Bsdf), 0.0);
}

#[test]
fn lights_load_from_gltf_with_node_transforms() {
    let json = r#"{"asset":{"version":"2.0"},"extensionsUsed":["KHR_lights_punctual"],
      "extensions":{"KHR_lights_punctual":{"lights":[
        {"type":"spot","color":[1,0.5,0.25],"intensity":10,"spot":{"innerConeAngle":0.2,"outerConeAngle":0.5}},
        {"type":"directional","intensity":2}]}},
      "scene":0,"scenes":[{"nodes":[0,1]}],
      "nodes":[{"translation":[1,2,3],"extensions":{"KHR_lights_punctual":{"light":0}}},
               {"rotation":[-0.7071068,0,0,0.7071068],"extensions":{"KHR_lights_punctual":{"light":1}}}]}"#;
    let s =
        renderer::gltf_loader::load_from_bytes(std::path::Path::new("lights.gltf"), json.as_bytes()).expect("loads");
    assert_eq!(s.lights.punctual.len(), 2);
    let spot = s.lights.punctual.iter().find(|l| matches!(l.kind, PunctualKind::Spot { .. })).unwrap();
    assert_eq!(spot.position, Vec3::new(1.0, 2.0, 3.0));
    assert!((spot.intensity - Vec3::new(10.0, 5.0, 2.5)).length() < 1e-6);
    let sun = s.lights.punctual.iter().find(|l| l.kind == PunctualKind::Directional).unwrap();
    // −90° about X turns the light's −Z into −Y: straight down.
    assert!((sun.direction - -Vec3::Y).length() < 1e-5, "{:?}", sun.direction);
    let bad = json.replace("\"outerConeAngle\":0.5", "\"outerConeAngle\":0.1");
    let e = renderer::gltf_loader::load_from_bytes(std::path::Path::new("lights.gltf"), bad.as_bytes())
        .err()
        .expect("inner > outer is refused");
    assert!(e.to_string().contains("cone"), "{e}");
}
