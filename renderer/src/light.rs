//! Emissive triangles as area lights. A light is chosen in proportion to its power with an alias
//! table, then a point is sampled uniformly by area and the area pdf is converted to solid angle
//! (pbrt-v4 §12.2 and §12.5; Veach 1997 §9). Closed convex emitters are one light each, a
//! [`Bulb`], sampled by the cone of directions their ball subtends (`bulb`).

use crate::alias::AliasTable;
use crate::bulb::{Bulb, BulbHit};
use crate::environment::{Environment, MapPoint};
use crate::light_tree::{LightBounds, LightTree, MAX_WALKS};
use crate::material::Material;
use crate::math::{luminance, sample_uniform_triangle, Vec2, Vec3, PI};
use crate::mesh::Mesh;
use crate::punctual::{PunctualKind, PunctualLight};
use crate::texture::Texture;

/// An emissive triangle, with what sampling a point on it needs copied out of the mesh: sampling
/// then reads one 64-byte record instead of the triangle, its three vertices and its material
/// through four indirections. The light set is rebuilt whenever a frame's pose moves vertices
/// (`Scene::set_frame`), so the copy never goes stale.
#[derive(Clone, Copy, Debug)]
pub struct AreaLight {
    /// First vertex and the two edges from it (`Mesh::position_normal_uv`'s arithmetic, so a
    /// sampled point is bit for bit the one the mesh would give).
    pub(crate) p0: Vec3,
    pub(crate) e1: Vec3,
    pub(crate) e2: Vec3,
    /// Unit winding normal (`Mesh::position_normal_uv`'s).
    pub(crate) ng: Vec3,
    pub triangle: u32,
    pub area: f32,
    pub two_sided: bool,
    pub(crate) material: u32,
    /// The material's emission where no texture coordinates are read (`Material::emission` at
    /// the default ones): the radiance the SPMD kernel's samples start from, worked out once.
    pub(crate) le: Vec3,
    /// Whether an emissive texture makes the radiance vary over the triangle (then it is read at
    /// the sampled point): known when the set is built, so a sample does not look the material up.
    pub(crate) textured: bool,
}

/// A point sampled on a light, seen from a reference point.
#[derive(Clone, Copy, Debug)]
pub struct LightSample {
    pub p: Vec3,
    /// Geometric normal of the emitter at `p`, oriented to the emitting side facing the reference.
    pub n: Vec3,
    // For the environment, `dist` is infinite and `p` is merely a point along `wi`.
    /// Unit direction from the reference point to `p`.
    pub wi: Vec3,
    pub dist: f32,
    /// Emitted radiance towards the reference point (zero from a one-sided emitter's back).
    pub le: Vec3,
    /// Solid-angle pdf including the light-selection probability; for a delta light, the selection
    /// probability alone, and `le` is the irradiance it delivers (so f·le·cos/pdf still holds).
    pub pdf: f32,
    pub delta: bool,
    /// The area light sampled (its index in [`LightSet::lights`]), else `clear_box::NONE`: what
    /// [`LightSet::shadow_tmax`] needs.
    pub light: u32,
}

#[derive(Default)]
pub struct LightSet {
    /// Every emissive triangle NEE may sample: the first `area_count` are lights of their own,
    /// the rest the bulbs' triangles, each bulb's together in its `triangles` order.
    pub lights: Vec<AreaLight>,
    area_count: usize,
    /// Closed convex emitters, one light each: entries `area_count .. area_count + bulbs.len()`
    /// of the selection table...
    bulbs: Vec<Bulb>,
    /// ...and, for each record from `area_count` on, its bulb.
    bulb_of: Vec<u32>,
    selection: AliasTable,
    /// For each scene triangle, its light index or `u32::MAX`.
    triangle_light: Vec<u32>,
    /// Punctual (delta) lights: the selection table's entries after the bulbs'.
    pub punctual: Vec<PunctualLight>,
    /// The environment, if the scene has one. When it is importance-sampled it is the last entry of
    /// the selection table.
    pub environment: Option<Environment>,
    /// How lights are chosen (see `LightSamplerKind`).
    pub kind: LightSamplerKind,
    /// With `Tree`: the light BVH over the finite lights (area, point, spot)...
    tree: Option<LightTree>,
    /// ...the global index of each tree light...
    tree_lights: Vec<usize>,
    /// ...each global index's tree light (or u32::MAX)...
    tree_index: Vec<u32>,
    /// ...and the lights at infinity (directional, environment), chosen uniformly beside the tree.
    infinite: Vec<usize>,
    /// The boxes shadow rays to isolated convex emitters may stop at (`clear_box`), and each
    /// area light's box index (or `clear_box::NONE`).
    clear_boxes: Vec<crate::clear_box::ClearBox>,
    clear_of: Vec<u32>,
    /// The selection weights of the area lights and bulbs (the table's first entries): what
    /// [`Self::with_others`] keeps when the punctual lights or the environment change.
    area_power: Vec<f32>,
}

/// Light selection for next-event estimation (`--light-sampler`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LightSamplerKind {
    /// Power, uniform or tree, whichever a deterministic pilot run measures as the most efficient on
    /// this scene (`light_choice`): a light count says nothing about benefit (issue 10).
    #[default]
    Auto,
    /// Every light equally likely.
    Uniform,
    /// In proportion to emitted power (alias table).
    Power,
    /// By a light BVH's importance for the shading point (power, distance, orientation).
    Tree,
}

crate::named_choices!(LightSamplerKind, "light sampler", { "auto" => Self::Auto, "uniform" => Self::Uniform, "power" => Self::Power, "tree" => Self::Tree });

/// Radiance leaving an emissive surface point towards direction `w` (pointing away from the
/// surface). Emission is one-sided along the winding normal `ng` unless the material is double-sided.
#[inline]
pub fn emitted(m: &Material, textures: &[Texture], ng: Vec3, uv: crate::texture::TexCoords, w: Vec3) -> Vec3 {
    if !m.is_emissive() || (!m.double_sided && ng.dot(w) <= 0.0) {
        return Vec3::ZERO;
    }
    m.emission(textures, uv)
}

