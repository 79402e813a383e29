//! glTF animation: a moving emitter and an animated camera land where the analytic pose puts them;
//! a frame is the same whatever was posed before it; skinning and morph targets match the glTF
//! formulas (and, in `blender.rs`, Blender's own pose of a rig it made).

use base64::Engine;
use renderer::film::Rect;
use renderer::gltf_loader::load_from_bytes;
use renderer::math::Vec3;
use renderer::{render_tile, RenderSettings};
use std::path::Path;

/// An emissive 0.2-wide square moving from x = −1 (t = 0) to x = +1 (t = 1) in front of a camera
/// that rises from y = 0 to y = 0.5 over the same second (both LINEAR), and a static grey floor.
fn moving_scene(interpolation: &str) -> String {
    let mut bin: Vec<u8> = Vec::new();
    let mut put = |v: &[f32]| {
        for x in v {
            bin.extend_from_slice(&x.to_le_bytes());
        }
    };
    // 0: square (4 × vec3), 1: floor (4 × vec3), 2: times (2), 3: square path (2 × vec3), 4: camera path.
    put(&[-0.1, -0.1, 0.0, 0.1, -0.1, 0.0, 0.1, 0.1, 0.0, -0.1, 0.1, 0.0]);
    put(&[-5.0, -1.0, -5.0, 5.0, -1.0, -5.0, 5.0, -1.0, 2.0, -5.0, -1.0, 2.0]);
    put(&[0.0, 1.0]);
    put(&[-1.0, 0.0, 0.0, 1.0, 0.0, 0.0]);
    put(&[0.0, 0.0, 5.0, 0.0, 0.5, 5.0]);
    for i in [0u32, 1, 2, 0, 2, 3] {
        bin.extend_from_slice(&i.to_le_bytes());
    }
    let uri =
        format!("data:application/octet-stream;base64,{}", base64::engine::general_purpose::STANDARD.encode(&bin));
    format!(
        r#"{{"asset":{{"version":"2.0"}},"scene":0,"scenes":[{{"nodes":[0,1,2]}}],
        "nodes":[{{"mesh":0,"name":"light"}},{{"mesh":1}},{{"camera":0,"translation":[0,0,5]}}],
        "meshes":[{{"primitives":[{{"attributes":{{"POSITION":0}},"indices":5,"material":0}}]}},
                  {{"primitives":[{{"attributes":{{"POSITION":1}},"indices":5,"material":1}}]}}],
        "materials":[{{"emissiveFactor":[1,1,1],"doubleSided":true,"pbrMetallicRoughness":{{"baseColorFactor":[0,0,0,1]}}}},
                     {{"pbrMetallicRoughness":{{"baseColorFactor":[0.5,0.5,0.5,1],"metallicFactor":0}}}}],
        "cameras":[{{"type":"perspective","perspective":{{"yfov":0.8,"aspectRatio":1.0,"znear":0.1}}}}],
        "animations":[{{"name":"move","channels":[{{"sampler":0,"target":{{"node":0,"path":"translation"}}}}],
                        "samplers":[{{"input":2,"output":3,"interpolation":"{interpolation}"}}]}},
                      {{"name":"crane","channels":[{{"sampler":0,"target":{{"node":2,"path":"translation"}}}}],
                        "samplers":[{{"input":2,"output":4,"interpolation":"{interpolation}"}}]}}],
        "accessors":[{{"bufferView":0,"componentType":5126,"count":4,"type":"VEC3","min":[-0.1,-0.1,0],"max":[0.1,0.1,0]}},
                     {{"bufferView":1,"componentType":5126,"count":4,"type":"VEC3","min":[-5,-1,-5],"max":[5,-1,2]}},
                     {{"bufferView":2,"componentType":5126,"count":2,"type":"SCALAR","min":[0],"max":[1]}},
                     {{"bufferView":3,"componentType":5126,"count":2,"type":"VEC3"}},
                     {{"bufferView":4,"componentType":5126,"count":2,"type":"VEC3"}},
                     {{"bufferView":5,"componentType":5125,"count":6,"type":"SCALAR"}}],
        "bufferViews":[{{"buffer":0,"byteOffset":0,"byteLength":48}},{{"buffer":0,"byteOffset":48,"byteLength":48}},
                       {{"buffer":0,"byteOffset":96,"byteLength":8}},{{"buffer":0,"byteOffset":104,"byteLength":24}},
                       {{"buffer":0,"byteOffset":128,"byteLength":24}},{{"buffer":0,"byteOffset":152,"byteLength":24}}],
        "buffers":[{{"byteLength":176,"uri":"{uri}"}}]}}"#
    )
}

