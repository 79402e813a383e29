//! A render-ready scene: flattened world-space mesh, materials, textures, acceleration structure,
//! lights and cameras. Built once per job; everything here is read-only while rendering.

use crate::accel::{Accel, Hit};
use crate::bsdf::Bsdf;
use crate::camera::Camera;
use crate::light::LightSet;
use crate::material::{AlphaMode, Material};

/// Most transparent surfaces a ray passes before it is considered absorbed.
const MAX_TRANSPARENT_LAYERS: u32 = 256;
use crate::math::Vec3;
use crate::mesh::Mesh;
use crate::texture::Texture;

pub struct Scene {
    pub mesh: Mesh,
    /// Fixed once the scene is built: `transparent`, `blends` and `base_colour_bsdfs` are derived
    /// from it there.
    pub materials: Vec<Material>,
    pub textures: Vec<Texture>,
    pub cameras: Vec<Camera>,
    pub accel: Accel,
    /// The closed convex glass objects whose inward rays may skip their boxes
    /// ([`crate::convex_solid`]).
    solids: crate::convex_solid::ConvexSolids,
    pub lights: LightSet,
    pub bounds: (Vec3, Vec3),
    /// The ray-origin offset's scale for these bounds ([`crate::math::offset_scale`]).
    offset_scale: f32,
    /// Some material is MASK or BLEND (computed once: it is asked on every ray).
    transparent: bool,
    /// Per material, its BSDF but for the base colour when no other texture feeds it
    /// ([`Material::bsdf_but_base_colour`]; with no base colour texture either, its BSDF
    /// everywhere without vertex colours: [`Material::uniform_bsdf`]).
    base_colour_bsdfs: Vec<Option<Bsdf>>,
    /// Some material is alpha-blended ([`crate::material::any_blends`]).
    blends: bool,
    /// What the loader could not honour but rendered without (optional extensions), for the user.
    pub warnings: Vec<String>,
    /// The file's `asset.generator` (decides `--light-units auto`).
    pub generator: Option<String>,
    /// The units the punctual lights are in now (set once by `prepare`).
    light_units: crate::punctual::LightUnits,
    /// Animations, skins and morph targets (None for a static scene).
    animator: Option<crate::animation::Animator>,
    /// The time the scene is posed at, in seconds.
    time: f32,
    /// What `set_frame` last posed: (frame, fps bits, animation).
    pose_key: Option<(u32, u32, Option<String>)>,
    /// Overrides [`Scene::batches_paths`]' rule (tests; images are the same either way).
    batch_paths: Option<bool>,
    /// Per material, what the eight-lane kernel reads of it, when every surface the mesh uses is
    /// one it renders ([`crate::spmd::LaneMaterial::table`]; fixed with the materials).
    lane_materials: Option<crate::spmd::LaneTable>,
    /// False when [`Self::set_scalar_reference`] or [`Self::set_lanes`] turned the kernel off.
    lanes: bool,
}

/// The visibility of an opaque scene's shadow ray: 1 where it gets through, else 0.
#[inline(always)]
fn passes(through: bool) -> f32 {
    if through {
        1.0
    } else {
        0.0
    }
}

/// The closed convex solids ([`crate::convex_solid`]). Glass ones: among the triangles whose
/// material transmits light (only those send rays inward: refraction and internal reflection)
/// and is opaque to shadow rays (alpha OPAQUE: a shadow ray through a solid is blocked,
/// `ConvexSolids::blocks`). Opaque ones (every other alpha-OPAQUE triangle): their rays never go
/// inward, and the occlusion shortcut alone did not pay for its ray–ball tests (envlit's two
/// spheres: the same time; veach's four sphere lights: 1.07× the time, every shadow ray testing
/// four balls), so they only skip themselves when a ray leaves them (`ConvexSolids::leaving`):
/// on envlit, whose two spheres are 2 560 of its 2 562 triangles, a ray leaving a sphere
/// started inside its boxes and tested the triangles around its origin.
///
/// The scene's BVH `accel` is marked by solid, so rays leaving one skip its subtrees.
fn find_solids(mesh: &Mesh, materials: &[Material], accel: &mut Accel) -> crate::convex_solid::ConvexSolids {
    let opaque = |m: u32| materials.get(m as usize).is_some_and(|m| m.alpha_mode == AlphaMode::Opaque);
    let transmits =
        |m: u32| materials.get(m as usize).is_some_and(|m| m.transmission > 0.0 || m.transmission_texture.is_some());
    // Emitters are left out of the opaque ones: a path that meets a light seldom goes on from
    // it, and every ray from a solid's triangle pays the solid's checks (veach's four sphere
    // lights: 1.6 % more instructions, nothing saved).
    let emits = |m: u32| materials.get(m as usize).is_some_and(Material::is_emissive);
    let solids =
        crate::convex_solid::ConvexSolids::find(mesh, |m| transmits(m) && opaque(m), |m| opaque(m) && !emits(m));
    solids.mark_nodes(accel);
    solids
}

/// [`crate::math::offset_scale`] of the largest coordinate within `bounds`.
fn offset_scale_of((min, max): (Vec3, Vec3)) -> f32 {
    crate::math::offset_scale(min.abs().max(max.abs()).max_element())
}

impl Scene {
    /// Builds the acceleration structure and light set. Lights are built only from emissive
    /// triangles; a scene without emitters gets an empty set and renders black.
    pub fn new(mesh: Mesh, materials: Vec<Material>, textures: Vec<Texture>, cameras: Vec<Camera>) -> Self {
        let (min, max) = mesh.world_bounds().unwrap_or((Vec3::splat(-1.0), Vec3::splat(1.0)));
        let t = std::time::Instant::now();
        let mut accel = Accel::build(&mesh);
        tracing::debug!(triangles = mesh.triangles.len(), seconds = t.elapsed().as_secs_f64(), "BVH built");
        let lights = LightSet::build(&mesh, &materials, &textures, Vec::new(), None, (max - min).length() * 0.5);
        tracing::debug!(triangles = mesh.triangles.len(), lights = lights.lights.len(), "scene built");
        let transparent = materials.iter().any(|m| m.alpha_mode != AlphaMode::Opaque);
        let base_colour_bsdfs: Vec<Option<Bsdf>> = materials.iter().map(Material::bsdf_but_base_colour).collect();
        let blends = crate::material::any_blends(&materials);
        let lane_materials = crate::spmd::LaneMaterial::table(&mesh, &materials, &base_colour_bsdfs, &textures);
        let solids = find_solids(&mesh, &materials, &mut accel);
        Scene {
            mesh,
            materials,
            textures,
            cameras,
            accel,
            solids,
            lights,
            bounds: (min, max),
            offset_scale: offset_scale_of((min, max)),
            transparent,
            base_colour_bsdfs,
            blends,
            warnings: Vec::new(),
            animator: None,
            time: 0.0,
            pose_key: None,
            batch_paths: None,
            lane_materials,
            lanes: true,
            generator: None,
            light_units: crate::punctual::LightUnits::Gltf,
        }
    }

