//! The glTF loader on arbitrary bytes (a GLB when they start with its magic, else glTF JSON): it
//! must return a scene or an error, never panic or abort, and a scene that loads must render to
//! finite values, checked as `renderer/tests/mutation_fuzz.rs` checks its mutated scenes
//! (`renderer::testing::loads_and_renders_finitely`).
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let name = if data.starts_with(b"glTF") { "fuzz.glb" } else { "fuzz.gltf" };
    if let Err(e) = renderer::testing::loads_and_renders_finitely(name, data) {
        panic!("{e}");
    }
});
