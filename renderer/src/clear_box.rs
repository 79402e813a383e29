//! Where a shadow ray to an area light may stop: the box around a convex emitter that nothing
//! else enters.
//!
//! A shadow ray aimed at a point q on a light's triangle only needs to be tested up to where it
//! enters the light's own bounding box, when two things hold:
//!
//! * **Isolation**: no other triangle of the scene reaches into the box (checked once, at load,
//!   against every triangle's bounds). Past the box's boundary the ray can then meet only the
//!   light's own group of triangles.
//! * **Convexity, seen from the front**: every vertex of the group lies on or behind the plane of
//!   every one of its triangles (the group is a piece of the boundary of its convex hull: a
//!   closed convex mesh such as a sphere bulb, a planar quad, a convex cap), and the ray's origin
//!   lies in front of the plane of q's triangle. That plane supports the hull, so the whole
//!   segment from the origin to just off q stays in the open half-space in front of it and meets
//!   no triangle of the group.
//!
//! Nothing the walk could find beyond the box is real, so the answer is the same; what changes is
//! the cost. A walk to a point on a sphere light descends the light's subtree down to the leaves
//! around q and tests them, only to find nothing (the scene `veach`: about a thousand
//! instructions a shadow ray); stopped at the box, it ends after the nodes above the light. The
//! one difference the stop can make is on purpose: a false hit on the light's own triangles near
//! q, from rounding, can no longer darken the sample.
//!
//! Groups are the lights' connected pieces: triangles sharing a vertex position (exact bits, so
//! flat-shaded meshes whose faces do not share vertex indices still form one group).

use crate::convex_solid;
use crate::light::AreaLight;
use crate::mesh::Mesh;
use glam::Vec3;

/// No clear box (the light is not in an isolated convex group, or is not an area light).
pub const NONE: u32 = u32::MAX;

/// Which groups get a box ([`crate::convex_solid::convex_groups`]): 16 triangles or more
/// (smaller ones lie in a leaf or two, whose test is all a stop could save, and computing the stop
/// costs about as much: the Cornell box's two-triangle light, 2.9 % more instructions, the walks'
/// count unchanged) up to 4096 (the convexity test is triangles × vertices), at most 64 of them,
/// within 6.4·10⁷ vertex-plane tests (a closed 4096-triangle mesh has about 2050 vertices, so
/// about 8·10⁶ tests): scene preparation stays within milliseconds.
const SEARCH: crate::convex_solid::Search =
    crate::convex_solid::Search { sizes: 16..=4096, max_groups: 64, budget: 64_000_000 };

/// An emitter group's box, grown a little (the margin a ray stopped at its boundary keeps from
/// the group's triangles), with what the facing test needs.
#[derive(Clone, Copy, Debug)]
pub struct ClearBox {
    lo: Vec3,
    hi: Vec3,
    /// +1 when the group's winding normals point out of its hull, −1 when they point in.
    outward: f32,
    /// How far in front of its own triangle's plane a ray's origin must be (the convexity test's
    /// rounding allowance).
    front: f32,
}

impl ClearBox {
    /// Where a shadow ray from `o` along unit `d`, aimed at a point of light `light`'s triangle
    /// and stopping at `tmax`, may stop instead: where it enters the box, when its origin is in
    /// front of the light's triangle and outside the box; else `tmax`.
    #[inline]
    pub fn shadow_tmax(&self, light: &AreaLight, o: Vec3, d: Vec3, tmax: f32) -> f32 {
        // In front by more than the convexity test's allowance plus the rounding of this f32 dot
        // product itself, which grows with the distance (a few units in the last place of it).
        let to = o - light.p0;
        if !(self.outward * light.ng.dot(to) > self.front + 2e-6 * to.abs().max_element()) {
            return tmax;
        }
        let inside = o.cmpge(self.lo).all() && o.cmple(self.hi).all();
        if inside {
            return tmax;
        }
        match self.entry(o, d) {
            Some(near) if near < tmax => near,
            _ => tmax,
        }
    }

    /// The box's corners.
    pub fn bounds(&self) -> (Vec3, Vec3) {
        (self.lo, self.hi)
    }