fn load(json: &str) -> renderer::Scene {
    load_from_bytes(Path::new("anim.gltf"), json.as_bytes()).expect("animated scene")
}

const SIZE: u32 = 96;

fn settings(animation: Option<&str>) -> RenderSettings {
    RenderSettings {
        width: SIZE,
        height: SIZE,
        spp: 4,
        max_depth: 0,
        animation: animation.map(str::to_owned),
        ..RenderSettings::default()
    }
}

/// The centroid (pixel coordinates) of the bright pixels of a frame.
fn centroid(scene: &renderer::Scene, s: &RenderSettings) -> (f32, f32, Vec<[f32; 3]>) {
    let sums = render_tile(scene, s, Rect { x0: 0, y0: 0, width: SIZE, height: SIZE }, 0..s.spp);
    let (mut sx, mut sy, mut n) = (0.0f32, 0.0f32, 0.0f32);
    let mut pixels = Vec::new();
    for i in 0..sums.rect.pixels() {
        let m = sums.mean(i);
        pixels.push(m);
        let (x, y) = ((i as u32 % SIZE) as f32 + 0.5, (i as u32 / SIZE) as f32 + 0.5);
        sx += m[0] * x;
        sy += m[0] * y;
        n += m[0];
    }
    (sx / n, sy / n, pixels)
}

#[test]
fn a_moving_emitter_seen_by_a_moving_camera_lands_where_the_pose_puts_it() {
    let mut scene = load(&moving_scene("LINEAR"));
    assert!(scene.is_animated());
    assert_eq!(scene.animations().len(), 2);
    let s = settings(None);
    scene.prepare(&s, Path::new(".")).expect("prepare");
    let half = (0.8f32 / 2.0).tan();
    for frame in [0u32, 6, 12, 18, 24] {
        scene.set_frame(&s, frame).expect("frame");
        let t = frame as f32 / 24.0;
        // The square's centre relative to the camera: x from −1 to 1, y from 0 down to −0.5, z −5.
        let (x, y) = (-1.0 + 2.0 * t, -0.5 * t);
        let u = (x / (5.0 * half) + 1.0) * 0.5 * SIZE as f32;
        let v = (1.0 - y / (5.0 * half)) * 0.5 * SIZE as f32;
        let (cx, cy, _) = centroid(&scene, &s);
        assert!(
            (cx - u).abs() < 0.25 && (cy - v).abs() < 0.25,
            "frame {frame}: centroid ({cx}, {cy}), expected ({u}, {v})"
        );
        // The light set follows the emitter (NEE lights the floor from where the square is).
        let lights_x: f32 = scene.mesh.positions[0..4].iter().map(|p| p.x).sum::<f32>() / 4.0;
        assert!((lights_x - x).abs() < 1e-5, "frame {frame}: emitter at {lights_x}, expected {x}");
    }
    // One animation alone: only the square moves, the camera stays at y = 0.
    let s = settings(Some("move"));
    scene.set_frame(&s, 24).expect("frame");
    let (cx, cy, _) = centroid(&scene, &s);
    let u = (1.0 / (5.0 * half) + 1.0) * 0.5 * SIZE as f32;
    assert!((cx - u).abs() < 0.25 && (cy - SIZE as f32 / 2.0).abs() < 0.25, "({cx}, {cy})");
    let e = scene.set_frame(&settings(Some("nope")), 1).expect_err("no such animation");
    assert!(e.to_string().contains("nope") && e.to_string().contains("move"), "{e}");
}

