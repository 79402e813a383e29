//! The surface of a closed convex solid (`convex_solid`), walked facet to facet to where a ray from
//! inside leaves it: the closest hit of an inward ray without a BVH walk.
//!
//! A line meets a convex solid's surface at most twice, so a ray that starts inside leaves
//! through exactly one facet, and no other facet lies on the ray before that exit. The walk finds
//! that facet the way point location walks a triangulation (Devillers, Pion and Teillaud 2002,
//! "Walking in a triangulation"): starting from a facet near the exit, it tests on which side of
//! each of the facet's edges the ray's line passes (Plücker coordinates: the sign of
//! `d · ((a − o) × (b − o))` for the edge from a to b, positive on the inner side when the
//! corners run counter-clockwise seen from outside) and steps across an edge the line passes
//! outside of, until the line passes inside all three.
//!
//! What a walk answers must be what the BVH walk answers, bit for bit (`renderer/tests/
//! convex_solid.rs`): so the facet it finds is tested with the BVH's own triangle test, on the
//! BVH's corners of the triangle bit for bit (kept in the facet's record), and the answer is
//! taken only where no rounding could have let another facet report a hit first: the exit point
//! well inside its facet (every barycentric coordinate at least [`MARGIN`]) and the ray not
//! grazing it (the cosine with its normal at least [`MIN_COS`]). Elsewhere, or where the walk
//! does not settle within [`MAX_STEPS`], the caller walks the solid's BVH as before. The solid's
//! convexity is only tested to 10⁻⁶ of its size (`convex_solid::convex_hull`); the margins are
//! far above that on any facet that is not itself that small.

use crate::accel::{Accel, Hit, NO_INSTANCE};
use crate::convex_solid::key;
use crate::triangle::{RtTriangle, WatertightRay};
use glam::{Vec3, Vec3A};

/// A walk gives up after this many steps (a walk between two nearby facets usually takes one or
/// two; a walk that circles would not end).
const MAX_STEPS: usize = 16;
/// The least barycentric coordinate of an exit point the walk's answer is taken at.
const MARGIN: f32 = 1e-3;
/// The least cosine between the ray and the exit facet's outward normal the answer is taken at.
const MIN_COS: f32 = 0.02;

/// One facet as the walk and its confirmation read it, in one cache line: its corners in the
/// BVH's own order and bits (so the confirmation's triangle test is the BVH's, bit for bit), the
/// mesh triangle it is, which way its corners wind seen from outside, and its neighbours. Kept
/// as separate arrays (edges in Plücker coordinates, normals, neighbours, and the corners read
/// from the BVH's eight-triangle blocks) an exit touched about nine lines: 9.0 first-level cache
/// misses an exit on the glass scene, 2.1 in this record (callgrind's cache model, 32 KiB L1d,
/// 64×48, 16 spp). Each step works its edges out again from the corners, and the confirmation
/// its unit normal: 11.43 M instructions for the scene's 30 053 exits, against 11.01 M.
#[derive(Clone, Copy, Debug, Default)]
#[repr(C, align(64))]
struct Facet {
    corners: [Vec3; 3],
    /// 1 where the corners run counter-clockwise seen from outside, −1 where clockwise: the
    /// sign that makes an edge's Plücker side positive on the facet's inner side.
    outward: f32,
    /// The facet across the edge from corner i to corner i + 1 (mod 3).
    across: [u32; 3],
    /// The mesh triangle (`RtTriangle::id`).
    id: u32,
}

impl Facet {
    /// Which side of this facet's edges the line from `o` along `d` passes: for the edge from
    /// corner a to corner b, d · ((a − o) × (b − o)), its Plücker product, times the winding
    /// sign, so positive on the facet's inner side.
    #[inline(always)]
    fn sides(&self, o: Vec3, d: Vec3) -> [f32; 3] {
        let [a, b, c] = self.corners;
        let (a, b, c) = (Vec3A::from(a - o), Vec3A::from(b - o), Vec3A::from(c - o));
        let d = Vec3A::from(d) * self.outward;
        [d.dot(a.cross(b)), d.dot(b.cross(c)), d.dot(c.cross(a))]
    }
}