    /// Where a ray from `o` (outside the box) along `d` enters the box; None when it misses it
    /// or starts inside or on it.
    #[inline]
    pub fn entry(&self, o: Vec3, d: Vec3) -> Option<f32> {
        // The slab test (Kay and Kajiya 1986): the entry is the latest of the three axes' nearer
        // plane crossings. An axis the ray runs parallel to gives ±∞ (or NaN for an origin on
        // its plane, which `max` passes over).
        let inv = d.recip();
        let (a, b) = ((self.lo - o) * inv, (self.hi - o) * inv);
        let near = a.min(b).max_element();
        let far = a.max(b).min_element();
        (near > 0.0 && near <= far).then_some(near)
    }
}

/// The lights' clear boxes: `(boxes, per light its box index or NONE)`.
pub fn find(mesh: &Mesh, lights: &[AreaLight]) -> (Vec<ClearBox>, Vec<u32>) {
    let mut of_light = vec![NONE; lights.len()];
    if lights.is_empty() || !mesh.instances.is_empty() || mesh.triangles.len() > convex_solid::MAX_SCENE_TRIANGLES {
        return (Vec::new(), of_light);
    }
    let tris: Vec<u32> = lights.iter().map(|l| l.triangle).collect();
    let (candidates, _) = convex_solid::convex_groups(mesh, &tris, &SEARCH, |_, hull| Some(clear_box(hull)));
    if candidates.is_empty() {
        return (Vec::new(), of_light);
    }
    // Isolation: no triangle outside the group reaches into its box.
    let isolated = convex_solid::isolated(mesh, &candidates, |c| (c.value.lo, c.value.hi), |_, _| false);
    let mut boxes = Vec::new();
    for (c, ok) in candidates.into_iter().zip(isolated) {
        if ok {
            for l in c.members {
                of_light[l] = boxes.len() as u32;
            }
            boxes.push(c.value);
        }
    }
    (boxes, of_light)
}

/// The grown box of a group whose `hull` is convex: grown by 10⁻⁴ of its size and the hull
/// test's allowance, the margin a ray stopped at its boundary keeps from the group's triangles.
fn clear_box(hull: &convex_solid::Hull) -> ClearBox {
    let extent = (hull.hi - hull.lo).length();
    let grow = Vec3::splat(1e-4 * extent + 4.0 * hull.tol as f32);
    ClearBox { lo: hull.lo - grow, hi: hull.hi + grow, outward: hull.outward as f32, front: 4.0 * hull.tol as f32 }
}

#[cfg(test)]
mod tests {
    use super::*;

    use crate::testing::mesh_of;

    fn lights_of(m: &Mesh, tris: std::ops::Range<u32>) -> Vec<AreaLight> {
        tris.map(|i| {
            let [p0, p1, p2] = m.vertices(i);
            let (e1, e2) = (p1 - p0, p2 - p0);
            let ng = e1.cross(e2).normalize();
            AreaLight {
                p0,
                e1,
                e2,
                ng,
                triangle: i,
                area: 0.5 * e1.cross(e2).length(),
                two_sided: false,
                material: 0,
                le: Vec3::ZERO,
                textured: false,
            }
        })
        .collect()
    }

    /// An icosphere of 80 faces with outward winding, each face its own vertex triple (as a
    /// flat-shaded export has them); `dent` pushes its first vertex towards the centre.
    fn ball(c: Vec3, r: f32, dent: f32) -> Vec<[Vec3; 3]> {
        let (v, f) = crate::testing::icosphere(1);
        let first = v[0];
        let at = |p: Vec3| c + if p == first { p * r * (1.0 - dent) } else { p * r };
        f.iter().map(|t| [at(v[t[0] as usize]), at(v[t[1] as usize]), at(v[t[2] as usize])]).collect()
    }