#[test]
fn a_frame_renders_the_same_whatever_was_posed_before() {
    let s = RenderSettings { max_depth: 3, ..settings(None) };
    let mut a = load(&moving_scene("LINEAR"));
    a.prepare(&s, Path::new(".")).expect("prepare");
    a.set_frame(&s, 3).expect("frame");
    let fresh = centroid(&a, &s).2;
    let mut b = load(&moving_scene("LINEAR"));
    b.prepare(&s, Path::new(".")).expect("prepare");
    for f in [20, 1, 7] {
        b.set_frame(&s, f).expect("frame");
    }
    b.set_frame(&s, 3).expect("frame");
    let again = centroid(&b, &s).2;
    assert!(fresh == again, "frame 3 differs after other frames were posed");
}

#[test]
fn step_interpolation_holds_the_key() {
    let mut scene = load(&moving_scene("STEP"));
    let s = settings(Some("move"));
    scene.prepare(&s, Path::new(".")).expect("prepare");
    scene.set_frame(&s, 23).expect("frame");
    let x: f32 = scene.mesh.positions[0..4].iter().map(|p| p.x).sum::<f32>() / 4.0;
    assert!((x + 1.0).abs() < 1e-6, "STEP holds the first key until t = 1: {x}");
    scene.set_frame(&s, 24).expect("frame");
    let x: f32 = scene.mesh.positions[0..4].iter().map(|p| p.x).sum::<f32>() / 4.0;
    assert!((x - 1.0).abs() < 1e-6, "{x}");
}