/// One solid's facets for the walk, indexed by their slots in the solid's own BVH (so the facet
/// a walk ends on is the slot the BVH's triangle test reads), and where walks start.
#[derive(Clone, Debug, Default)]
pub struct SolidSurface {
    facets: Vec<Facet>,
    /// The start of a walk per direction from `center`: a cube map of `n` × `n` cells a face,
    /// each holding the facet its centre's direction leaves through (`SolidSurface::new`).
    center: Vec3,
    n: usize,
    start: Vec<u32>,
}

impl SolidSurface {
    /// The surface of the closed solid whose BVH is `own` (a BVH of that solid's triangles
    /// alone: every edge, by vertex positions, shared by exactly two of them), around `center` (a
    /// point inside). None where its triangles do not pair up so.
    pub fn new(own: &Accel, center: Vec3) -> Option<SolidSurface> {
        let blocks = own.triangle_blocks();
        let mut s = SolidSurface { center, ..SolidSurface::default() };
        for slot in 0..blocks.len() {
            let tri = blocks.get(slot);
            let [a, b, c] = tri.v.map(Vec3::from);
            let n = (b - a).cross(c - a);
            let outward = if n.dot((a + b + c) / 3.0 - center) >= 0.0 { 1.0 } else { -1.0 };
            s.facets.push(Facet { corners: [a, b, c], outward, across: [u32::MAX; 3], id: tri.id });
        }
        // Each edge's two facets: the edges sorted by their corners' exact bits (lower first),
        // so an edge's two sides are neighbours in the list.
        let mut sides: Vec<_> = s
            .facets
            .iter()
            .enumerate()
            .flat_map(|(f, facet)| {
                let c = facet.corners;
                (0..3).map(move |i| {
                    let (a, b) = (key(c[i]), key(c[(i + 1) % 3]));
                    (a.min(b), a.max(b), f as u32, i)
                })
            })
            .collect();
        sides.sort_unstable();
        for pair in sides.chunks(2) {
            let &[(a, b, f, i), (a2, b2, g, j)] = pair else { return None };
            if (a, b) != (a2, b2) {
                return None;
            }
            s.facets[f as usize].across[i] = g;
            s.facets[g as usize].across[j] = f;
        }
        if s.facets.iter().flat_map(|f| f.across).any(|g| g == u32::MAX) {
            return None;
        }
        // About four cells a facet (6n² ≥ 4 facets; 4 bytes a cell, 22 KB for the glass scene's
        // 1 280-facet spheres). With each cell starting on the facet its centre's direction
        // leaves through (below), 73 % of that scene's walks end where they start, 25 % take one
        // step and 2 % more; at two facets a cell with the centroid fill alone, 33 %, 44 % and
        // 22 % (a counting build, 128×96, 64 spp). Twelve cells a facet timed the same (0.99,
        // 0.97–1.02, nine pairs).
        s.n = ((s.facets.len() as f64 / 1.5).sqrt().ceil() as usize).max(1);
        s.start = vec![u32::MAX; 6 * s.n * s.n];
        for f in 0..s.facets.len() {
            let c = s.facets[f].corners;
            let cell = s.cell((c[0] + c[1] + c[2]) / 3.0 - center);
            if s.start[cell] == u32::MAX {
                s.start[cell] = f as u32;
            }
        }
        // An empty cell takes a filled neighbour's facet on its face, sweep after sweep; any left
        // (a face no centroid points to) starts at facet 0, a walk that may take longer.
        let n = s.n;
        for _ in 0..2 * n {
            let mut changed = false;
            for at in 0..s.start.len() {
                let (face, i, j) = (at / (n * n), at / n % n, at % n);
                if s.start[at] != u32::MAX {
                    continue;
                }
                let near = [(i.wrapping_sub(1), j), (i + 1, j), (i, j.wrapping_sub(1)), (i, j + 1)];
                let filled =
                    near.iter().filter(|&&(a, b)| a < n && b < n).map(|&(a, b)| s.start[(face * n + a) * n + b]);
                if let Some(f) = filled.into_iter().find(|&f| f != u32::MAX) {
                    s.start[at] = f;
                    changed = true;
                }
            }
            if !changed {
                break;
            }
        }
        for f in s.start.iter_mut().filter(|f| **f == u32::MAX) {
            *f = 0;
        }
        // Each cell then starts at the facet its centre's direction leaves through, found by
        // walking there from the filled start: a query walk then starts on its exit facet or a
        // neighbour.
        for at in 0..s.start.len() {
            if let Some(f) = s.facet_towards(s.cell_centre(at), s.start[at] as usize) {
                s.start[at] = f as u32;
            }
        }
        Some(s)
    }