    /// Lights the scene with an environment: the light set's selection made again so NEE can
    /// choose it, its area lights kept (`LightSet::with_others`: the mesh must be the one the set
    /// was built on, as it is from loading on; `set_frame` rebuilds all after a pose).
    pub fn set_environment(&mut self, env: Option<crate::environment::Environment>) {
        let punctual = std::mem::take(&mut self.lights.punctual);
        self.relight(punctual, env, false);
    }

    /// Chooses how NEE selects lights (builds the light tree only when asked for); `auto` as seen
    /// through the default camera at 64×64.
    pub fn set_light_sampler(&mut self, kind: crate::light::LightSamplerKind) {
        let view = self.camera(None).ok().map(|c| (c, 64, 64));
        self.set_light_sampler_for(kind, view);
    }

    /// As `set_light_sampler`, with `auto` measured through `view` (camera, image width, height).
    pub fn set_light_sampler_for(&mut self, kind: crate::light::LightSamplerKind, view: Option<(Camera, u32, u32)>) {
        if kind != crate::light::LightSamplerKind::Auto {
            return self.lights.set_kind_exact(kind, &self.mesh);
        }
        let (chosen, scores) = crate::light_choice::choose(self, view);
        tracing::info!(?chosen, ?scores, "light sampler auto");
    }

    /// What `prepare` reads from the settings, as a key: a scene prepared for one job may serve
    /// another only when their keys are equal (workers cache prepared scenes by it). Kept next to
    /// `prepare` so that an input added there cannot be forgotten here.
    pub fn prepare_key(settings: &crate::RenderSettings) -> String {
        format!(
            "{:?} {:?} {:?} {:?} {:?} {}x{}",
            settings.environment,
            settings.integrator,
            settings.light_units,
            settings.light_sampler,
            settings.camera,
            settings.width,
            settings.height
        )
    }

    /// Everything a render with `settings` needs beyond the glTF: the light units, the environment
    /// (map paths relative to `base`) and the light sampler (`auto` measured through the camera at
    /// the image size). Its inputs are `prepare_key`'s.
    pub fn prepare(
        &mut self,
        settings: &crate::RenderSettings,
        base: &std::path::Path,
    ) -> Result<(), crate::RenderError> {
        self.set_light_units(settings.light_units);
        let mis = settings.integrator == crate::settings::IntegratorKind::Mis;
        self.attach_environment(&settings.environment, base, mis)?;
        let view = self.camera(settings.camera).ok().map(|c| (c, settings.width, settings.height));
        self.set_light_sampler_for(settings.light_sampler, view);
        Ok(())
    }

    /// Makes the SIMD parts of ray queries and light selection (eight-wide leaf triangles, the
    /// light tree's family evaluation) run their one-at-a-time reference instead: same images, bit for bit
    /// (`renderer/tests/watertight.rs` renders every test scene both ways). Lasts until the
    /// light set or BVH is rebuilt.
    pub fn set_scalar_reference(&mut self, on: bool) {
        self.accel.set_scalar_reference(on);
        self.lights.set_scalar_reference(on);
        self.lanes = !on;
    }

    /// Turns the eight-lane kernel ([`crate::spmd`]) on (the default) or off; the images are the
    /// same either way (`renderer/tests/spmd.rs`). Also set by [`Self::set_scalar_reference`].
    pub fn set_lanes(&mut self, on: bool) {
        self.lanes = on;
    }

    /// The eight-lane kernel's material table when it renders this scene with `settings`
    /// ([`crate::spmd::radiance8`]): some surface a metallic-roughness material the kernel shades
    /// ([`crate::spmd::LaneMaterial::table`]; it hands the others' vertices to the scalar path),
    /// the MIS integrator and some light to sample.
    pub fn lanes(&self, settings: &crate::RenderSettings) -> Option<&crate::spmd::LaneTable> {
        let usable = cfg!(all(target_arch = "x86_64", target_feature = "avx2"))
            && self.lanes
            && settings.integrator == crate::settings::IntegratorKind::Mis
            && !self.lights.is_empty();
        if usable {
            self.lane_materials.as_ref()
        } else {
            None
        }
    }

    /// Overrides whether renders trace a pixel's samples' paths as a batch (by default only above
    /// [`crate::accel::BATCH_RAYS_ABOVE`] triangles): same images either way
    /// (`renderer/tests/batched_paths.rs`). Lasts until the BVH is rebuilt.
    pub fn set_batch_rays(&mut self, on: bool) {
        self.accel.set_batch_rays(on);
    }

    /// Attaches the animation data the loader gathered (the scene is posed at time 0).
    pub fn set_animator(&mut self, animator: crate::animation::Animator) {
        self.animator = Some(animator);
        self.time = 0.0;
    }

    /// Whether frames differ: the file animates something.
    pub fn is_animated(&self) -> bool {
        self.animator.as_ref().is_some_and(|a| !a.clips.is_empty())
    }

    /// The file's animations: (index, name).
    pub fn animations(&self) -> Vec<(usize, Option<String>)> {
        self.animator.as_ref().map_or(Vec::new(), |a| a.clips.iter().map(|c| c.name.clone()).enumerate().collect())
    }