/// A two-bone strip (joints at y = 0 and y = 1) with one morph target, posed by hand-computed
/// formulas: the bend of joint 1 by 90° about z and the target's weight 0.5.
fn rig() -> String {
    let mut bin: Vec<u8> = Vec::new();
    let f = |bin: &mut Vec<u8>, v: &[f32]| {
        for x in v {
            bin.extend_from_slice(&x.to_le_bytes());
        }
    };
    // 6 vertices: pairs at y = 0, 1, 2 (x = ±0.1).
    f(&mut bin, &[-0.1, 0.0, 0.0, 0.1, 0.0, 0.0, -0.1, 1.0, 0.0, 0.1, 1.0, 0.0, -0.1, 2.0, 0.0, 0.1, 2.0, 0.0]); // 0..72
                                                                                                                 // joints (u8 × 4 per vertex): bottom → joint 0, middle → half/half, top → joint 1.
    for j in [[0u8, 1, 0, 0]; 6] {
        bin.extend_from_slice(&j);
    } // 72..96
    let w: [[f32; 4]; 6] = [
        [1.0, 0.0, 0.0, 0.0],
        [1.0, 0.0, 0.0, 0.0],
        [0.5, 0.5, 0.0, 0.0],
        [0.5, 0.5, 0.0, 0.0],
        [0.0, 1.0, 0.0, 0.0],
        [0.0, 1.0, 0.0, 0.0],
    ];
    for x in w {
        f(&mut bin, &x);
    } // 96..192
      // inverse bind matrices: joint 0 at origin (identity), joint 1 at y = 1 (translate −1).
    f(&mut bin, &[1., 0., 0., 0., 0., 1., 0., 0., 0., 0., 1., 0., 0., 0., 0., 1.]);
    f(&mut bin, &[1., 0., 0., 0., 0., 1., 0., 0., 0., 0., 1., 0., 0., -1., 0., 1.]); // 192..320
                                                                                     // morph target: every vertex +0.2 in z.
    f(&mut bin, &[0.0, 0.0, 0.2].repeat(6)); // 320..392
    for i in [0u16, 1, 2, 1, 3, 2, 2, 3, 4, 3, 5, 4] {
        bin.extend_from_slice(&i.to_le_bytes());
    } // 392..416
      // animation: times [0, 1]; rotation of joint 1: identity → 90° about z; weights 0 → 1.
    f(&mut bin, &[0.0, 1.0]); // 416..424
    let s = std::f32::consts::FRAC_1_SQRT_2;
    f(&mut bin, &[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, s, s]); // 424..456
    f(&mut bin, &[0.0, 1.0]); // 456..464
    let uri =
        format!("data:application/octet-stream;base64,{}", base64::engine::general_purpose::STANDARD.encode(&bin));
    format!(
        r#"{{"asset":{{"version":"2.0"}},"scene":0,"scenes":[{{"nodes":[0,1]}}],
        "nodes":[{{"mesh":0,"skin":0}},{{"children":[2]}},{{"translation":[0,1,0]}}],
        "skins":[{{"joints":[1,2],"inverseBindMatrices":4}}],
        "meshes":[{{"primitives":[{{"attributes":{{"POSITION":0,"JOINTS_0":1,"WEIGHTS_0":2}},"indices":5,
                  "targets":[{{"POSITION":3}}]}}],"weights":[0]}}],
        "animations":[{{"channels":[{{"sampler":0,"target":{{"node":2,"path":"rotation"}}}},{{"sampler":1,"target":{{"node":0,"path":"weights"}}}}],
                        "samplers":[{{"input":6,"output":7}},{{"input":6,"output":8}}]}}],
        "accessors":[{{"bufferView":0,"componentType":5126,"count":6,"type":"VEC3","min":[-0.1,0,0],"max":[0.1,2,0]}},
                     {{"bufferView":1,"componentType":5121,"count":6,"type":"VEC4"}},
                     {{"bufferView":2,"componentType":5126,"count":6,"type":"VEC4"}},
                     {{"bufferView":3,"componentType":5126,"count":6,"type":"VEC3","min":[0,0,0.2],"max":[0,0,0.2]}},
                     {{"bufferView":4,"componentType":5126,"count":2,"type":"MAT4"}},
                     {{"bufferView":5,"componentType":5123,"count":12,"type":"SCALAR"}},
                     {{"bufferView":6,"componentType":5126,"count":2,"type":"SCALAR","min":[0],"max":[1]}},
                     {{"bufferView":7,"componentType":5126,"count":2,"type":"VEC4"}},
                     {{"bufferView":8,"componentType":5126,"count":2,"type":"SCALAR"}}],
        "bufferViews":[{{"buffer":0,"byteOffset":0,"byteLength":72}},{{"buffer":0,"byteOffset":72,"byteLength":24}},
                       {{"buffer":0,"byteOffset":96,"byteLength":96}},{{"buffer":0,"byteOffset":320,"byteLength":72}},
                       {{"buffer":0,"byteOffset":192,"byteLength":128}},{{"buffer":0,"byteOffset":392,"byteLength":24}},
                       {{"buffer":0,"byteOffset":416,"byteLength":8}},{{"buffer":0,"byteOffset":424,"byteLength":32}},
                       {{"buffer":0,"byteOffset":456,"byteLength":8}}],
        "buffers":[{{"byteLength":464,"uri":"{uri}"}}]}}"#
    )
}

