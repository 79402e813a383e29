//! Tessera's renderer: a CPU path tracer for glTF 2.0 scenes. It has no networking; the farm calls
//! [`render::render_tile`] and ships the [`film::PartialSums`] it returns.
//!
//! One concept per module (pbrt-v4 style): `camera`, `sampler`, `microfacet`, `bsdf`, `light`,
//! `integrator`, ... See ARCHITECTURE.md at the repository root for the map and the invariants.

// `!(x > 0.0)` is this crate's idiom for "not a positive number, NaN included": keep it.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

/// Implements `FromStr` for a settings enum from its lowercase names, with an error that lists
/// them (clap parses command-line flags through it).
#[macro_export]
macro_rules! named_choices {
    ($ty:ty, $what:literal, { $($name:literal => $variant:expr),+ $(,)? }) => {
        impl std::str::FromStr for $ty {
            type Err = String;
            fn from_str(s: &str) -> Result<Self, String> {
                match s {
                    $($name => Ok($variant),)+
                    other => Err(format!(concat!("unknown ", $what, " '{}' (expected {})"), other, [$($name),+].join(", "))),
                }
            }
        }
    };
}

pub mod accel;
pub mod alias;
pub mod animation;
pub mod bsdf;
pub mod bsdf8;
pub mod budget;
pub mod bulb;
pub mod bundle;
pub mod bvh;
pub mod camera;
pub mod clear_box;
pub mod clearcoat;
pub mod convex_solid;
pub mod cwbvh_node;
pub mod dielectric;
pub mod distribution;
pub mod environment;
pub mod error;
pub mod film;
pub mod frames;
pub mod gltf_loader;
pub mod image_io;
pub mod integrator;
pub mod lanes;
pub mod light;
pub mod light_choice;
pub mod light_tree;
pub mod material;
pub mod math;
pub mod mesh;
pub mod meshopt_views;
pub mod microfacet;
pub mod node_ray;
pub mod noise;
pub mod punctual;
pub mod ray_bundle;
pub mod render;
pub mod sampler;
pub mod scene;
pub mod settings;
pub mod settings_request;
pub mod sheen;
pub mod solid_surface;
pub mod spmd;
pub mod stats;
pub mod testing;
pub mod texture;
pub mod triangle;
pub mod wide_node;

pub use error::{RenderError, SceneError};
pub use film::{PartialSums, Rect};
pub use render::{render, render_tile, Counters, Rendered};
pub use scene::Scene;
pub use settings::{IntegratorKind, MisHeuristic, PixelFilter, RenderSettings};