/// Average emitted radiance over a triangle, estimated from the texture at seven interior points
/// (cheap, and only used for selection probabilities: any positive estimate keeps the estimator
/// unbiased, and a triangle estimated at zero is simply not a light — the integrator then counts
/// it when BSDF sampling hits it).
fn mean_emission(mesh: &Mesh, m: &Material, textures: &[Texture], tri: u32) -> Vec3 {
    if m.emissive_texture.is_none() {
        return m.emissive;
    }
    const B: [(f32, f32); 7] =
        [(1.0 / 3.0, 1.0 / 3.0), (0.1, 0.1), (0.8, 0.1), (0.1, 0.8), (0.45, 0.1), (0.45, 0.45), (0.1, 0.45)];
    let sum: Vec3 = B.iter().map(|&(b1, b2)| m.emission(textures, mesh.surface_point(tri, b1, b2).uv)).sum();
    sum / B.len() as f32
}

/// The light sample an environment's sample `(wi, le, pdf)` gives at `reference` when the
/// environment was chosen with probability `pmf`; None when the joint pdf is not positive and finite.
#[inline]
fn environment_sample(reference: Vec3, pmf: f32, (wi, le, pdf): (Vec3, Vec3, f32)) -> Option<LightSample> {
    let pdf = pmf * pdf;
    (pdf > 0.0 && pdf.is_finite()).then_some(LightSample {
        p: reference + wi,
        n: -wi,
        wi,
        dist: f32::INFINITY,
        le,
        pdf,
        delta: false,
        light: crate::clear_box::NONE,
    })
}

impl LightSet {
    /// `scene_radius` sizes the environment's power for light selection: pbrt-v4's
    /// `ImageInfiniteLight::Phi` = 4π² r² × mean radiance.
    pub fn build(
        mesh: &Mesh,
        materials: &[Material],
        textures: &[Texture],
        punctual: Vec<PunctualLight>,
        environment: Option<Environment>,
        scene_radius: f32,
    ) -> Self {
        let mut records = Vec::new();
        let mut record_power = Vec::new();
        let mut triangle_light = vec![u32::MAX; mesh.triangles.len()];
        for (i, t) in mesh.triangles.iter().enumerate() {
            let m = &materials[t.material as usize];
            // Instanced prototypes never hold emitters (the loader flattens emissive meshes).
            if !m.is_emissive() || t.flags & crate::mesh::flags::OBJECT_SPACE != 0 {
                continue;
            }
            let area = mesh.area(i as u32);
            if !(area > 0.0) || !area.is_finite() {
                continue;
            }
            let sides = if m.double_sided { 2.0 } else { 1.0 };
            let p = luminance(mean_emission(mesh, m, textures, i as u32)) * area * PI * sides;
            if !(p > 0.0) {
                continue;
            }
            triangle_light[i] = records.len() as u32;
            let [p0, p1, p2] = mesh.vertices(i as u32);
            let (e1, e2) = (p1 - p0, p2 - p0);
            records.push(AreaLight {
                p0,
                e1,
                e2,
                // A positive, finite area makes this a unit vector: `position_normal_uv`'s +Z
                // fallback for degenerate triangles never applies to a light.
                ng: e1.cross(e2).normalize_or_zero(),
                triangle: i as u32,
                area,
                two_sided: m.double_sided,
                material: t.material,
                le: m.emission(textures, Default::default()),
                textured: m.emissive_texture.is_some(),
            });
            record_power.push(p);
        }
        // The bulbs among them (untextured emission: a cone sample reads no texture
        // coordinates); the other triangles stay lights of their own, in scene order, first.
        let candidates: Vec<(u32, f32)> = records.iter().map(|l| (l.triangle, l.area)).collect();
        let mut bulbs =
            Bulb::find(mesh, &candidates, |m| materials.get(m as usize).is_some_and(|m| m.emissive_texture.is_none()));
        let mut member = vec![false; records.len()];
        for bulb in &bulbs {
            for &t in &bulb.triangles {
                member[triangle_light[t as usize] as usize] = true;
            }
        }
        let mut lights: Vec<AreaLight> = records.iter().zip(&member).filter(|(_, &m)| !m).map(|(l, _)| *l).collect();
        let mut power: Vec<f32> = record_power.iter().zip(&member).filter(|(_, &m)| !m).map(|(p, _)| *p).collect();
        let area_count = lights.len();
        let mut bulb_of = Vec::new();
        for (b, bulb) in bulbs.iter().enumerate() {
            let mut sum = 0.0f64;
            for &t in &bulb.triangles {
                let r = triangle_light[t as usize] as usize;
                lights.push(records[r]);
                bulb_of.push(b as u32);
                sum += record_power[r] as f64;
            }
            power.push(sum as f32);
        }
        for (r, l) in lights.iter().enumerate() {
            triangle_light[l.triangle as usize] = r as u32;
        }
        let (clear_boxes, clear_of) = crate::clear_box::find(mesh, &lights);
        // A bulb whose triangles all have one clear box is isolated: its sure directions' shadow
        // rays end at that box.
        let mut first = area_count;
        for bulb in &mut bulbs {
            let of = &clear_of[first..first + bulb.triangles.len()];
            if let Some(&b) = of.first().filter(|&&b| b != crate::clear_box::NONE && of.iter().all(|&o| o == b)) {
                bulb.clear = clear_boxes.get(b as usize).copied();
            }
            first += bulb.triangles.len();
        }
        // The area lights alone; `with_others` adds the rest and the selection over them all.
        let area = LightSet {
            clear_boxes,
            clear_of,
            lights,
            area_count,
            bulbs,
            bulb_of,
            triangle_light,
            area_power: power,
            ..LightSet::default()
        };
        area.with_others(punctual, environment, scene_radius)
    }

