//! The path tracer: unidirectional paths with BSDF sampling, next-event estimation and multiple
//! importance sampling between the two (Veach 1997 ch. 9; pbrt-v4 §13.4 `PathIntegrator`).
//!
//! Conventions: `depth` counts scattering events; a path with `max_depth = 0` sees only emission,
//! `max_depth = 1` adds direct lighting. Russian roulette (pbrt-v4 §13.4.3) starts once `depth`
//! reaches `rr_depth` and is based on the path throughput times the η² of the transmissions so far
//! (radiance scaling at glass boundaries is not energy the path will lose), and plays only below
//! [`RR_THRESHOLD`] of it.

use crate::accel::{Hit, MAX_BATCH};
use crate::bsdf::{Bsdf, BsdfSample};
use crate::light::emitted;
use crate::math::{balance_heuristic, power_heuristic, Frame, Vec2, Vec3, SHADOW_EPSILON};
use crate::sampler::{dims, PixelSample};
use crate::scene::Scene;
use crate::settings::{IntegratorKind, MisHeuristic, RenderSettings};

/// Russian roulette plays only once a path's throughput (its largest channel, times η²) is below
/// this: such a path survives with probability throughput / threshold and goes on carrying the
/// threshold, so roulette never raises a path's weight above it (the lower bound of a weight
/// window, as Monte Carlo particle transport calls it; Arvo and Kirk 1990 brought roulette to
/// rendering). pbrt-v4 and Mitsuba play below throughput 1: in a bright scene the paths they kill
/// there still carry much of the image, and their survivors' boost (up to 1/throughput) was where
/// our deep paths' noise was. Unbiased whatever the value (survivors are divided by their
/// survival probability); 1/4 is the measured choice (docs/performance-journal.md, thirteenth round:
/// `bench_peers.py --variants none --before <previous build>`). The SPMD kernel uses the same
/// constant in the same arithmetic.
pub const RR_THRESHOLD: f32 = 0.25;

#[inline]
pub(crate) fn mis_weight(h: MisHeuristic, f: f32, g: f32) -> f32 {
    match h {
        MisHeuristic::Power => power_heuristic(f, g),
        MisHeuristic::Balance => balance_heuristic(f, g),
    }
}

/// Radiance arriving at `o` from direction `-d`, estimated with one path. Adds the number of rays
/// traced to `rays`. The caller checks finiteness (a non-finite result is a bug to be counted).
pub fn radiance(
    scene: &Scene,
    settings: &RenderSettings,
    o: Vec3,
    d: Vec3,
    sampler: &PixelSample,
    rays: &mut u64,
) -> Vec3 {
    let mut path = Path::new(scene, settings, o, d);
    path.run(scene, settings, sampler, rays);
    path.l
}

/// Where a path stands between two bounces: what [`Path`] carries from one to the next, as the
/// SPMD kernel ([`crate::spmd::radiance8`]) keeps it in a lane.
#[derive(Clone, Copy, Debug)]
pub struct PathState {
    /// Radiance gathered so far.
    pub l: Vec3,
    /// Path throughput.
    pub beta: Vec3,
    /// The previous vertex, its shading normal and its BSDF pdf (None after the camera and after
    /// a delta bounce): what MIS weighs the emission the next hit may find against.
    pub prev: Option<(Vec3, Vec3, f32)>,
    /// Scattering events so far (the bounce the next hit belongs to).
    pub depth: u32,
    /// η² of the transmissions so far.
    pub eta_scale: f32,
    /// The next ray, and the triangle it starts on (`convex_solid::NONE` for a camera ray; not
    /// read where the ray has been traced, as [`bounce_from_hit`]'s is on the way in).
    pub o: Vec3,
    pub d: Vec3,
    pub from: u32,
    /// Absorption coefficient of the medium the path is in (zero outside every absorbing mesh).
    pub medium: Vec3,
}

/// The stochastic-transparency seed bounce `depth`'s ray is traced with ([`Path::begin_bounce`]:
/// the spare dimension of the bounce's light set, as [`Path::draw_sets`] draws it; the light set
/// alone, which `get_4d_pair` gives bit for bit), for the SPMD kernel, which draws a bounce's
/// sets after its rays are traced.
pub fn transparency_seed(sampler: &PixelSample, depth: u32) -> u32 {
    let base = dims::BOUNCE_BASE + dims::BOUNCE_STRIDE * depth;
    sampler.get_4d((base + dims::LIGHT_POS) / 4)[(dims::SPARE % 4) as usize].to_bits()
}