    /// Poses the scene at `frame` (time frame / settings.fps, the animations `settings.animation`
    /// names, default all) and rebuilds what the pose moves: instance transforms, posed vertices,
    /// cameras, punctual lights, the top-level BVH, the light set and — for `auto` — the light
    /// sampler choice. A pure function of (scene as loaded and prepared, settings, frame): frame N
    /// renders the same whatever frame the scene was posed at before. A static scene is unchanged.
    pub fn set_frame(&mut self, settings: &crate::RenderSettings, frame: u32) -> Result<(), crate::RenderError> {
        let Some(mut animator) = self.animator.take() else { return Ok(()) };
        if let Err(e) = animator.select(settings.animation.as_deref()) {
            self.animator = Some(animator);
            return Err(crate::RenderError::Settings(e.0));
        }
        let fps =
            if settings.fps > 0.0 && settings.fps.is_finite() { settings.fps } else { crate::animation::DEFAULT_FPS };
        let t = frame as f32 / fps;
        let clock = std::time::Instant::now();
        let mut punctual = animator.apply(t, &mut self.mesh, &mut self.cameras);
        let posed = clock.elapsed();
        let scale = self.light_units.scale();
        for p in &mut punctual {
            p.intensity *= scale;
        }
        self.animator = Some(animator);
        self.time = t;
        self.pose_key = Some((frame, settings.fps.to_bits(), settings.animation.clone()));
        self.accel.rebuild_top(&self.mesh);
        self.solids = find_solids(&self.mesh, &self.materials, &mut self.accel);
        if let Some(b) = self.mesh.world_bounds() {
            self.bounds = b;
            self.offset_scale = offset_scale_of(b);
        }
        let rebuilt = clock.elapsed();
        self.set_punctual(punctual);
        let view = self.camera(settings.camera).ok().map(|c| (c, settings.width, settings.height));
        self.set_light_sampler_for(settings.light_sampler, view);
        tracing::debug!(
            frame,
            pose_s = posed.as_secs_f64(),
            top_level_bvh_s = (rebuilt - posed).as_secs_f64(),
            lights_s = (clock.elapsed() - rebuilt).as_secs_f64(),
            "frame posed"
        );
        Ok(())
    }

    /// What the scene was last posed for by `set_frame`: (frame, fps bits, animation).
    pub fn pose_key(&self) -> Option<&(u32, u32, Option<String>)> {
        self.pose_key.as_ref()
    }

    /// The time (seconds) the scene is posed at.
    pub fn time(&self) -> f32 {
        self.time
    }

    /// Reads the punctual lights in `units` (`auto`: by the file's generator); idempotent.
    pub fn set_light_units(&mut self, units: crate::punctual::LightUnits) {
        let units = units.resolve(self.generator.as_deref());
        if units == self.light_units || self.lights.punctual.is_empty() {
            self.light_units = units;
            return;
        }
        let f = units.scale() / self.light_units.scale();
        let mut punctual = self.lights.punctual.clone();
        for p in &mut punctual {
            p.intensity *= f;
        }
        tracing::info!(?units, generator = ?self.generator, "punctual light units");
        self.light_units = units;
        self.replace_punctual(punctual);
    }

    /// Adds KHR_lights_punctual lights and rebuilds the whole light set, area lights included
    /// (`set_frame` calls it after moving the mesh).
    pub fn set_punctual(&mut self, punctual: Vec<crate::punctual::PunctualLight>) {
        let env = self.lights.environment.take();
        self.relight(punctual, env, true);
    }

    /// [`Self::set_punctual`] on a mesh that has not changed since the light set was built: its
    /// area lights kept (`LightSet::with_others`), only the selection made again.
    pub(crate) fn replace_punctual(&mut self, punctual: Vec<crate::punctual::PunctualLight>) {
        let env = self.lights.environment.take();
        self.relight(punctual, env, false);
    }

    /// The light set with `punctual` lights and `env`: built anew (`area_lights`: the mesh may
    /// have moved) or over the area lights it has, choosing as it did.
    fn relight(
        &mut self,
        punctual: Vec<crate::punctual::PunctualLight>,
        env: Option<crate::environment::Environment>,
        area_lights: bool,
    ) {
        let radius = (self.bounds.1 - self.bounds.0).length() * 0.5;
        let kind = self.lights.kind;
        let old = std::mem::take(&mut self.lights);
        self.lights = if area_lights {
            LightSet::build(&self.mesh, &self.materials, &self.textures, punctual, env, radius)
        } else {
            old.with_others(punctual, env, radius)
        };
        self.lights.set_kind_exact(kind, &self.mesh);
    }

    /// Loads and attaches the environment described by `settings`; `base` resolves a relative map
    /// path. `mis_compensation`: the integrator combines light and BSDF samples by MIS, so the
    /// map's sampling may leave its dim part to BSDF sampling (`Environment::from_texels`).
    pub fn attach_environment(
        &mut self,
        settings: &crate::environment::EnvironmentSettings,
        base: &std::path::Path,
        mis_compensation: bool,
    ) -> Result<(), crate::RenderError> {
        use crate::environment::Environment;
        let env = match (&settings.map, settings.color) {
            (Some(map), _) => Some(Environment::load(
                &base.join(map),
                settings.strength,
                settings.rotate_deg,
                settings.sampling,
                mis_compensation,
            )?),
            (None, Some(c)) => {
                let c = crate::math::Vec3::from(c) * settings.strength;
                if !c.is_finite() || c.min_element() < 0.0 {
                    return Err(crate::RenderError::Settings(format!(
                        "environment color {c:?} must be finite and non-negative"
                    )));
                }
                Some(Environment::uniform(c, settings.sampling))
            }
            (None, None) => None,
        };
        self.set_environment(env);
        Ok(())
    }

    /// Where the closest-hit walk of a ray from `o` along `d` starting on triangle `from` may
    /// begin its node tests ([`crate::convex_solid::ConvexSolids::tmin`]; 0: from the start).
    pub fn solid_tmin(&self, from: u32, o: Vec3, d: Vec3) -> f32 {
        self.solids.tmin(from, o, d)
    }

    /// Whether a closed convex glass solid certainly blocks the segment from `o` to `o + tmax·d`
    /// ([`crate::convex_solid::ConvexSolids::blocks`]; shadow rays stop there without a walk).
    /// (Inlined as a count test: scenes without glass solids keep their shadow-ray path as it was.)
    #[inline]
    pub fn solid_blocks(&self, o: Vec3, d: Vec3, tmax: f32) -> bool {
        self.solids.glass_len() != 0 && self.solids.blocks(o, d, tmax)
    }

    /// The exit of an inward ray from triangle `from` found by walking its solid's surface
    /// ([`crate::solid_surface`]): None where the ray is not bounded or the walk is not sure.
    pub fn solid_surface_exit(&self, from: u32, o: Vec3, d: Vec3) -> Option<crate::accel::Hit> {
        self.solids.surface_exit(from, o, d)
    }

    /// The closed convex solid triangle `t` is a facet of ([`crate::convex_solid`]), if any.
    pub fn solid_of(&self, t: u32) -> Option<u32> {
        self.solids.solid_of(t)
    }

