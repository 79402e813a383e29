//! The glTF loader on arbitrary bytes (a GLB when they start with its magic, else glTF JSON): it
//! must return a scene or an error, never panic or abort; a scene that loads renders a 4 × 3
//! image, two samples a pixel, to finite values (as `renderer/tests/mutation_fuzz.rs` asks of
//! its mutated scenes).
#![no_main]

use libfuzzer_sys::fuzz_target;
use renderer::render::{render, Counters};
use renderer::RenderSettings;

fuzz_target!(|data: &[u8]| {
    let name = if data.starts_with(b"glTF") { "fuzz.glb" } else { "fuzz.gltf" };
    let Ok(scene) = renderer::gltf_loader::load_from_bytes(std::path::Path::new(name), data) else { return };
    let settings = RenderSettings { width: 4, height: 3, spp: 2, pass_spp: 2, ..Default::default() };
    let image = render(&scene, &settings, &Counters::default()).image;
    for i in 0..image.rect.pixels() {
        assert!(image.mean(i).iter().all(|c| c.is_finite()), "pixel {i} is {:?}", image.mean(i));
    }
});