/// One bounce of a path whose ray (`state.o + t state.d`) found `hit`, as [`radiance`] does it:
/// the bounce's sample sets, the vertex's emission, shading, next-event estimation, the next
/// direction and Russian roulette; `state` becomes the path's state after it. True when the path
/// goes on (with its next ray, not yet traced or counted), false when it ended (`state.l` is its
/// radiance).
///
/// Why: the SPMD kernel shades eight paths side by side but only the materials its eight-wide
/// BSDF knows; a lane whose ray reaches a coated, sheened, partly transmissive or unlit surface
/// has that vertex shaded here and goes on in its lane. Each of [`Path`]'s steps is a function
/// of the state above (the medium the path is in among it) and of the sample sets, themselves
/// functions of (pixel, sample index, bounce), so the path is the one [`radiance`] traces, bit
/// for bit. The hit's ray was counted by the caller; the rays traced here are added to `rays`.
#[inline(never)]
pub fn bounce_from_hit(
    scene: &Scene,
    settings: &RenderSettings,
    sampler: &PixelSample,
    state: &mut PathState,
    hit: Hit,
    rays: &mut u64,
) -> bool {
    let mut path = Path::new(scene, settings, state.o, state.d);
    (path.l, path.beta, path.prev, path.depth, path.eta_scale, path.from, path.medium) =
        (state.l, state.beta, state.prev, state.depth, state.eta_scale, state.from, state.medium);
    // `begin_bounce`'s and `draw_held_sets`' draws for a ray that hit something.
    path.draw_sets(sampler);
    let goes_on = path.after_hit(scene, settings, Some(hit), rays);
    *state = PathState {
        l: path.l,
        beta: path.beta,
        prev: path.prev,
        depth: path.depth,
        eta_scale: path.eta_scale,
        o: path.o,
        d: path.d,
        from: path.from,
        medium: path.medium,
    };
    goes_on
}

