//! Bulbs: closed convex emitters (a sphere lamp's 1152 triangles, a cube's twelve…) sampled as
//! one light, by the cone of directions their bounding ball subtends.
//!
//! Seen from a point outside the ball, the bulb lies inside the cone of half-angle θmax,
//! sin²θmax = R²/d². A direction drawn uniformly in that cone (pbrt-v4 §6.2.4, `Sphere::Sample`
//! by solid angle; Shirley et al. 1996) and the first point where it meets the bulb's triangles
//! is a next-event sample whose solid-angle density is 1/(2π(1 − cos θmax)) wherever the bulb is
//! met, and whose directions that miss it (past the inscribed mesh's silhouette) carry nothing.
//! Against choosing one of the bulb's triangles (by power or by a light tree's importance) and a
//! point on it by area, this
//!
//! * never samples the bulb's far side, which a closed emitter hides from every outside point;
//! * spreads the samples evenly over the solid angle the bulb covers, so the estimate of a
//!   uniformly emitting bulb varies only with the receiver's BSDF and cosine and with visibility;
//! * turns thousands of selection entries into one, so a light tree's walk stops a few levels up
//!   (`scenes/sphere_lights`: 4608 triangles became four bulbs).
//!
//! The estimator stays unbiased for any emitter inside the ball; convexity and closedness only
//! make the cone a tight fit. A BSDF-sampled ray that hits the bulb from outside the ball meets
//! the same first point the cone's direction would, so MIS weighs it with the cone's density
//! (`pdf`). From inside the ball (a point on the bulb itself, or between the bulb and its ball)
//! the cone is undefined; there a point is drawn uniformly by area over the whole bulb, and `pdf`
//! answers with that technique's density: both sides test the same `d² > R²` in the same f32
//! arithmetic, so they always agree on which technique applies.
//!
//! Where the cone's direction meets the bulb needs no search when it passes through the ball
//! inscribed in the bulb (inside every facet's plane, so inside the bulb): it then surely meets
//! the bulb, on its near side, where a uniform emitter's radiance is the same everywhere. When the
//! bulb is also isolated (nothing else reaches into its clear box, `clear_box`), the shadow ray
//! needs to go only as far as the box: the sample aims there (`BulbHit::Along`), and the kernel
//! draws such directions eight lanes at once (`spmd::radiance8`). Only the other directions,
//! near the silhouette, search the bulb's own BVH for the point (`BulbHit::Point`): 2.4 % of
//! those that meet the test's 24 × 12 UV sphere (`bulb_samples_follow_the_density_mis_uses`
//! prints the counts), 5.5 % of `scenes/sphere_lights`' bulb samples at about 515 instructions
//! a search (callgrind, 64×48, 16 spp: 2 005 `Accel::intersect_from` calls for 36 177 light
//! choices).

use crate::accel::Accel;
use crate::clear_box::ClearBox;
use crate::convex_solid::{self, Search};
use crate::math::{sin_cos_azimuth, Frame, Vec2, Vec3, PI};
use crate::mesh::Mesh;

/// Which emissive groups become bulbs: 16 triangles or more (smaller ones are a leaf or two of a
/// light tree, and a cone around a quad wastes the directions its ball adds), up to 8192 (the
/// convexity test is triangles × vertices), at most 64 of them, within 6.4·10⁷ vertex-plane tests.
const SEARCH: Search = Search { sizes: 16..=8192, max_groups: 64, budget: 64_000_000 };