    /// This set's area lights and bulbs (the costly part of [`Self::build`]: every emissive
    /// triangle's mean emission, the bulbs' hulls, the clear boxes) with `punctual` lights and
    /// `environment` in place of its own, and the selection table over them all, as
    /// [`Self::build`] would make it; choosing by power (set the kind again after). Only for a
    /// mesh unchanged since this set was built (the area lights are its triangles as they were):
    /// adding an environment or punctual lights to a loaded scene used to build the whole set
    /// anew each time, two or three times a load.
    pub(crate) fn with_others(
        self,
        punctual: Vec<PunctualLight>,
        environment: Option<Environment>,
        scene_radius: f32,
    ) -> Self {
        let mut power = self.area_power.clone();
        let punctual: Vec<PunctualLight> =
            punctual.into_iter().filter(|p| p.power(scene_radius.max(1e-3)) > 0.0).collect();
        for p in &punctual {
            power.push(p.power(scene_radius.max(1e-3)));
        }
        if let Some(env) = environment.as_ref().filter(|e| e.is_sampled()) {
            let r = scene_radius.max(1e-3);
            power.push((4.0 * PI * PI * r * r * env.mean_luminance).max(1e-12));
        }
        let selection = AliasTable::new(&power).unwrap_or_default();
        LightSet {
            selection,
            punctual,
            environment,
            kind: LightSamplerKind::Power,
            tree: None,
            tree_lights: Vec::new(),
            tree_index: Vec::new(),
            infinite: Vec::new(),
            ..self
        }
    }

    fn count(&self) -> usize {
        self.selection.len()
    }

    /// Makes the light tree's walk evaluate children one at a time (the reference; tests compare).
    pub fn set_scalar_reference(&mut self, on: bool) {
        if let Some(tree) = &mut self.tree {
            tree.set_scalar_reference(on);
        }
    }

    /// Finite lights (area lights, bulbs, point and spot lights): what a tree would be built over.
    pub fn finite_count(&self) -> usize {
        self.bulbs_end() + self.punctual.iter().filter(|p| p.kind != PunctualKind::Directional).count()
    }

    /// The selection index after the last bulb's (the first punctual light's).
    #[inline(always)]
    fn bulbs_end(&self) -> usize {
        self.area_count + self.bulbs.len()
    }

    /// The area light of selection index `idx`, if it is one (a triangle that is a light of its
    /// own, not a bulb's).
    #[inline(always)]
    pub fn area_light(&self, idx: usize) -> Option<&AreaLight> {
        if idx < self.area_count {
            self.lights.get(idx)
        } else {
            None
        }
    }

    /// Whether selection index `idx` is a bulb.
    #[inline(always)]
    pub fn is_bulb(&self, idx: usize) -> bool {
        (self.area_count..self.bulbs_end()).contains(&idx)
    }

    /// Selection index `idx`'s bulb as the kernel draws it, if it is an isolated bulb.
    #[inline(always)]
    pub fn bulb_lane(&self, idx: usize, materials: &[Material]) -> Option<crate::bulb::BulbLane> {
        let bulb = self.bulbs.get(idx.checked_sub(self.area_count)?)?;
        bulb.lane(materials.get(bulb.material as usize)?.emissive)
    }

    /// How many bulbs (closed convex emitters sampled as one light) the set holds.
    pub fn bulb_count(&self) -> usize {
        self.bulbs.len()
    }

    /// Switches the selection strategy; `Tree` builds the light BVH (only when there are at least
    /// two finite lights: with one, every strategy picks it). `Auto` is decided by the scene, which
    /// runs `light_choice::choose`; here it falls back to power.
    pub fn set_kind_exact(&mut self, kind: LightSamplerKind, mesh: &Mesh) {
        let kind = if kind == LightSamplerKind::Auto { LightSamplerKind::Power } else { kind };
        self.kind = kind;
        self.tree = None;
        if kind != LightSamplerKind::Tree {
            return;
        }
        let n = self.count();
        self.tree_index = vec![u32::MAX; n];
        self.tree_lights.clear();
        self.infinite.clear();
        let mut bounds = Vec::new();
        for g in 0..n {
            let b = if g < self.area_count {
                let l = &self.lights[g];
                let [a, b, c] = mesh.vertices(l.triangle);
                let ng = (b - a).cross(c - a).normalize_or_zero();
                Some(LightBounds {
                    min: a.min(b).min(c),
                    max: a.max(b).max(c),
                    phi: self.selection.pmf(g),
                    w: ng,
                    cos_theta_o: 1.0,
                    cos_theta_e: 0.0,
                    two_sided: l.two_sided,
                })
            } else if g < self.bulbs_end() {
                // A bulb emits every way from within its box, as a point light does from its point.
                let bulb = &self.bulbs[g - self.area_count];
                Some(LightBounds {
                    min: bulb.lo,
                    max: bulb.hi,
                    phi: self.selection.pmf(g),
                    w: Vec3::Y,
                    cos_theta_o: -1.0,
                    cos_theta_e: 0.0,
                    two_sided: false,
                })
            } else if g < self.environment_index() {
                let p = &self.punctual[g - self.bulbs_end()];
                match p.kind {
                    PunctualKind::Directional => None,
                    PunctualKind::Point => Some(LightBounds {
                        min: p.position,
                        max: p.position,
                        phi: self.selection.pmf(g),
                        w: Vec3::Y,
                        cos_theta_o: -1.0,
                        cos_theta_e: 0.0,
                        two_sided: false,
                    }),
                    PunctualKind::Spot { cos_outer, .. } => Some(LightBounds {
                        min: p.position,
                        max: p.position,
                        phi: self.selection.pmf(g),
                        w: p.direction,
                        cos_theta_o: cos_outer,
                        cos_theta_e: 0.0,
                        two_sided: false,
                    }),
                }
            } else {
                None
            };
            match b {
                Some(b) => {
                    self.tree_index[g] = bounds.len() as u32;
                    self.tree_lights.push(g);
                    bounds.push(b);
                }
                None => self.infinite.push(g),
            }
        }
        if bounds.len() >= 2 {
            self.tree = LightTree::build(&bounds);
        }
    }