/// [`radiance`] for up to [`MAX_BATCH`] samples at once (`d[k]` with `samplers[k]` into
/// `out[k]`): each round, the live paths' bounce rays go to the BVH together
/// ([`Scene::intersect_surface_batch`]), their vertices choose their lights together
/// ([`crate::light::LightSet::select_batch`]), then their shadow rays go to the BVH together
/// ([`Scene::visibility_batch`]); the last path alive goes on alone. Each path does exactly the
/// arithmetic it does alone, its light sample added before anything later in it, so each result
/// is bit-equal to its own [`radiance`]. Pays where the BVH misses cache and the traversals
/// overlap their waits, and where light-tree walks overlap theirs ([`Scene::batches_paths`]).
pub fn radiance_batch(
    scene: &Scene,
    settings: &RenderSettings,
    o: Vec3,
    d: &[Vec3],
    samplers: &[PixelSample],
    rays: &mut u64,
    out: &mut [Vec3],
) {
    let n = d.len().min(samplers.len()).min(out.len()).min(MAX_BATCH);
    if n == 0 {
        return;
    }
    let mut paths = [Path::new(scene, settings, o, d[0]); MAX_BATCH];
    // The live paths are `paths[live[..count]]`, in sample order.
    let mut live = [0u8; MAX_BATCH];
    for k in 0..n {
        if k > 0 {
            paths[k] = Path::new(scene, settings, o, d[k]);
        }
        live[k] = k as u8;
    }
    let mut count = n;
    let (mut ro, mut rd, mut seeds) = ([Vec3::ZERO; MAX_BATCH], [Vec3::ZERO; MAX_BATCH], [0u32; MAX_BATCH]);
    let mut from = [crate::convex_solid::NONE; MAX_BATCH];
    let mut hits = [None; MAX_BATCH];
    let (mut tmax, mut visible) = ([0f32; MAX_BATCH], [0f32; MAX_BATCH]);
    // The triangles the shadow rays start on.
    let mut shadow_from = [crate::convex_solid::NONE; MAX_BATCH];
    // The shadow rays' paths and light samples.
    let mut waiting = [(0u8, ShadowRay::default()); MAX_BATCH];
    // The shaded vertices and their light choices.
    let mut vertices: [Option<Vertex>; MAX_BATCH] = [None; MAX_BATCH];
    let (mut qp, mut qn, mut qu) = ([Vec3::ZERO; MAX_BATCH], [None; MAX_BATCH], [0f32; MAX_BATCH]);
    let mut selected = [None; MAX_BATCH];
    while count > 1 {
        for j in 0..count {
            let k = live[j] as usize;
            seeds[j] = paths[k].begin_bounce(scene, &samplers[k], rays);
            (ro[j], rd[j], from[j]) = (paths[k].o, paths[k].d, paths[k].from);
        }
        scene.intersect_surface_batch(&ro[..count], &rd[..count], &seeds[..count], &from[..count], &mut hits[..count]);
        // The hits' triangles, then their vertices, asked of the cache for all before any is
        // shaded: on a mesh that misses cache, the shading's first loads otherwise wait one
        // after another.
        for h in hits[..count].iter().flatten() {
            scene.mesh.prefetch_triangle(h.triangle);
        }
        for h in hits[..count].iter().flatten() {
            scene.mesh.prefetch_vertices(h.triangle);
        }
        // Every path's vertex shaded, then their lights chosen together (interleaved light-tree
        // walks), then each vertex's light sample and next ray, then their shadow rays together
        // (a path that ends at this vertex still adds its light sample), then the survivors go on
        // in sample order.
        let mut queries = 0;
        for j in 0..count {
            let k = live[j] as usize;
            paths[k].draw_held_sets(scene, &samplers[k], &hits[j]);
            vertices[j] = paths[k].shade(scene, settings, hits[j]);
            if let Some((p, n, u)) = vertices[j].as_ref().and_then(|v| paths[k].light_query(v)) {
                (qp[queries], qn[queries], qu[queries]) = (p, Some(n), u);
                queries += 1;
            }
        }
        scene.lights.select_batch(&qp[..queries], &qn[..queries], &qu[..queries], &mut selected[..queries]);
        let (mut still, mut shadows, mut query) = (0, 0, 0);
        for j in 0..count {
            let k = live[j] as usize;
            let Some(v) = vertices[j] else { continue };
            let choice = if v.nee {
                query += 1;
                selected[query - 1]
            } else {
                None
            };
            let mut shadow = None;
            let more = paths[k].finish::<true>(scene, settings, v, LightChoice::Made(choice), &mut shadow, rays);
            if let Some(s) = shadow {
                (ro[shadows], rd[shadows], tmax[shadows], shadow_from[shadows]) = (s.o, s.d, s.tmax, s.from);
                waiting[shadows] = (k as u8, s);
                shadows += 1;
            }
            if more {
                live[still] = k as u8;
                still += 1;
            }
        }
        scene.visibility_batch(
            &ro[..shadows],
            &rd[..shadows],
            &tmax[..shadows],
            &shadow_from[..shadows],
            &mut visible[..shadows],
        );
        for (i, (k, s)) in waiting[..shadows].iter().enumerate() {
            paths[*k as usize].add_direct(s, visible[i]);
        }
        count = still;
    }
    if count == 1 {
        let k = live[0] as usize;
        paths[k].run(scene, settings, &samplers[k], rays);
    }
    for k in 0..n {
        out[k] = paths[k].l;
    }
}

/// One path between bounces: what [`radiance`] carries from one vertex to the next.
#[derive(Clone, Copy)]
struct Path {
    /// Radiance gathered so far.
    l: Vec3,
    /// Path throughput.
    beta: Vec3,
    /// The previous vertex and its BSDF pdf, when the last bounce was not a delta event (camera rays
    /// and mirror bounces leave it None: NEE cannot have sampled what they hit).
    prev: Option<(Vec3, Vec3, f32)>,
    depth: u32,
    /// Absorption coefficient of the medium the path is in (KHR_materials_volume): set when a
    /// transmission enters a mesh through its front face, cleared when one leaves. Meshes are taken
    /// as closed and not nested (a path inside two absorbing meshes at once sees the inner one).
    medium: Vec3,
    /// Product of η² over the transmissions so far: radiance crossing into glass is divided by η²
    /// (dielectric.rs), which says nothing about how much the path will carry once it leaves again,
    /// so Russian roulette looks at beta·eta_scale (pbrt-v4 §13.4.3 `etaScale`; Mitsuba's `eta`).
    /// Without it, paths inside glass were killed with probability 1 − 1/η² = 56 % at ior 1.5 and
    /// the survivors came back out 2.25× brighter: fireflies.
    eta_scale: f32,
    /// The next ray.
    o: Vec3,
    d: Vec3,
    /// The triangle the next ray starts on (`convex_solid::NONE` for a camera ray): a glass
    /// solid's inward rays skip its boxes ([`Scene::intersect_surface`]).
    from: u32,
    /// Whether a bounce draws its light-sampling set (NEE; the stochastic-transparency bits share it).
    draws_light_set: bool,
    /// The current bounce's two 4D sample sets ([`Path::begin_bounce`]).
    u_bsdf: [f32; 4],
    u_light: [f32; 4],
}

