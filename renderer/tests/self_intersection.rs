//! A ray leaving a surface never finds that surface again.
//!
//! Found by `bench_embree.py --scene scenes/veach/veach.gltf` (session 35): 1 019 of 10⁶ rays
//! leaving the Veach scene's surfaces hit the plate they had just left, at t = 6·10⁻⁹ to 2.6·10⁻⁶
//! (in f64 the same rays meet its plane behind them, t = −2.5·10⁻⁷ to −1.1·10⁻⁶); the rays start
//! area-weighted and each plate is 21.9 % of the scene's area, so about half a percent of the rays
//! leaving that plate. The plate is 8 units wide and tilted (normal (0, 0.963, 0.27)), and
//! it straddles y = 0, so its points' coordinates are small next to its size: the origin offset,
//! 16 ulps of each coordinate (Wächter & Binder), lifts them off the plane by less than the
//! rounding error of the triangle test, which grows with the triangle's size, not with the point's
//! coordinates. Here that plate alone (so that any hit is a self-hit), its points reached as the
//! renderer reaches them (camera rays), rays leaving either side in cosine-distributed directions,
//! with every BVH, one at a time and in batches, as world geometry and as a scaled instance: none
//! may hit it, and no shadow ray from it may be blocked.

use base64::Engine;
use renderer::accel::AccelKind;
use renderer::math::{sample_cosine_hemisphere, Frame, Vec2, Vec3};
use renderer::sampler::hash_unit as u;
use renderer::scene::Scene;
use renderer::testing::{lambert, trace_in_batches, SceneBuilder};

/// The Veach scene's `plate1`, vertex for vertex as `scenes/veach/veach.gltf` has it: its centre
/// and the half extents across and along it (`SceneBuilder::quad`'s corners c ∓ u ∓ v).
const PLATE: (Vec3, Vec3, Vec3) =
    (Vec3::new(0.0, -0.05, 1.5), Vec3::new(4.0, 0.0, 0.0), Vec3::new(0.0, 0.148_521_1, -0.529_567_2));

/// The camera of the Veach scene, which the plate's points are reached from.
const EYE: Vec3 = Vec3::new(0.0, 2.0, 12.0);

fn veach_plate() -> Scene {
    let mut b = SceneBuilder::default();
    let m = b.material(lambert(Vec3::splat(0.5)));
    b.quad(PLATE.0, PLATE.1, PLATE.2, m);
    b.look_at(EYE, PLATE.0, 30.0);
    b.build()
}

/// The same plate as an instance scaled by 100 (a mesh placed twice is instanced; the second
/// placement is a hundredth of the size, 10⁴ units up, out of the way of every ray here).
fn instanced_plate() -> Scene {
    let (c, a, l) = PLATE;
    let corners = [c - a - l, c + a - l, c + a + l, c - a + l];
    let mut bin = Vec::new();
    for v in corners {
        for x in v.to_array() {
            bin.extend_from_slice(&x.to_le_bytes());
        }
    }
    for i in [0u32, 1, 2, 0, 2, 3] {
        bin.extend_from_slice(&i.to_le_bytes());
    }
    let uri = base64::engine::general_purpose::STANDARD.encode(&bin);
    let json = format!(
        r#"{{"asset":{{"version":"2.0"}},"scene":0,"scenes":[{{"nodes":[0,1]}}],
        "nodes":[{{"mesh":0,"scale":[100,100,100]}},{{"mesh":0,"translation":[0,10000,0],"scale":[0.01,0.01,0.01]}}],
        "meshes":[{{"primitives":[{{"attributes":{{"POSITION":0}},"indices":1,"material":0}}]}}],
        "materials":[{{"pbrMetallicRoughness":{{"baseColorFactor":[0.5,0.5,0.5,1],"metallicFactor":0}}}}],
        "accessors":[{{"bufferView":0,"componentType":5126,"count":4,"type":"VEC3","min":[-4,-0.2,0.97],"max":[4,0.1,2.03]}},
                     {{"bufferView":1,"componentType":5125,"count":6,"type":"SCALAR"}}],
        "bufferViews":[{{"buffer":0,"byteOffset":0,"byteLength":48}},{{"buffer":0,"byteOffset":48,"byteLength":24}}],
        "buffers":[{{"byteLength":72,"uri":"data:application/octet-stream;base64,{uri}"}}]}}"#
    );
    let scene = renderer::gltf_loader::load_from_bytes(std::path::Path::new("plate.gltf"), json.as_bytes())
        .unwrap_or_else(|e| panic!("{e}"));
    assert!(!scene.mesh.instances.is_empty(), "the plate placed twice is instanced");
    scene
}