    /// [`Self::select`] for several shading points (`reference[k]`, `normal[k]`, `u[k]` into
    /// `out[k]`; at most [`crate::light_tree::MAX_WALKS`] at a time are walked together): with a
    /// light tree the walks are interleaved ([`LightTree::sample_batch`]). The same choices and
    /// probabilities as one at a time, bit for bit.
    pub fn select_batch(
        &self,
        reference: &[Vec3],
        normal: &[Option<Vec3>],
        u: &[f32],
        out: &mut [Option<(usize, f32)>],
    ) {
        let count = reference.len().min(normal.len()).min(u.len()).min(out.len());
        // Without a tree, or with a tree of one node (a few bulbs), one at a time: there is no
        // chain of levels for the batch to interleave, and the batch's state (its arrays here and
        // `LightTree::sample_batch`'s) cost more than the one level it walks.
        let (LightSamplerKind::Tree, Some(tree)) = (self.kind, self.tree.as_ref().filter(|t| !t.is_one_node())) else {
            #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
            if self.chooses_by_table() {
                // The power table's choices eight at a time (`AliasTable::sample_lanes`).
                let mut chosen = [(0usize, 0f32); 8];
                for s in (0..count).step_by(8) {
                    let e = (s + 8).min(count);
                    self.selection.sample_lanes(&u[s..e], &mut chosen[..e - s]);
                    for k in s..e {
                        out[k] = Some(chosen[k - s]);
                    }
                }
                return;
            }
            for k in 0..count {
                out[k] = self.select(reference[k], normal[k], u[k]);
            }
            return;
        };
        // The choices between infinite lights and the tree as `select` makes them; the tree's
        // walks together.
        let mut walks = [0u8; MAX_WALKS];
        let (mut wp, mut wn, mut wu) = ([Vec3::ZERO; MAX_WALKS], [None; MAX_WALKS], [0f32; MAX_WALKS]);
        let mut found = [None; MAX_WALKS];
        for s in (0..count).step_by(MAX_WALKS) {
            let e = (s + MAX_WALKS).min(count);
            let mut w = 0;
            for k in s..e {
                match self.infinite_or_tree(u[k]) {
                    Ok(infinite) => out[k] = Some(infinite),
                    Err(u_tree) => {
                        (wp[w], wn[w], wu[w]) = (reference[k], normal[k], u_tree);
                        walks[w] = (k - s) as u8;
                        w += 1;
                    }
                }
            }
            tree.sample_batch(&wp[..w], &wn[..w], &wu[..w], &mut found[..w]);
            for (i, f) in found[..w].iter().enumerate() {
                let choice = self.global_of_tree_choice(*f);
                if let Some((g, _)) = choice {
                    self.prefetch_light(g);
                }
                out[s + walks[i] as usize] = choice;
            }
        }
    }

    /// [`Self::select`] for the lanes of `lanes` (bits) when the lights are a light tree of one
    /// node (eight lights or fewer; `scenes/sphere_lights`' four bulbs): the tree's choices at
    /// the eight points at once, the points in the lanes ([`LightTree::sample_root_lanes`]),
    /// into `out` lane for lane. The same choices and probabilities as `select`, bit for bit;
    /// false, with nothing written, for any other light sampler.
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2", target_feature = "fma"))]
    pub fn select_root_lanes(
        &self,
        p: &[Vec3; 8],
        n: &[Vec3; 8],
        u: &[f32; 8],
        lanes: u32,
        out: &mut [Option<(usize, f32)>; 8],
    ) -> bool {
        let (LightSamplerKind::Tree, Some(tree)) = (self.kind, self.tree.as_ref().filter(|t| t.is_one_node())) else {
            return false;
        };
        // The choices between infinite lights and the tree as `select` makes them. Without
        // infinite lights every lane walks, with `infinite_or_tree`'s number: (u − 0) / (1 − 0)
        // is u exactly, so only its clamp below 1 is left.
        let (mut u_tree, mut walks) = (u.map(|u| u.min(1.0 - f32::EPSILON)), lanes & 0xff);
        if !self.infinite.is_empty() {
            walks = 0;
            for k in crate::accel::bits_of(lanes & 0xff) {
                match self.infinite_or_tree(u[k]) {
                    Ok(infinite) => out[k] = Some(infinite),
                    Err(x) => (u_tree[k], walks) = (x, walks | 1 << k),
                }
            }
        }
        if walks != 0 {
            let mut found = [None; 8];
            tree.sample_root_lanes(p, n, &u_tree, &mut found);
            for k in crate::accel::bits_of(walks) {
                out[k] = self.global_of_tree_choice(found[k]);
                if let Some((g, _)) = out[k] {
                    self.prefetch_light(g);
                }
            }
        }
        true
    }

    /// [`Self::select`] for the eight lanes of `u` where the choice reads `u` alone (the power
    /// table: [`AliasTable::sample_eight`]), into `out` lane for lane; false, with nothing
    /// written, where it does not (a tree, uniform choice, no light). For the SPMD kernel, whose
    /// lanes then choose where they lie, not packed into [`Self::select_batch`]'s slices and
    /// unpacked again (docs/performance-journal.md, thirty-fourth round).
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    #[inline(always)]
    pub fn select_by_table_lanes(&self, u: &[f32; 8], out: &mut [(usize, f32); 8]) -> bool {
        if !self.chooses_by_table() {
            return false;
        }
        self.selection.sample_eight(u, out);
        true
    }

    /// Asks the cache for light `g`'s record and clear-box entry: the caller reads them next,
    /// and a walk's pick is a random one of thousands of records (a sphere bulb's triangles),
    /// so each read missed the cache on its own (`perf annotate` of `scenes/sphere_lights`:
    /// the load of the chosen record's material held 9.6 % of `spmd::radiance8`'s samples).
    /// Asked for all of a batch's picks first, the misses overlap.
    #[inline(always)]
    fn prefetch_light(&self, g: usize) {
        if let Some(light) = self.area_light(g) {
            crate::accel::prefetch_record(light);
            if let Some(b) = self.clear_of.get(g) {
                crate::accel::prefetch_record(b);
            }
        }
    }