    /// The solid a ray from triangle `from` along `d` leaves (it points out of the solid through
    /// that facet), whose walk then skips the solid's subtrees
    /// ([`crate::accel::Accel::intersect_leaving`]); None otherwise.
    pub fn solid_left(&self, from: u32, d: Vec3) -> Option<u32> {
        self.solids.leaving(&self.mesh, from, d)
    }

    /// Turns the solids' surface walk off (inward rays then walk the solid's BVH) or on again
    /// (`renderer/tests/convex_solid.rs` renders both; the hits are the same). Finding the solids
    /// again (`set_convex_solids`) turns it back on.
    pub fn set_solid_surface_walk(&mut self, on: bool) {
        self.solids.set_surface_walk(on);
    }

    /// How many closed convex glass solids the scene has ([`crate::convex_solid`]).
    pub fn convex_solids(&self) -> usize {
        self.solids.glass_len()
    }

    /// How many closed convex opaque solids the scene has: rays leaving one skip it
    /// ([`crate::convex_solid::ConvexSolids::leaving`]), and that is all they do.
    pub fn opaque_solids(&self) -> usize {
        self.solids.len() - self.solids.glass_len()
    }

    /// Turns the solids' bound off (false: every walk starts at 0) or finds them again
    /// (`renderer/tests/convex_solid.rs` renders both; the hits are the same).
    pub fn set_convex_solids(&mut self, on: bool) {
        self.solids = if on {
            find_solids(&self.mesh, &self.materials, &mut self.accel)
        } else {
            self.accel.mark_solids(&[]);
            Default::default()
        };
    }

    /// Rebuilds the ray-query structure with another BVH (benchmarks compare them).
    pub fn use_accel(&mut self, kind: crate::accel::AccelKind) {
        self.accel = Accel::build_with(&self.mesh, kind);
        self.solids.mark_nodes(&mut self.accel);
    }

    #[inline]
    pub fn intersect(&self, o: Vec3, d: Vec3, tmax: f32) -> Option<Hit> {
        self.accel.intersect(o, d, tmax)
    }

    #[inline]
    pub fn occluded(&self, o: Vec3, d: Vec3, tmax: f32) -> bool {
        self.accel.occluded(o, d, tmax)
    }

    /// True when some material is MASK or BLEND (rays may pass through surfaces).
    #[inline]
    pub fn has_transparency(&self) -> bool {
        self.transparent
    }

    /// Whether some surface is alpha-blended (BLEND: it passes a ray by the sample's numbers and
    /// shadow rays in part).
    pub fn blends(&self) -> bool {
        self.blends
    }

    /// The world-space surface point of a hit (on world geometry or on an instance).
    #[inline]
    pub fn surface_point(&self, hit: &Hit) -> crate::mesh::SurfacePoint {
        match self.mesh.instances.get(hit.instance as usize) {
            Some(inst) => self.mesh.instance_surface_point(inst, hit.triangle, hit.b1, hit.b2),
            None => self.mesh.surface_point(hit.triangle, hit.b1, hit.b2),
        }
    }

    /// The BSDF of material `material` at `sp`: the scene's precomputed one when nothing varies it
    /// there (no texture, no vertex colour: multiplying by a colour of ones is exact, so the two
    /// are the same bits), else resolved from the textures.
    #[inline]
    pub fn bsdf(&self, material: u32, sp: &crate::mesh::SurfacePoint) -> Bsdf {
        self.bsdf_at(material, || sp.uv, sp.color)
    }

    /// [`Self::bsdf`] from a hit's vertex colour and texture coordinates (`uv`, asked for only
    /// where a texture reads them). Where no texture but the base colour's feeds the material, it
    /// is the precomputed BSDF with the base colour resolved at the point
    /// (`Material::base_color_at`): nothing else of [`Material::bsdf`] reads the base colour
    /// texture or the vertex colour, so the two are the same bits
    /// (`base_coloured_bsdf_is_the_materials_own`), without `Material::bsdf`'s clamps, roughness
    /// mapping and F0 division at every hit (`BoxTextured.glb`: 2.1 % fewer instructions a
    /// render; docs/performance-journal.md, thirty-second round).
    #[inline]
    pub fn bsdf_at(
        &self,
        material: u32,
        uv: impl FnOnce() -> crate::texture::TexCoords,
        color: crate::math::Vec4,
    ) -> Bsdf {
        let m = &self.materials[material as usize];
        match self.base_colour_bsdfs.get(material as usize) {
            // Nothing varies it here: the precomputed BSDF (a colour of ones multiplies exactly).
            Some(Some(b)) if m.base_color_texture.is_none() && color == crate::math::Vec4::ONE => *b,
            Some(Some(b)) => {
                let uv = if m.base_color_texture.is_some() { uv() } else { Default::default() };
                Bsdf { base_color: m.base_color_at(&self.textures, uv, color), ..*b }
            }
            _ => m.bsdf(&self.textures, uv(), color),
        }
    }

    /// The first surface along the ray that stops it: MASK cut-outs are skipped, BLEND surfaces stop
    /// the ray with probability alpha, decided by `seed` (a pure function of the sample, so the
    /// determinism rule holds).
    #[inline]
    pub fn intersect_surface(&self, o: Vec3, d: Vec3, seed: u32, from: u32) -> Option<Hit> {
        if self.walks_past_cutouts() && !self.batches_rays() {
            return self.accel.intersect_accepted(o, d, f32::INFINITY, |h| self.stops_at(h, seed));
        }
        // Without solids, the plain walk (its node tests start at 0, a constant).
        let first = if self.solids.is_empty() {
            self.accel.intersect(o, d, f32::INFINITY)
        } else if let Some((tmin, solid)) = self.solids.bound(from, o, d) {
            self.solids.closest(solid, o, d, tmin)
        } else if let Some(solid) = self.solids.leaving(&self.mesh, from, d) {
            // Asked after the bound: asked first it charged every inward ray the facet's normal
            // (glass +0.8 % instructions). The batch below asks in the same order; a helper for
            // both cost glass 0.6 % more instructions (callgrind), so the two stay written out.
            self.accel.intersect_leaving(o, d, solid)
        } else {
            self.accel.intersect(o, d, f32::INFINITY)
        };
        if !self.has_transparency() {
            return first;
        }
        self.through_layers(o, d, seed, first)
    }

