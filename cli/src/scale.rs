//! `tessera bench scale`: production-size scenes generated in memory as GLB files — many instances
//! of one dense mesh, and one mesh of many unique triangles — timed through the real loader, BVH
//! build and renderer, with the process's resident memory read from /proc after each stage.

use anyhow::{Context, Result};
use clap::Args;
use renderer::{Counters, RenderSettings};
use std::path::Path;
use std::sync::atomic::Ordering;
use std::time::Instant;

#[derive(Args, Debug)]
pub struct ScaleArgs {
    /// Instances of the dense mesh in the instanced scene (0 skips it).
    #[arg(long, default_value_t = 10_000)]
    pub instances: u32,
    /// Triangles of the instanced mesh (a UV sphere; rounded to its grid).
    #[arg(long, default_value_t = 100_000)]
    pub instance_triangles: u32,
    /// Triangles of the unique-geometry scene (a displaced grid; 0 skips it).
    #[arg(long, default_value_t = 10_000_000)]
    pub unique_triangles: u64,
    /// Image of the timed render of each scene.
    #[arg(long, default_value_t = 320)]
    pub width: u32,
    #[arg(long, default_value_t = 180)]
    pub height: u32,
    #[arg(long, default_value_t = 4)]
    pub spp: u32,
    /// Also write the generated scenes as GLB files into this folder.
    #[arg(long)]
    pub write: Option<std::path::PathBuf>,
}

/// Resident and peak resident memory of this process in bytes (Linux /proc; 0 elsewhere).
fn memory() -> (u64, u64) {
    let status = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    let field = |name: &str| {
        status
            .lines()
            .find(|l| l.starts_with(name))
            .and_then(|l| l.split_whitespace().nth(1))
            .and_then(|v| v.parse::<u64>().ok())
            .map_or(0, |kb| kb * 1024)
    };
    (field("VmRSS:"), field("VmHWM:"))
}

fn mb(b: u64) -> f64 {
    b as f64 / (1 << 20) as f64
}

/// A GLB from a JSON document and one binary buffer.
fn glb(json: &str, bin: &[u8]) -> Vec<u8> {
    let mut j = json.as_bytes().to_vec();
    while !j.len().is_multiple_of(4) {
        j.push(b' ');
    }
    let mut b = bin.to_vec();
    while !b.len().is_multiple_of(4) {
        b.push(0);
    }
    let total = 12 + 8 + j.len() + 8 + b.len();
    let mut out = Vec::with_capacity(total);
    out.extend_from_slice(b"glTF");
    out.extend_from_slice(&2u32.to_le_bytes());
    out.extend_from_slice(&(total as u32).to_le_bytes());
    out.extend_from_slice(&(j.len() as u32).to_le_bytes());
    out.extend_from_slice(b"JSON");
    out.extend_from_slice(&j);
    out.extend_from_slice(&(b.len() as u32).to_le_bytes());
    out.extend_from_slice(b"BIN\0");
    out.extend_from_slice(&b);
    out
}

/// Positions (f32 xyz) and u32 triangle indices of a `cols`×`rows` vertex grid mapped by `f`.
fn grid(cols: u32, rows: u32, f: impl Fn(f32, f32) -> [f32; 3]) -> (Vec<u8>, Vec<u8>, u64) {
    let mut pos = Vec::with_capacity((cols * rows * 12) as usize);
    for j in 0..rows {
        for i in 0..cols {
            let p = f(i as f32 / (cols - 1) as f32, j as f32 / (rows - 1) as f32);
            for c in p {
                pos.extend_from_slice(&c.to_le_bytes());
            }
        }
    }
    let mut idx = Vec::with_capacity(((cols - 1) * (rows - 1) * 24) as usize);
    for j in 0..rows - 1 {
        for i in 0..cols - 1 {
            let a = j * cols + i;
            for v in [a, a + cols, a + 1, a + 1, a + cols, a + cols + 1] {
                idx.extend_from_slice(&v.to_le_bytes());
            }
        }
    }
    let tris = (cols as u64 - 1) * (rows as u64 - 1) * 2;
    (pos, idx, tris)
}

/// One mesh (positions + indices in `bin`), placed by `nodes` (JSON node objects with "mesh":0),
/// a grey material, a camera node looking from `eye` down at the origin.
fn document(nodes: &[String], verts: usize, pos_len: usize, idx_len: usize, eye: [f32; 3], pitch: f32) -> String {
    let (s, c) = ((pitch * 0.5).sin(), (pitch * 0.5).cos());
    let mut all: Vec<String> = nodes.to_vec();
    all.push(format!(r#"{{"camera":0,"translation":{eye:?},"rotation":[{},0,0,{}]}}"#, -s, c));
    let roots: Vec<usize> = (0..all.len()).collect();
    format!(
        r#"{{"asset":{{"version":"2.0","generator":"tessera bench scale"}},"scene":0,"scenes":[{{"nodes":{roots:?}}}],
        "nodes":[{}],"meshes":[{{"primitives":[{{"attributes":{{"POSITION":0}},"indices":1,"material":0}}]}}],
        "materials":[{{"pbrMetallicRoughness":{{"baseColorFactor":[0.7,0.7,0.7,1],"metallicFactor":0,"roughnessFactor":0.7}}}}],
        "cameras":[{{"type":"perspective","perspective":{{"yfov":0.8,"znear":0.1}}}}],
        "accessors":[{{"bufferView":0,"componentType":5126,"count":{verts},"type":"VEC3","min":[-1e9,-1e9,-1e9],"max":[1e9,1e9,1e9]}},
                     {{"bufferView":1,"componentType":5125,"count":{},"type":"SCALAR"}}],
        "bufferViews":[{{"buffer":0,"byteOffset":0,"byteLength":{pos_len}}},{{"buffer":0,"byteOffset":{pos_len},"byteLength":{idx_len}}}],
        "buffers":[{{"byteLength":{}}}]}}"#,
        all.join(","),
        idx_len / 4,
        pos_len + idx_len
    )
}