/// Next-event estimation's light sample, waiting for its shadow ray: the ray, and the radiance it
/// adds if nothing is in the way, in the factors [`Path::add_direct`] multiplies in order.
#[derive(Clone, Copy, Default)]
struct ShadowRay {
    o: Vec3,
    d: Vec3,
    tmax: f32,
    /// The triangle the ray leaves (a solid's facet skips its solid: [`Scene::visibility_from`]).
    from: u32,
    /// Beer–Lambert transmittance to the light, inside an absorbing mesh.
    medium: Option<Vec3>,
    /// β·f·Le.
    unshadowed: Vec3,
    /// |cos θ|·(MIS weight)/pdf.
    scale: f32,
}

/// How [`Path::finish`] gets its vertex's light: chosen there (a path alone), or already
/// chosen, with the batch's others ([`crate::light::LightSet::select_batch`]); the same choice either way.
#[derive(Clone, Copy)]
enum LightChoice {
    Now,
    Made(Option<(usize, f32)>),
}

/// A vertex a path has reached and shaded ([`Path::shade`]), waiting for its light choice: what
/// next-event estimation and the step to the next vertex need from it.
#[derive(Clone, Copy)]
struct Vertex {
    p: Vec3,
    /// How far off its triangle's plane a ray leaving `p` starts (`SurfacePoint::plane_error`).
    plane_error: f32,
    /// The geometric normal as wound (front face: counter-clockwise): which side is the mesh's
    /// inside, for glass and its medium.
    ng_winding: Vec3,
    /// The geometric normal turned to the side the path arrives from.
    ng: Vec3,
    /// The shading normal (normal-mapped, on the arrival side).
    ns: Vec3,
    frame: Frame,
    /// The direction back along the arriving ray, in `frame`.
    wo: Vec3,
    bsdf: Bsdf,
    /// The next ray's origin when it leaves on the arrival side.
    origin: Vec3,
    /// The BSDF's sample of the next direction.
    next: Option<BsdfSample>,
    /// The medium inside this mesh (KHR_materials_volume).
    absorption: Vec3,
    /// Whether next-event estimation samples a light here.
    nee: bool,
    /// The hit triangle (where the next ray starts: [`Path::from`]).
    triangle: u32,
}

impl Path {
    #[inline(always)]
    fn new(scene: &Scene, settings: &RenderSettings, o: Vec3, d: Vec3) -> Self {
        let draws_light_set =
            (settings.integrator != IntegratorKind::Bsdf && !scene.lights.is_empty()) || scene.has_transparency();
        Path {
            l: Vec3::ZERO,
            beta: Vec3::ONE,
            prev: None,
            depth: 0,
            medium: Vec3::ZERO,
            eta_scale: 1.0,
            o,
            d,
            from: crate::convex_solid::NONE,
            draws_light_set,
            u_bsdf: [0.0; 4],
            u_light: [0.0; 4],
        }
    }

    /// The path to its end, a ray at a time.
    #[inline(always)]
    fn run(&mut self, scene: &Scene, settings: &RenderSettings, sampler: &PixelSample, rays: &mut u64) {
        loop {
            let seed = self.begin_bounce(scene, sampler, rays);
            let hit = scene.intersect_surface(self.o, self.d, seed, self.from);
            self.draw_held_sets(scene, sampler, &hit);
            if !self.after_hit(scene, settings, hit, rays) {
                break;
            }
        }
    }

    /// Adds next-event estimation's light sample once its shadow ray is answered (`visible`: the
    /// fraction of light that gets through). The arithmetic of `ShadowRay`'s fields is the
    /// expression's own, in its order: β·f·Le, then visibility, then |cos|·w/pdf.
    #[inline(always)]
    fn add_direct(&mut self, ray: &ShadowRay, visible: f32) {
        let visible = match ray.medium {
            Some(t) => visible * t,
            None => Vec3::splat(visible),
        };
        if visible != Vec3::ZERO {
            self.l += ray.unshadowed * visible * ray.scale;
        }
    }

    /// Draws the current bounce's two 4D sample sets (the light set only where it is used).
    #[inline(always)]
    fn draw_sets(&mut self, sampler: &PixelSample) {
        let base = dims::BOUNCE_BASE + dims::BOUNCE_STRIDE * self.depth;
        (self.u_bsdf, self.u_light) = if self.draws_light_set {
            sampler.get_4d_pair((base + dims::BSDF_DIR) / 4, (base + dims::LIGHT_POS) / 4)
        } else {
            (sampler.get_4d((base + dims::BSDF_DIR) / 4), [0.0; 4])
        };
    }

