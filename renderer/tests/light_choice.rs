//! `--light-sampler auto` chooses by measured benefit (issue 10), not by counting triangles: the
//! choices below are the strategies `tessera bench convergence` measured as best at equal time on
//! these scenes (docs/speed-vs-accuracy/summary.md and issue 10's note).

use renderer::light::LightSamplerKind;
use std::path::{Path, PathBuf};

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

fn auto_choice(name: &str) -> LightSamplerKind {
    let mut scene =
        renderer::gltf_loader::load(&root().join(format!("scenes/{name}/{name}.gltf"))).expect("scene loads");
    scene.set_light_sampler(LightSamplerKind::Auto);
    scene.lights.kind
}

#[test]
fn auto_picks_what_measures_best() {
    // 1024 separate small lamps: the tree, 125× better than power at equal time.
    assert_eq!(auto_choice("many_lights"), LightSamplerKind::Tree);
    // Four unequal 1152-triangle bulbs over a floor: tree 5.9e-4, uniform 7.7e-4, power 1.4e-3.
    assert_eq!(auto_choice("sphere_lights"), LightSamplerKind::Tree);
    // Four equal bulbs (1280 triangles) seen from everywhere: with the walk at two levels per AVX
    // pass the tree pays here too (`bench_peers.py --tessera-args "--light-sampler K" veach`, 64
    // spp, medians of 5: relMSE tree 1.94e-3 in 0.192 s, uniform 3.98e-3 in 0.128 s, power
    // 3.92e-3 in 0.129 s: the tree 1.37× as efficient). With the walk at one level per child
    // (2.25× a power sample) uniform had been better, and the pilot picked it.
    assert_eq!(auto_choice("veach"), LightSamplerKind::Tree);
    // One emitter: nothing to choose.
    assert_eq!(auto_choice("cornell"), LightSamplerKind::Power);
}

#[test]
fn auto_is_a_function_of_the_scene() {
    // The farm's determinism rule: every worker must make the same choice.
    for name in ["veach", "sphere_lights"] {
        let a = auto_choice(name);
        for _ in 0..3 {
            assert_eq!(auto_choice(name), a, "{name}");
        }
    }
}