    /// The direction from `center` through the middle of cube-map cell `at` ([`Self::cell`]'s
    /// inverse).
    fn cell_centre(&self, at: usize) -> Vec3 {
        let n = self.n;
        let (face, i, j) = (at / (n * n), at / n % n, at % n);
        let mid = |k: usize| (k as f32 + 0.5) * 2.0 / n as f32 - 1.0;
        let (u, v, s) = (mid(i), mid(j), if face % 2 == 0 { 1.0 } else { -1.0 });
        match face / 2 {
            0 => Vec3::new(s, u, v),
            1 => Vec3::new(u, s, v),
            _ => Vec3::new(u, v, s),
        }
    }

    /// The facet the ray from `center` along `q` leaves through, walked to from facet `from`: one
    /// the line passes inside or on all three edges of (on an edge or a corner either facet
    /// there is as good a start). None where the walk does not settle within a few times a cube
    /// face's width in steps (`from` is a neighbouring cell's facet; a visibility walk can circle
    /// on a triangulation that is not Delaunay, and a bad mesh must not make loading quadratic).
    fn facet_towards(&self, q: Vec3, from: usize) -> Option<usize> {
        self.walk(from, 4 * self.n + MAX_STEPS, self.center, q, |least| least >= 0.0)
    }

    /// The walk both [`Self::exit`] and the start cells take: from facet `f`, across the edge
    /// the line from `o` along `d` passes farthest outside of, until `settled(least side)`;
    /// None where it steps back where it came from (the line passes by their shared edge) or
    /// has not settled within `steps`.
    #[inline(always)]
    fn walk(&self, mut f: usize, steps: usize, o: Vec3, d: Vec3, settled: impl Fn(f32) -> bool) -> Option<usize> {
        let mut came_from = usize::MAX;
        for _ in 0..steps {
            let facet = self.facets.get(f)?;
            let side = facet.sides(o, d);
            // The edge the line passes farthest outside of, if any.
            let (k, least) =
                side.iter().enumerate().fold((0, f32::INFINITY), |(k, m), (i, &s)| if s < m { (i, s) } else { (k, m) });
            if settled(least) {
                return Some(f);
            }
            let next = facet.across[k] as usize;
            if next == came_from {
                return None;
            }
            (came_from, f) = (f, next);
        }
        None
    }

    /// The cube-map cell of direction `q` (any length; the zero vector has cell 0).
    #[inline(always)]
    fn cell(&self, q: Vec3) -> usize {
        let a = q.abs();
        let (face, u, v, m) = if a.x >= a.y && a.x >= a.z {
            (usize::from(q.x < 0.0), q.y, q.z, a.x)
        } else if a.y >= a.z {
            (2 + usize::from(q.y < 0.0), q.x, q.z, a.y)
        } else {
            (4 + usize::from(q.z < 0.0), q.x, q.y, a.z)
        };
        if !(m > 0.0) {
            return 0;
        }
        let n = self.n;
        let scale = 0.5 * n as f32 / m;
        // Through u32: the same integer as `as usize` (both saturate, n is small), cheaper.
        let index = |x: f32| (((x + m) * scale) as u32 as usize).min(n - 1);
        (face * n + index(u)) * n + index(v)
    }