/// One closed convex emitter.
pub struct Bulb {
    /// The ball about `center` of squared radius `radius2` holds every vertex (with margins for
    /// the f32 centre's rounding).
    center: Vec3,
    radius2: f32,
    /// The inscribed ball's squared radius (every facet plane farther from `center`, with
    /// margins): a direction through it surely meets the bulb. 0 when there is none.
    inner2: f32,
    /// The bulb's material (one for all its triangles, untextured).
    pub(crate) material: u32,
    /// The box nothing else reaches into, when the bulb is isolated (`clear_box`): a sure
    /// direction's shadow ray ends where it enters it.
    pub(crate) clear: Option<ClearBox>,
    /// Its triangles' box, for the light tree.
    pub(crate) lo: Vec3,
    pub(crate) hi: Vec3,
    /// The scene triangles it is made of, in the order of `cdf`.
    pub(crate) triangles: Vec<u32>,
    /// Running sums of the triangles' areas (the last is `area`): the inside technique's choice.
    cdf: Vec<f32>,
    /// Total surface area.
    pub(crate) area: f32,
    /// A BVH over its triangles alone: where a cone direction meets the bulb.
    accel: Accel,
}

/// Where a bulb sample landed: a scene triangle and the barycentrics (b1, b2) of the point.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BulbPoint {
    pub triangle: u32,
    pub b1: f32,
    pub b2: f32,
}

/// A bulb sample: the point found, or (for a direction that surely meets an isolated bulb's
/// near side) the direction and where it enters the bulb's clear box.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum BulbHit {
    Point(BulbPoint),
    Along { d: Vec3, t: f32 },
}

/// What the kernel needs to draw an isolated bulb's sure directions eight lanes at once
/// (`spmd::radiance8`, the same arithmetic as [`Bulb::sample`]'s).
#[derive(Clone, Copy, Debug)]
pub struct BulbLane {
    pub center: Vec3,
    pub radius2: f32,
    pub inner2: f32,
    /// The clear box's corners.
    pub lo: Vec3,
    pub hi: Vec3,
    /// The bulb's emitted radiance (untextured).
    pub le: Vec3,
}

/// A sure direction is taken without a search only from within a thousand inner radii of the
/// centre (this, squared): the test's cross product is off by a few units in the last place of
/// the distance (6·10⁻⁸ of it, so 6·10⁻⁵ of the inner radius at that range), which stays far
/// below the inner ball's margin (`INNER_MARGIN2`: 10⁻³ of its radius). (An estimate from the
/// operations' rounding, not a measurement.)
pub const SURE_RANGE2: f32 = 1e6;

/// The solids' inner ball (`convex_solid::inner_ball`, a part in 10⁴ inside every facet plane)
/// shrunk by a further part in 10³ of its radius (this is the factor on its square), the margin
/// the sure test's rounding stays below out to `SURE_RANGE2`.
const INNER_MARGIN2: f32 = 0.998;

impl Bulb {
    /// The bulbs among `candidates` (emissive triangles NEE may sample, with their areas): groups
    /// that are closed (every edge shared by two triangles), convex with their winding normals
    /// outward, and whose triangles share a material `uniform` accepts (untextured emission,
    /// so a cone sample needs no texture coordinates).
    pub fn find(mesh: &Mesh, candidates: &[(u32, f32)], uniform: impl Fn(u32) -> bool) -> Vec<Bulb> {
        if candidates.len() < *SEARCH.sizes.start() || mesh.triangles.len() > convex_solid::MAX_SCENE_TRIANGLES {
            return Vec::new();
        }
        let tris: Vec<u32> = candidates.iter().map(|&(t, _)| t).collect();
        let material = |t: u32| mesh.triangles[t as usize].material;
        let (found, _) = convex_solid::convex_groups(mesh, &tris, &SEARCH, |g, hull| {
            let m = material(g[0]);
            (hull.outward > 0.0 && g.iter().all(|&t| material(t) == m) && uniform(m) && convex_solid::closed(mesh, g))
                .then_some(())
        });
        found
            .into_iter()
            .filter_map(|c| {
                let areas: Vec<f32> = c.members.iter().map(|&i| candidates[i].1).collect();
                let m = material(c.tris[0]);
                let ball = convex_solid::inner_ball(mesh, &c.tris, &c.hull)?;
                Bulb::new(mesh, c.tris, &areas, &c.hull, ball, m)
            })
            .collect()
    }

