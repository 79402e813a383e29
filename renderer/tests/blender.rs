//! Blender round trip without Blender (issue 12): `scenes/blender/lights.glb` was made and exported by
//! Blender 4.5 with its own glTF exporter, and `lights_cycles.exr` rendered by Cycles from the same
//! scene (`scenes/blender/make_blender_scene.py`, needs bpy). Tessera must show the brightness the user
//! saw in Blender: the exporter writes lights in candela and lux (683× Cycles' radiometric values), and
//! `--light-units auto` reads files from Blender's exporter back in Blender's units.

use renderer::film::Rect;
use renderer::image_io::read_exr;
use renderer::punctual::LightUnits;
use renderer::stats::lum;
use renderer::{render_tile, RenderSettings};
use std::path::{Path, PathBuf};

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// Mean luminance of rows [r0, r1) (fractions of the height) of a Tessera render of the Blender scene.
fn render_mean(units: LightUnits, rows: (f32, f32)) -> f64 {
    let mut scene = renderer::gltf_loader::load(&root().join("scenes/blender/lights.glb")).expect("lights.glb");
    let settings =
        RenderSettings { width: 160, height: 120, spp: 64, max_depth: 8, light_units: units, ..Default::default() };
    scene.prepare(&settings, &root()).expect("prepare");
    let sums = render_tile(&scene, &settings, Rect { x0: 0, y0: 0, width: 160, height: 120 }, 0..settings.spp);
    let (a, b) = ((rows.0 * 120.0) as usize, (rows.1 * 120.0) as usize);
    (a * 160..b * 160).map(|i| lum(sums.mean(i)) as f64).sum::<f64>() / ((b - a) * 160) as f64
}

fn cycles_mean(rows: (f32, f32)) -> f64 {
    let img = read_exr(&root().join("scenes/blender/lights_cycles.exr")).expect("Cycles EXR");
    let (r, g, b) = (img.channel("R").unwrap(), img.channel("G").unwrap(), img.channel("B").unwrap());
    let (w, h) = (img.width as usize, img.height as usize);
    let (a, e) = ((rows.0 * h as f32) as usize, (rows.1 * h as f32) as usize);
    (a * w..e * w).map(|i| lum([r[i], g[i], b[i]]) as f64).sum::<f64>() / ((e - a) * w) as f64
}

#[test]
fn a_blender_export_renders_as_bright_as_cycles_shows_it() {
    let scene = renderer::gltf_loader::load(&root().join("scenes/blender/lights.glb")).expect("lights.glb");
    assert!(scene.generator.as_deref().unwrap_or_default().starts_with("Khronos glTF Blender I/O"));
    assert_eq!(LightUnits::Auto.resolve(scene.generator.as_deref()), LightUnits::Blender);
    for (what, rows, tolerance) in
        [("image", (0.0, 1.0), 0.03), ("lower half", (0.5, 1.0), 0.04), ("upper half", (0.0, 0.5), 0.04)]
    {
        let (ours, cycles) = (render_mean(LightUnits::Auto, rows), cycles_mean(rows));
        let rel = ours / cycles - 1.0;
        println!("{what}: Tessera {ours:.5}, Cycles {cycles:.5} ({:+.2} %)", 100.0 * rel);
        assert!(rel.abs() < tolerance, "{what}: Tessera {ours} vs Cycles {cycles} ({:+.2} %)", 100.0 * rel);
    }
    // Read as plain glTF photometric numbers, the same file is 683× brighter (issue 12's finding).
    let ratio = render_mean(LightUnits::Gltf, (0.0, 1.0)) / render_mean(LightUnits::Blender, (0.0, 1.0));
    assert!((ratio / 683.0 - 1.0).abs() < 1e-3, "{ratio}");
}
