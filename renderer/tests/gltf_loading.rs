//! glTF loading: the sample models load, and every kind of bad input gets an error naming the file
//! and the problem (never a panic).

use base64::Engine;
use renderer::gltf_loader::{load, load_from_bytes};
use renderer::mesh::flags;
use renderer::SceneError;
use std::path::{Path, PathBuf};

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// A minimal glTF with one triangle (positions only, optional indices), a material, and `extra`
/// JSON merged into the top level; `nodes` replaces the default single node.
fn gltf_json(nodes: &str, extra: &str, indices: bool) -> String {
    gltf_json_with([[0.0f32, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], nodes, extra, indices)
}

/// As `gltf_json`, with the triangle's three vertices given.
fn gltf_json_with(vertices: [[f32; 3]; 3], nodes: &str, extra: &str, indices: bool) -> String {
    let mut bin = Vec::new();
    for v in vertices {
        for c in v {
            bin.extend_from_slice(&c.to_le_bytes());
        }
    }
    for i in [0u32, 1, 2] {
        bin.extend_from_slice(&i.to_le_bytes());
    }
    let uri =
        format!("data:application/octet-stream;base64,{}", base64::engine::general_purpose::STANDARD.encode(&bin));
    let idx = if indices { r#","indices":1"# } else { "" };
    format!(
        r#"{{"asset":{{"version":"2.0"}},"scene":0,"scenes":[{{"nodes":[0]}}],"nodes":{nodes},
        "meshes":[{{"primitives":[{{"attributes":{{"POSITION":0}}{idx},"material":0}}]}}],
        "materials":[{{"emissiveFactor":[1,1,1]}}],
        "accessors":[{{"bufferView":0,"componentType":5126,"count":3,"type":"VEC3","min":[0,0,0],"max":[1,1,0]}},
                     {{"bufferView":1,"componentType":5125,"count":3,"type":"SCALAR"}}],
        "bufferViews":[{{"buffer":0,"byteOffset":0,"byteLength":36}},{{"buffer":0,"byteOffset":36,"byteLength":12}}],
        "buffers":[{{"byteLength":48,"uri":"{uri}"}}]{extra}}}"#
    )
}

fn load_str(json: &str) -> Result<renderer::Scene, SceneError> {
    load_from_bytes(Path::new("test.gltf"), json.as_bytes())
}

#[test]
fn sample_models_load() {
    // The binary and the JSON form of the Cornell box give the same scene.
    let glb = load(&root().join("scenes/cornell/cornell.glb")).expect("cornell.glb");
    let gltf = load(&root().join("scenes/cornell/cornell.gltf")).expect("cornell.gltf");
    assert_eq!(glb.mesh.positions, gltf.mesh.positions);
    assert_eq!(glb.cameras.len(), 1);
    // Its walls carry a NORMAL per corner, all flat: the loader leaves them to the winding normal
    // (`Mesh::drop_flat_normals`), while the helmet's smooth ones stay.
    assert!(gltf.mesh.triangles.iter().all(|t| t.flags & flags::NORMALS == 0), "cornell's flat normals dropped");
    let h = load(&root().join("scenes/khronos/DamagedHelmet/DamagedHelmet.gltf")).expect("DamagedHelmet");
    assert_eq!(h.mesh.triangles.len(), 46_356 / 3);
    assert!(!h.lights.is_empty(), "the helmet's emissive texture makes lights");
    // Normal map without TANGENT: tangents were generated.
    assert!(h.mesh.triangles.iter().all(|t| t.flags & flags::TANGENTS != 0));
    assert!(h.mesh.triangles.iter().all(|t| t.flags & flags::NORMALS != 0));
    assert!(h.mesh.tangents.iter().any(|t| t.truncate().length() > 0.5));
}

#[test]
fn node_hierarchy_and_trs_are_applied() {
    // Parent translates by (10,0,0) and scales ×2; child rotates 90° about Z (quaternion) — the
    // triangle's (1,0,0) vertex ends at 10 + 2·(0,1,0).
    let nodes = r#"[{"translation":[10,0,0],"scale":[2,2,2],"children":[1]},{"rotation":[0,0,0.70710678,0.70710678],"mesh":0}]"#;
    let s = load_str(&gltf_json(nodes, "", true)).unwrap();
    let p = s.mesh.positions[1];
    assert!((p - renderer::math::Vec3::new(10.0, 2.0, 0.0)).length() < 1e-5, "{p:?}");
    // Matrix form, and a mirroring transform flips the winding so the front stays the front.
    let nodes = r#"[{"matrix":[-1,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1],"mesh":0}]"#;
    let s = load_str(&gltf_json(nodes, "", true)).unwrap();
    let sp = s.mesh.surface_point(0, 0.2, 0.2);
    assert!(sp.ng.z > 0.99, "mirrored triangle keeps +Z front: {:?}", sp.ng);
}