    /// Whether [`Path::begin_bounce`] holds the bounce's sample sets back until its ray has hit
    /// something: the camera ray's (one that escapes needs none), unless stochastic transparency
    /// needs their bits to trace it.
    #[inline(always)]
    fn holds_sets(&self, scene: &Scene) -> bool {
        self.depth == 0 && !scene.has_transparency()
    }

    /// Draws the sample sets [`Path::holds_sets`] held back, once the ray has hit something.
    #[inline(always)]
    fn draw_held_sets(&mut self, scene: &Scene, sampler: &PixelSample, hit: &Option<Hit>) {
        if hit.is_some() && self.holds_sets(scene) {
            self.draw_sets(sampler);
        }
    }

    /// Counts the bounce's ray and draws its sample sets; returns the stochastic-transparency seed
    /// its ray is traced with.
    #[inline(always)]
    fn begin_bounce(&mut self, scene: &Scene, sampler: &PixelSample, rays: &mut u64) -> u32 {
        *rays += 1;
        // The bounce's two 4D sets, drawn before its ray is traced although only the vertex it
        // finds uses them: they do not depend on the hit, and each is a chain of hashes that can
        // then overlap the traversal instead of holding up the shading (Cornell box 3–4 % faster,
        // same bits). A path that ends at this hit wastes them, so the camera
        // ray's, which in an open scene may hit nothing, wait for its hit (`holds_sets`).
        if !self.holds_sets(scene) {
            self.draw_sets(sampler);
        }
        // Per-bounce random bits for stochastic (BLEND) transparency, only drawn when it can matter.
        if scene.has_transparency() {
            self.u_light[(dims::SPARE % 4) as usize].to_bits()
        } else {
            0
        }
    }

    /// The vertex the bounce's ray found (or the escape), its emission, next-event estimation and
    /// the next ray; false when the path ends here. [`Path::shade`], then [`Path::finish`] with
    /// the light chosen there; a batch runs the two apart, its paths' lights chosen between.
    #[inline(always)]
    fn after_hit(&mut self, scene: &Scene, settings: &RenderSettings, hit: Option<Hit>, rays: &mut u64) -> bool {
        let Some(v) = self.shade(scene, settings, hit) else { return false };
        self.finish::<false>(scene, settings, v, LightChoice::Now, &mut None, rays)
    }