    /// Whether rays pass transparent surfaces inside their walk ([`Accel::intersect_accepted`],
    /// [`Accel::occluded_accepted`]) rather than by a walk per layer: no ray starts inside a
    /// glass solid (whose walks are their own) and the BVH is obvhs' (one level or two).
    fn walks_past_cutouts(&self) -> bool {
        self.transparent && self.solids.is_empty() && self.accel.walks_accepted()
    }

    /// A hit surface's alpha mode and coverage there (the alpha at the hit's texture coordinates
    /// and colour, which an instance's hit shares with its prototype's; 1 on an opaque surface).
    fn coverage(&self, hit: &Hit) -> (AlphaMode, f32) {
        let tri = hit.triangle;
        let Some(m) = self.mesh.triangles.get(tri as usize).and_then(|t| self.materials.get(t.material as usize))
        else {
            return (AlphaMode::Opaque, 1.0);
        };
        if m.alpha_mode == AlphaMode::Opaque {
            return (AlphaMode::Opaque, 1.0);
        }
        let (uv, color) = (self.mesh.tex_coords_at(tri, hit.b1, hit.b2), self.mesh.color_at(tri, hit.b1, hit.b2));
        (m.alpha_mode, m.alpha(&self.textures, uv, color))
    }

    /// Whether a ray with transparency seed `seed` stops at `hit`: always on an opaque surface,
    /// where the alpha reaches the cutoff on a MASK cut-out, with probability alpha on a BLEND
    /// surface — by the hash of the seed, the triangle and the instance, so each blended surface a
    /// ray meets (each copy of a prototype's too) decides by a number of its own whatever order a
    /// walk meets them in (the walk per layer hashed the layer's number).
    fn stops_at(&self, hit: &Hit, seed: u32) -> bool {
        match self.coverage(hit) {
            (AlphaMode::Opaque, _) => true,
            (AlphaMode::Mask(cutoff), a) => a >= cutoff,
            (AlphaMode::Blend, a) => {
                let key = ((seed as u64) << 32) | hit.triangle as u64;
                let key = match hit.instance {
                    crate::accel::NO_INSTANCE => key,
                    i => key ^ crate::sampler::hash_u64(i as u64),
                };
                crate::sampler::hash_unit(key) < a
            }
        }
    }

    /// [`Self::intersect_surface`] on from the hit `first` of its first layer (the ray `o + t d`'s
    /// closest hit): the first surface the ray stops at. Where [`Self::walks_past_cutouts`] (on
    /// a BVH large enough to batch: a smaller one's rays walk past the cut-outs from the start),
    /// `first` if the ray stops there, else one walk from `o` past every cut-out; so the batched
    /// first walks are kept where most rays stop at their first hit. Otherwise a walk per layer,
    /// passing through (MASK below the cutoff, BLEND by its random bits) at most
    /// [`MAX_TRANSPARENT_LAYERS`] layers, each walk from just past the last.
    fn through_layers(&self, o: Vec3, d: Vec3, seed: u32, first: Option<Hit>) -> Option<Hit> {
        if self.walks_past_cutouts() {
            let hit = first?;
            if self.stops_at(&hit, seed) {
                return Some(hit);
            }
            return self.accel.intersect_accepted(o, d, f32::INFINITY, |h| self.stops_at(h, seed));
        }
        let mut hit = first?;
        for layer in 0..MAX_TRANSPARENT_LAYERS {
            let stops = match self.coverage(&hit) {
                (AlphaMode::Opaque, _) => true,
                (AlphaMode::Mask(cutoff), a) => a >= cutoff,
                (AlphaMode::Blend, a) => crate::sampler::hash_unit(((seed as u64) << 32) | layer as u64) < a,
            };
            if stops {
                return Some(hit);
            }
            if layer + 1 == MAX_TRANSPARENT_LAYERS {
                break;
            }
            hit = self.accel.intersect(self.pass_through(&hit, d), d, f32::INFINITY)?;
        }
        None
    }

    /// [`Self::intersect_surface`] for up to [`crate::accel::MAX_BATCH`] rays into `out`: traced
    /// together ([`Accel::intersect_batch`]) where the BVH batches them; a ray that meets a
    /// transparent layer goes on through the others alone. On a smaller BVH without transparency,
    /// as [`Self::intersect_lanes_where`] answers them (a solid's rays by the solid, the others'
    /// walks in one call), else one query each. The same hits every way.
    pub fn intersect_surface_batch(&self, o: &[Vec3], d: &[Vec3], seed: &[u32], from: &[u32], out: &mut [Option<Hit>]) {
        let n = o.len().min(d.len()).min(seed.len()).min(from.len()).min(out.len());
        if !self.batches_rays() {
            if self.walks_lanes() && n <= 32 {
                self.intersect_lanes_where(o, d, from, crate::accel::low_bits(n), out);
            } else {
                for k in 0..n {
                    out[k] = self.intersect_surface(o[k], d[k], seed[k], from[k]);
                }
            }
            return;
        }
        if self.solids.is_empty() {
            self.accel.intersect_batch(&o[..n], &d[..n], f32::INFINITY, &mut out[..n]);
        } else {
            // A ray inside a glass solid walks the solid's own BVH (as `intersect_surface`); the
            // others are walked together.
            const B: usize = crate::accel::MAX_BATCH;
            for s in (0..n).step_by(B) {
                let e = (s + B).min(n);
                let (mut qo, mut qd, mut at) = ([Vec3::ZERO; B], [Vec3::ZERO; B], [0usize; B]);
                let mut m = 0;
                for k in s..e {
                    if let Some((tmin, solid)) = self.solids.bound(from[k], o[k], d[k]) {
                        out[k] = self.solids.closest(solid, o[k], d[k], tmin);
                    } else if let Some(solid) = self.solids.leaving(&self.mesh, from[k], d[k]) {
                        out[k] = self.accel.intersect_leaving(o[k], d[k], solid);
                    } else {
                        (qo[m], qd[m], at[m]) = (o[k], d[k], k);
                        m += 1;
                    }
                }
                let mut hits = [None; B];
                self.accel.intersect_batch(&qo[..m], &qd[..m], f32::INFINITY, &mut hits[..m]);
                for j in 0..m {
                    out[at[j]] = hits[j];
                }
            }
        }
        if self.has_transparency() {
            for (k, h) in out.iter_mut().enumerate().take(o.len().min(d.len()).min(seed.len())) {
                *h = self.through_layers(o[k], d[k], seed[k], *h);
            }
        }
    }