    /// Whether lights are chosen by walking a light tree.
    pub fn walks_tree(&self) -> bool {
        matches!((self.kind, &self.tree), (LightSamplerKind::Tree, Some(_)))
    }

    /// Whether [`Self::select`] draws from the power table (`selection`) alone: not uniform, no
    /// tree to walk, and some light to choose. Its choice then reads only the number `u`, not
    /// the shading point.
    fn chooses_by_table(&self) -> bool {
        self.count() > 0 && !matches!(self.kind, LightSamplerKind::Uniform) && !self.walks_tree()
    }

    /// Chooses a light for a shading point: (global index, probability).
    #[inline(always)]
    pub fn select(&self, reference: Vec3, normal: Option<Vec3>, u: f32) -> Option<(usize, f32)> {
        let n = self.count();
        if n == 0 {
            return None;
        }
        match (self.kind, &self.tree) {
            (LightSamplerKind::Uniform, _) => Some((((u * n as f32) as usize).min(n - 1), 1.0 / n as f32)),
            (LightSamplerKind::Tree, Some(tree)) => match self.infinite_or_tree(u) {
                Ok(infinite) => Some(infinite),
                Err(u_tree) => self.global_of_tree_choice(tree.sample(reference, normal, u_tree)),
            },
            _ => Some(self.selection.sample(u)),
        }
    }

    /// With a light tree, the probability of choosing an infinite light (directional or the
    /// environment) rather than the tree: each infinite light weighs as much as the whole tree.
    #[inline(always)]
    fn p_infinite(&self) -> f32 {
        let ni = self.infinite.len() as f32;
        ni / (ni + 1.0)
    }

    /// With a light tree, `select`'s first choice for `u`: an infinite light and its probability,
    /// or (`Err`) `u` rescaled for the walk down the tree.
    #[inline(always)]
    fn infinite_or_tree(&self, u: f32) -> Result<(usize, f32), f32> {
        let (ni, p_inf) = (self.infinite.len(), self.p_infinite());
        if u < p_inf {
            let k = ((u / p_inf * ni as f32) as usize).min(ni - 1);
            Ok((self.infinite[k], p_inf / ni as f32))
        } else {
            Err(((u - p_inf) / (1.0 - p_inf)).min(1.0 - f32::EPSILON))
        }
    }

    /// The tree's choice (tree light, probability) as a global light and its probability.
    #[inline(always)]
    fn global_of_tree_choice(&self, found: Option<(usize, f32)>) -> Option<(usize, f32)> {
        found.map(|(t, pmf)| (self.tree_lights[t], pmf * (1.0 - self.p_infinite())))
    }

    /// Probability that `select` picks global light `g` for this shading point.
    fn select_pmf(&self, g: usize, reference: Vec3, normal: Option<Vec3>) -> f32 {
        let n = self.count();
        if g >= n {
            return 0.0;
        }
        match (self.kind, &self.tree) {
            (LightSamplerKind::Uniform, _) => 1.0 / n as f32,
            (LightSamplerKind::Tree, Some(tree)) => {
                let (ni, p_inf) = (self.infinite.len() as f32, self.p_infinite());
                match self.tree_index[g] {
                    u32::MAX => p_inf / ni,
                    t => tree.pmf(reference, normal, t as usize) * (1.0 - p_inf),
                }
            }
            _ => self.selection.pmf(g),
        }
    }

    /// [`Self::sample_selected`] for several points at once (`reference[k]`, `selected[k]`,
    /// `u[k]` into `out[k]`), the same samples: the ones of the environment go through
    /// `Environment::sample_batch`, whose cache misses overlap; the others one at a time.
    #[allow(clippy::too_many_arguments)]
    pub fn sample_selected_batch(
        &self,
        mesh: &Mesh,
        materials: &[Material],
        textures: &[Texture],
        reference: &[Vec3],
        selected: &[Option<(usize, f32)>],
        u: &[Vec2],
        out: &mut [Option<LightSample>],
    ) {
        let n = reference.len().min(selected.len()).min(u.len()).min(out.len());
        let env_index = self.environment_index();
        const B: usize = crate::distribution::BATCH;
        for s in (0..n).step_by(B) {
            // This stretch's environment samples, gathered on the stack; the rest one at a time.
            let (mut lanes, mut us, mut count) = ([0usize; B], [Vec2::ZERO; B], 0);
            for k in s..(s + B).min(n) {
                match (selected[k], &self.environment) {
                    (Some((i, _)), Some(_)) if i == env_index => {
                        (lanes[count], us[count]) = (k, u[k]);
                        count += 1;
                    }
                    _ => out[k] = self.sample_selected(mesh, materials, textures, reference[k], selected[k], u[k]),
                }
            }
            let (Some(env), true) = (&self.environment, count > 0) else { continue };
            let mut found = [None; B];
            env.sample_batch(&us[..count], &mut found[..count]);
            for (&k, &f) in lanes[..count].iter().zip(&found) {
                if let Some((_, pmf)) = selected[k] {
                    out[k] = f.and_then(|sample| environment_sample(reference[k], pmf, sample));
                }
            }
        }
    }

    fn environment_index(&self) -> usize {
        self.bulbs_end() + self.punctual.len()
    }

    /// True when next-event estimation has nothing to sample.
    pub fn is_empty(&self) -> bool {
        self.selection.is_empty()
    }

    /// The environment's radiance from direction `d` and the probability that NEE samples it
    /// there (0 when it is not sampled), with the map looked up once. None without an environment.
    pub fn environment_eval_pdf(&self, d: Vec3, reference: Vec3, normal: Option<Vec3>) -> Option<(Vec3, f32)> {
        let env = self.environment.as_ref()?;
        self.environment_eval_pdf_at(env.map_point(d), reference, normal)
    }