    /// The first part of [`Path::after_hit`]: the vertex's emission, its shading frame and BSDF,
    /// and the BSDF's sample of the next direction; None when the path ends here (it escaped, hit
    /// an unlit surface, reached `max_depth`, or sees the surface from behind).
    #[inline(always)]
    fn shade(&mut self, scene: &Scene, settings: &RenderSettings, hit: Option<Hit>) -> Option<Vertex> {
        let (mesh, materials, textures) = (&scene.mesh, &scene.materials, &scene.textures);
        let Some(hit) = hit else {
            if self.medium != Vec3::ZERO {
                // An absorbing medium that never ends (an open mesh): nothing gets out.
                self.beta *= transmittance(self.medium, f32::INFINITY);
            }
            if let Some(env) = &scene.lights.environment {
                match (settings.integrator, self.prev) {
                    (_, None) | (IntegratorKind::Bsdf, _) => self.l += self.beta * env.eval(self.d),
                    // NEE already sampled the environment where it can: where the light pdf is 0
                    // (sampling off, or directions MIS compensation leaves to BSDF sampling:
                    // environment.rs) only this path finds it.
                    (IntegratorKind::Nee, Some((p_prev, n_prev, _))) => {
                        // (A float pattern: matches a light pdf of ±0.)
                        if let Some((le, 0.0)) = scene.lights.environment_eval_pdf(self.d, p_prev, Some(n_prev)) {
                            self.l += self.beta * le;
                        }
                    }
                    (IntegratorKind::Mis, Some((p_prev, n_prev, bsdf_pdf))) => {
                        if let Some((le, light_pdf)) = scene.lights.environment_eval_pdf(self.d, p_prev, Some(n_prev)) {
                            self.l += self.beta * le * mis_weight(settings.mis_heuristic, bsdf_pdf, light_pdf);
                        }
                    }
                }
            }
            return None;
        };
        let sp = scene.surface_point(&hit);
        let material_id = mesh.triangles[hit.triangle as usize].material;
        let material = &materials[material_id as usize];
        if self.medium != Vec3::ZERO {
            // Beer–Lambert over the segment's real length (from the vertex, not `o`, which
            // transparent layers may have moved).
            self.beta *= transmittance(self.medium, (sp.p - self.o).length());
        }
        if material.unlit {
            // KHR_materials_unlit: the surface shows its color and scatters nothing. No light
            // sampler picks it, so every strategy adds it with full weight.
            self.l += self.beta * material.base_color_at(textures, sp.uv, sp.color);
            return None;
        }

        if material.is_emissive() {
            let le = emitted(material, textures, sp.ng, sp.uv, -self.d);
            if le != Vec3::ZERO {
                match (settings.integrator, self.prev) {
                    (_, None) | (IntegratorKind::Bsdf, _) => self.l += self.beta * le,
                    // NEE already counted this emitter, unless it is not in the light set.
                    (IntegratorKind::Nee, Some(_)) => {
                        if !scene.lights.is_light(hit.triangle) {
                            self.l += self.beta * le;
                        }
                    }
                    (IntegratorKind::Mis, Some((p_prev, n_prev, bsdf_pdf))) => {
                        let light_pdf = scene.lights.pdf(hit.triangle, p_prev, Some(n_prev), sp.p, sp.ng);
                        self.l += self.beta * le * mis_weight(settings.mis_heuristic, bsdf_pdf, light_pdf);
                    }
                }
            }
        }
        if self.depth >= settings.max_depth {
            return None;
        }

        // Shading frame: normal map first (in the mesh's orientation), then turn both normals to the
        // side the ray came from, so every surface reflects from both faces.
        let wo_world = -self.d;
        let mut ns = sp.ns;
        let mut tangent_hint = None;
        if let Some(t) = sp.tangent {
            if let Some(n_ts) = material.tangent_space_normal(textures, sp.uv) {
                ns = normal_mapped(ns, t, n_ts);
            }
            tangent_hint = Some(t.truncate());
        }
        let mut ng = sp.ng;
        if ng.dot(wo_world) < 0.0 {
            ng = -ng;
        }
        if ns.dot(ng) < 0.0 {
            ns = -ns;
        }
        let mut frame = match tangent_hint {
            Some(t) => Frame::from_normal_tangent(ns, t),
            None => Frame::from_normal(ns),
        };
        let mut wo = frame.to_local(wo_world);
        if wo.z <= 0.0 {
            // The shading normal faces away from the viewer: fall back to the true surface.
            frame = Frame::from_normal(ng);
            wo = frame.to_local(wo_world);
            if wo.z <= 0.0 {
                return None;
            }
        }
        let mut bsdf = scene.bsdf(material_id, &sp);
        if let Some(coat) = bsdf.coat.as_mut() {
            // The coat's normal: its own normal map on the interpolated vertex normal, or that
            // normal alone (not the base's mapped one: KHR_materials_clearcoat), in the shading frame.
            let mut nc = sp.ns;
            if let (Some(t), Some(n_ts)) = (sp.tangent, material.clearcoat_tangent_space_normal(textures, sp.uv)) {
                let tan = t.truncate();
                let mapped = (tan * n_ts.x + sp.ns.cross(tan) * t.w * n_ts.y + sp.ns * n_ts.z).normalize_or_zero();
                if mapped != Vec3::ZERO && mapped.is_finite() {
                    nc = mapped;
                }
            }
            if nc.dot(ng) < 0.0 {
                nc = -nc;
            }
            let local = frame.to_local(nc).normalize_or_zero();
            coat.normal = if local.z > 1e-3 && local.is_finite() { local } else { Vec3::Z };
        }
        // Glass: entering through the front (winding) face goes from outside (n = 1) into ior;
        // leaving through it from inside, the relative index inverts.
        if sp.ng.dot(wo_world) < 0.0 {
            bsdf.eta = 1.0 / bsdf.eta;
        }
        let origin = scene.spawn_origin(sp.p, ng, sp.plane_error);
        // The other side is only needed by rays that go through the surface (glass).

        // BSDF sampling for the next segment, done before next-event estimation although used
        // after it: it does not depend on NEE's result, and drawn first it can overlap the shadow
        // ray's traversal (with f6d57ed's other two changes: Cornell box 3 % faster, same bits).
        let u_dir =
            Vec2::new(self.u_bsdf[(dims::BSDF_DIR % 4) as usize], self.u_bsdf[(dims::BSDF_DIR % 4 + 1) as usize]);
        let next = bsdf.sample(wo, self.u_bsdf[(dims::BSDF_LOBE % 4) as usize], u_dir);
        let nee = settings.integrator != IntegratorKind::Bsdf && !scene.lights.is_empty() && !bsdf.is_delta_only();
        Some(Vertex {
            p: sp.p,
            plane_error: sp.plane_error,
            ng_winding: sp.ng,
            ng,
            ns,
            frame,
            wo,
            bsdf,
            origin,
            next,
            absorption: material.absorption,
            nee,
            triangle: hit.triangle,
        })
    }