    #[test]
    fn an_isolated_convex_light_gets_a_box_that_stops_rays_from_the_front() {
        let mut tris = ball(Vec3::new(0.0, 3.0, 0.0), 0.5, 0.0);
        let n = tris.len() as u32;
        // A floor far below.
        tris.push([Vec3::new(-5.0, 0.0, -5.0), Vec3::new(5.0, 0.0, -5.0), Vec3::new(0.0, 0.0, 5.0)]);
        let m = mesh_of(&tris);
        let lights = lights_of(&m, 0..n);
        let (boxes, of) = find(&m, &lights);
        assert_eq!(boxes.len(), 1);
        assert!(of.iter().all(|&b| b == 0), "{of:?}");
        // From the floor to a point of a face that looks down.
        let o = Vec3::new(0.2, 0.01, 0.1);
        let down = (0..lights.len()).find(|&l| lights[l].ng.y < -0.9).unwrap();
        let l = &lights[down];
        let q = l.p0 + l.e1 * 0.3 + l.e2 * 0.3;
        let d = (q - o).normalize();
        let tmax = (q - o).length();
        let t = boxes[0].shadow_tmax(l, o, d, tmax);
        assert!(t < tmax && t > 0.0);
        // It stops at the box: below every vertex of the light.
        let stop = o + d * t;
        assert!(stop.y < 3.0 - 0.5 && stop.y > 3.0 - 0.5 - 0.01, "{stop}");
        // A face that looks away from the origin is behind the hull: no stop.
        let up = (0..lights.len()).find(|&l| lights[l].ng.y > 0.9).unwrap();
        let l = &lights[up];
        let q = l.p0 + l.e1 * 0.3 + l.e2 * 0.3;
        let d = (q - o).normalize();
        assert_eq!(boxes[0].shadow_tmax(l, o, d, (q - o).length()), (q - o).length());
    }

    #[test]
    fn a_light_with_something_in_its_box_a_dent_or_few_triangles_gets_none() {
        let ball_lights = |tris: &[[Vec3; 3]], n: u32| {
            let m = mesh_of(tris);
            let lights = lights_of(&m, 0..n);
            find(&m, &lights)
        };
        // A triangle reaching into the ball's box.
        let mut tris = ball(Vec3::new(0.0, 3.0, 0.0), 0.5, 0.0);
        let n = tris.len() as u32;
        tris.push([Vec3::new(0.4, 2.6, 0.4), Vec3::new(2.0, 2.6, 0.4), Vec3::new(2.0, 2.6, 2.0)]);
        let (boxes, of) = ball_lights(&tris, n);
        assert!(boxes.is_empty() && of.iter().all(|&b| b == NONE));
        // The same ball alone has one; dented, none (a vertex in front of its neighbours' planes).
        assert_eq!(ball_lights(&tris[..n as usize], n).0.len(), 1);
        let dented = ball(Vec3::new(0.0, 3.0, 0.0), 0.5, 0.3);
        assert!(ball_lights(&dented, n).0.is_empty());
        // Turned inside out (winding inward), it is convex the other way round.
        let inside_out: Vec<[Vec3; 3]> = tris[..n as usize].iter().map(|t| [t[0], t[2], t[1]]).collect();
        let (boxes, _) = ball_lights(&inside_out, n);
        assert_eq!(boxes.len(), 1);
        assert_eq!(boxes[0].outward, -1.0);
        // A quad light (two triangles): too small to save a walk anything.
        let quad = [
            [Vec3::new(0.0, 2.0, 0.0), Vec3::new(1.0, 2.0, 0.0), Vec3::new(1.0, 2.0, 1.0)],
            [Vec3::new(0.0, 2.0, 0.0), Vec3::new(1.0, 2.0, 1.0), Vec3::new(0.0, 2.0, 1.0)],
        ];
        assert!(ball_lights(&quad, 2).0.is_empty());
    }

    #[test]
    fn groups_join_triangles_that_share_a_vertex_position() {
        // Three faces in a chain with no shared vertex index, and one apart.
        let tris = [
            [Vec3::new(0.0, 0.0, 0.0), Vec3::new(0.0, 0.0, 1.0), Vec3::new(1.0, 1.0, 0.0)],
            [Vec3::new(0.0, 0.0, 0.0), Vec3::new(-1.0, 1.0, 0.0), Vec3::new(0.0, 0.0, 1.0)],
            [Vec3::new(-1.0, 1.0, 0.0), Vec3::new(-1.0, 1.0, 1.0), Vec3::new(-2.0, 0.0, 0.0)],
            [Vec3::new(5.0, 0.0, 0.0), Vec3::new(6.0, 0.0, 0.0), Vec3::new(5.0, 1.0, 0.0)],
        ];
        let m = mesh_of(&tris);
        let tris: Vec<u32> = lights_of(&m, 0..4).iter().map(|l| l.triangle).collect();
        assert_eq!(convex_solid::connected_groups(&m, &tris), vec![vec![0, 1, 2], vec![3]]);
    }
}