#[test]
fn non_indexed_and_normal_less_primitives_are_flat_shaded() {
    let s = load_str(&gltf_json(r#"[{"mesh":0}]"#, "", false)).unwrap();
    assert_eq!(s.mesh.triangles.len(), 1);
    assert_eq!(s.mesh.triangles[0].flags & flags::NORMALS, 0);
    assert_eq!(s.mesh.surface_point(0, 0.3, 0.3).ns, s.mesh.surface_point(0, 0.3, 0.3).ng);
}

fn expect_err(json: &str, needle: &str) {
    match load_str(json) {
        Ok(_) => panic!("expected an error containing '{needle}'"),
        Err(e) => {
            let msg = e.to_string();
            assert!(msg.contains("test.gltf"), "error must name the file: {msg}");
            assert!(msg.contains(needle), "error '{msg}' should mention '{needle}'");
        }
    }
}

#[test]
fn unsupported_features_are_named() {
    let base = gltf_json(r#"[{"mesh":0}]"#, "", true);
    let with = |k: &str| base.replacen(r#""asset":"#, &format!(r#"{k},"asset":"#), 1);
    expect_err(
        &with(r#""extensionsUsed":["KHR_texture_basisu"],"extensionsRequired":["KHR_texture_basisu"]"#),
        "KHR_texture_basisu",
    );
    // Refused when the file requires them (used-only ones warn: see optional_extensions_warn_...).
    let required = |e: &str| with(&format!(r#""extensionsUsed":["{e}"],"extensionsRequired":["{e}"]"#));
    expect_err(&required("KHR_materials_iridescence"), "KHR_materials_iridescence");
    expect_err(&required("KHR_materials_anisotropy"), "KHR_materials_anisotropy");
}

/// KHR_draco_mesh_compression is decoded (draco-core): the Khronos Box and BoxTextured samples,
/// both Draco-compressed, give the cube they encode — 12 triangles within ±0.5, vertex normals
/// agreeing with the faces' winding, UVs spanning the declared [0, 6] × [0, 1] — and a damaged stream is an error naming it.
#[test]
fn draco_compressed_models_decode() {
    for f in ["Box.glb", "BoxTextured.glb"] {
        let s = load(&root().join("scenes/khronos").join(f)).unwrap_or_else(|e| panic!("{f}: {e}"));
        assert_eq!(s.mesh.triangles.len(), 12, "{f}");
        for p in &s.mesh.positions {
            assert!(p.abs().max_element() <= 0.5 + 1e-3, "{f}: {p:?}");
        }
        let (lo, hi) = s.bounds;
        assert!((hi - lo - renderer::math::Vec3::ONE).abs().max_element() < 1e-3, "{f}: {lo:?} {hi:?}");
        for t in 0..12 {
            let sp = s.mesh.surface_point(t, 0.3, 0.3);
            assert!(sp.ns.dot(sp.ng) > 0.99, "{f} triangle {t}: normal {:?} vs face {:?}", sp.ns, sp.ng);
        }
        if f == "BoxTextured.glb" {
            assert!(s.mesh.triangles.iter().all(|t| t.flags & flags::UVS != 0));
            // Within the accessor's declared min [0, 0] and max [6, 1], and spanning them.
            let (mut lo, mut hi) =
                (renderer::math::Vec2::splat(f32::INFINITY), renderer::math::Vec2::splat(-f32::INFINITY));
            for uv in &s.mesh.uvs {
                (lo, hi) = (lo.min(*uv), hi.max(*uv));
            }
            assert!((lo - renderer::math::Vec2::ZERO).abs().max_element() < 2e-3, "{lo:?}");
            assert!((hi - renderer::math::Vec2::new(6.0, 1.0)).abs().max_element() < 2e-3, "{hi:?}");
            assert_eq!(s.textures.len(), 1);
        }
    }
    // A damaged stream: overwrite the middle of the GLB's binary chunk (the Draco data).
    let mut bytes = std::fs::read(root().join("scenes/khronos/Box.glb")).expect("Box.glb");
    let json_len = u32::from_le_bytes(bytes[12..16].try_into().unwrap()) as usize;
    let bin = 20 + json_len + 8;
    for b in &mut bytes[bin + 4..bin + 40] {
        *b = 0xA5;
    }
    match load_from_bytes(Path::new("Box.glb"), &bytes) {
        Ok(s) => panic!("a damaged Draco stream loaded ({} triangles)", s.mesh.triangles.len()),
        Err(e) => assert!(e.to_string().contains("KHR_draco_mesh_compression"), "{e}"),
    }
}

#[test]
fn broken_files_get_clear_errors() {
    // Garbage and truncated binaries.
    expect_err("this is not json", "not a valid glTF");
    let glb = std::fs::read(root().join("scenes/cornell/cornell.glb")).unwrap();
    let e = load_from_bytes(Path::new("test.gltf"), &glb[..glb.len() / 2]).err().expect("truncated glb fails");
    assert!(e.to_string().contains("test.gltf"), "{e}");
    let e = load_from_bytes(Path::new("test.gltf"), &glb[..20]).err().expect("header-only glb fails");
    assert!(e.to_string().contains("test.gltf"), "{e}");
    // Accessor running past its buffer view.
    let base = gltf_json(r#"[{"mesh":0}]"#, "", true);
    expect_err(&base.replacen(r#""count":3,"type":"VEC3""#, r#""count":300,"type":"VEC3""#, 1), "run past");
    // Index out of range.
    let base = gltf_json(r#"[{"mesh":0}]"#, "", true);
    expect_err(
        &base.replace(r#""count":3,"type":"SCALAR""#, r#""count":3,"type":"SCALAR","byteOffset":0"#).replace(
            r#"{"bufferView":0,"componentType":5126,"count":3"#,
            r#"{"bufferView":0,"componentType":5126,"count":2"#,
        ),
        "out of range for 2 vertices",
    );
    // Missing file.
    let e = load(Path::new("/nonexistent/scene.glb")).err().unwrap();
    assert!(e.to_string().contains("/nonexistent/scene.glb"), "{e}");
}

#[test]
fn uris_cannot_escape_the_scene_folder() {
    let base = gltf_json(r#"[{"mesh":0}]"#, "", true);
    let start = base.find("data:application").unwrap();
    let end = start + base[start..].find('"').unwrap();
    for uri in [
        "../secret.bin",
        "/etc/passwd",
        "http://example.com/x.bin",
        "sub/../../x.bin",
        "file:///etc/passwd",
        "%2e%2e/x.bin",
    ] {
        let json = format!("{}{}{}", &base[..start], uri, &base[end..]);
        match load_str(&json) {
            Err(SceneError::ForbiddenUri { .. }) => {}
            other => panic!("{uri}: expected ForbiddenUri, got {:?}", other.err()),
        }
    }
}

#[test]
fn cyclic_node_graphs_are_rejected() {
    let nodes = r#"[{"children":[1]},{"children":[0],"mesh":0}]"#;
    assert!(load_str(&gltf_json(nodes, "", true)).is_err());
}

#[test]
fn own_bvh_and_obvhs_agree_on_every_hit() {
    use renderer::accel::{Accel, AccelKind};
    use renderer::math::Vec3;
    use renderer::sampler::{PixelSample, SamplerKind};
    let scene = load(&root().join("scenes/khronos/DamagedHelmet/DamagedHelmet.gltf")).unwrap();
    let (a, b) = (Accel::build_with(&scene.mesh, AccelKind::Obvhs), Accel::build_with(&scene.mesh, AccelKind::Own));
    let (lo, hi) = scene.bounds;
    let mut hits = 0;
    for i in 0..20_000u32 {
        let s = PixelSample::new(SamplerKind::Independent, 1, (0, 0), i);
        let o = lo + (hi - lo) * Vec3::new(s.get_1d(0), s.get_1d(1), s.get_1d(2)) * 1.4 - (hi - lo) * 0.2;
        let d = renderer::math::sample_cosine_hemisphere(s.get_2d(4)) * if s.get_1d(6) < 0.5 { 1.0 } else { -1.0 };
        let d = Vec3::new(d.x, d.z, d.y).normalize();
        let (ha, hb) = (a.intersect(o, d, f32::INFINITY), b.intersect(o, d, f32::INFINITY));
        match (ha, hb) {
            (Some(x), Some(y)) => {
                hits += 1;
                assert!((x.t - y.t).abs() <= 1e-5 * x.t.max(1.0), "ray {i}: t {} vs {}", x.t, y.t);
            }
            (None, None) => {}
            other => panic!("ray {i}: {other:?}"),
        }
        assert_eq!(a.occluded(o, d, 1.0), b.occluded(o, d, 1.0), "ray {i}");
    }
    assert!(hits > 1000, "the test rays must hit the helmet ({hits})");
}

#[test]
fn non_finite_vertices_are_refused_naming_mesh_accessor_and_vertex() {
    for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
        let json = gltf_json_with([[0.0, 0.0, 0.0], [1.0, bad, 0.0], [0.0, 1.0, 0.0]], "[{\"mesh\":0}]", "", true);
        let e = load_str(&json).err().expect("a non-finite vertex must be refused").to_string();
        assert!(e.contains("mesh 0 primitive 0") && e.contains("POSITION accessor 0 vertex 1"), "{e}");
    }
    // Finite in the file, infinite once scaled by the node: refused too.
    let e = load_str(&gltf_json(r#"[{"mesh":0,"translation":[3e38,0,0],"scale":[1e38,1,1]}]"#, "", true))
        .err()
        .expect("overflowing transform must be refused")
        .to_string();
    assert!(e.contains("not finite once placed"), "{e}");
}

/// Findings of `tests/mutation_fuzz.rs`, each of which panicked: references the gltf crate's
/// validation leaves unchecked, and geometry finite but too far out for the BVH builder.
#[test]
fn references_the_gltf_crate_leaves_unchecked_and_far_out_geometry_get_errors() {
    let one = r#"[{"mesh":0}]"#;
    // A primitive's POSITION accessor out of range (the crate's validation hook indexed it).
    expect_err(&gltf_json(one, "", true).replace(r#""POSITION":0"#, r#""POSITION":7"#), "POSITION");
    // Indices out of range.
    expect_err(&gltf_json(one, "", true).replace(r#""indices":1"#, r#""indices":9"#), "indices");
    // An animation channel aimed at a node that does not exist, or at no known property.
    let anim = |node: u32, path: &str| {
        format!(
            r#","animations":[{{"channels":[{{"sampler":0,"target":{{"node":{node},"path":"{path}"}}}}],
            "samplers":[{{"input":1,"output":0}}]}}]"#
        )
    };
    expect_err(&gltf_json(one, &anim(5, "translation"), true), "animations[0].channels[0].target.node");
    expect_err(&gltf_json(one, &anim(0, "MAT4"), true), "animations[0].channels[0].target.path");
    // An image with no source, and one in a buffer view with no MIME type.
    expect_err(&gltf_json(one, r#","images":[{}]"#, true), "images[0].uri");
    expect_err(&gltf_json(one, r#","images":[{"bufferView":0}]"#, true), "images[0].mimeType");
    // A vertex finite but far past any scene (3e38 made the BVH builder index out of bounds).
    let json = gltf_json_with([[0.0, 0.0, 0.0], [1.0, 3e38, 0.0], [0.0, 1.0, 0.0]], one, "", true);
    expect_err(&json, "POSITION accessor 0 vertex 1");
    let e = load_str(&gltf_json(one.replace("0}", r#"0,"translation":[0,2e9,0]}"#).as_str(), "", true))
        .err()
        .expect("a vertex placed past the limit is refused")
        .to_string();
    assert!(e.contains("past ±1e9"), "{e}");
    // The same mesh placed twice (an instanced prototype: it does not emit), once far out:
    // refused by name.
    let dark =
        |nodes: &str| gltf_json(nodes, "", true).replace(r#""emissiveFactor":[1,1,1]"#, r#""emissiveFactor":[0,0,0]"#);
    let twice = r#"[{"mesh":0,"children":[1]},{"mesh":0,"translation":[0,0,5e9]}]"#;
    expect_err(&dark(twice), "an instance of mesh prototype 0 reaches past");
    // Placed twice with no triangles (two indices: no whole triangle): an empty prototype, whose
    // inverted box broke the top-level build. It loads, and renders black.
    let empty = dark(r#"[{"mesh":0,"children":[1]},{"mesh":0,"translation":[0,0,5]}]"#)
        .replace(r#""componentType":5125,"count":3"#, r#""componentType":5125,"count":2"#);
    let scene = load_str(&empty).expect("an empty instanced mesh loads");
    assert_eq!((scene.mesh.instances.len(), scene.mesh.triangles.len()), (2, 0));
    let settings = renderer::RenderSettings { width: 4, height: 4, spp: 1, ..Default::default() };
    let r = renderer::render::render(&scene, &settings, &renderer::render::Counters::default());
    assert!((0..16).all(|i| r.image.mean(i) == [0.0; 3]));
}

/// Issue 12's policy: an unmodelled extension the file *requires* is refused by name; one it only
/// *uses* renders without it and is named in `Scene::warnings` (and from there in the CLI output,
/// the EXR header and the REST job). KHR_texture_transform is modelled (Blender writes it as
/// required for any Mapping node).
#[test]
fn optional_extensions_warn_required_ones_refuse() {
    let used = gltf_json(
        r#"[{"mesh":0}]"#,
        r#","extensionsUsed":["KHR_materials_iridescence","KHR_materials_anisotropy"]"#,
        true,
    );
    let scene = load_str(&used).expect("optional extensions render without them");
    assert_eq!(scene.warnings.len(), 2, "{:?}", scene.warnings);
    assert!(scene.warnings[0].contains("KHR_materials_iridescence"), "{:?}", scene.warnings);
    let required = gltf_json(
        r#"[{"mesh":0}]"#,
        r#","extensionsUsed":["KHR_materials_anisotropy"],"extensionsRequired":["KHR_materials_anisotropy"]"#,
        true,
    );
    let e = load_str(&required).err().expect("a required unmodelled extension is refused").to_string();
    assert!(e.contains("KHR_materials_anisotropy") && e.contains("required"), "{e}");
    let transform = gltf_json(
        r#"[{"mesh":0}]"#,
        r#","extensionsUsed":["KHR_texture_transform"],"extensionsRequired":["KHR_texture_transform"]"#,
        true,
    );
    let scene = load_str(&transform).expect("KHR_texture_transform is modelled");
    assert!(scene.warnings.is_empty());
}

/// A 2×1 RGBA PNG of the two texels `rgba` (left, right).
fn png_2x1(rgba: [u8; 8]) -> Vec<u8> {
    let mut png = Vec::new();
    let img = image::RgbaImage::from_raw(2, 1, rgba.to_vec()).expect("2x1");
    image::DynamicImage::ImageRgba8(img)
        .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
        .expect("png");
    png
}

/// KHR_texture_transform is applied: a 2×1 texture (red | green) read at u = 0.25 shows red; with
/// an offset of 0.5 it shows green; with `texCoord: 1` the second UV set (u = 0.75) is read.
#[test]
fn texture_transform_and_second_uv_set_are_honoured() {
    let png = png_2x1([255, 0, 0, 255, 0, 255, 0, 255]);
    let mut bin = Vec::new();
    for v in [[0.0f32, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]] {
        v.iter().for_each(|c| bin.extend_from_slice(&c.to_le_bytes()));
    }
    for _ in 0..3 {
        [0.25f32, 0.5].iter().for_each(|c| bin.extend_from_slice(&c.to_le_bytes()));
    }
    for _ in 0..3 {
        [0.75f32, 0.5].iter().for_each(|c| bin.extend_from_slice(&c.to_le_bytes()));
    }
    let b64 = |d: &[u8]| base64::engine::general_purpose::STANDARD.encode(d);
    let doc = |texinfo: &str| {
        format!(
            r#"{{"asset":{{"version":"2.0"}},"extensionsUsed":["KHR_texture_transform"],"scene":0,"scenes":[{{"nodes":[0]}}],"nodes":[{{"mesh":0}}],
            "meshes":[{{"primitives":[{{"attributes":{{"POSITION":0,"TEXCOORD_0":1,"TEXCOORD_1":2}},"material":0}}]}}],
            "materials":[{{"emissiveFactor":[1,1,1],"emissiveTexture":{texinfo}}}],
            "textures":[{{"source":0,"sampler":0}}],"samplers":[{{"magFilter":9729,"wrapS":33071,"wrapT":33071}}],
            "images":[{{"uri":"data:image/png;base64,{}"}}],
            "accessors":[{{"bufferView":0,"componentType":5126,"count":3,"type":"VEC3","min":[0,0,0],"max":[1,1,0]}},
                         {{"bufferView":1,"componentType":5126,"count":3,"type":"VEC2"}},
                         {{"bufferView":2,"componentType":5126,"count":3,"type":"VEC2"}}],
            "bufferViews":[{{"buffer":0,"byteOffset":0,"byteLength":36}},{{"buffer":0,"byteOffset":36,"byteLength":24}},{{"buffer":0,"byteOffset":60,"byteLength":24}}],
            "buffers":[{{"byteLength":84,"uri":"data:application/octet-stream;base64,{}"}}]}}"#,
            b64(&png),
            b64(&bin)
        )
    };
    let emission = |texinfo: &str| {
        let scene = load_str(&doc(texinfo)).expect("loads");
        let sp = scene.mesh.surface_point(0, 0.3, 0.3);
        scene.materials[0].emission(&scene.textures, sp.uv)
    };
    let red = emission(r#"{"index":0}"#);
    assert!(red.x > 0.99 && red.y < 0.01, "{red:?}");
    let green = emission(r#"{"index":0,"extensions":{"KHR_texture_transform":{"offset":[0.5,0]}}}"#);
    assert!(green.y > 0.99 && green.x < 0.01, "{green:?}");
    let set1 = emission(r#"{"index":0,"extensions":{"KHR_texture_transform":{"texCoord":1}}}"#);
    assert!(set1.y > 0.99 && set1.x < 0.01, "{set1:?}");
    let plain_set1 = emission(r#"{"index":0,"texCoord":1}"#);
    assert!(plain_set1.y > 0.99, "{plain_set1:?}");
    let rotated =
        emission(r#"{"index":0,"extensions":{"KHR_texture_transform":{"rotation":3.14159265,"offset":[1,1]}}}"#);
    // (0.25, 0.5) rotated by π is (−0.25, −0.5); offset (1, 1) gives (0.75, 0.5): green.
    assert!(rotated.y > 0.99, "{rotated:?}");
}

/// The materials' images are decoded ahead, in parallel: an image read in both colour spaces
/// becomes two textures with the same texels; an undecodable image fails the load with an error
/// naming it when a material reads it, and is not even decoded when only an occlusion texture
/// (ignored on purpose) names it.
#[test]
fn images_are_decoded_for_what_materials_read() {
    let png = png_2x1([255, 0, 0, 255, 0, 255, 0, 128]);
    let b64 = |d: &[u8]| base64::engine::general_purpose::STANDARD.encode(d);
    let images = format!(
        r#","textures":[{{"source":0}},{{"source":1}}],
        "images":[{{"uri":"data:image/png;base64,{}"}},{{"uri":"data:image/png;base64,{}"}}]"#,
        b64(&png),
        b64(b"not an image at all")
    );
    let doc = |material: &str| {
        gltf_json(r#"[{"mesh":0}]"#, &images, true).replace(r#""materials":[{"emissiveFactor":[1,1,1]}]"#, material)
    };
    let both = load_str(&doc(r#""materials":[{"emissiveFactor":[1,1,1],"emissiveTexture":{"index":0},
        "pbrMetallicRoughness":{"metallicRoughnessTexture":{"index":0}},"occlusionTexture":{"index":1}}]"#))
    .expect("the broken image is only an occlusion texture's");
    assert_eq!(both.textures.len(), 2, "image 0 as sRGB and as linear data");
    assert_eq!(both.textures[0].texels, both.textures[1].texels);
    assert_eq!(both.textures[0].texels, vec![[255, 0, 0, 255], [0, 255, 0, 128]]);
    assert_ne!(both.textures[0].srgb, both.textures[1].srgb);
    let e = load_str(&doc(r#""materials":[{"emissiveFactor":[1,1,1],"emissiveTexture":{"index":1}}]"#))
        .err()
        .expect("a material reads the broken image");
    let msg = e.to_string();
    assert!(msg.contains("image 1") && msg.contains("cannot decode"), "{msg}");
}

/// One triangle stored as KHR_mesh_quantization allows (i16 POSITION, not normalized, scaled by its
/// node; u16 normalized TEXCOORD_0; i8 normalized NORMAL) with u8 normalized RGBA COLOR_0, and the
/// material extensions clearcoat, sheen, volume and unlit.
fn quantized_gltf(material_ext: &str, required: &str) -> String {
    let mut bin = Vec::new();
    for v in [[0i16, 0, 0], [100, 0, 0], [0, 100, 0]] {
        for c in v {
            bin.extend_from_slice(&c.to_le_bytes());
        }
        bin.extend_from_slice(&[0, 0]); // padding to the 8-byte stride
    }
    for c in [[255u8, 0, 0, 255], [0, 255, 0, 128], [0, 0, 255, 255]] {
        bin.extend_from_slice(&c);
    }
    for uv in [[0u16, 0], [65535, 0], [0, 32768]] {
        for c in uv {
            bin.extend_from_slice(&c.to_le_bytes());
        }
    }
    for _ in 0..3 {
        bin.extend_from_slice(&[0u8, 0, 127, 0]); // +z, padded to 4 bytes
    }
    let uri =
        format!("data:application/octet-stream;base64,{}", base64::engine::general_purpose::STANDARD.encode(&bin));
    format!(
        r#"{{"asset":{{"version":"2.0"}},"extensionsUsed":["KHR_mesh_quantization","KHR_materials_clearcoat","KHR_materials_sheen","KHR_materials_volume","KHR_materials_unlit"],
        "extensionsRequired":[{required}],
        "scene":0,"scenes":[{{"nodes":[0]}}],"nodes":[{{"mesh":0,"scale":[0.01,0.01,0.01]}}],
        "meshes":[{{"primitives":[{{"attributes":{{"POSITION":0,"COLOR_0":1,"TEXCOORD_0":2,"NORMAL":3}},"material":0}}]}}],
        "materials":[{{"extensions":{material_ext}}}],
        "accessors":[{{"bufferView":0,"componentType":5122,"count":3,"type":"VEC3","min":[0,0,0],"max":[100,100,0]}},
                     {{"bufferView":1,"componentType":5121,"normalized":true,"count":3,"type":"VEC4"}},
                     {{"bufferView":2,"componentType":5123,"normalized":true,"count":3,"type":"VEC2"}},
                     {{"bufferView":3,"componentType":5120,"normalized":true,"count":3,"type":"VEC3"}}],
        "bufferViews":[{{"buffer":0,"byteOffset":0,"byteLength":24,"byteStride":8}},{{"buffer":0,"byteOffset":24,"byteLength":12}},
                       {{"buffer":0,"byteOffset":36,"byteLength":12}},{{"buffer":0,"byteOffset":48,"byteLength":12,"byteStride":4}}],
        "buffers":[{{"byteLength":60,"uri":"{uri}"}}]}}"#
    )
}

#[test]
fn quantized_attributes_vertex_colors_and_material_extensions_load() {
    let ext = r#"{"KHR_materials_clearcoat":{"clearcoatFactor":0.8,"clearcoatRoughnessFactor":0.2},
        "KHR_materials_sheen":{"sheenColorFactor":[0.5,0.4,0.3],"sheenRoughnessFactor":0.6},
        "KHR_materials_volume":{"attenuationColor":[0.5,1.0,0.25],"attenuationDistance":2.0,"thicknessFactor":0.1}}"#;
    let s = load_str(&quantized_gltf(ext, r#""KHR_mesh_quantization""#)).expect("quantized scene");
    assert!(s.warnings.is_empty(), "every extension here is modelled: {:?}", s.warnings);
    // i16 positions dequantized by the node's 0.01 scale.
    let p = &s.mesh.positions;
    assert!((p[1] - renderer::math::Vec3::new(1.0, 0.0, 0.0)).length() < 1e-6, "{p:?}");
    assert!((p[2] - renderer::math::Vec3::new(0.0, 1.0, 0.0)).length() < 1e-6, "{p:?}");
    assert!(s.mesh.triangles[0].flags & flags::COLORS != 0);
    // COLOR_0 u8 normalized: vertex 1 is (0, 1, 0, 128/255); UVs u16 normalized.
    let c = s.mesh.colors[1];
    assert!((c - renderer::math::Vec4::new(0.0, 1.0, 0.0, 128.0 / 255.0)).abs().max_element() < 1e-6, "{c:?}");
    assert!((s.mesh.uvs[2].y - 32768.0 / 65535.0).abs() < 1e-6);
    assert!((s.mesh.normals[0] - renderer::math::Vec3::Z).length() < 1e-6);
    let sp = s.mesh.surface_point(0, 0.5, 0.25);
    assert!(
        (sp.color - renderer::math::Vec4::new(0.25, 0.5, 0.25, 0.25 + 0.5 * 128.0 / 255.0 + 0.25)).abs().max_element()
            < 1e-5
    );
    let m = &s.materials[0];
    assert_eq!((m.clearcoat, m.clearcoat_roughness), (0.8, 0.2));
    assert_eq!((m.sheen_color, m.sheen_roughness), (renderer::math::Vec3::new(0.5, 0.4, 0.3), 0.6));
    // σ = −ln(color) / distance.
    let want = renderer::math::Vec3::new(-(0.5f32.ln()) / 2.0, 0.0, -(0.25f32.ln()) / 2.0);
    assert!((m.absorption - want).abs().max_element() < 1e-6, "{:?}", m.absorption);
    assert!(!m.unlit);
    // The base color the BSDF sees is multiplied by the vertex color.
    let b = m.bsdf(&s.textures, sp.uv, sp.color);
    assert!((b.base_color - renderer::math::Vec3::new(0.25, 0.5, 0.25)).abs().max_element() < 1e-5);
    assert!(b.coat.is_some() && b.sheen.is_some());

    let unlit = load_str(&quantized_gltf(r#"{"KHR_materials_unlit":{}}"#, "")).expect("unlit");
    assert!(unlit.materials[0].unlit);

    // A thickness of 0 (the default) is a thin wall: no volume behind the surface, so nothing
    // absorbs, however the attenuation is set.
    for thin in [
        r#"{"KHR_materials_volume":{"attenuationColor":[0.5,1.0,0.25],"attenuationDistance":2.0}}"#,
        r#"{"KHR_materials_volume":{"attenuationColor":[0.5,1.0,0.25],"attenuationDistance":2.0,"thicknessFactor":0}}"#,
    ] {
        let s = load_str(&quantized_gltf(thin, "")).expect("thin-walled volume");
        assert_eq!(s.materials[0].absorption, renderer::math::Vec3::ZERO, "{thin}");
    }

    for (ext, needle) in [
        (r#"{"KHR_materials_volume":{"attenuationDistance":0}}"#, "attenuationDistance 0 must be positive"),
        (r#"{"KHR_materials_volume":{"thicknessFactor":-1,"attenuationDistance":1}}"#, "thicknessFactor -1 must be"),
        (r#"{"KHR_materials_volume":{"attenuationColor":[1,-1,1],"attenuationDistance":1}}"#, "attenuationColor"),
        (r#"{"KHR_materials_clearcoat":{"clearcoatFactor":"x"}}"#, "clearcoatFactor"),
        (r#"{"KHR_materials_sheen":{"sheenColorTexture":{"index":7}}}"#, "texture 7 does not exist"),
    ] {
        expect_err(&quantized_gltf(ext, ""), needle);
    }
}

#[test]
fn meshopt_compressed_views_decode_to_the_plain_data() {
    let plain = load_str(&renderer::testing::meshopt_grid_gltf(false)).expect("plain grid");
    let packed = load_str(&renderer::testing::meshopt_grid_gltf(true)).expect("meshopt grid");
    assert!(packed.warnings.is_empty(), "{:?}", packed.warnings);
    assert_eq!(plain.mesh.positions, packed.mesh.positions, "the vertex codec is lossless");
    assert_eq!(
        plain.mesh.triangles.iter().map(|t| t.v).collect::<Vec<_>>(),
        packed.mesh.triangles.iter().map(|t| t.v).collect::<Vec<_>>()
    );
    assert_eq!(plain.mesh.normals, packed.mesh.normals, "the same octahedral bytes decode to the same normals");
    assert!(packed.mesh.normals.iter().all(|n| (n.length() - 1.0).abs() < 1e-3 && n.y > 0.5));
    // Bad streams are errors naming the view and the extension.
    let bad = renderer::testing::meshopt_grid_gltf(true).replace("\"filter\":\"OCTAHEDRAL\"", "\"filter\":\"SPIRAL\"");
    expect_err(&bad, "unknown filter SPIRAL");
    let cut = renderer::testing::meshopt_grid_gltf(true).replacen(
        "\"byteStride\":12,\"count\"",
        "\"byteStride\":16,\"count\"",
        1,
    );
    expect_err(&cut, "EXT_meshopt_compression");
}