    /// Where next-event estimation at `v` chooses its light: the point, its shading normal and
    /// the selection number; None when the vertex samples no light.
    #[inline(always)]
    fn light_query(&self, v: &Vertex) -> Option<(Vec3, Vec3, f32)> {
        v.nee.then(|| (v.p, v.ns, self.u_light[(dims::LIGHT_SELECT % 4) as usize]))
    }

    /// The rest of [`Path::after_hit`]: next-event estimation with the light `choice` gives
    /// (made, it is what `LightSet::select` answers [`Path::light_query`]), then the step to the
    /// next vertex and Russian roulette; false when the path ends here.
    ///
    /// With `DEFER`, next-event estimation's shadow ray is left in `shadow` for the caller
    /// to trace (a batch traces its paths' together) and hand to [`Path::add_direct`]; the
    /// radiance it adds is the same, and added before anything later in the path.
    #[inline(always)]
    fn finish<const DEFER: bool>(
        &mut self,
        scene: &Scene,
        settings: &RenderSettings,
        v: Vertex,
        choice: LightChoice,
        shadow: &mut Option<ShadowRay>,
        rays: &mut u64,
    ) -> bool {
        let (mesh, materials, textures) = (&scene.mesh, &scene.materials, &scene.textures);
        let Vertex { p, plane_error, ng_winding, ng, ns, frame, wo, bsdf, origin, next, absorption, nee, triangle } = v;
        let wo_world = -self.d;

        // Next-event estimation.
        if nee {
            let u = Vec2::new(
                self.u_light[(dims::LIGHT_POS % 4) as usize],
                self.u_light[(dims::LIGHT_POS % 4 + 1) as usize],
            );
            let (lights, u_sel) = (&scene.lights, self.u_light[(dims::LIGHT_SELECT % 4) as usize]);
            let sample = match choice {
                LightChoice::Now => lights.sample(mesh, materials, textures, p, Some(ns), u_sel, u),
                LightChoice::Made(selected) => lights.sample_selected(mesh, materials, textures, p, selected, u),
            };
            if let Some(ls) = sample {
                let wi = frame.to_local(ls.wi);
                // Reflection needs the light above the true surface; transmission (glass), below.
                let above = wi.z > 0.0 && ls.wi.dot(ng) > 0.0;
                let below = bsdf.transmits() && wi.z < 0.0 && ls.wi.dot(ng) < 0.0;
                if ls.le != Vec3::ZERO && (above || below) {
                    let (f, bsdf_pdf) = bsdf.eval_pdf(wo, wi);
                    let origin = if above { origin } else { scene.spawn_origin(p, -ng, plane_error) };
                    if f != Vec3::ZERO {
                        *rays += 1;
                        let to_light = if ls.delta && ls.dist.is_finite() {
                            // A point light: no surface to offset from; stop just short of it.
                            let to = ls.p - origin;
                            let dist = to.length();
                            (dist > 0.0).then(|| (origin, to / dist, dist * (1.0 - 1e-5)))
                        } else if ls.dist.is_infinite() {
                            Some((origin, ls.wi, f32::INFINITY))
                        } else {
                            // An area light: aim just off its surface and stop a relative
                            // SHADOW_EPSILON short, so the emitter's own triangle (or a coplanar
                            // neighbour) is never reported as the occluder (see SHADOW_EPSILON).
                            // Where the light is an isolated convex emitter, the ray may stop
                            // at its box (`LightSet::shadow_tmax`): the same visibility.
                            let target = scene.offset_ray_origin(ls.p, ls.n);
                            let to = target - origin;
                            let dist = to.length();
                            (dist > 0.0).then(|| {
                                let d = to / dist;
                                (
                                    origin,
                                    d,
                                    scene.lights.shadow_tmax(ls.light, origin, d, dist * (1.0 - SHADOW_EPSILON)),
                                )
                            })
                        };
                        if let Some((o, d, tmax)) = to_light {
                            // Alone, the ray is traced first and the rest is only worked out when
                            // light gets through; deferred, it all waits in `shadow`.
                            let visible = if DEFER { 1.0 } else { scene.visibility_from(o, d, tmax, triangle) };
                            if visible != 0.0 {
                                let w = match settings.integrator {
                                    IntegratorKind::Mis if !ls.delta => {
                                        mis_weight(settings.mis_heuristic, ls.pdf, bsdf_pdf)
                                    }
                                    _ => 1.0,
                                };
                                // The medium the shadow ray crosses: that of the side it leaves
                                // by (glass stops shadow rays, so it stays in that one medium up
                                // to the light).
                                let entering = ng_winding.dot(wo_world) > 0.0;
                                let medium = medium_beyond(self.medium, below, entering, absorption);
                                let ray = ShadowRay {
                                    o,
                                    d,
                                    tmax,
                                    from: triangle,
                                    medium: (medium != Vec3::ZERO).then(|| transmittance(medium, ls.dist)),
                                    unshadowed: self.beta * f * ls.le,
                                    scale: wi.z.abs() * w / ls.pdf,
                                };
                                if DEFER {
                                    *shadow = Some(ray);
                                } else {
                                    self.add_direct(&ray, visible);
                                }
                            }
                        }
                    }
                }
            }
        }

        let Some(bs) = next else { return false };
        let wi_world = frame.to_world(bs.wi);
        let transmitted = bs.wi.z < 0.0;
        if (wi_world.dot(ng) <= 0.0) != transmitted || wi_world.dot(ng) == 0.0 {
            // A shading normal can send a direction to the wrong side of the true surface; that
            // energy is lost.
            return false;
        }
        self.beta *= bs.weight();
        if !self.beta.is_finite() || self.beta == Vec3::ZERO {
            return false;
        }
        if transmitted {
            self.eta_scale *= bsdf.eta * bsdf.eta;
            self.medium = medium_beyond(self.medium, true, ng_winding.dot(wo_world) > 0.0, absorption);
        }
        self.prev = if bs.delta { None } else { Some((p, ns, bs.pdf)) };
        self.o = if transmitted { scene.spawn_origin(p, -ng, plane_error) } else { origin };
        self.d = wi_world;
        self.from = triangle;
        self.depth += 1;

        if self.depth >= settings.rr_depth {
            // β·η² in units of the threshold: the roulette plays below 1 ([`RR_THRESHOLD`]).
            let m = self.beta.max_element() * self.eta_scale * (1.0 / RR_THRESHOLD);
            if m < 1.0 {
                let q = (1.0 - m).max(0.0);
                if self.u_bsdf[(dims::RUSSIAN_ROULETTE % 4) as usize] < q {
                    return false;
                }
                self.beta /= 1.0 - q;
            }
        }
        true
    }
}