    /// [`Self::environment_eval_pdf`] of the direction `p` was found for
    /// ([`Environment::map_point`]).
    pub fn environment_eval_pdf_at(&self, p: MapPoint, reference: Vec3, normal: Option<Vec3>) -> Option<(Vec3, f32)> {
        let env = self.environment.as_ref()?;
        if !env.is_sampled() {
            return Some((env.eval_at(p), 0.0));
        }
        let (le, pdf) = env.eval_pdf_at(p);
        Some((le, self.select_pmf(self.environment_index(), reference, normal) * pdf))
    }

    /// Samples a light and a point on it as seen from `reference` (on a surface with `normal`, which
    /// the light tree uses to discount lights behind it).
    #[allow(clippy::too_many_arguments)] // the scene's three tables, the shading point, two random numbers
    #[inline(never)] // one function with `select` and `sample_selected` inside, as it was before the split
    pub fn sample(
        &self,
        mesh: &Mesh,
        materials: &[Material],
        textures: &[Texture],
        reference: Vec3,
        normal: Option<Vec3>,
        u_select: f32,
        u: Vec2,
    ) -> Option<LightSample> {
        let selected = self.select(reference, normal, u_select);
        self.sample_selected(mesh, materials, textures, reference, selected, u)
    }

    /// [`Self::sample`] once the light is chosen (`selected`: [`Self::select`]'s answer for
    /// this shading point), so a batch of points can choose theirs together
    /// ([`Self::select_batch`]).
    #[inline(always)]
    pub fn sample_selected(
        &self,
        mesh: &Mesh,
        materials: &[Material],
        textures: &[Texture],
        reference: Vec3,
        selected: Option<(usize, f32)>,
        u: Vec2,
    ) -> Option<LightSample> {
        let (idx, pmf) = selected?;
        if idx >= self.area_count && idx < self.bulbs_end() {
            let bulb = &self.bulbs[idx - self.area_count];
            let at = match bulb.sample(reference, u)? {
                BulbHit::Point(at) => at,
                BulbHit::Along { d, t } => {
                    // The near side of a uniform, isolated bulb: its radiance, and a shadow ray
                    // that stops where the direction enters the bulb's box (aimed at the point
                    // there, its normal facing back, as at an area light's surface).
                    let m = materials.get(bulb.material as usize)?;
                    // A sure direction comes from outside the ball: the cone's density.
                    let pdf = pmf * bulb.cone_pdf(reference)?;
                    return (pdf > 0.0 && pdf.is_finite()).then(|| LightSample {
                        p: reference + d * t,
                        n: -d,
                        wi: d,
                        dist: t,
                        // Untextured (`Bulb::find`): the emission is the factor.
                        le: m.emissive,
                        pdf,
                        delta: false,
                        light: crate::clear_box::NONE,
                    });
                }
            };
            let r = *self.triangle_light.get(at.triangle as usize)? as usize;
            let light = self.lights.get(r)?;
            let p = light.p0 + light.e1 * at.b1 + light.e2 * at.b2;
            return self.surface_sample(materials, textures, reference, r, p, Default::default(), |dist2, cos_l| {
                pmf * bulb.density(reference, || (dist2, cos_l))
            });
        }
        if idx >= self.bulbs_end() && idx < self.environment_index() {
            let (wi, dist, e) = self.punctual[idx - self.bulbs_end()].illuminate(reference)?;
            return Some(LightSample {
                p: reference + wi * dist.min(1e30),
                n: -wi,
                wi,
                dist,
                le: e,
                pdf: pmf,
                delta: true,
                light: crate::clear_box::NONE,
            });
        }
        if idx == self.environment_index() {
            return environment_sample(reference, pmf, self.environment.as_ref()?.sample(u)?);
        }
        let light = &self.lights[idx];
        let b = sample_uniform_triangle(u);
        let p = light.p0 + light.e1 * b.y + light.e2 * b.z;
        let m = &materials[light.material as usize];
        // Texture coordinates only matter to a textured emitter; they are the one thing read from the mesh.
        let uv = match m.emissive_texture {
            Some(_) => mesh.position_normal_uv(light.triangle, b.y, b.z).2,
            None => Default::default(),
        };
        self.surface_sample(materials, textures, reference, idx, p, uv, |dist2, cos_l| {
            pmf * dist2 / (cos_l.abs() * light.area)
        })
    }

    /// The light sample of point `p` (texture coordinates `uv`) on record `r`'s triangle seen
    /// from `reference`, with the solid-angle pdf `pdf(dist², cos at the light)`; None where the
    /// geometry or the pdf is degenerate.
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    fn surface_sample(
        &self,
        materials: &[Material],
        textures: &[Texture],
        reference: Vec3,
        r: usize,
        p: Vec3,
        uv: crate::texture::TexCoords,
        pdf: impl FnOnce(f32, f32) -> f32,
    ) -> Option<LightSample> {
        let light = &self.lights[r];
        let ng = light.ng;
        let to = p - reference;
        let dist2 = to.length_squared();
        if !(dist2 > 0.0) || !dist2.is_finite() {
            return None;
        }
        let dist = dist2.sqrt();
        let wi = to / dist;
        let cos_l = ng.dot(-wi);
        if cos_l == 0.0 {
            return None;
        }
        let m = &materials[light.material as usize];
        let le = emitted(m, textures, ng, uv, -wi);
        let pdf = pdf(dist2, cos_l);
        if !(pdf > 0.0) || !pdf.is_finite() {
            return None;
        }
        let n = if cos_l > 0.0 { ng } else { -ng };
        Some(LightSample { p, n, wi, dist, le, pdf, delta: false, light: r as u32 })
    }

    /// Solid-angle pdf with which `sample()` from `reference` would have produced the point `p` on
    /// triangle `tri` (geometric normal `ng`); 0 for a triangle that is not a light.
    pub fn pdf(&self, tri: u32, reference: Vec3, normal: Option<Vec3>, p: Vec3, ng: Vec3) -> f32 {
        let Some(&li) = self.triangle_light.get(tri as usize) else {
            return 0.0;
        };
        if li == u32::MAX {
            return 0.0;
        }
        if let Some(&b) = (li as usize).checked_sub(self.area_count).and_then(|i| self.bulb_of.get(i)) {
            let pmf = self.select_pmf(self.area_count + b as usize, reference, normal);
            return pmf * self.bulbs[b as usize].pdf(reference, p, ng);
        }
        let light = &self.lights[li as usize];
        let to = p - reference;
        let dist2 = to.length_squared();
        let cos_l = ng.dot(to).abs() / dist2.sqrt();
        if !(cos_l > 0.0) {
            return 0.0;
        }
        self.select_pmf(li as usize, reference, normal) * dist2 / (cos_l * light.area)
    }