    /// The bulb of `triangles` (with their `areas`), whose balls are the solids' (`ball`: the
    /// outer one holds every vertex with margins, so every direction towards the bulb lies in
    /// its cone; a line through the inner one crosses the bulb, being inside every facet plane).
    fn new(
        mesh: &Mesh,
        triangles: Vec<u32>,
        areas: &[f32],
        hull: &convex_solid::Hull,
        ball: convex_solid::Solid,
        material: u32,
    ) -> Option<Bulb> {
        let (lo, hi, center, radius2) = (hull.lo, hull.hi, ball.center32, ball.outer_sq);
        let inner2 = ball.inner_sq * INNER_MARGIN2;
        let mut cdf = Vec::with_capacity(areas.len());
        let mut sum = 0.0f64;
        for &a in areas {
            sum += a as f64;
            cdf.push(sum as f32);
        }
        let area = sum as f32;
        (radius2 > 0.0 && radius2.is_finite() && area > 0.0 && area.is_finite()).then(|| Bulb {
            center,
            radius2,
            inner2,
            material,
            clear: None,
            lo,
            hi,
            accel: Accel::build_subset(mesh, triangles.clone()),
            triangles,
            cdf,
            area,
        })
    }

    /// The kernel's view of an isolated bulb (None when it is not: no sure directions then) whose
    /// material emits `le`.
    pub fn lane(&self, le: Vec3) -> Option<BulbLane> {
        let (lo, hi) = self.clear?.bounds();
        Some(BulbLane { center: self.center, radius2: self.radius2, inner2: self.inner2, lo, hi, le })
    }

    /// 1 − cos θmax of the cone the ball subtends from `reference`, when it lies outside the
    /// ball (else None: the inside technique applies). Written as sin²/(1 + cos), which keeps its
    /// digits when the bulb is small and far (1 − cos would cancel).
    #[inline]
    fn cone(&self, reference: Vec3) -> Option<(f32, Vec3, f32)> {
        let to = self.center - reference;
        let d2 = to.length_squared();
        if !(d2 > self.radius2) || !d2.is_finite() {
            return None;
        }
        let sin2 = self.radius2 / d2;
        let cos_max = (1.0 - sin2).max(0.0).sqrt();
        Some((sin2 / (1.0 + cos_max), to, d2))
    }

    /// A point on the bulb for next-event estimation from `reference` with the 2D sample `u`; None
    /// where the cone's direction misses the bulb (that sample carries no light).
    #[inline]
    pub fn sample(&self, reference: Vec3, u: Vec2) -> Option<BulbHit> {
        match self.cone(reference) {
            Some((omc, to, d2)) => {
                // cos θ uniform in [cos θmax, 1]: 1 − cos θ = u·(1 − cos θmax), and
                // sin²θ = (1 − cos θ)(1 + cos θ) without cancellation.
                let one_minus_cos = u.x * omc;
                let cos = 1.0 - one_minus_cos;
                let sin = (one_minus_cos * (2.0 - one_minus_cos)).max(0.0).sqrt();
                let (s, c) = sin_cos_azimuth(2.0 * PI * u.y);
                let frame = Frame::from_normal(to / d2.sqrt());
                let d = frame.to_world(Vec3::new(sin * c, sin * s, cos));
                // Through the inner ball: surely the bulb's near side, and an isolated bulb's box
                // is all the shadow ray must cross. The line's distance from the centre is
                // |to × d| for the direction as rounded (no cancellation, unlike d² − (to·d)²).
                if let Some(clear) = &self.clear {
                    if to.cross(d).length_squared() < self.inner2 && d2 < SURE_RANGE2 * self.inner2 {
                        if let Some(t) = clear.entry(reference, d) {
                            return Some(BulbHit::Along { d, t });
                        }
                    }
                }
                let hit = self.accel.intersect_from(reference, d, 0.0, f32::INFINITY)?;
                Some(BulbHit::Point(BulbPoint { triangle: hit.triangle, b1: hit.b1, b2: hit.b2 }))
            }
            None => {
                // Uniform by area: a triangle by its share of the area, the rest of u.x reused.
                let x = u.x * self.area;
                let i = self.cdf.partition_point(|&c| c <= x).min(self.cdf.len() - 1);
                let start = if i == 0 { 0.0 } else { self.cdf[i - 1] };
                let width = self.cdf[i] - start;
                let ux = if width > 0.0 { ((x - start) / width).clamp(0.0, 1.0 - f32::EPSILON) } else { 0.5 };
                let b = crate::math::sample_uniform_triangle(Vec2::new(ux, u.y));
                Some(BulbHit::Point(BulbPoint { triangle: self.triangles[i], b1: b.y, b2: b.z }))
            }
        }
    }

