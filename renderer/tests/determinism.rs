//! The determinism rule (ARCHITECTURE.md): for a fixed pass plan, the image does not depend by a
//! single bit on thread count, tile shapes, or how render_tile calls are split.

use renderer::film::{PartialSums, Rect};
use renderer::gltf_loader;
use renderer::sampler::SamplerKind;
use renderer::testing::sum_bits;
use renderer::{render, render_tile, Counters, IntegratorKind, RenderSettings};
use std::path::Path;

fn cornell() -> renderer::Scene {
    gltf_loader::load(&Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/cornell/cornell.gltf"))
        .expect("cornell loads")
}

/// Folds per-tile, per-pass sums into an image in pass order, the way the farm does.
fn assemble(settings: &RenderSettings, tile: u32, scene: &renderer::Scene) -> PartialSums {
    let mut image = PartialSums::new(Rect { x0: 0, y0: 0, width: settings.width, height: settings.height });
    // Tiles in reverse order, to show tile order does not matter either.
    let mut tiles = Rect::tiles(settings.width, settings.height, tile);
    tiles.reverse();
    for pass in (0..settings.pass_count()).map(|k| settings.pass_range(k)) {
        for t in &tiles {
            image.merge_tile(&render_tile(scene, settings, *t, pass.clone())).unwrap();
        }
    }
    image
}

#[test]
fn splitting_threads_tiles_and_calls_changes_no_bit() {
    let scene = cornell();
    for (integrator, sampler) in
        [(IntegratorKind::Mis, SamplerKind::Sobol), (IntegratorKind::Bsdf, SamplerKind::Independent)]
    {
        let s = RenderSettings {
            width: 37,
            height: 29,
            spp: 24,
            pass_spp: 8,
            integrator,
            sampler,
            seed: 5,
            ..RenderSettings::default()
        };
        let r = render(&scene, &s, &Counters::default());
        assert_eq!((r.spp_max(&s), r.stop), (24, renderer::budget::StopReason::SampleCount));
        let local = r.image;
        let one_thread =
            rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap().install(|| assemble(&s, 16, &scene));
        let three_threads =
            rayon::ThreadPoolBuilder::new().num_threads(3).build().unwrap().install(|| assemble(&s, 7, &scene));
        assert_eq!(sum_bits(&local), sum_bits(&one_thread), "{integrator:?}: 1 thread, 16px tiles");
        assert_eq!(sum_bits(&local), sum_bits(&three_threads), "{integrator:?}: 3 threads, 7px tiles");
        assert!(local.count.iter().all(|&c| c == 24));
    }
}

#[test]
fn seed_changes_the_noise_but_not_the_plan() {
    let scene = cornell();
    let a = RenderSettings { width: 16, height: 16, spp: 4, pass_spp: 4, ..RenderSettings::default() };
    let b = RenderSettings { seed: 1, ..a.clone() };
    let ra = render_tile(&scene, &a, Rect { x0: 0, y0: 0, width: 16, height: 16 }, 0..4);
    let rb = render_tile(&scene, &b, Rect { x0: 0, y0: 0, width: 16, height: 16 }, 0..4);
    assert_ne!(sum_bits(&ra), sum_bits(&rb));
}
