//! Emissive triangles as area lights. A light is chosen in proportion to its power with an alias
//! table, then a point is sampled uniformly by area and the area pdf is converted to solid angle
//! (pbrt-v4 §12.2 and §12.5; Veach 1997 §9).

use crate::alias::AliasTable;
use crate::environment::Environment;
use crate::material::Material;
use crate::math::{luminance, sample_uniform_triangle, Vec2, Vec3, PI};
use crate::mesh::Mesh;
use crate::punctual::PunctualLight;
use crate::texture::Texture;

#[derive(Clone, Copy, Debug)]
pub struct AreaLight {
    pub triangle: u32,
    pub area: f32,
    pub two_sided: bool,
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
}

#[derive(Default)]
pub struct LightSet {
    pub lights: Vec<AreaLight>,
    selection: AliasTable,
    /// For each scene triangle, its light index or `u32::MAX`.
    triangle_light: Vec<u32>,
    /// Punctual (delta) lights: entries `lights.len() .. lights.len() + punctual.len()` of the
    /// selection table.
    pub punctual: Vec<PunctualLight>,
    /// The environment, if the scene has one. When it is importance-sampled it is the last entry of
    /// the selection table.
    pub environment: Option<Environment>,
}

/// Radiance leaving an emissive surface point towards direction `w` (pointing away from the
/// surface). Emission is one-sided along the winding normal `ng` unless the material is double-sided.
#[inline]
pub fn emitted(m: &Material, textures: &[Texture], ng: Vec3, uv: Vec2, w: Vec3) -> Vec3 {
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
        let mut lights = Vec::new();
        let mut power = Vec::new();
        let mut triangle_light = vec![u32::MAX; mesh.triangles.len()];
        for (i, t) in mesh.triangles.iter().enumerate() {
            let m = &materials[t.material as usize];
            if !m.is_emissive() {
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
            triangle_light[i] = lights.len() as u32;
            lights.push(AreaLight { triangle: i as u32, area, two_sided: m.double_sided });
            power.push(p);
        }
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
        LightSet { lights, selection, triangle_light, punctual, environment }
    }

    fn environment_index(&self) -> usize {
        self.lights.len() + self.punctual.len()
    }

    /// True when next-event estimation has nothing to sample.
    pub fn is_empty(&self) -> bool {
        self.selection.is_empty()
    }

    /// The probability that NEE samples the environment from direction `d` (0 when it is not sampled).
    pub fn environment_pdf(&self, d: Vec3) -> f32 {
        match &self.environment {
            Some(env) if env.is_sampled() => self.selection.pmf(self.environment_index()) * env.pdf(d),
            _ => 0.0,
        }
    }

    /// Samples a light and a point on it as seen from `reference`.
    pub fn sample(
        &self,
        mesh: &Mesh,
        materials: &[Material],
        textures: &[Texture],
        reference: Vec3,
        u_select: f32,
        u: Vec2,
    ) -> Option<LightSample> {
        if self.selection.is_empty() {
            return None;
        }
        let (idx, pmf) = self.selection.sample(u_select);
        if idx >= self.lights.len() && idx < self.environment_index() {
            let (wi, dist, e) = self.punctual[idx - self.lights.len()].illuminate(reference)?;
            return Some(LightSample {
                p: reference + wi * dist.min(1e30),
                n: -wi,
                wi,
                dist,
                le: e,
                pdf: pmf,
                delta: true,
            });
        }
        if idx == self.environment_index() {
            let env = self.environment.as_ref()?;
            let (wi, le, pdf) = env.sample(u)?;
            let pdf = pmf * pdf;
            if !(pdf > 0.0) || !pdf.is_finite() {
                return None;
            }
            return Some(LightSample { p: reference + wi, n: -wi, wi, dist: f32::INFINITY, le, pdf, delta: false });
        }
        let light = &self.lights[idx];
        let b = sample_uniform_triangle(u);
        let (p, ng, uv) = mesh.position_normal_uv(light.triangle, b.y, b.z);
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
        let m = &materials[mesh.triangles[light.triangle as usize].material as usize];
        let le = emitted(m, textures, ng, uv, -wi);
        let pdf = pmf * dist2 / (cos_l.abs() * light.area);
        if !(pdf > 0.0) || !pdf.is_finite() {
            return None;
        }
        let n = if cos_l > 0.0 { ng } else { -ng };
        Some(LightSample { p, n, wi, dist, le, pdf, delta: false })
    }

    /// Solid-angle pdf with which `sample()` from `reference` would have produced the point `p` on
    /// triangle `tri` (geometric normal `ng`); 0 for a triangle that is not a light.
    pub fn pdf(&self, tri: u32, reference: Vec3, p: Vec3, ng: Vec3) -> f32 {
        let Some(&li) = self.triangle_light.get(tri as usize) else {
            return 0.0;
        };
        if li == u32::MAX {
            return 0.0;
        }
        let light = &self.lights[li as usize];
        let to = p - reference;
        let dist2 = to.length_squared();
        let cos_l = ng.dot(to).abs() / dist2.sqrt();
        if !(cos_l > 0.0) {
            return 0.0;
        }
        self.selection.pmf(li as usize) * dist2 / (cos_l * light.area)
    }

    /// True when triangle `tri` is in the light set (NEE can sample it).
    pub fn is_light(&self, tri: u32) -> bool {
        self.triangle_light.get(tri as usize).is_some_and(|&l| l != u32::MAX)
    }

    /// The light-selection probability of light `i`.
    pub fn pmf(&self, i: usize) -> f32 {
        self.selection.pmf(i)
    }
}