    /// [`Self::intersect_surface_batch`] for rays from one `origin` whose directions lie close
    /// together (a pixel's camera rays), their node tests done once for all
    /// ([`crate::accel::Accel::intersect_bundle`]): the same hits. False, with nothing written,
    /// where that does not apply (then trace them as a batch).
    pub fn intersect_bundle(&self, origin: Vec3, directions: &[Vec3], out: &mut [Option<Hit>]) -> bool {
        !self.has_transparency() && self.accel.intersect_bundle(origin, directions, out)
    }

    /// [`Self::visibility_from`] for up to [`crate::accel::MAX_BATCH`] rays, ray k to `tmax[k]`
    /// from triangle `from[k]`, into `out`: traced together ([`Accel::occluded_batch`]) where the
    /// BVH batches them and no surface is transparent; on a smaller BVH without transparency, as
    /// [`Self::occluded_lanes_where`] answers them; else one query each. The same fractions
    /// every way.
    pub fn visibility_batch(&self, o: &[Vec3], d: &[Vec3], tmax: &[f32], from: &[u32], out: &mut [f32]) {
        let n = o.len().min(d.len()).min(tmax.len()).min(from.len()).min(out.len());
        if self.walks_lanes() && n <= 32 {
            let blocked = self.occluded_lanes_where(o, d, tmax, from, crate::accel::low_bits(n));
            for (k, out) in out.iter_mut().enumerate().take(n) {
                *out = passes(blocked & (1 << k) == 0);
            }
            return;
        }
        if self.has_transparency() || !self.batches_rays() {
            for k in 0..n {
                out[k] = self.visibility_from(o[k], d[k], tmax[k], from[k]);
            }
            return;
        }
        const B: usize = crate::accel::MAX_BATCH;
        let mut blocked = [false; B];
        for s in (0..n).step_by(B) {
            let e = (s + B).min(n);
            // The rays a solid blocks need no walk; the others are walked together.
            let (mut qo, mut qd, mut qt, mut at) = ([Vec3::ZERO; B], [Vec3::ZERO; B], [0f32; B], [0usize; B]);
            let mut m = 0;
            for k in s..e {
                if self.solid_blocks(o[k], d[k], tmax[k]) {
                    out[k] = 0.0;
                } else if let Some(solid) = self.solids.leaving(&self.mesh, from[k], d[k]) {
                    out[k] = passes(!self.accel.occluded_leaving(o[k], d[k], tmax[k], solid));
                } else {
                    (qo[m], qd[m], qt[m], at[m]) = (o[k], d[k], tmax[k], k);
                    m += 1;
                }
            }
            self.accel.occluded_batch(&qo[..m], &qd[..m], &qt[..m], &mut blocked[..m]);
            for j in 0..m {
                out[at[j]] = passes(!blocked[j]);
            }
        }
    }

    /// Whether a batch's rays are answered one by one where they lie, the BVH's walks one after
    /// another in one call ([`Self::intersect_lanes_where`], [`Self::occluded_lanes_where`]): no
    /// transparent surface stands between, and the BVH is too small to batch them. The SPMD
    /// kernel then asks for its rays where they lie in its lanes, the same answers as
    /// [`Self::intersect_surface_batch`] and [`Self::visibility_batch`] give.
    pub fn walks_lanes(&self) -> bool {
        !self.has_transparency() && !self.batches_rays()
    }

    /// [`Self::intersect_surface`] (its seed unread: no surface is transparent where
    /// [`Self::walks_lanes`]) for the rays whose bits are set in `lanes` (ray k from triangle
    /// `from[k]`, k below 32 and every slice's length), into their entries of `out`. A ray inside
    /// a glass solid or leaving one is answered as `intersect_surface` answers it; the others'
    /// walks go one after another in one call ([`Accel::intersect_lanes_where`]): on a small
    /// BVH a call and a walk's setup cost more than most walks' own work (docs/performance-journal.md,
    /// thirty-third and thirty-fourth rounds).
    #[inline(always)]
    pub fn intersect_lanes_where(&self, o: &[Vec3], d: &[Vec3], from: &[u32], lanes: u32, out: &mut [Option<Hit>]) {
        if self.solids.is_empty() {
            self.accel.intersect_lanes_where(o, d, lanes, out);
        } else {
            self.intersect_lanes_among_solids(o, d, from, lanes, out);
        }
    }

    /// [`Self::intersect_lanes_where`] where the scene has solids (out of line: the kernel of a
    /// scene without them keeps its direct call, which it had before this existed).
    #[inline(never)]
    fn intersect_lanes_among_solids(&self, o: &[Vec3], d: &[Vec3], from: &[u32], lanes: u32, out: &mut [Option<Hit>]) {
        let n = o.len().min(d.len()).min(from.len()).min(out.len());
        let mut walked = 0u32;
        // The dispatch of `intersect_surface` written out again, as there and in the batched
        // path: a helper for the three cost glass 0.6–0.8 % more instructions (callgrind; the
        // thirty-fourth round's review tried one returning the answer and one writing it).
        for k in crate::accel::bits_of(lanes & crate::accel::low_bits(n)) {
            if let Some((tmin, solid)) = self.solids.bound(from[k], o[k], d[k]) {
                out[k] = self.solids.closest(solid, o[k], d[k], tmin);
            } else if let Some(solid) = self.solids.leaving(&self.mesh, from[k], d[k]) {
                out[k] = self.accel.intersect_leaving(o[k], d[k], solid);
            } else {
                walked |= 1 << k;
            }
        }
        self.accel.intersect_lanes_where(o, d, walked, out);
    }

    /// Whether something blocks each ray whose bit is set in `lanes` (ray k from triangle
    /// `from[k]` to `tmax[k]`), as [`Self::visibility_from`] answers it where
    /// [`Self::walks_lanes`] (0 or 1): the bits of the blocked rays. As
    /// [`Self::intersect_lanes_where`], the walks of the rays no solid answers go in one call.
    #[inline(always)]
    pub fn occluded_lanes_where(&self, o: &[Vec3], d: &[Vec3], tmax: &[f32], from: &[u32], lanes: u32) -> u32 {
        if self.solids.is_empty() {
            self.accel.occluded_lanes_where(o, d, tmax, lanes)
        } else {
            self.occluded_lanes_among_solids(o, d, tmax, from, lanes)
        }
    }