#[test]
fn skinning_and_morph_targets_follow_the_gltf_formulas() {
    let mut scene = load(&rig());
    let s = settings(None);
    scene.prepare(&s, Path::new(".")).expect("prepare");
    for frame in [0u32, 12, 24] {
        scene.set_frame(&s, frame).expect("frame");
        let t = frame as f32 / 24.0;
        // Joint 1's rotation: slerp from identity to 90° about z, i.e. angle t·π/2; weight t.
        let r = glam::Quat::from_rotation_z(t * std::f32::consts::FRAC_PI_2);
        let joint1 = glam::Mat4::from_rotation_translation(r, Vec3::new(0.0, 1.0, 0.0));
        let m1 = joint1 * glam::Mat4::from_translation(Vec3::new(0.0, -1.0, 0.0));
        let rest = [(-0.1, 0.0), (0.1, 0.0), (-0.1, 1.0), (0.1, 1.0), (-0.1, 2.0), (0.1, 2.0)];
        for (i, &(x, y)) in rest.iter().enumerate() {
            let p = Vec3::new(x, y, 0.2 * t);
            let w1 = [0.0, 0.0, 0.5, 0.5, 1.0, 1.0][i];
            let m = glam::Mat4::IDENTITY * (1.0 - w1) + m1 * w1;
            let expect = m.transform_point3(p);
            let got = scene.mesh.positions[i];
            assert!((got - expect).length() < 1e-5, "frame {frame} vertex {i}: {got:?}, expected {expect:?}");
        }
    }
}

/// Skinning and morph targets against Blender: `scenes/animation/rig.glb` (a bar on a two-bone
/// armature with a shape key, both animated, made and exported by Blender 4.5) posed at frames 1,
/// 12 and 24 must put its vertices where Blender puts them after importing the same file
/// (`rig_pose.json`, both written by `make_rig.py`). Vertex order may differ between the two, so
/// each vertex set must lie within 1e-4 of the other (nearest neighbours both ways).
#[test]
fn a_blender_rig_poses_as_blender_poses_it() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/animation");
    let mut scene = renderer::gltf_loader::load(&root.join("rig.glb")).expect("rig.glb");
    let reference: serde_json::Value =
        serde_json::from_slice(&std::fs::read(root.join("rig_pose.json")).expect("rig_pose.json")).expect("json");
    let s = RenderSettings { width: 8, height: 8, ..RenderSettings::default() };
    scene.prepare(&s, Path::new(".")).expect("prepare");
    // Its faces are flat at rest, but skinning bends them: each keeps its vertex normals
    // (`Mesh::drop_flat_normals` is for rigid geometry only).
    let normals = renderer::mesh::flags::NORMALS;
    assert!(scene.mesh.triangles.iter().all(|t| t.flags & normals != 0), "the rig's vertex normals are kept");
    let mut moved = 0.0f32;
    for frame in [1u32, 12, 24] {
        scene.set_frame(&s, frame).expect("frame");
        let ours: Vec<Vec3> = scene.mesh.positions.clone();
        let theirs: Vec<Vec3> = reference["frames"][frame.to_string()]
            .as_array()
            .expect("frame")
            .iter()
            .map(|p| {
                Vec3::new(p[0].as_f64().unwrap() as f32, p[1].as_f64().unwrap() as f32, p[2].as_f64().unwrap() as f32)
            })
            .collect();
        let nearest = |p: Vec3, set: &[Vec3]| set.iter().map(|q| (*q - p).length()).fold(f32::INFINITY, f32::min);
        let worst_a = theirs.iter().map(|p| nearest(*p, &ours)).fold(0.0f32, f32::max);
        let worst_b = ours.iter().map(|p| nearest(*p, &theirs)).fold(0.0f32, f32::max);
        println!("frame {frame}: worst distance Blender→Tessera {worst_a:.2e}, Tessera→Blender {worst_b:.2e}");
        if let Some(p) = theirs.iter().max_by(|a, b| nearest(**a, &ours).total_cmp(&nearest(**b, &ours))) {
            let q = ours.iter().min_by(|a, b| (**a - *p).length().total_cmp(&(**b - *p).length()));
            println!("  worst: Blender {p:?}, nearest Tessera {q:?}");
        }
        assert!(worst_a < 1e-4 && worst_b < 1e-4, "frame {frame}: {worst_a} / {worst_b}");
        // The pose really changes (the top of the bar swings from y ≈ 2 down towards z).
        moved = moved.max(ours.iter().map(|p| p.z.abs()).fold(0.0, f32::max));
    }
    assert!(moved > 0.5, "the rig did not move: {moved}");
}