    /// Where a shadow ray from `o` along unit `d` to a point of area light `light` (stopping at
    /// `tmax`) may stop: at the box of the light's isolated convex group when the origin is in
    /// front of the light's triangle and outside the box (`clear_box`), else at `tmax`. The
    /// visibility is the same; the walk is shorter.
    #[inline]
    pub fn shadow_tmax(&self, light: u32, o: Vec3, d: Vec3, tmax: f32) -> f32 {
        match (self.clear_of.get(light as usize), self.lights.get(light as usize)) {
            (Some(&b), Some(l)) if b != crate::clear_box::NONE => {
                self.clear_boxes[b as usize].shadow_tmax(l, o, d, tmax)
            }
            _ => tmax,
        }
    }

    /// Whether some area light has a clear box: without one [`Self::shadow_tmax`] is `tmax`
    /// for every light, and a caller with many rays can skip asking it ray by ray.
    #[inline]
    pub fn has_clear_boxes(&self) -> bool {
        !self.clear_boxes.is_empty()
    }

    /// True when triangle `tri` is in the light set (NEE can sample it).
    pub fn is_light(&self, tri: u32) -> bool {
        self.triangle_light.get(tri as usize).is_some_and(|&l| l != u32::MAX)
    }

    /// The power-proportional selection probability of light `i`.
    pub fn pmf(&self, i: usize) -> f32 {
        self.selection.pmf(i)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::Scene;
    use crate::testing::{emitter, SceneBuilder};

    /// A light sample is the point the mesh itself gives for the same barycentrics, bit for bit
    /// (the `AreaLight` record copies the mesh's arithmetic), with the mesh's normal — also after
    /// the vertices move and the light set is rebuilt, as `Scene::set_frame` does.
    #[test]
    fn samples_are_the_meshs_points_bit_for_bit() {
        let mut b = SceneBuilder::default();
        let m = b.material(emitter(Vec3::splat(2.0)));
        b.triangles(
            &[Vec3::new(-1.0, 2.0, -0.3), Vec3::new(1.3, 2.1, -1.0), Vec3::new(0.2, 1.9, 1.7)],
            &[[0, 1, 2]],
            m,
        );
        let mut scene = b.build();
        for pose in 0..2 {
            if pose == 1 {
                for p in &mut scene.mesh.positions {
                    *p = *p * 1.7 + Vec3::new(0.3, -0.2, 0.9);
                }
                scene.set_punctual(Vec::new());
            }
            let reference = Vec3::new(0.1, -0.5, 0.2);
            for i in 0..1000u64 {
                let u = Vec2::new(crate::sampler::hash_unit(2 * i), crate::sampler::hash_unit(2 * i + 1));
                let ls = scene
                    .lights
                    .sample(&scene.mesh, &scene.materials, &scene.textures, reference, None, 0.5, u)
                    .expect("the triangle faces the reference from either side: two-sided emitter");
                let bc = sample_uniform_triangle(u);
                let (p, ng, _) = scene.mesh.position_normal_uv(0, bc.y, bc.z);
                assert_eq!(ls.p, p, "pose {pose}, sample {i}");
                assert!(ls.n == ng || ls.n == -ng, "pose {pose}: normal {} vs the mesh's {ng}", ls.n);
            }
        }
    }

    /// A scene of `count` small emitting triangles in the plane y = 2, triangle i at (x, z) with
    /// radiance r for `(x, z, r) = at(i)`.
    fn emitter_triangles(count: usize, at: impl Fn(usize) -> (f32, f32, f32)) -> Scene {
        let mut b = SceneBuilder::default();
        for i in 0..count {
            let (x, z, r) = at(i);
            let m = b.material(emitter(Vec3::splat(r)));
            b.triangles(
                &[Vec3::new(x, 2.0, z), Vec3::new(x + 0.3, 2.0, z), Vec3::new(x, 2.0, z + 0.3)],
                &[[0, 1, 2]],
                m,
            );
        }
        b.build()
    }

    /// A directional light of radiance 3 along `d`.
    fn sun(d: Vec3) -> PunctualLight {
        PunctualLight {
            kind: PunctualKind::Directional,
            intensity: Vec3::splat(3.0),
            position: Vec3::ZERO,
            direction: d.normalize(),
        }
    }

    /// Adding punctual lights or an environment to a loaded scene keeps its area lights
    /// (`with_others`) and gives the set a fresh build would: the same lights, selection
    /// probabilities to the bit, and choices.
    #[test]
    fn punctual_and_environment_added_as_a_fresh_build_adds_them() {
        let mut scene = emitter_triangles(7, |i| (i as f32 - 3.0, 0.4 * i as f32 - 1.0, 0.5 + i as f32));
        scene.replace_punctual(vec![sun(Vec3::new(0.2, -1.0, 0.1))]);
        scene.set_environment(Some(crate::environment::Environment::uniform(Vec3::splat(0.3), true)));
        let radius = (scene.bounds.1 - scene.bounds.0).length() * 0.5;
        let fresh = LightSet::build(
            &scene.mesh,
            &scene.materials,
            &scene.textures,
            scene.lights.punctual.clone(),
            Some(crate::environment::Environment::uniform(Vec3::splat(0.3), true)),
            radius,
        );
        let kept = &scene.lights;
        assert_eq!(
            (kept.count(), kept.area_count, kept.lights.len()),
            (fresh.count(), fresh.area_count, fresh.lights.len())
        );
        assert_eq!(kept.count(), 7 + 1 + 1, "seven triangles, a sun, the environment");
        for i in 0..fresh.count() {
            assert_eq!(kept.pmf(i).to_bits(), fresh.pmf(i).to_bits(), "light {i}");
        }
        for j in 0..200u64 {
            let (p, u) = (Vec3::new(0.1, -0.5, 0.2), crate::sampler::hash_unit(j));
            let pick = |s: &LightSet| s.select(p, None, u).map(|(l, pmf)| (l, pmf.to_bits()));
            assert_eq!(pick(kept), pick(&fresh), "u {u}");
        }
    }

    /// `select_root_lanes` makes `select`'s choices, bit for bit, on the lanes it is asked for
    /// (and writes no other), for a one-node light tree with and without directional lights
    /// beside it; it declines (false, nothing written) for the other sampler kinds.
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2", target_feature = "fma"))]
    #[test]
    fn root_lanes_choose_what_one_at_a_time_chooses() {
        let mut scene = emitter_triangles(5, |i| (i as f32 - 2.0, 0.5 * i as f32 - 1.0, 1.0 + i as f32));
        let h = |j: u64| crate::sampler::hash_unit(j);
        for suns in [false, true] {
            scene.set_punctual(if suns { vec![sun(Vec3::new(0.2, -1.0, 0.1))] } else { Vec::new() });
            scene.lights.set_kind_exact(LightSamplerKind::Tree, &scene.mesh);
            assert!(scene.lights.tree.as_ref().is_some_and(|t| t.is_one_node()));
            let (mut tree_picks, mut sun_picks) = (0, 0);
            for batch in 0..100u64 {
                let at = |k: usize| 64 * batch + 8 * k as u64;
                let p: [Vec3; 8] =
                    std::array::from_fn(|k| Vec3::new(h(at(k)) * 8.0 - 4.0, 0.0, h(at(k) + 1) * 6.0 - 3.0));
                let n: [Vec3; 8] = std::array::from_fn(|k| Vec3::new(h(at(k) + 2) - 0.5, 1.0, 0.0).normalize());
                let u: [f32; 8] = std::array::from_fn(|k| if k == 7 { 1.0 - f32::EPSILON / 2.0 } else { h(at(k) + 3) });
                let lanes = (h(at(0) + 4) * 256.0) as u32 | 1;
                let mut out = [Some((usize::MAX, -1.0)); 8];
                assert!(scene.lights.select_root_lanes(&p, &n, &u, lanes, &mut out));
                for k in 0..8 {
                    let bits = |x: Option<(usize, f32)>| x.map(|(l, pmf)| (l, pmf.to_bits()));
                    if lanes & (1 << k) == 0 {
                        assert_eq!(bits(out[k]), Some((usize::MAX, (-1.0f32).to_bits())), "lane {k} not asked for");
                        continue;
                    }
                    let alone = scene.lights.select(p[k], Some(n[k]), u[k]);
                    assert_eq!(bits(out[k]), bits(alone), "suns {suns}, batch {batch}, lane {k}");
                    match alone {
                        Some((l, _)) if l >= scene.lights.lights.len() => sun_picks += 1,
                        Some(_) => tree_picks += 1,
                        None => {}
                    }
                }
            }
            assert!(
                tree_picks > 100 && (sun_picks > 10) == suns,
                "suns {suns}: {tree_picks} tree, {sun_picks} sun picks"
            );
        }
        for kind in [LightSamplerKind::Power, LightSamplerKind::Uniform] {
            scene.lights.set_kind_exact(kind, &scene.mesh);
            // A sentinel that no answer is, so that writing anything (None included) shows.
            let mut out = [Some((usize::MAX, -1.0)); 8];
            assert!(!scene.lights.select_root_lanes(&[Vec3::ZERO; 8], &[Vec3::Y; 8], &[0.5; 8], 0xff, &mut out));
            assert_eq!(out, [Some((usize::MAX, -1.0)); 8], "{kind:?}: nothing written");
        }
    }

    /// `select_batch` makes `select`'s choices, bit for bit, for every sampler kind, with two
    /// directional lights (chosen outside the tree) beside the tree's triangles, for batches
    /// longer than the walks interleaved at once.
    #[test]
    fn choosing_together_chooses_what_one_at_a_time_chooses() {
        let mut scene = emitter_triangles(40, |i| ((i % 8) as f32 - 3.5, (i / 8) as f32 - 2.0, 1.0 + (i % 5) as f32));
        scene.set_punctual(vec![sun(Vec3::new(0.2, -1.0, 0.1)), sun(Vec3::new(-0.5, -1.0, 0.3))]);
        let count = 2 * MAX_WALKS + 5;
        let h = |j: u64| crate::sampler::hash_unit(j);
        let p: Vec<Vec3> =
            (0..count as u64).map(|k| Vec3::new(h(3 * k) * 8.0 - 4.0, 0.0, h(3 * k + 1) * 6.0 - 3.0)).collect();
        let n: Vec<Option<Vec3>> = (0..count).map(|k| (!k.is_multiple_of(3)).then_some(Vec3::Y)).collect();
        let u: Vec<f32> = (0..count as u64).map(|k| h(3 * k + 2)).collect();
        for kind in [LightSamplerKind::Tree, LightSamplerKind::Power, LightSamplerKind::Uniform] {
            scene.lights.set_kind_exact(kind, &scene.mesh);
            assert_eq!(scene.lights.walks_tree(), kind == LightSamplerKind::Tree);
            let mut out = vec![None; count];
            scene.lights.select_batch(&p, &n, &u, &mut out);
            let mut infinite = 0;
            for k in 0..count {
                let alone = scene.lights.select(p[k], n[k], u[k]);
                let bits = |x: Option<(usize, f32)>| x.map(|(l, pmf)| (l, pmf.to_bits()));
                assert_eq!(bits(out[k]), bits(alone), "{kind:?}, point {k}");
                infinite += usize::from(alone.is_some_and(|(l, _)| l >= scene.lights.lights.len()));
            }
            assert!(infinite > 0 && infinite < count, "{kind:?}: {infinite} of {count} chose a sun");
        }
    }
}