    /// The bits of the rays among `lanes` that [`Self::solid_blocks`] blocks (each slice holds at
    /// least the rays `lanes` names): the kernel's eight rays at once
    /// (`ConvexSolids::blocks_lanes`, the same answers), other batches ray by ray.
    #[inline(always)]
    fn solid_blocked_lanes(&self, o: &[Vec3], d: &[Vec3], tmax: &[f32], lanes: u32) -> u32 {
        if self.solids.glass_len() == 0 {
            return 0;
        }
        #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
        if let (Ok(o), Ok(d), Ok(tmax)) = (o.try_into(), d.try_into(), tmax.try_into()) {
            return self.solids.blocks_lanes(o, d, tmax, lanes);
        }
        crate::accel::bits_of(lanes).filter(|&k| self.solids.blocks(o[k], d[k], tmax[k])).fold(0, |b, k| b | 1 << k)
    }

    /// [`Self::occluded_lanes_where`] where the scene has solids (out of line, as
    /// [`Self::intersect_lanes_among_solids`]).
    #[inline(never)]
    fn occluded_lanes_among_solids(&self, o: &[Vec3], d: &[Vec3], tmax: &[f32], from: &[u32], lanes: u32) -> u32 {
        let n = o.len().min(d.len()).min(tmax.len()).min(from.len());
        let lanes = lanes & crate::accel::low_bits(n);
        let mut blocked = self.solid_blocked_lanes(o, d, tmax, lanes);
        let mut walked = 0u32;
        // `visibility_from`'s dispatch written out again (see `intersect_lanes_among_solids`).
        for k in crate::accel::bits_of(lanes & !blocked) {
            if let Some(solid) = self.solids.leaving(&self.mesh, from[k], d[k]) {
                blocked |= u32::from(self.accel.occluded_leaving(o[k], d[k], tmax[k], solid)) << k;
            } else {
                walked |= 1 << k;
            }
        }
        blocked | self.accel.occluded_lanes_where(o, d, tmax, walked)
    }

    /// Whether the BVH traces a batch's rays together ([`Self::intersect_surface_batch`],
    /// [`Self::visibility_batch`]): where it is large enough to miss cache
    /// ([`Accel::batches_rays`]); below, its walks do not wait on memory and a batch's are
    /// answered one at a time. In scenes with transparent surfaces the bounce rays' first layers
    /// are batched and shadow rays go one at a time.
    pub fn batches_rays(&self) -> bool {
        self.accel.batches_rays()
    }

    /// Whether a render runs a pixel's samples a batch at a time
    /// ([`crate::integrator::radiance_batch`]): where the BVH batches rays, or where a light
    /// tree chooses the lights (the batch's walks down it are interleaved,
    /// [`LightSet::select_batch`]).
    pub fn batches_paths(&self) -> bool {
        self.batch_paths.unwrap_or_else(|| self.batches_rays() || self.lights.walks_tree())
    }

    /// Overrides [`Self::batches_paths`]' rule: `Some(on)` batches paths or not whatever the
    /// scene, None restores the rule. The images are the same either way (tests compare them).
    pub fn set_batch_paths(&mut self, on: Option<bool>) {
        self.batch_paths = on;
    }

    /// [`Self::visibility`] of a ray that starts on triangle `from` (`convex_solid::NONE` for
    /// none): where it leaves a closed convex solid through that facet, its walk skips the
    /// solid's subtrees ([`Accel::occluded_leaving`]), which it cannot meet. With transparent
    /// surfaces, the layer-by-layer walk of [`Self::visibility`].
    #[inline]
    pub fn visibility_from(&self, o: Vec3, d: Vec3, tmax: f32, from: u32) -> f32 {
        // Without solids no ray leaves one: the start triangle is not read (asked, it cost
        // Cornell 1 % more instructions).
        if self.solids.is_empty() {
            return self.visibility(o, d, tmax);
        }
        match self.solids.leaving(&self.mesh, from, d) {
            Some(solid) if !self.has_transparency() => {
                passes(!(self.solid_blocks(o, d, tmax) || self.accel.occluded_leaving(o, d, tmax, solid)))
            }
            _ => self.visibility(o, d, tmax),
        }
    }

    /// Fraction of light that gets from `o` along `d` to distance `tmax`: 0 behind an opaque (or
    /// uncut) surface, Π(1 − alpha) through BLEND surfaces.
    pub fn visibility(&self, mut o: Vec3, d: Vec3, mut tmax: f32) -> f32 {
        if self.solid_blocks(o, d, tmax) {
            return 0.0;
        }
        if !self.has_transparency() {
            return passes(!self.accel.occluded(o, d, tmax));
        }
        if self.walks_past_cutouts() {
            // One walk over every surface before tmax: blocked at an opaque one or an uncut
            // cut-out, each BLEND surface's 1 − alpha multiplied in as it is met.
            let mut through = 1.0f32;
            let blocked = self.accel.occluded_accepted(o, d, tmax, |h| match self.coverage(h) {
                (AlphaMode::Opaque, _) => true,
                (AlphaMode::Mask(cutoff), a) => a >= cutoff,
                (AlphaMode::Blend, a) => {
                    through *= 1.0 - a;
                    through <= 0.0
                }
            });
            return if blocked { 0.0 } else { through };
        }
        let mut t_total = 1.0f32;
        for _ in 0..MAX_TRANSPARENT_LAYERS {
            let Some(hit) = self.accel.intersect(o, d, tmax) else { return t_total };
            match self.coverage(&hit) {
                (AlphaMode::Opaque, _) => return 0.0,
                (AlphaMode::Mask(cutoff), a) if a >= cutoff => return 0.0,
                (AlphaMode::Blend, a) => t_total *= 1.0 - a,
                _ => {}
            }
            if t_total <= 0.0 {
                return 0.0;
            }
            let next = self.pass_through(&hit, d);
            tmax -= (next - o).length();
            o = next;
            if tmax <= 0.0 {
                return t_total;
            }
        }
        0.0
    }

    /// The origin for continuing a ray past a transparent hit.
    fn pass_through(&self, hit: &Hit, d: Vec3) -> Vec3 {
        let sp = self.surface_point(hit);
        let n = if sp.ng.dot(d) > 0.0 { sp.ng } else { -sp.ng };
        self.spawn_origin(sp.p, n, sp.plane_error)
    }

    /// The origin of a ray leaving a surface point `p` to the side `n` (± the geometric normal)
    /// points to: lifted off the triangle's plane by the point's `plane_error`
    /// ([`crate::mesh::SurfacePoint::plane_error`]), then moved on by the ulp offset, which also
    /// covers the rounding of that lift.
    #[inline(always)]
    pub fn spawn_origin(&self, p: Vec3, n: Vec3, plane_error: f32) -> Vec3 {
        self.offset_ray_origin(p + n * plane_error, n)
    }