/// Rays leaving the plate (the plate of `veach_plate`, in `scene` scaled by `scale`), as
/// (hits on the instance they leave, shadow rays blocked) alone and in batches, and how many.
fn self_hits(mut scene: Scene, kind: AccelKind, scale: f32) -> ([usize; 4], usize) {
    const RAYS: u64 = 200_000;
    scene.use_accel(kind);
    let (c, a, l) = PLATE;
    let (mut o, mut d, mut inst) = (Vec::new(), Vec::new(), Vec::new());
    for i in 0..RAYS {
        let k = 8 * i;
        // A point on the plate, reached from the camera (or from behind the plate).
        let target = (c + a * (2.0 * u(k) - 1.0) + l * (2.0 * u(k + 1) - 1.0)) * scale;
        let eye = if u(k + 2) < 0.5 { EYE } else { Vec3::new(EYE.x, -EYE.y, -EYE.z) } * scale;
        let dir = (target - eye).normalize();
        let Some(hit) = scene.intersect(eye, dir, f32::INFINITY) else { continue };
        let sp = scene.surface_point(&hit);
        // Leaving on the side the camera ray came from (reflection) or through it (glass).
        let toward = if sp.ng.dot(dir) < 0.0 { sp.ng } else { -sp.ng };
        let n = if u(k + 3) < 0.5 { toward } else { -toward };
        o.push(scene.spawn_origin(sp.p, n, sp.plane_error));
        d.push(Frame::from_normal(n).to_world(sample_cosine_hemisphere(Vec2::new(u(k + 4), u(k + 5)))));
        inst.push(hit.instance);
    }
    assert!(o.len() as u64 > RAYS * 9 / 10, "{} of {RAYS} camera rays reached the plate", o.len());
    let reach = 100.0 * scale;
    let mut found = [0; 4];
    for k in 0..o.len() {
        found[0] += scene.intersect(o[k], d[k], f32::INFINITY).is_some_and(|h| h.instance == inst[k]) as usize;
        found[1] += scene.occluded(o[k], d[k], reach) as usize;
    }
    if kind != AccelKind::Own {
        let (hits, seen) = trace_in_batches(&mut scene, &o, &d, reach);
        found[2] = hits.iter().zip(&inst).filter(|(h, i)| h.is_some_and(|h| h.instance == **i)).count();
        found[3] = seen.iter().filter(|&&v| v == 0.0).count();
    }
    (found, o.len())
}

/// [`self_hits`] with every BVH: none of the rays may hit what they leave or be blocked by it.
fn assert_no_self_hits(scene: impl Fn() -> Scene, scale: f32, what: &str) {
    for kind in [AccelKind::Obvhs, AccelKind::ObvhsCompressed, AccelKind::Own] {
        let (found, rays) = self_hits(scene(), kind, scale);
        assert_eq!(
            found,
            [0; 4],
            "{}: of {rays} rays leaving {what}, (hit it, blocked by it) alone and in batches",
            kind.name()
        );
    }
}

#[test]
fn rays_leaving_a_large_tilted_plate_never_hit_it() {
    assert_no_self_hits(veach_plate, 1.0, "the plate");
}

/// The plate as an instance 100 times its size: the triangle test runs in object space, so the
/// lift must be the object-space bound scaled up to world space.
#[test]
fn rays_leaving_a_scaled_instance_never_hit_it() {
    assert_no_self_hits(instanced_plate, 100.0, "the instanced plate");
}
