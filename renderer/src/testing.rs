//! Small programmatic scenes for tests, benchmarks and the numerical-extremes suite (furnaces,
//! spheres, single lights), built directly as meshes so they depend on nothing but this crate.

use crate::camera::Camera;
use crate::material::Material;
use crate::math::{Vec2, Vec3, Vec4};
use crate::mesh::{Mesh, Triangle};
use crate::scene::Scene;

/// Unit icosphere subdivided `level` times: (positions, outward-wound triangles).
pub fn icosphere(level: u32) -> (Vec<Vec3>, Vec<[u32; 3]>) {
    let t = (1.0 + 5f32.sqrt()) / 2.0;
    let mut v: Vec<Vec3> = [
        [-1.0, t, 0.0],
        [1.0, t, 0.0],
        [-1.0, -t, 0.0],
        [1.0, -t, 0.0],
        [0.0, -1.0, t],
        [0.0, 1.0, t],
        [0.0, -1.0, -t],
        [0.0, 1.0, -t],
        [t, 0.0, -1.0],
        [t, 0.0, 1.0],
        [-t, 0.0, -1.0],
        [-t, 0.0, 1.0],
    ]
    .iter()
    .map(|p| Vec3::from(*p).normalize())
    .collect();
    let mut f: Vec<[u32; 3]> = vec![
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ];
    for _ in 0..level {
        let mut cache = std::collections::HashMap::new();
        let mut mid = |a: u32, b: u32, v: &mut Vec<Vec3>| -> u32 {
            *cache.entry((a.min(b), a.max(b))).or_insert_with(|| {
                v.push(((v[a as usize] + v[b as usize]) * 0.5).normalize());
                v.len() as u32 - 1
            })
        };
        let mut nf = Vec::with_capacity(f.len() * 4);
        for [a, b, c] in f {
            let ab = mid(a, b, &mut v);
            let bc = mid(b, c, &mut v);
            let ca = mid(c, a, &mut v);
            nf.extend([[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]);
        }
        f = nf;
    }
    (v, f)
}

/// Accumulates meshes and materials into a [`Scene`].
#[derive(Default)]
pub struct SceneBuilder {
    pub mesh: Mesh,
    pub materials: Vec<Material>,
    pub cameras: Vec<Camera>,
}

impl SceneBuilder {
    pub fn material(&mut self, m: Material) -> u32 {
        self.materials.push(m);
        self.materials.len() as u32 - 1
    }

    /// Adds triangles (no vertex normals, no UVs: flat shading).
    pub fn triangles(&mut self, positions: &[Vec3], tris: &[[u32; 3]], material: u32) {
        let base = self.mesh.positions.len() as u32;
        self.mesh.positions.extend_from_slice(positions);
        self.mesh.normals.extend(std::iter::repeat_n(Vec3::ZERO, positions.len()));
        self.mesh.tangents.extend(std::iter::repeat_n(Vec4::ZERO, positions.len()));
        self.mesh.uvs.extend(std::iter::repeat_n(Vec2::ZERO, positions.len()));
        for t in tris {
            self.mesh.triangles.push(Triangle { v: [base + t[0], base + t[1], base + t[2]], material, flags: 0 });
        }
    }

    /// Sphere of `radius` at `center`; `inward` flips the winding so the front faces the inside.
    pub fn sphere(&mut self, center: Vec3, radius: f32, level: u32, inward: bool, material: u32) {
        let (v, f) = icosphere(level);
        let p: Vec<Vec3> = v.iter().map(|p| center + *p * radius).collect();
        let f: Vec<[u32; 3]> = if inward { f.iter().map(|t| [t[0], t[2], t[1]]).collect() } else { f };
        self.triangles(&p, &f, material);
    }

    /// Blender-style UV sphere: `segments` around, `rings` from pole to pole, single-vertex poles with
    /// triangle fans and flat triangles (no vertex normals), front faces outwards. It has
    /// 2·segments·(rings − 1) triangles: 48 × 24 gives 2208, the case of issue 10.
    pub fn uv_sphere(&mut self, center: Vec3, radius: f32, segments: u32, rings: u32, material: u32) {
        let (segments, rings) = (segments.max(3), rings.max(2));
        let mut p = vec![center + Vec3::Y * radius];
        for r in 1..rings {
            let theta = std::f32::consts::PI * r as f32 / rings as f32;
            for s in 0..segments {
                let phi = 2.0 * std::f32::consts::PI * s as f32 / segments as f32;
                let dir = Vec3::new(theta.sin() * phi.cos(), theta.cos(), -theta.sin() * phi.sin());
                p.push(center + dir * radius);
            }
        }
        p.push(center - Vec3::Y * radius);
        let ring = |r: u32, s: u32| 1 + (r - 1) * segments + s % segments;
        let bottom = p.len() as u32 - 1;
        let mut t = Vec::new();
        for s in 0..segments {
            t.push([0, ring(1, s), ring(1, s + 1)]);
            for r in 1..rings - 1 {
                let (a, b, c, d) = (ring(r, s), ring(r + 1, s), ring(r + 1, s + 1), ring(r, s + 1));
                t.push([a, b, c]);
                t.push([a, c, d]);
            }
            t.push([ring(rings - 1, s), bottom, ring(rings - 1, s + 1)]);
        }
        self.triangles(&p, &t, material);
    }

    /// Disc of `radius` at `c` as a fan of `segments` triangles, front face along `normal`.
    pub fn disc(&mut self, c: Vec3, normal: Vec3, radius: f32, segments: u32, material: u32) {
        let f = crate::math::Frame::from_normal(normal.normalize());
        let mut p = vec![c];
        for s in 0..segments.max(3) {
            let phi = 2.0 * std::f32::consts::PI * s as f32 / segments.max(3) as f32;
            p.push(c + (f.s * phi.cos() + f.t * phi.sin()) * radius);
        }
        let n = segments.max(3);
        let t: Vec<[u32; 3]> = (0..n).map(|s| [0, 1 + s, 1 + (s + 1) % n]).collect();
        self.triangles(&p, &t, material);
    }

    /// Quad centred at `c` spanning ±u, ±v, front face along u × v.
    pub fn quad(&mut self, c: Vec3, u: Vec3, v: Vec3, material: u32) {
        let p = [c - u - v, c + u - v, c + u + v, c - u + v];
        self.triangles(&p, &[[0, 1, 2], [0, 2, 3]], material);
    }

    pub fn look_at(&mut self, eye: Vec3, target: Vec3, yfov_deg: f32) {
        let forward = (target - eye).normalize();
        let right = forward.cross(if forward.cross(Vec3::Y).length() < 1e-4 { Vec3::Z } else { Vec3::Y }).normalize();
        let up = right.cross(forward);
        self.cameras.push(Camera { origin: eye, right, up, forward, yfov: yfov_deg.to_radians(), aspect_ratio: None });
    }

    pub fn build(self) -> Scene {
        Scene::new(self.mesh, self.materials, Vec::new(), self.cameras)
    }
}

/// A mesh of separate triangles (each its own vertex triple, as a flat-shaded export has them),
/// material 0.
pub fn mesh_of(tris: &[[Vec3; 3]]) -> crate::mesh::Mesh {
    let mut m = crate::mesh::Mesh::default();
    for t in tris {
        let base = m.positions.len() as u32;
        m.positions.extend_from_slice(t);
        m.triangles.push(crate::mesh::Triangle { v: [base, base + 1, base + 2], material: 0, flags: 0 });
    }
    m
}

/// An icosphere of `20·4^level` faces about `center` (outward winding), each face its own vertex
/// triple, as a flat-shaded export has them (for [`mesh_of`]).
pub fn icosphere_faces(center: Vec3, radius: f32, level: u32) -> Vec<[Vec3; 3]> {
    let (v, f) = icosphere(level);
    f.iter().map(|t| t.map(|k| center + v[k as usize] * radius)).collect()
}

/// A Lambert material (KHR_materials_specular specularFactor 0).
pub fn lambert(albedo: Vec3) -> Material {
    Material {
        name: "lambert".into(),
        base_color: albedo.extend(1.0),
        metallic: 0.0,
        roughness: 1.0,
        specular: 0.0,
        ..Material::default()
    }
}

/// A metal with base color `color` and `roughness`.
pub fn metal(color: Vec3, roughness: f32) -> Material {
    Material { name: "metal".into(), base_color: color.extend(1.0), metallic: 1.0, roughness, ..Material::default() }
}

/// A black emitter of radiance `le`, emitting from its front face only (glTF's default, not
/// `doubleSided`).
pub fn one_sided_emitter(le: Vec3) -> Material {
    Material { double_sided: false, ..emitter(le) }
}

/// A black, double-sided emitter of radiance `le`.
pub fn emitter(le: Vec3) -> Material {
    Material {
        name: "emitter".into(),
        base_color: Vec4::new(0.0, 0.0, 0.0, 1.0),
        metallic: 0.0,
        specular: 0.0,
        emissive: le,
        double_sided: true,
        ..Material::default()
    }
}

/// White furnace: a sphere of `inner` material at the origin (radius 1) inside a closed, uniform,
/// double-sided emitter of radiance 1 (radius 10), camera looking at the sphere.
pub fn furnace(inner: Material) -> Scene {
    let mut b = SceneBuilder::default();
    let m = b.material(inner);
    let e = b.material(emitter(Vec3::ONE));
    b.sphere(Vec3::ZERO, 1.0, 3, false, m);
    b.sphere(Vec3::ZERO, 10.0, 2, true, e);
    b.look_at(Vec3::new(0.0, 0.0, 4.0), Vec3::ZERO, 35.0);
    b.build()
}

/// obvhs' CWBVH ("medium" build, as `Accel` builds it) over an icosphere of `level` mapped
/// through `place` — and, with `shell`, a second copy stretched and offset to (3, 0.5, 2)·p + 0.3,
/// so nodes have both leaf and inner children. For the node-test tests.
pub fn icosphere_cwbvh(level: u32, place: impl Fn(glam::Vec3A) -> glam::Vec3A, shell: bool) -> obvhs::cwbvh::CwBvh {
    let (p, f) = icosphere(level);
    let tri = |t: &[u32; 3], m: &dyn Fn(glam::Vec3A) -> glam::Vec3A| obvhs::triangle::Triangle {
        v0: m(place(p[t[0] as usize].into())),
        v1: m(place(p[t[1] as usize].into())),
        v2: m(place(p[t[2] as usize].into())),
    };
    let mut tris: Vec<obvhs::triangle::Triangle> = f.iter().map(|t| tri(t, &|v| v)).collect();
    if shell {
        tris.extend(f.iter().map(|t| tri(t, &|v| v * glam::Vec3A::new(3.0, 0.5, 2.0) + 0.3)));
    }
    obvhs::cwbvh::builder::build_cwbvh_from_tris(&tris, obvhs::BvhBuildParams::medium_build(), &mut Default::default())
}

/// Ray `i` of the node-test tests: from a point in [−4, 4]³ aimed at a point of [−1, 1]³ (into
/// the shapes of [`icosphere_cwbvh`], so most cross boxes), every seventh exactly along x and
/// the next in the y = 0 plane (zero direction components), every third with a finite `tmax`.
/// None for a zero direction.
pub fn node_test_ray(i: u64) -> Option<obvhs::ray::Ray> {
    use glam::Vec3A;
    let u = crate::sampler::hash_unit;
    let o = Vec3A::new(u(8 * i), u(8 * i + 1), u(8 * i + 2)) * 8.0 - 4.0;
    let mut d = Vec3A::new(u(8 * i + 3), u(8 * i + 4), u(8 * i + 5)) * 2.0 - 1.0 - o;
    match i % 7 {
        0 => d = Vec3A::new(d.x, 0.0, 0.0),
        1 => d.y = 0.0,
        _ => {}
    }
    if d.length_squared() == 0.0 {
        return None;
    }
    let tmax = if i.is_multiple_of(3) { 2.0 * u(8 * i + 6) } else { f32::INFINITY };
    Some(obvhs::ray::Ray::new(o, d.normalize(), 0.0, tmax))
}

/// The scene files the "same bits either way" tests render (paths from the repository root), each
/// with whether it is also lit by `scenes/env/sunset.exr`: the suite, the Blender exports, the
/// Khronos models and the animations.
pub const BIT_TEST_SCENES: [(&str, bool); 14] = [
    ("scenes/cornell/cornell.gltf", false),
    ("scenes/envlit/envlit.gltf", true),
    ("scenes/glass/glass.gltf", false),
    ("scenes/glass_absorb/glass_absorb.gltf", false),
    ("scenes/many_lights/many_lights.gltf", false),
    ("scenes/sphere_light/sphere_light.gltf", false),
    ("scenes/sphere_lights/sphere_lights.gltf", false),
    ("scenes/veach/veach.gltf", false),
    ("scenes/blender/materials.glb", false),
    ("scenes/blender/lights.glb", false),
    ("scenes/khronos/DamagedHelmet/DamagedHelmet.gltf", true),
    ("scenes/khronos/BoxTextured.glb", true),
    ("scenes/animation/moving_light.gltf", false),
    ("scenes/animation/rig.glb", true),
];

/// One of [`BIT_TEST_SCENES`] loaded from `root`, its environment set in `settings` where the
/// table says, prepared for `settings` and posed at frame 5. Test support: panics naming the file.
pub fn load_bit_test_scene(
    root: &std::path::Path,
    (rel, sunset): (&str, bool),
    settings: &mut crate::RenderSettings,
) -> Scene {
    let mut scene = crate::gltf_loader::load(&root.join(rel)).unwrap_or_else(|e| panic!("{rel}: {e}"));
    if sunset {
        settings.environment.map = Some("scenes/env/sunset.exr".into());
    }
    scene.prepare(settings, root).unwrap_or_else(|e| panic!("{rel}: {e}"));
    scene.set_frame(settings, 5).unwrap_or_else(|e| panic!("{rel}: {e}"));
    scene
}

/// Every bit of an image's sums, colour then squared luminance: what "the same image" means to
/// the determinism rule.
pub fn sum_bits(p: &crate::film::PartialSums) -> Vec<u64> {
    p.sum_rgb
        .iter()
        .flat_map(|c| c.iter().map(|v| v.to_bits()))
        .chain(p.sum_lum_sq.iter().map(|v| v.to_bits()))
        .collect()
}

/// The rays `o + t d` traced the way renders of large scenes trace them, in batches of up to
/// [`crate::accel::MAX_BATCH`]:
/// each ray's first surface ([`Scene::intersect_surface_batch`], seed 0) and its visibility up to
/// `tmax` ([`Scene::visibility_batch`]: 0 blocked, 1 clear). Turns batching on for `scene`.
pub fn trace_in_batches(
    scene: &mut Scene,
    o: &[Vec3],
    d: &[Vec3],
    tmax: f32,
) -> (Vec<Option<crate::accel::Hit>>, Vec<f32>) {
    use crate::accel::MAX_BATCH;
    scene.set_batch_rays(true);
    let (mut hits, mut seen) = (vec![None; o.len()], vec![0f32; o.len()]);
    for s in (0..o.len()).step_by(MAX_BATCH) {
        let e = (s + MAX_BATCH).min(o.len());
        scene.intersect_surface_batch(
            &o[s..e],
            &d[s..e],
            &[0; MAX_BATCH][..e - s],
            &[crate::convex_solid::NONE; MAX_BATCH][..e - s],
            &mut hits[s..e],
        );
        let from = [crate::convex_solid::NONE; MAX_BATCH];
        scene.visibility_batch(&o[s..e], &d[s..e], &[tmax; MAX_BATCH][..e - s], &from[..e - s], &mut seen[s..e]);
    }
    (hits, seen)
}

/// A displaced 12×9 grid, written once plainly and once with EXT_meshopt_compression (positions
/// as a plain ATTRIBUTES stream, normals octahedral-filtered to bytes, indices as TRIANGLES), with
/// the compressed streams made here by meshoptimizer's encoders (the loader's test and the
/// mutation fuzz test's corpus).
pub fn meshopt_grid_gltf(compressed: bool) -> String {
    use base64::Engine;
    let (cols, rows) = (12u32, 9u32);
    let mut pos: Vec<[f32; 3]> = Vec::new();
    let mut nrm: Vec<[f32; 4]> = Vec::new();
    for j in 0..rows {
        for i in 0..cols {
            let (x, z) = (i as f32 * 0.3, j as f32 * 0.3);
            pos.push([x, 0.2 * (x * 2.0).sin() * z.cos(), z]);
            let n = Vec3::new(-0.4 * (x * 2.0).cos() * z.cos(), 1.0, 0.2 * (x * 2.0).sin() * z.sin()).normalize();
            nrm.push([n.x, n.y, n.z, 0.0]);
        }
    }
    let mut idx: Vec<u32> = Vec::new();
    for j in 0..rows - 1 {
        for i in 0..cols - 1 {
            let a = j * cols + i;
            idx.extend_from_slice(&[a, a + cols, a + 1, a + 1, a + cols, a + cols + 1]);
        }
    }
    let oct: Vec<[i8; 4]> = meshopt::encode_filter_oct(&nrm, 8);
    let raw_pos: Vec<u8> = pos.iter().flatten().flat_map(|c| c.to_le_bytes()).collect();
    // The plain file holds what the filter decodes to (meshoptimizer's decoder, applied here).
    let mut decoded_oct = oct.clone();
    meshopt::decode_filter_oct(&mut decoded_oct);
    let raw_nrm: Vec<u8> = decoded_oct.iter().flat_map(|o| o.map(|b| b as u8)).collect();
    let raw_idx: Vec<u8> = idx.iter().flat_map(|i| i.to_le_bytes()).collect();
    let (np, nn, ni) = (raw_pos.len(), raw_nrm.len(), raw_idx.len());
    let b64 = |b: &[u8]| {
        format!("data:application/octet-stream;base64,{}", base64::engine::general_purpose::STANDARD.encode(b))
    };
    let (views, buffers, ext) = if compressed {
        let cp = meshopt::encode_vertex_buffer(&pos).expect("encode positions");
        let cn = meshopt::encode_vertex_buffer(&oct).expect("encode normals");
        let ci = meshopt::encode_index_buffer(&idx, pos.len()).expect("encode indices");
        let (lp, ln, li) = (cp.len(), cn.len(), ci.len());
        let data = [cp, cn, ci].concat();
        let n = pos.len();
        (
            format!(
                r#"[{{"buffer":1,"byteOffset":0,"byteLength":{np},"byteStride":12,"extensions":{{"EXT_meshopt_compression":{{"buffer":0,"byteOffset":0,"byteLength":{lp},"byteStride":12,"count":{n},"mode":"ATTRIBUTES"}}}}}},
                   {{"buffer":1,"byteOffset":{np},"byteLength":{nn},"byteStride":4,"extensions":{{"EXT_meshopt_compression":{{"buffer":0,"byteOffset":{lp},"byteLength":{ln},"byteStride":4,"count":{n},"mode":"ATTRIBUTES","filter":"OCTAHEDRAL"}}}}}},
                   {{"buffer":1,"byteOffset":{},"byteLength":{ni},"extensions":{{"EXT_meshopt_compression":{{"buffer":0,"byteOffset":{},"byteLength":{li},"byteStride":4,"count":{},"mode":"TRIANGLES"}}}}}}]"#,
                np + nn,
                lp + ln,
                idx.len()
            ),
            format!(
                r#"[{{"byteLength":{},"uri":"{}"}},{{"byteLength":{},"extensions":{{"EXT_meshopt_compression":{{"fallback":true}}}}}}]"#,
                data.len(),
                b64(&data),
                np + nn + ni
            ),
            r#","extensionsUsed":["EXT_meshopt_compression"],"extensionsRequired":["EXT_meshopt_compression"]"#,
        )
    } else {
        (
            format!(
                r#"[{{"buffer":0,"byteOffset":0,"byteLength":{np},"byteStride":12}},{{"buffer":0,"byteOffset":{np},"byteLength":{nn},"byteStride":4}},{{"buffer":0,"byteOffset":{},"byteLength":{ni}}}]"#,
                np + nn
            ),
            format!(r#"[{{"byteLength":{},"uri":"{}"}}]"#, np + nn + ni, b64(&[raw_pos, raw_nrm, raw_idx].concat())),
            "",
        )
    };
    format!(
        r#"{{"asset":{{"version":"2.0"}}{ext},"scene":0,"scenes":[{{"nodes":[0]}}],"nodes":[{{"mesh":0}}],
        "meshes":[{{"primitives":[{{"attributes":{{"POSITION":0,"NORMAL":1}},"indices":2}}]}}],
        "accessors":[{{"bufferView":0,"componentType":5126,"count":{n},"type":"VEC3","min":[0,-1,0],"max":[4,1,3]}},
                     {{"bufferView":1,"componentType":5120,"normalized":true,"count":{n},"type":"VEC3"}},
                     {{"bufferView":2,"componentType":5125,"count":{},"type":"SCALAR"}}],
        "bufferViews":{views},"buffers":{buffers}}}"#,
        idx.len(),
        n = pos.len()
    )
}

