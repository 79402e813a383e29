//! Instancing: a mesh placed by several nodes, or by EXT_mesh_gpu_instancing, is stored once and
//! traced through a two-level BVH. The same placements written as separate meshes (flattened into
//! world space) must give the same hits and the same image.

use base64::Engine;
use renderer::film::Rect;
use renderer::gltf_loader::load_from_bytes;
use renderer::math::Vec3;
use renderer::{render_tile, IntegratorKind, RenderSettings};
use std::path::Path;

/// Three placements (translation, rotation quaternion, scale), one of them mirroring.
const PLACEMENTS: [([f32; 3], [f32; 4], [f32; 3]); 3] = [
    ([-1.5, 0.5, 0.0], [0.0, 0.0, 0.0, 1.0], [1.0, 1.0, 1.0]),
    ([0.0, 0.7, -0.5], [0.2, 0.3, 0.1, 0.927_361_85], [0.8, 1.2, 0.8]),
    ([1.6, 0.4, 0.3], [0.0, 0.382_683_43, 0.0, 0.923_879_5], [-0.7, 0.7, 0.7]),
];

/// A cube (8 vertices, 12 triangles) placed three times, a floor and an emitter. `mode`: "nodes"
/// (one mesh, three nodes), "gpu" (one node with EXT_mesh_gpu_instancing), "flat" (three meshes).
fn scene_json(mode: &str) -> String {
    let mut bin: Vec<u8> = Vec::new();
    let cube: Vec<[f32; 3]> = (0..8)
        .map(|i| {
            [
                if i & 1 != 0 { 0.5 } else { -0.5 },
                if i & 2 != 0 { 0.5 } else { -0.5 },
                if i & 4 != 0 { 0.5 } else { -0.5 },
            ]
        })
        .collect();
    let quad = [[-5.0f32, 0.0, -5.0], [5.0, 0.0, -5.0], [5.0, 0.0, 5.0], [-5.0, 0.0, 5.0]];
    for p in cube.iter().chain(quad.iter()) {
        for c in p {
            bin.extend_from_slice(&c.to_le_bytes());
        }
    }
    let cube_idx: [u32; 36] =
        [0, 2, 1, 1, 2, 3, 4, 5, 6, 5, 7, 6, 0, 1, 4, 1, 5, 4, 2, 6, 3, 3, 6, 7, 0, 4, 2, 2, 4, 6, 1, 3, 5, 3, 7, 5];
    let quad_idx: [u32; 6] = [0, 2, 1, 0, 3, 2];
    for i in cube_idx.iter().chain(quad_idx.iter()) {
        bin.extend_from_slice(&i.to_le_bytes());
    }
    // Instance TRS accessors for EXT_mesh_gpu_instancing.
    let trs_at = bin.len();
    for (t, _, _) in PLACEMENTS {
        for c in t {
            bin.extend_from_slice(&c.to_le_bytes());
        }
    }
    for (_, r, _) in PLACEMENTS {
        for c in r {
            bin.extend_from_slice(&c.to_le_bytes());
        }
    }
    for (_, _, s) in PLACEMENTS {
        for c in s {
            bin.extend_from_slice(&c.to_le_bytes());
        }
    }
    let uri =
        format!("data:application/octet-stream;base64,{}", base64::engine::general_purpose::STANDARD.encode(&bin));
    let trs =
        |(t, r, s): ([f32; 3], [f32; 4], [f32; 3])| format!(r#""translation":{t:?},"rotation":{r:?},"scale":{s:?}"#);
    let (meshes, nodes, ext) = match mode {
        "nodes" => (
            1,
            PLACEMENTS.iter().map(|&p| format!(r#"{{"mesh":0,{}}}"#, trs(p))).collect::<Vec<_>>(),
            "",
        ),
        "gpu" => (
            1,
            vec![r#"{"mesh":0,"extensions":{"EXT_mesh_gpu_instancing":{"attributes":{"TRANSLATION":3,"ROTATION":4,"SCALE":5}}}}"#.to_string()],
            r#","extensionsUsed":["EXT_mesh_gpu_instancing"],"extensionsRequired":["EXT_mesh_gpu_instancing"]"#,
        ),
        _ => (3, PLACEMENTS.iter().enumerate().map(|(i, &p)| format!(r#"{{"mesh":{i},{}}}"#, trs(p))).collect(), ""),
    };
    let cube_mesh = r#"{"primitives":[{"attributes":{"POSITION":0},"indices":1,"material":0}]}"#;
    let mut mesh_list: Vec<String> = (0..meshes).map(|_| cube_mesh.to_string()).collect();
    mesh_list.push(r#"{"primitives":[{"attributes":{"POSITION":2},"indices":6,"material":1}]}"#.into());
    mesh_list.push(r#"{"primitives":[{"attributes":{"POSITION":2},"indices":6,"material":2}]}"#.into());
    let floor = mesh_list.len() - 2;
    let mut node_list = nodes;
    let n0 = node_list.len();
    node_list.push(format!(r#"{{"mesh":{floor}}}"#));
    node_list.push(format!(r#"{{"mesh":{},"translation":[0,6,0],"rotation":[1,0,0,0]}}"#, floor + 1));
    node_list.push(r#"{"camera":0,"translation":[0,3,8],"rotation":[-0.17364818,0,0,0.98480775]}"#.into());
    let roots: Vec<usize> = (0..node_list.len()).collect();
    let _ = n0;
    format!(
        r#"{{"asset":{{"version":"2.0"}}{ext},"scene":0,"scenes":[{{"nodes":{roots:?}}}],"nodes":[{}],
        "meshes":[{}],
        "cameras":[{{"type":"perspective","perspective":{{"yfov":0.6,"znear":0.1}}}}],
        "materials":[{{"pbrMetallicRoughness":{{"baseColorFactor":[0.8,0.5,0.3,1],"metallicFactor":0,"roughnessFactor":0.6}}}},
                     {{"pbrMetallicRoughness":{{"baseColorFactor":[0.6,0.6,0.6,1],"metallicFactor":0}}}},
                     {{"emissiveFactor":[1,1,1],"pbrMetallicRoughness":{{"baseColorFactor":[0,0,0,1]}}}}],
        "accessors":[{{"bufferView":0,"componentType":5126,"count":8,"type":"VEC3","min":[-0.5,-0.5,-0.5],"max":[0.5,0.5,0.5]}},
                     {{"bufferView":1,"componentType":5125,"count":36,"type":"SCALAR"}},
                     {{"bufferView":2,"componentType":5126,"count":4,"type":"VEC3","min":[-5,0,-5],"max":[5,0,5]}},
                     {{"bufferView":3,"componentType":5126,"count":3,"type":"VEC3"}},
                     {{"bufferView":4,"componentType":5126,"count":3,"type":"VEC4"}},
                     {{"bufferView":5,"componentType":5126,"count":3,"type":"VEC3"}},
                     {{"bufferView":6,"componentType":5125,"count":6,"type":"SCALAR"}}],
        "bufferViews":[{{"buffer":0,"byteOffset":0,"byteLength":96}},{{"buffer":0,"byteOffset":144,"byteLength":144}},
                       {{"buffer":0,"byteOffset":96,"byteLength":48}},
                       {{"buffer":0,"byteOffset":{trs_at},"byteLength":36}},{{"buffer":0,"byteOffset":{},"byteLength":48}},
                       {{"buffer":0,"byteOffset":{},"byteLength":36}},{{"buffer":0,"byteOffset":288,"byteLength":24}}],
        "buffers":[{{"byteLength":{},"uri":"{uri}"}}]}}"#,
        node_list.join(","),
        mesh_list.join(","),
        trs_at + 36,
        trs_at + 84,
        bin.len()
    )
}

fn load(mode: &str) -> renderer::Scene {
    load_from_bytes(Path::new("instancing.gltf"), scene_json(mode).as_bytes()).unwrap_or_else(|e| panic!("{mode}: {e}"))
}

#[test]
fn instances_hit_what_flattened_copies_hit() {
    let flat = load("flat");
    assert!(flat.mesh.instances.is_empty());
    assert_eq!(flat.mesh.triangles.len(), 3 * 12 + 4);
    for mode in ["nodes", "gpu"] {
        let inst = load(mode);
        assert_eq!((inst.mesh.instances.len(), inst.mesh.prototypes.len()), (3, 1), "{mode}");
        // The cube is stored once: 12 + floor 2 + emitter 2 (the emitter stays flattened).
        assert_eq!(inst.mesh.triangles.len(), 12 + 4, "{mode}");
        assert!((inst.bounds.0 - flat.bounds.0).abs().max_element() < 1e-5, "{mode} bounds");
        assert!((inst.bounds.1 - flat.bounds.1).abs().max_element() < 1e-5, "{mode} bounds");
        // A fan of rays from several origins: same distance, same material, same world point and
        // normal; and the same answer to occlusion queries.
        let (mut hits, mut checked) = (0, 0);
        for k in 0..4000u32 {
            let a = k as f32 * 0.618_034;
            let b = k as f32 * 0.414_213_5;
            let d = Vec3::new(
                (a * std::f32::consts::TAU).cos() * (b.fract() * 0.9 + 0.1),
                -(a.fract() * 0.8 + 0.1),
                (a * std::f32::consts::TAU).sin(),
            )
            .normalize();
            let o = Vec3::new((k % 7) as f32 * 0.5 - 1.5, 3.0, (k % 5) as f32 * 0.6 - 1.2);
            let (h1, h2) = (flat.intersect(o, d, f32::INFINITY), inst.intersect(o, d, f32::INFINITY));
            checked += 1;
            match (h1, h2) {
                (None, None) => {}
                (Some(a), Some(b)) => {
                    hits += 1;
                    assert!((a.t - b.t).abs() <= 1e-4 * a.t.max(1.0), "{mode} ray {k}: t {} vs {}", a.t, b.t);
                    let (pa, pb) = (flat.surface_point(&a), inst.surface_point(&b));
                    assert!((pa.p - pb.p).length() < 1e-4, "{mode} ray {k}: {:?} vs {:?}", pa.p, pb.p);
                    assert!(pa.ng.dot(pb.ng) > 0.9999, "{mode} ray {k}: normal {:?} vs {:?}", pa.ng, pb.ng);
                    let ma = flat.mesh.triangles[a.triangle as usize].material;
                    let mb = inst.mesh.triangles[b.triangle as usize].material;
                    assert_eq!(ma, mb, "{mode} ray {k}: material");
                    let short = a.t * 0.999;
                    assert_eq!(flat.occluded(o, d, short), inst.occluded(o, d, short), "{mode} ray {k}");
                    assert!(inst.occluded(o, d, a.t * 1.001), "{mode} ray {k}: occlusion past the hit");
                }
                (a, b) => panic!("{mode} ray {k}: flat {a:?}, instanced {b:?}"),
            }
        }
        assert!(hits > checked / 2, "{mode}: only {hits} of {checked} rays hit");
    }
}

#[test]
fn instanced_and_flattened_scenes_render_the_same_image() {
    let s =
        RenderSettings { width: 48, height: 32, spp: 16, integrator: IntegratorKind::Mis, ..RenderSettings::default() };
    let rect = Rect { x0: 0, y0: 0, width: 48, height: 32 };
    let flat = render_tile(&load("flat"), &s, rect, 0..s.spp);
    for mode in ["nodes", "gpu"] {
        let inst = render_tile(&load(mode), &s, rect, 0..s.spp);
        let (mut same, mut sum_a, mut sum_b) = (0usize, 0.0f64, 0.0f64);
        for i in 0..rect.pixels() {
            let (a, b) = (flat.mean(i), inst.mean(i));
            sum_a += a.iter().sum::<f32>() as f64;
            sum_b += b.iter().sum::<f32>() as f64;
            if a.iter().zip(b.iter()).all(|(x, y)| (x - y).abs() <= 1e-3 * x.abs().max(1e-3)) {
                same += 1;
            }
        }
        // Same samples, same geometry: identical but for paths that a last-ulp difference in a
        // hit point sends elsewhere.
        assert!(same as f64 >= 0.9 * rect.pixels() as f64, "{mode}: only {same} of {} pixels agree", rect.pixels());
        println!("{mode}: {same} of {} pixels agree; image sums {sum_a:.3} vs {sum_b:.3}", rect.pixels());
        assert!(sum_a > 0.05 * rect.pixels() as f64, "the scene is lit ({sum_a})");
        assert!((sum_a / sum_b - 1.0).abs() < 0.01, "{mode}: image sums {sum_a} vs {sum_b}");
    }
}

#[test]
fn bad_gpu_instancing_is_an_error_naming_it() {
    let gpu = scene_json("gpu");
    for (from, to, needle) in [
        (r#""SCALE":5"#, r#""SCALE":9"#, "accessor 9 does not exist"),
        (r#""TRANSLATION":3"#, r#""TRANSLATION":0"#, "attribute counts differ"),
        (r#""attributes":{"TRANSLATION":3,"ROTATION":4,"SCALE":5}"#, r#""attributes":{}"#, "no attributes"),
    ] {
        let json = gpu.replacen(from, to, 1);
        assert_ne!(json, gpu, "{from} not found");
        match load_from_bytes(Path::new("instancing.gltf"), json.as_bytes()) {
            Ok(_) => panic!("{to}: loaded"),
            Err(e) => {
                assert!(e.to_string().contains(needle) && e.to_string().contains("EXT_mesh_gpu_instancing"), "{e}")
            }
        }
    }
}