    /// The solid-angle density with which [`Self::sample`] from `reference` gives the point `p`
    /// of the bulb (geometric normal `ng`): the cone's, uniform, from outside the ball; the
    /// area technique's dist²/(|cos|·area) from inside. 0 where it is not positive and finite.
    #[inline]
    pub fn pdf(&self, reference: Vec3, p: Vec3, ng: Vec3) -> f32 {
        self.density(reference, || {
            let to = p - reference;
            let dist2 = to.length_squared();
            (dist2, ng.dot(to) / dist2.sqrt())
        })
    }

    /// [`Self::pdf`] with the point given by its squared distance and the cosine at the bulb
    /// (`at`, asked only from inside the ball, where the area technique needs them): what a
    /// sample that has worked them out already passes.
    #[inline]
    pub fn density(&self, reference: Vec3, at: impl FnOnce() -> (f32, f32)) -> f32 {
        let pdf = self.cone_pdf(reference).unwrap_or_else(|| {
            let (dist2, cos) = at();
            dist2 / (cos.abs() * self.area)
        });
        if pdf > 0.0 && pdf.is_finite() {
            pdf
        } else {
            0.0
        }
    }

    /// The cone technique's density, uniform over the cone, from `reference` outside the ball
    /// (None from inside); not yet checked for being positive and finite.
    #[inline]
    pub fn cone_pdf(&self, reference: Vec3) -> Option<f32> {
        self.cone(reference).map(|(omc, ..)| 1.0 / (2.0 * PI * omc))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::Scene;
    use crate::testing::{one_sided_emitter, SceneBuilder};

    const LE: f32 = 3.0;

    /// One 24 × 12 UV sphere bulb (528 triangles) of radius `r` about `c`, wound outward.
    fn bulb_scene(c: Vec3, r: f32) -> Scene {
        let mut b = SceneBuilder::default();
        let m = b.material(one_sided_emitter(Vec3::splat(LE)));
        b.uv_sphere(c, r, 24, 12, m);
        b.build()
    }

    fn bulbs_of(scene: &Scene) -> Vec<Bulb> {
        let cands: Vec<(u32, f32)> = (0..scene.mesh.triangles.len() as u32).map(|t| (t, scene.mesh.area(t))).collect();
        Bulb::find(&scene.mesh, &cands, |_| true)
    }

    fn u2(i: u64) -> Vec2 {
        Vec2::new(crate::sampler::hash_unit(2 * i), crate::sampler::hash_unit(2 * i + 1))
    }

    /// A closed outward sphere is one bulb (and the light set's one light, with a clear box); the
    /// same sphere wound inward, or with a triangle missing (not closed), is none.
    #[test]
    fn a_closed_outward_sphere_is_a_bulb_and_nothing_else_is() {
        let scene = bulb_scene(Vec3::new(0.3, 1.0, -0.2), 0.5);
        let bulbs = bulbs_of(&scene);
        assert_eq!(bulbs.len(), 1);
        assert_eq!(bulbs[0].triangles.len(), scene.mesh.triangles.len());
        assert_eq!(scene.lights.bulb_count(), 1);
        assert_eq!(scene.lights.finite_count(), 1);
        let mesh = &scene.mesh;
        let tris: Vec<[u32; 3]> = mesh.triangles.iter().map(|t| t.v).collect();
        for variant in 0..2 {
            let mut b = SceneBuilder::default();
            let m = b.material(one_sided_emitter(Vec3::ONE));
            let t: Vec<[u32; 3]> = match variant {
                0 => tris.iter().map(|&[a, b, c]| [a, c, b]).collect(),
                _ => tris[1..].to_vec(),
            };
            b.triangles(&mesh.positions, &t, m);
            let other = b.build();
            assert!(bulbs_of(&other).is_empty(), "variant {variant}");
            assert_eq!(other.lights.bulb_count(), 0, "variant {variant}");
        }
    }

    /// The first surface a ray from `x` along `w` meets, if it is the bulb: (triangle, point,
    /// normal).
    fn first_bulb_hit(scene: &Scene, x: Vec3, w: Vec3) -> Option<(u32, Vec3, Vec3)> {
        let hit = scene.intersect(x, w, f32::INFINITY)?;
        let sp = scene.mesh.surface_point(hit.triangle, hit.b1, hit.b2);
        scene.lights.is_light(hit.triangle).then_some((hit.triangle, sp.p, sp.ng))
    }

    /// Next-event samples of a bulb (the light set's, both kinds of cone sample and the inside
    /// technique) against the density `LightSet::pdf` gives a BSDF-sampled ray that hits the
    /// bulb: a chi-square test over directions, from outside the ball (near and far) and from
    /// between the bulb and its ball. A sample whose direction first meets something else than
    /// its point (the inside technique's far side) is mass outside every cell, as is a miss.
    #[test]
    fn bulb_samples_follow_the_density_mis_uses() {
        let c = Vec3::new(1.5, 1.0, 0.2);
        let scene = bulb_scene(c, 0.5);
        let (mesh, mats, tex) = (&scene.mesh, &scene.materials, &scene.textures);
        // A facet's centre pushed out half way to the ball: inside the ball, outside the bulb.
        let f = mesh.surface_point(100, 1.0 / 3.0, 1.0 / 3.0);
        let between = c + (f.p - c) * (1.0 + 0.5 * (0.5 / (f.p - c).length() - 1.0));
        // Each case's (θ, φ) bins and midpoint subdivision. The far bulb spans about 4°: finer
        // bins than 2.8° leave silhouette cells where a sample lands but no midpoint sees the
        // bulb, which the helper counts as certain failure. The inside technique's directions
        // fill a hemisphere: coarse bins keep its cells above five expected samples.
        let cases = [
            ("near", Vec3::ZERO, (64, 128, 12)),
            ("far", c + Vec3::new(-6.0, -3.0, 2.0), (64, 128, 16)),
            ("between", between, (16, 32, 24)),
        ];
        for (case, x, (theta_bins, phi_bins, sub)) in cases {
            let (mut along, mut points) = (0, 0);
            let n = 60_000;
            let chi = crate::stats::chi2_directions(
                n,
                theta_bins,
                phi_bins,
                sub,
                |i| {
                    let ls = scene.lights.sample(mesh, mats, tex, x, None, 0.5, u2(i as u64))?;
                    let (tri, p, _) = first_bulb_hit(&scene, x, ls.wi)?;
                    if ls.light == crate::clear_box::NONE {
                        along += 1;
                    } else {
                        points += 1;
                        // The point sampled is the one its direction meets first.
                        if scene.lights.lights[ls.light as usize].triangle != tri || (p - ls.p).length() > 1e-4 {
                            return None;
                        }
                    }
                    Some(ls.wi)
                },
                |w| match first_bulb_hit(&scene, x, w) {
                    Some((tri, p, ng)) => scene.lights.pdf(tri, x, None, p, ng) as f64,
                    None => 0.0,
                },
            );
            println!("{case}: {along} sure directions, {points} searched or by area, {chi:?}");
            assert!(chi.p_value > 1e-4, "{case}: {chi:?}");
            match case {
                "between" => assert!(along == 0 && points > n / 4, "{case}: {along} sure, {points} searched"),
                _ => assert!(along > points && points > 0, "{case}: {along} sure, {points} searched"),
            }
        }
    }

    /// The irradiance next-event estimation gives at a point below the bulb equals the bulb's
    /// near side integrated by quadrature (on a convex body, a point is seen from outside iff its
    /// facet faces the viewer): Σ over facing triangles of Le ∫ cos cos′ / d² dA.
    #[test]
    fn bulb_irradiance_matches_quadrature() {
        let c = Vec3::new(0.2, 1.3, -0.1);
        let scene = bulb_scene(c, 0.5);
        let (mesh, mats, tex) = (&scene.mesh, &scene.materials, &scene.textures);
        for x in [Vec3::ZERO, Vec3::new(0.9, 0.6, 0.3)] {
            let normal = Vec3::Y;
            let mut quadrature = 0.0f64;
            let k = 24;
            for t in 0..mesh.triangles.len() as u32 {
                let area = mesh.area(t) as f64;
                // The centroids of the k² equal triangles a k-fold subdivision makes: the
                // upright ones, then the inverted ones.
                let upright = (0..k).flat_map(|a| (0..k - a).map(move |b| (a, b, 1.0 / 3.0)));
                let inverted = (0..k - 1).flat_map(|a| (0..k - 1 - a).map(move |b| (a, b, 2.0 / 3.0)));
                for (a, b, o) in upright.chain(inverted) {
                    {
                        let (b1, b2) = ((a as f32 + o) / k as f32, (b as f32 + o) / k as f32);
                        let sp = mesh.surface_point(t, b1, b2);
                        let to = (sp.p - x).as_dvec3();
                        let d2 = to.length_squared();
                        let w = to / d2.sqrt();
                        let (cos_r, cos_l) = (normal.as_dvec3().dot(w), -sp.ng.as_dvec3().dot(w));
                        if cos_l > 0.0 && cos_r > 0.0 {
                            quadrature += LE as f64 * cos_r * cos_l / d2 * area / (k * k) as f64;
                        }
                    }
                }
            }
            let n = 200_000u64;
            let (mut sum, mut sum2) = (0.0f64, 0.0f64);
            for i in 0..n {
                let e = match scene.lights.sample(mesh, mats, tex, x, Some(normal), 0.5, u2(i)) {
                    Some(ls) if first_bulb_hit(&scene, x, ls.wi).is_some() => {
                        ls.le.x as f64 * normal.dot(ls.wi).max(0.0) as f64 / ls.pdf as f64
                    }
                    _ => 0.0,
                };
                sum += e;
                sum2 += e * e;
            }
            let mean = sum / n as f64;
            let se = ((sum2 / n as f64 - mean * mean) / n as f64).sqrt();
            assert!(
                (mean - quadrature).abs() < 4.0 * se + 2e-3 * quadrature,
                "{x}: NEE {mean} ± {se} against quadrature {quadrature}"
            );
        }
    }

    /// The density is finite at the extremes: a bulb 10⁴ away (θmax ≈ 5·10⁻⁵), a point just
    /// outside the ball, a point on the bulb (inside technique).
    #[test]
    fn densities_stay_finite_at_the_extremes() {
        let scene = bulb_scene(Vec3::ZERO, 0.5);
        let (mesh, mats, tex) = (&scene.mesh, &scene.materials, &scene.textures);
        for reference in [Vec3::new(1e4, 0.0, 0.0), Vec3::new(0.0, 0.5001, 0.0), Vec3::new(0.0, -0.4999, 0.0)] {
            let mut found = 0;
            for i in 0..64 {
                let Some(ls) = scene.lights.sample(mesh, mats, tex, reference, None, 0.5, u2(i)) else { continue };
                assert!(ls.pdf > 0.0 && ls.pdf.is_finite(), "{reference}: pdf {}", ls.pdf);
                assert!(ls.le.is_finite() && ls.wi.is_finite() && ls.dist.is_finite(), "{reference}: {ls:?}");
                found += 1;
            }
            assert!(found > 0, "{reference}: no sample");
        }
    }
}