/// Loads `bytes` as the scene file `name` and renders it small (12 × 8 pixels, 2 samples, both
/// integrators, and a later frame of an animated scene) the way a farm would: Ok when the file is
/// refused with an error (an answer, not a failure) or when every pixel of every render is finite;
/// Err naming the first pixel that is not. Shared by `tests/mutation_fuzz.rs` and the cargo-fuzz
/// target `fuzz/fuzz_targets/gltf_loader.rs`; a panic inside is the caller's to catch.
pub fn loads_and_renders_finitely(name: &str, bytes: &[u8]) -> Result<(), String> {
    use crate::render::{render, Counters};
    use crate::settings::IntegratorKind;
    let Ok(mut scene) = crate::gltf_loader::load_from_bytes(std::path::Path::new(name), bytes) else { return Ok(()) };
    for integrator in [IntegratorKind::Mis, IntegratorKind::Nee] {
        let mut settings =
            crate::RenderSettings { width: 12, height: 8, spp: 2, pass_spp: 2, integrator, ..Default::default() };
        for frame in [0u32, 7] {
            settings.frame = frame;
            if frame > 0 && !scene.is_animated() {
                continue;
            }
            if scene.set_frame(&settings, frame).is_err() {
                continue;
            }
            let image = render(&scene, &settings, &Counters::default()).image;
            for i in 0..image.rect.pixels() {
                let m = image.mean(i);
                if !m.iter().all(|c| c.is_finite()) {
                    return Err(format!("pixel {i} is {m:?} ({integrator:?}, frame {frame})"));
                }
            }
        }
    }
    Ok(())
}