    /// The closest hit of the ray from `o` along `d`, which starts inside the solid and passes
    /// the point `inside` (inside the solid, nearer the exit than `o`: the inner ball's exit), as
    /// the solid's own BVH would answer it; None where the walk cannot be sure (then walk that
    /// BVH).
    #[inline]
    pub fn exit(&self, o: Vec3, d: Vec3, inside: Vec3) -> Option<Hit> {
        let start = *self.start.get(self.cell(inside - self.center))? as usize;
        let f = self.walk(start, MAX_STEPS, o, d, |least| least > 0.0)?;
        self.confirm(f, o, d)
    }

    /// Facet `f`'s hit by the BVH's own test, where the margins make it the only one.
    #[inline(always)]
    fn confirm(&self, f: usize, o: Vec3, d: Vec3) -> Option<Hit> {
        let facet = self.facets.get(f)?;
        let [a, b, c] = facet.corners;
        // cos ≥ MIN_COS·|d| with the outward unit normal, squared (a NaN fails it; a facet of no
        // area has no normal and fails it too).
        let n = ((b - a).cross(c - a) * facet.outward).normalize_or_zero();
        let cos = n.dot(d);
        if !(cos > 0.0 && cos * cos >= MIN_COS * MIN_COS * d.length_squared()) {
            return None;
        }
        let ray = WatertightRay::new(Vec3A::from(o), Vec3A::from(d));
        // The slot's triangle, its corners the BVH's, by the one-at-a-time test, the eight-lane
        // walk's reference: the same numbers (`triangle.rs`' tests).
        let tri = RtTriangle::new(facet.corners, facet.id);
        let (t, b1, b2) = tri.intersect(&ray, f32::INFINITY)?;
        let b0 = 1.0 - b1 - b2;
        (b0.min(b1).min(b2) >= MARGIN).then_some(Hit { t, triangle: tri.id, b1, b2, instance: NO_INSTANCE })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sampler::hash_unit as u;
    use crate::testing::{icosphere_faces, mesh_of};

    /// An icosphere of `20·4^level` faces around `c`; `inward` reverses the winding (the walk
    /// orients facets itself).
    fn ball(c: Vec3, r: f32, level: u32, inward: bool) -> Vec<[Vec3; 3]> {
        let faces = icosphere_faces(c, r, level);
        faces.into_iter().map(|[a, b, e]| if inward { [a, e, b] } else { [a, b, e] }).collect()
    }

    /// The BVH of `tris` and their surface about `c`.
    fn surface(tris: &[[Vec3; 3]], c: Vec3) -> (Accel, SolidSurface) {
        let own = Accel::build_subset(&mesh_of(tris), (0..tris.len() as u32).collect());
        let s = SolidSurface::new(&own, c).expect("a closed solid");
        (own, s)
    }

    fn key(h: Option<Hit>) -> Option<(u32, u32, u32, u32)> {
        h.map(|h| (h.triangle, h.t.to_bits(), h.b1.to_bits(), h.b2.to_bits()))
    }

    /// From points inside, in every direction: every answer is the BVH's, and nearly every ray
    /// gets one, whichever way the facets are wound.
    #[test]
    fn exits_are_the_bvhs_hits() {
        for (level, inward) in [(1, false), (3, false), (3, true)] {
            let c = Vec3::new(0.3, -1.2, 2.0);
            let tris = ball(c, 0.7, level, inward);
            let (own, s) = surface(&tris, c);
            // The walk starts where the ray leaves the ball inside the facets' planes, as
            // `ConvexSolids::closest` starts it.
            let r_in = tris.iter().map(|t| (t[1] - t[0]).cross(t[2] - t[0]).normalize().dot(t[0] - c).abs());
            let r_in = r_in.fold(f32::INFINITY, f32::min) * 0.999;
            let (n, mut answered) = (4000u64, 0);
            for i in 0..n {
                let o = c + Vec3::new(u(6 * i) - 0.5, u(6 * i + 1) - 0.5, u(6 * i + 2) - 0.5) * 0.6;
                assert!((o - c).length() < 0.52);
                let (z, phi) = (2.0 * u(6 * i + 3) - 1.0, std::f32::consts::TAU * u(6 * i + 4));
                let r = (1.0 - z * z).max(0.0).sqrt();
                let d = Vec3::new(r * phi.cos(), r * phi.sin(), z);
                let bvh = own.intersect(o, d, f32::INFINITY);
                assert!(bvh.is_some(), "level {level}: a ray from inside leaves");
                let oc = o - c;
                let b = oc.dot(d);
                let leave = -b + (b * b - oc.length_squared() + r_in * r_in).sqrt();
                if let Some(hit) = s.exit(o, d, o + d * leave) {
                    assert_eq!(key(Some(hit)), key(bvh), "level {level} inward {inward}, ray {i}");
                    answered += 1;
                }
            }
            assert!(answered * 100 > n * 97, "level {level}: the walk answered {answered} of {n}");
        }
    }

    /// Every cube-map cell starts its walks on the facet its centre's direction leaves through
    /// (where the line passes inside or on all three of that facet's edges: the icosphere's
    /// symmetry puts some centres exactly on an edge): a walk from a point in that direction
    /// has nowhere to go. With the centroid fill alone (a facet whose centroid lies in the cell
    /// or a neighbour's, two facets a cell), 67 % of the glass scene's walks took a step or more
    /// (a counting build, 128×96, 64 spp).
    #[test]
    fn every_cell_starts_on_the_facet_its_centre_leaves_through() {
        for level in [1, 3, 4] {
            let c = Vec3::new(0.3, -1.2, 2.0);
            let tris = ball(c, 0.7, level, false);
            let (_, s) = surface(&tris, c);
            let (mut exact, cells) = (0, s.start.len());
            for at in 0..cells {
                let q = s.cell_centre(at);
                assert_eq!(s.cell(q), at, "level {level}: cell {at}'s centre lies in it");
                let f = s.start[at] as usize;
                exact += usize::from(s.facets[f].sides(c, q).iter().all(|&side| side >= 0.0));
            }
            assert_eq!(exact, cells, "level {level}");
        }
    }

    /// A ray through a shared edge or a vertex is left to the BVH (no facet is sure there), as
    /// is one that leaves a facet at a grazing angle; neither is answered wrongly.
    #[test]
    fn edges_vertices_and_grazing_exits_are_left_to_the_bvh() {
        let c = Vec3::ZERO;
        let tris = ball(c, 1.0, 2, false);
        let (own, s) = surface(&tris, c);
        for t in &tris {
            for (a, b) in [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])] {
                for target in [a, (a + b) * 0.5] {
                    let d = target.normalize();
                    assert!(s.exit(c, d, c).is_none(), "towards {target}");
                }
            }
        }
        // From just inside one facet, almost along it.
        let t = tris[7];
        let n = (t[1] - t[0]).cross(t[2] - t[0]).normalize();
        let centroid = (t[0] + t[1] + t[2]) / 3.0;
        let along = (t[1] - t[0]).normalize();
        let o = centroid - n * 1e-3 - along * 0.05;
        let d = (along + n * 0.01).normalize();
        assert!(s.exit(o, d, o).is_none(), "a grazing exit");
        assert!(own.intersect(o, d, f32::INFINITY).is_some());
    }

    /// A facet's record is one cache line, what the walk's layout is for (above `Facet`).
    #[test]
    fn a_facet_is_one_cache_line() {
        assert_eq!(std::mem::size_of::<Facet>(), 64);
        assert_eq!(std::mem::align_of::<Facet>(), 64);
    }

    /// An open group has no surface to walk.
    #[test]
    fn an_open_group_has_no_surface() {
        let mut tris = ball(Vec3::ZERO, 1.0, 1, false);
        tris.pop();
        let own = Accel::build_subset(&mesh_of(&tris), (0..tris.len() as u32).collect());
        assert!(SolidSurface::new(&own, Vec3::ZERO).is_none());
    }
}