/// The shading normal `ns` bent by a normal map's tangent-space normal `n_ts` in the frame of
/// tangent `t` (xyz, handedness w: the bitangent is ns × t · w; glTF 2.0 §3.9.3); `ns` itself
/// where the mapped normal degenerates. Shared with the eight-lane kernel (`spmd.rs`).
#[inline]
pub(crate) fn normal_mapped(ns: Vec3, t: crate::math::Vec4, n_ts: Vec3) -> Vec3 {
    let tan = t.truncate();
    let bitangent = ns.cross(tan) * t.w;
    let mapped = (tan * n_ts.x + bitangent * n_ts.y + ns * n_ts.z).normalize_or_zero();
    if mapped != Vec3::ZERO && mapped.is_finite() {
        mapped
    } else {
        ns
    }
}

/// The medium on the side a direction leaving a vertex goes to: the path's own (`current`) on
/// the side it arrived from; through the surface (`through`), the mesh's inside (`absorption`)
/// when `entering` (it arrived on the front, winding face) and none when leaving. The path's
/// medium after a transmission and a light sample's shadow ray both take it (the kernel too).
#[inline(always)]
pub(crate) fn medium_beyond(current: Vec3, through: bool, entering: bool, absorption: Vec3) -> Vec3 {
    match (through, entering) {
        (false, _) => current,
        (true, true) => absorption,
        (true, false) => Vec3::ZERO,
    }
}

/// Beer–Lambert transmittance exp(−σ·t) per channel (a channel with σ = 0 is 1 even for t = ∞).
#[inline]
pub(crate) fn transmittance(sigma: Vec3, t: f32) -> Vec3 {
    let x = |s: f32| if s > 0.0 { (-s * t).exp() } else { 1.0 };
    Vec3::new(x(sigma.x), x(sigma.y), x(sigma.z))
}