    /// Moves a ray origin off a surface at `p` to the side `n` points to
    /// ([`crate::math::offset_ray_origin_scaled`], scaled to this scene's size).
    #[inline(always)]
    pub fn offset_ray_origin(&self, p: Vec3, n: Vec3) -> Vec3 {
        crate::math::offset_ray_origin_scaled(p, n, self.offset_scale)
    }

    /// The scale [`Self::offset_ray_origin`] offsets by ([`crate::math::offset_scale`]).
    pub fn offset_scale(&self) -> f32 {
        self.offset_scale
    }

    /// The camera to render through: the file's camera `index`, or a framing default when the file
    /// has none and no index was asked for.
    pub fn camera(&self, index: Option<usize>) -> Result<Camera, (usize, usize)> {
        match index {
            Some(i) => self.cameras.get(i).copied().ok_or((i, self.cameras.len())),
            None => Ok(self.cameras.first().copied().unwrap_or_else(|| Camera::framing(self.bounds.0, self.bounds.1))),
        }
    }
}

#[cfg(test)]
mod tests {
    use crate::material::Material;
    use crate::math::{Vec3, Vec4};
    use crate::testing::SceneBuilder;

    /// `Scene::bsdf` takes the precomputed BSDF only where the surface has no vertex colour: a
    /// coloured point gets the material's BSDF with that colour, an uncoloured one the same bits
    /// as resolving it there.
    #[test]
    fn scene_bsdf_honours_vertex_colour() {
        let mut b = SceneBuilder::default();
        let m =
            b.material(Material { base_color: Vec4::new(0.8, 0.6, 0.4, 1.0), roughness: 0.3, ..Material::default() });
        b.triangles(&[Vec3::ZERO, Vec3::X, Vec3::Y], &[[0, 1, 2]], m);
        let scene = b.build();
        let mut sp = scene.mesh.surface_point(0, 0.25, 0.25);
        assert_eq!(sp.color, Vec4::ONE, "an uncoloured point, so the precomputed BSDF is the one compared");
        let material = &scene.materials[m as usize];
        assert_eq!(
            format!("{:?}", scene.bsdf(m, &sp)),
            format!("{:?}", material.bsdf(&scene.textures, sp.uv, sp.color))
        );
        sp.color = Vec4::new(0.5, 1.0, 0.25, 1.0);
        let coloured = scene.bsdf(m, &sp);
        assert_eq!(format!("{coloured:?}"), format!("{:?}", material.bsdf(&scene.textures, sp.uv, sp.color)));
        assert_eq!(coloured.base_color, Vec3::new(0.4, 0.6, 0.1));
    }

    /// A material fed by no texture but its base colour's, under a vertex colour or not:
    /// `Scene::bsdf` resolves only the base colour over the precomputed BSDF, which is
    /// `Material::bsdf`'s answer to the last bit, for every lobe a material can have, with and
    /// without a base colour texture, at points across the texture, and colours out of range,
    /// zero, infinite and NaN.
    #[test]
    fn base_coloured_bsdf_is_the_materials_own() {
        use crate::texture::{TexCoords, Texture, TextureRef, Wrap};
        use glam::Vec2;
        let base = Material { base_color: Vec4::new(0.8, 0.6, 0.4, 1.0), roughness: 0.3, ..Material::default() };
        let materials = [
            base.clone(),
            Material { metallic: 1.0, roughness: 0.0, ..base.clone() },
            Material {
                metallic: 0.4,
                specular: 0.3,
                specular_color: Vec3::new(1.0, 0.5, 0.2),
                ior: 1.8,
                ..base.clone()
            },
            Material { transmission: 1.0, metallic: 0.0, roughness: 0.2, ..base.clone() },
            Material { transmission: 0.4, absorption: Vec3::new(0.1, 0.2, 0.3), ..base.clone() },
            Material { clearcoat: 0.7, clearcoat_roughness: 0.2, ..base.clone() },
            Material { sheen_color: Vec3::new(0.3, 0.9, 0.1), sheen_roughness: 0.6, ..base.clone() },
            Material { base_color: Vec4::new(3.0, f32::NAN, -1.0, 0.5), ior: f32::NAN, ..base.clone() },
        ];
        let checker =
            Some(TextureRef { texture: 0, wrap_s: Wrap::Repeat, wrap_t: Wrap::Repeat, set: 0, transform: None });
        let textured: Vec<Material> =
            materials.iter().map(|m| Material { base_color_texture: checker, ..m.clone() }).collect();
        let materials: Vec<Material> = materials.into_iter().chain(textured).collect();
        let colours = [
            Vec4::ONE,
            Vec4::new(0.5, 1.0, 0.25, 1.0),
            Vec4::new(0.0, 0.0, 0.0, 0.0),
            Vec4::new(7.0, 0.3, 1e-30, 0.2),
            Vec4::new(f32::INFINITY, f32::NAN, -0.5, 1.0),
        ];
        let mut b = SceneBuilder::default();
        let ids: Vec<u32> = materials.iter().map(|m| b.material(m.clone())).collect();
        for &m in &ids {
            b.triangles(&[Vec3::ZERO, Vec3::X, Vec3::Y], &[[0, 1, 2]], m);
        }
        let mut scene = b.build();
        let texels: Vec<[u8; 4]> = (0..16u8).map(|i| [i * 16, 255 - i * 9, (i * 37) % 255, 255]).collect();
        scene.textures = vec![Texture { width: 4, height: 4, texels, srgb: true }];
        for (i, &m) in ids.iter().enumerate() {
            let mut sp = scene.mesh.surface_point(i as u32, 0.25, 0.25);
            let material = &scene.materials[m as usize];
            assert!(material.bsdf_but_base_colour().is_some(), "material {i} has no other texture");
            for colour in colours {
                for uv in [Vec2::new(0.1, 0.3), Vec2::new(0.62, 0.9), Vec2::new(-3.3, 7.01)] {
                    (sp.color, sp.uv) = (colour, TexCoords([uv, uv]));
                    assert_eq!(
                        format!("{:?}", scene.bsdf(m, &sp)),
                        format!("{:?}", material.bsdf(&scene.textures, sp.uv, sp.color)),
                        "material {i}, colour {colour}, uv {uv}"
                    );
                }
            }
        }
    }
}