fn measure(name: &str, bytes: Vec<u8>, args: &ScaleArgs, placed: u64) -> Result<()> {
    let (rss0, _) = memory();
    let file_mb = mb(bytes.len() as u64);
    let t = Instant::now();
    let mut scene = renderer::gltf_loader::load_from_bytes(Path::new(name), &bytes).context("loading")?;
    let load = t.elapsed().as_secs_f64();
    drop(bytes);
    let (rss1, peak1) = memory();
    let stored = scene.mesh.triangles.len() as u64;
    let settings = RenderSettings {
        width: args.width,
        height: args.height,
        spp: args.spp,
        max_depth: 4,
        environment: renderer::environment::EnvironmentSettings { color: Some([0.8, 0.85, 1.0]), ..Default::default() },
        ..RenderSettings::default()
    };
    scene.prepare(&settings, Path::new("."))?;
    let counters = Counters::default();
    let t = Instant::now();
    renderer::render(&scene, &settings, &counters);
    let render = t.elapsed().as_secs_f64();
    let rays = counters.rays.load(Ordering::Relaxed) as f64;
    let (_, peak2) = memory();
    println!(
        "{name}: {placed} triangles placed, {stored} stored ({} instances) | GLB {file_mb:.0} MB | load + BVH {load:.2}s \
         | scene memory {:.0} MB = {:.1} bytes/stored triangle | peak RSS {:.0} MB (after load) {:.0} MB (after render) \
         | render {}x{} {} spp {render:.2}s, {:.2} Mrays/s",
        scene.mesh.instances.len(),
        mb(rss1.saturating_sub(rss0)),
        rss1.saturating_sub(rss0) as f64 / stored.max(1) as f64,
        mb(peak1),
        mb(peak2),
        args.width,
        args.height,
        args.spp,
        rays / render / 1e6
    );
    Ok(())
}

pub fn run(args: ScaleArgs) -> Result<()> {
    if args.instances > 0 {
        // A UV sphere of about `instance_triangles` triangles (radius 0.4), on a square grid of
        // instances 1 apart, each turned differently.
        let side = ((args.instance_triangles as f64 / 2.0).sqrt().ceil() as u32).max(4) + 1;
        let (pos, idx, tris) = grid(side, side, |u, v| {
            let (phi, theta) = (u * std::f32::consts::TAU, v * std::f32::consts::PI);
            [0.4 * theta.sin() * phi.cos(), 0.4 * theta.cos(), 0.4 * theta.sin() * phi.sin()]
        });
        let n = (args.instances as f64).sqrt().ceil() as u32;
        let nodes: Vec<String> = (0..args.instances)
            .map(|k| {
                let (x, z) = ((k % n) as f32 - n as f32 / 2.0, (k / n) as f32 - n as f32 / 2.0);
                let a = k as f32 * 0.7;
                format!(
                    r#"{{"mesh":0,"translation":[{x},0.4,{z}],"rotation":[0,{},0,{}]}}"#,
                    (a * 0.5).sin(),
                    (a * 0.5).cos()
                )
            })
            .collect();
        let json = document(&nodes, (side * side) as usize, pos.len(), idx.len(), [0.0, 6.0, n as f32 * 0.6], 0.6);
        let bytes = glb(&json, &[pos, idx].concat());
        if let Some(dir) = &args.write {
            std::fs::write(dir.join("instanced.glb"), &bytes)?;
        }
        measure("instanced", bytes, &args, tris * args.instances as u64)?;
    }
    if args.unique_triangles > 0 {
        let side = ((args.unique_triangles as f64 / 2.0).sqrt().ceil() as u32).max(2) + 1;
        let (pos, idx, tris) = grid(side, side, |u, v| {
            let (x, z) = (u * 20.0 - 10.0, v * 20.0 - 10.0);
            [x, 0.3 * (x * 3.0).sin() * (z * 2.0).cos(), z]
        });
        let json = document(
            &[r#"{"mesh":0}"#.to_string()],
            (side * side) as usize,
            pos.len(),
            idx.len(),
            [0.0, 5.0, 12.0],
            0.5,
        );
        let bytes = glb(&json, &[pos, idx].concat());
        if let Some(dir) = &args.write {
            std::fs::write(dir.join("unique.glb"), &bytes)?;
        }
        measure("unique", bytes, &args, tris)?;
    }
    Ok(())
}
