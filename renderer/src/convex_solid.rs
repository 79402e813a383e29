//! Closed convex objects: for glass ones, where a ray inside one can first hit anything and
//! which shadow rays one certainly blocks; for glass and opaque ones alike, that a ray leaving
//! one cannot meet it again.
//!
//! A ray refracted into a glass sphere, or reflected inside it, starts on the sphere's surface
//! and heads inward. Its closest-hit walk goes down the sphere's subtree and visits every box
//! around the entry point first (their entry distance is 0), only to find nothing there: the exit
//! is across the sphere. On the suite's `glass` scene such rays were 30 % of the closest-hit
//! queries and cost 10.1 node visits each against 2.8 for the others (a counting build, 128×96,
//! 64 spp, one thread).
//!
//! When the object is a **solid** — a connected group of triangles that is
//!
//! * **closed**: every edge (by vertex positions) shared by exactly two of its triangles,
//! * **convex**: every vertex on or behind every triangle's plane (the hull test `clear_box`
//!   uses too),
//! * **isolated**: no other triangle of the scene reaches into its hull (one whose bounds meet
//!   the hull's box must be separated from it by its own plane or by one of the hull's),
//!
//! — three things follow, all exact:
//!
//! * **Inward rays** ([`ConvexSolids::tmin`]): a ray that starts on one of its triangles and
//!   passes through the ball of radius `r` about the centre `c` that lies inside every facet plane
//!   stays inside the hull from its origin to where it leaves the ball (both ends lie in the
//!   convex hull, so the segment does), and inside the hull there is nothing to hit. So the walk
//!   may skip every box the ray leaves before then: its node tests start at that distance
//!   ([`crate::node_ray::NodeRay::tmin`]). A ray heading outward never reaches the ball (the hull
//!   lies behind its origin's facet), so no side test is needed. And the exit is one of the
//!   solid's own triangles, so the walk goes down the solid's own BVH (built over its triangles
//!   alone, [`ConvexSolids::bound`]), not the scene's from its root. The hit is the same
//!   triangle at the same distance as the scene's walk finds; on `glass` an inward ray's walk in
//!   the scene's BVH fell from 10.1 to 5.3 node visits with the bound, and its own BVH saves the
//!   levels above the sphere (0.96 of glass's time). Before any walk, the ray's exit facet is
//!   looked for by walking the solid's surface ([`crate::solid_surface`], [`ConvexSolids::closest`]):
//!   its answer, where it is sure of one, is the walk's hit at about half its instructions.
//! * **Shadow rays** ([`ConvexSolids::blocks`]): a segment with a point inside the inner ball
//!   and its end outside the ball around the solid crosses the closed surface between the two,
//!   so a walk would find a hit; the shadow ray is blocked without one (surfaces are opaque to
//!   shadow rays, glass included, so solids are made only of alpha-OPAQUE triangles). On `glass`
//!   15 % of the shadow rays were inward rays through a sphere, and the spheres' shadows on the
//!   floor add more.
//!
//! * **Leaving rays** ([`ConvexSolids::leaving`]): a ray that starts on one of its facets and
//!   points ahead of that facet's plane cannot meet the solid again (the solid lies on or
//!   behind every facet's plane), so its walk of the scene's BVH skips the subtrees that hold
//!   the solid's triangles alone ([`crate::accel::Accel::intersect_leaving`]). Such a walk
//!   started inside the solid's boxes and tested the triangles around its origin: on `glass`
//!   16 065 such rays cost 1 282 instructions each against 500 for the others (64×48, 16 spp);
//!   with the skip, the render's fell 4.0 % (callgrind `render_tile_counted`, 256.95 M →
//!   246.61 M). The same holds for shadow rays ([`crate::accel::Accel::occluded_leaving`],
//!   through `Scene::visibility_from`, which carries the triangle a shadow ray starts on): few
//!   of glass's start on a solid, many of envlit's (below).
//!
//! Glass solids are looked for among transmissive triangles; **opaque solids** among the other
//! alpha-OPAQUE, non-emissive ones, with a search budget of their own. An opaque solid only
//! skips itself for rays leaving it: no ray goes into it, and the shadow-ray shortcut did not
//! pay for its ball tests (`Scene`'s `find_solids` says why). On `envlit`, whose two spheres
//! are 2 560 of its 2 562 triangles, bounce and shadow rays leave a sphere at nearly every
//! vertex: the render's instructions fell 8.2 % (callgrind `render_tile_counted`, 64×48,
//! 16 spp, 221.19 M → 203.12 M), the image the same bits. Scenes with instances or more than
//! `MAX_SCENE_TRIANGLES` triangles get no solids, and scenes with more than
//! `MAX_CANDIDATE_TRIANGLES` glass or `MAX_OPAQUE_CANDIDATES` opaque triangles none of that kind.

use crate::accel::Hit;
use crate::mesh::Mesh;
use crate::solid_surface::SolidSurface;
use glam::{DVec3, Vec3};
use std::collections::HashMap;

/// No solid (the triangle is not part of one).
pub const NONE: u32 = u32::MAX;

/// How solids are looked for: groups of 16 triangles or more (smaller ones are a leaf or two
/// of a walk, nothing to skip) up to 8192 (the convexity test is triangles × vertices), at most
/// 64 of them (the isolation test passes over the scene once for all), within 6.4·10⁷
/// vertex-plane tests for convexity and the separation of the triangles near a solid.
const SEARCH: Search = Search { sizes: 16..=8192, max_groups: 64, budget: 64_000_000 };

/// Above this many glass triangles no glass solid is looked for: grouping them hashes every
/// vertex, and a scene with this much glass is not made of small convex pieces.
const MAX_CANDIDATE_TRIANGLES: usize = 1_000_000;

/// Above this many opaque triangles no opaque solid is looked for: the search's grouping (a hash
/// of every vertex) took `tessera bench scale --instances 0`'s "load + BVH" from 0.09–0.13 s to
/// 0.15–0.20 s at 100 352 triangles (three runs each) and from 1.41 to 1.95 s at 900 482 (one),
/// for a saving that needs a scene of small convex pieces; at 50 562, 0.08–0.12 s against
/// 0.10–0.12 s.
const MAX_OPAQUE_CANDIDATES: usize = 100_000;

/// Above this many scene triangles no isolated group is looked for (here or in `clear_box`):
/// the isolation test passes over every triangle.
pub(crate) const MAX_SCENE_TRIANGLES: usize = 4_000_000;

/// What a search for isolated convex groups ([`convex_groups`]) takes and may spend.
pub(crate) struct Search {
    /// Group sizes, in triangles.
    pub sizes: std::ops::RangeInclusive<usize>,
    /// At most this many groups are kept, the largest first.
    pub max_groups: usize,
    /// Vertex-plane tests in all: the convexity tests' and whatever the caller's tests spend.
    pub budget: usize,
}

/// A group [`convex_groups`] kept: its triangles, its hull and what the caller made of it.
pub(crate) struct Candidate<T> {
    /// Indices into the searched triangle list.
    pub members: Vec<usize>,
    pub tris: Vec<u32>,
    pub hull: Hull,
    pub value: T,
}

/// The connected groups of `tris` whose size `search` takes, the largest first (a group saves
/// most where its subtree is deep), that are convex and that `make` accepts, while the budget
/// lasts; and the budget left.
pub(crate) fn convex_groups<T>(
    mesh: &Mesh,
    tris: &[u32],
    search: &Search,
    mut make: impl FnMut(&[u32], &Hull) -> Option<T>,
) -> (Vec<Candidate<T>>, usize) {
    let mut groups = connected_groups(mesh, tris);
    groups.retain(|g| search.sizes.contains(&g.len()));
    groups.sort_by_key(|g| std::cmp::Reverse(g.len()));
    let mut budget = search.budget;
    let mut out = Vec::new();
    for members in groups {
        // Triangles × vertices, a closed mesh having about half as many vertices as triangles.
        let cost = members.len() * (members.len() / 2 + 3);
        if out.len() == search.max_groups || cost > budget {
            break;
        }
        budget -= cost;
        let group: Vec<u32> = members.iter().map(|&i| tris[i]).collect();
        let Some(hull) = convex_hull(mesh, &group) else { continue };
        let Some(value) = make(&group, &hull) else { continue };
        out.push(Candidate { members, tris: group, hull, value });
    }
    (out, budget)
}

/// Per candidate, whether every triangle of the scene outside it whose bounds meet its box
/// (`bounds`) is one `foreign(candidate, vertices)` accepts. One pass over the scene's triangles
/// for all candidates.
pub(crate) fn isolated<T>(
    mesh: &Mesh,
    candidates: &[Candidate<T>],
    bounds: impl Fn(&Candidate<T>) -> (Vec3, Vec3),
    mut foreign: impl FnMut(usize, [Vec3; 3]) -> bool,
) -> Vec<bool> {
    let mut owner = vec![NONE; mesh.triangles.len()];
    for (c, cand) in candidates.iter().enumerate() {
        for &t in &cand.tris {
            owner[t as usize] = c as u32;
        }
    }
    let boxes: Vec<(Vec3, Vec3)> = candidates.iter().map(bounds).collect();
    let (all_lo, all_hi) =
        boxes.iter().fold((Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)), |(a, b), (lo, hi)| {
            (a.min(*lo), b.max(*hi))
        });
    let mut ok = vec![true; candidates.len()];
    for (t, &own) in owner.iter().enumerate() {
        let v = mesh.vertices(t as u32);
        let (tlo, thi) = (v[0].min(v[1]).min(v[2]), v[0].max(v[1]).max(v[2]));
        if tlo.cmpgt(all_hi).any() || thi.cmplt(all_lo).any() {
            continue;
        }
        for (k, (lo, hi)) in boxes.iter().enumerate() {
            if own != k as u32 && ok[k] && !(tlo.cmpgt(*hi).any() || thi.cmplt(*lo).any()) {
                ok[k] = foreign(k, v);
            }
        }
    }
    ok
}

/// A convex hull's description: its box, which way its triangles' winding normals point, the
/// rounding allowance of its plane tests, and its distinct vertices.
pub(crate) struct Hull {
    pub lo: Vec3,
    pub hi: Vec3,
    /// +1 when the winding normals point out of the hull, −1 when in.
    pub outward: f64,
    /// How far a vertex may stray from a plane it lies on (the f32 vertices' rounding).
    pub tol: f64,
    pub verts: Vec<Vec3>,
}

/// The hull of triangles `tris` when every vertex lies on or behind every triangle's plane
/// (winding normals outward), or on or in front of every one (inward); None otherwise (or for
/// a degenerate triangle, or non-finite vertices). Tested in f64.
pub(crate) fn convex_hull(mesh: &Mesh, tris: &[u32]) -> Option<Hull> {
    let mut verts: Vec<Vec3> = tris.iter().flat_map(|&t| mesh.vertices(t)).collect();
    verts.sort_by(|a, b| a.to_array().partial_cmp(&b.to_array()).unwrap_or(std::cmp::Ordering::Equal));
    verts.dedup();
    let (lo, hi) = verts
        .iter()
        .fold((Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)), |(lo, hi), v| (lo.min(*v), hi.max(*v)));
    if !(lo.is_finite() && hi.is_finite()) {
        return None;
    }
    let extent = (hi - lo).length();
    let scale = extent + lo.abs().max(hi.abs()).max_element();
    let tol = 1e-6 * scale as f64;
    // The coordinates apart, so the test's loop runs in vector registers.
    let [xs, ys, zs] = [0, 1, 2].map(|k| verts.iter().map(|v| v[k] as f64).collect::<Vec<f64>>());
    let (mut ahead, mut behind) = (0.0f64, 0.0f64);
    for &t in tris {
        let (n, d) = plane(mesh, t)?;
        for ((x, y), z) in xs.iter().zip(&ys).zip(&zs) {
            let h = n.x * x + n.y * y + n.z * z - d;
            ahead = if h > ahead { h } else { ahead };
            behind = if h < behind { h } else { behind };
        }
        if ahead > tol && behind < -tol {
            return None;
        }
    }
    let outward = if ahead <= tol { 1.0 } else { -1.0 };
    Some(Hull { lo, hi, outward, tol, verts })
}

/// Triangle `t`'s unit winding normal and plane offset (n·x = d on the plane), in f64; None when
/// it is degenerate.
fn plane(mesh: &Mesh, t: u32) -> Option<(DVec3, f64)> {
    let [a, b, c] = mesh.vertices(t).map(|v| v.as_dvec3());
    let n = (b - a).cross(c - a).normalize_or_zero();
    (n != DVec3::ZERO).then(|| (n, n.dot(a)))
}

/// The connected groups of triangles `tris` (union-find over shared vertex positions, exact
/// bits, so flat-shaded meshes whose faces share no vertex index still form one group), as
/// indices into `tris`, in a fixed order (each group's first index ascending).
pub(crate) fn connected_groups(mesh: &Mesh, tris: &[u32]) -> Vec<Vec<usize>> {
    let mut parent: Vec<usize> = (0..tris.len()).collect();
    fn root(parent: &mut [usize], mut i: usize) -> usize {
        while parent[i] != i {
            parent[i] = parent[parent[i]];
            i = parent[i];
        }
        i
    }
    let mut first_at: HashMap<[u32; 3], usize> = HashMap::new();
    for (i, &t) in tris.iter().enumerate() {
        for v in mesh.vertices(t) {
            let other = *first_at.entry(key(v)).or_insert(i);
            let (a, b) = (root(&mut parent, i), root(&mut parent, other));
            parent[a] = b;
        }
    }
    let mut by_root: HashMap<usize, Vec<usize>> = HashMap::new();
    for i in 0..tris.len() {
        let r = root(&mut parent, i);
        by_root.entry(r).or_default().push(i);
    }
    let mut out: Vec<Vec<usize>> = by_root.into_values().collect();
    // A fixed order (the hash map's is not), so numbering is a function of the scene.
    out.sort_by_key(|g| g[0]);
    out
}

pub(crate) fn key(v: Vec3) -> [u32; 3] {
    v.to_array().map(f32::to_bits)
}

/// Whether every edge of `tris` (by vertex positions) belongs to exactly two of them.
pub(crate) fn closed(mesh: &Mesh, tris: &[u32]) -> bool {
    let mut edges: HashMap<([u32; 3], [u32; 3]), u32> = HashMap::with_capacity(tris.len() * 3 / 2);
    for &t in tris {
        let v = mesh.vertices(t).map(key);
        for (a, b) in [(v[0], v[1]), (v[1], v[2]), (v[2], v[0])] {
            if a == b {
                return false;
            }
            *edges.entry(if a < b { (a, b) } else { (b, a) }).or_insert(0) += 1;
        }
    }
    edges.values().all(|&n| n == 2)
}

/// One solid: the ball inside it and the ball around it.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Solid {
    center: DVec3,
    /// The ball's radius, a little under the least distance from the centre to a facet plane.
    radius: f64,
    /// The same in f32 for the occlusion test: the inner radius squared (rounded down) and the
    /// outer radius squared (a little over the farthest vertex's distance, rounded up).
    pub(crate) center32: Vec3,
    pub(crate) inner_sq: f32,
    pub(crate) outer_sq: f32,
    /// +1 when the solid's winding normals point out of it, −1 when in ([`Hull::outward`]).
    outward: f64,
}

/// How far ahead of a facet's plane, in cosine, a direction must point for [`ConvexSolids::leaving`]
/// to call the ray leaving (0.06° from grazing): grazing rays take the full walk.
const LEAVING_MARGIN: f64 = 1e-3;

/// At most this many solids are tried as occluders by a shadow ray ([`ConvexSolids::blocks`]):
/// each costs a ray–ball test, and a shadow ray that no solid blocks pays them all.
const MAX_OCCLUDERS: usize = 8;

/// The scene's solids and which triangle belongs to which.
#[derive(Default)]
pub struct ConvexSolids {
    /// Per triangle its solid's index or [`NONE`]; empty when the scene has no solid.
    of_triangle: Vec<u32>,
    solids: Vec<Solid>,
    /// Each solid's own BVH: an inward ray's exit is among its triangles.
    pub(crate) accels: Vec<crate::accel::Accel>,
    /// Each solid's surface, walked to an inward ray's exit before its BVH is
    /// ([`crate::solid_surface`]; None where it could not be built).
    surfaces: Vec<Option<SolidSurface>>,
    /// Inward rays skip the surface walk and walk the BVH alone (tests compare the two).
    bvh_only: bool,
    /// How many of `solids` (the first ones) are glass; `accels` and `surfaces` hold theirs.
    glass: usize,
}

impl ConvexSolids {
    /// The solids among the triangles `glass` admits (by material index): the largest groups
    /// (`SEARCH`) that are closed, convex and isolated. With `opaque` too, the same search among
    /// the triangles it admits (and `glass` does not) finds the opaque solids: those only skip
    /// themselves when a ray leaves them ([`Self::leaving`]), since no ray goes into an opaque
    /// solid and their occlusion test did not pay (`Scene`'s `find_solids`). Each kind is
    /// searched with a budget of its own, so opaque groups cannot crowd out the glass ones.
    pub fn find(mesh: &Mesh, glass: impl Fn(u32) -> bool, opaque: impl Fn(u32) -> bool) -> Self {
        let none = ConvexSolids::default();
        if !mesh.instances.is_empty() || mesh.triangles.len() > MAX_SCENE_TRIANGLES {
            return none;
        }
        let material = |t: &u32| mesh.triangles[*t as usize].material;
        let all = 0..mesh.triangles.len() as u32;
        let glass_tris: Vec<u32> = all.clone().filter(|t| glass(material(t))).collect();
        let opaque_tris: Vec<u32> = all.filter(|t| !glass(material(t)) && opaque(material(t))).collect();
        let mut candidates = Vec::new();
        let mut budget = 0;
        for (tris, is_glass) in [(glass_tris, true), (opaque_tris, false)] {
            let most = if is_glass { MAX_CANDIDATE_TRIANGLES } else { MAX_OPAQUE_CANDIDATES };
            if tris.len() > most || tris.is_empty() {
                continue;
            }
            // Each candidate's value: its solid, and whether it is glass.
            let (found, left) = convex_groups(mesh, &tris, &SEARCH, |g, hull| {
                if closed(mesh, g) {
                    inner_ball(mesh, g, hull).map(|solid| (solid, is_glass))
                } else {
                    None
                }
            });
            candidates.extend(found);
            budget += left;
        }
        if candidates.is_empty() {
            return none;
        }
        // Isolation: a triangle near a solid must be separated from its hull, within the budget.
        let facets: Vec<Vec<(DVec3, f64)>> =
            candidates.iter().map(|c| c.tris.iter().filter_map(|&t| plane(mesh, t)).collect()).collect();
        let bounds = |c: &Candidate<(Solid, bool)>| {
            let grow = Vec3::splat(4.0 * c.hull.tol as f32);
            (c.hull.lo - grow, c.hull.hi + grow)
        };
        let isolated = isolated(mesh, &candidates, bounds, |k, v| {
            let cost = candidates[k].hull.verts.len() + 3 * facets[k].len();
            if cost > budget {
                return false;
            }
            budget -= cost;
            apart(v.map(|p| p.as_dvec3()), &candidates[k].hull, &facets[k])
        });
        let mut out = none;
        // The glass solids first (each kind largest first), so that a glass solid's index is
        // also its BVH's and surface's, and the occlusion test's first solids are glass.
        for (c, ok) in candidates.into_iter().zip(isolated) {
            if !ok {
                continue;
            }
            if out.of_triangle.is_empty() {
                out.of_triangle = vec![NONE; mesh.triangles.len()];
            }
            for &t in &c.tris {
                out.of_triangle[t as usize] = out.solids.len() as u32;
            }
            let (solid, glass) = c.value;
            if glass {
                let own = crate::accel::Accel::build_subset(mesh, c.tris);
                out.surfaces.push(SolidSurface::new(&own, solid.center32));
                out.accels.push(own);
                out.glass += 1;
            }
            out.solids.push(solid);
        }
        out
    }

    /// Whether the segment from `o` to `o + tmax·d` certainly meets a solid's surface: it passes
    /// through the solid's inner ball (its point nearest the centre, on the segment, lies inside
    /// it) and ends outside the ball around the solid. Between the two it crosses the closed
    /// surface, so a walk would find a hit: a shadow ray may stop here. (Which triangle does
    /// not matter to a shadow ray; solids are opaque to them, as every surface is.) Tries the
    /// `MAX_OCCLUDERS` largest solids.
    #[inline]
    pub fn blocks(&self, o: Vec3, d: Vec3, tmax: f32) -> bool {
        !tmax.is_nan()
            && tmax > 0.0
            && self.solids[..self.glass].iter().take(MAX_OCCLUDERS).any(|s| s.blocks(o, d, tmax))
    }

    /// [`Self::blocks`] for eight rays at once: the bits of the rays among `lanes` (ray k from
    /// `o[k]` along `d[k]` to `tmax[k]`) that a glass solid certainly blocks. The same
    /// arithmetic as [`Solid::blocks`], lane for lane in the same order and without fused
    /// multiply-adds, so the same bits answer (`blocks_lanes_answer_as_blocks`). A shadow ray
    /// through a scene of glass balls took some 45 instructions a ball one ray at a time
    /// (callgrind, `glass`: 6.3 M of 189 M in 70 280 calls); eight at a time the balls' loads,
    /// divisions and compares are shared.
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    #[inline]
    pub fn blocks_lanes(&self, o: &[Vec3; 8], d: &[Vec3; 8], tmax: &[f32; 8], lanes: u32) -> u32 {
        use crate::lanes::{F8, M8, V8};
        let (o, d, tmax) = (V8::from_lanes(o), V8::from_lanes(d), F8::from_array(*tmax));
        let zero = F8::zero();
        let dd = d.dot(d);
        // `!tmax.is_nan() && tmax > 0.0` and `dd > 0.0` (ordered compares: false on NaN).
        let live = tmax.gt(zero) & dd.gt(zero);
        let unbounded = tmax.eq(F8::splat(f32::INFINITY));
        let end = o + d.scale(tmax);
        let mut blocked = M8::from_bits(0);
        for s in self.solids[..self.glass].iter().take(MAX_OCCLUDERS) {
            let c = V8::splat(s.center32);
            let oc = c - o;
            let t = oc.dot(d) / dd;
            let near = oc - d.scale(t);
            let far = end - c;
            let inside = t.gt(zero) & t.lt(tmax) & near.dot(near).lt(F8::splat(s.inner_sq));
            blocked = blocked | (inside & (unbounded | far.dot(far).gt(F8::splat(s.outer_sq))));
        }
        (live & blocked).bits() & lanes & 0xff
    }

    /// How many solids the scene has, glass and opaque.
    pub fn len(&self) -> usize {
        self.solids.len()
    }

    /// How many of them are glass (the rest only skip themselves when a ray leaves them).
    pub fn glass_len(&self) -> usize {
        self.glass
    }

    pub fn is_empty(&self) -> bool {
        self.solids.is_empty()
    }

    /// For a ray from `o` along `d` that starts on triangle `from`: where its closest-hit walk
    /// may begin its node tests (where the ray leaves the ball inside `from`'s solid), and that
    /// solid, when the ray passes through that ball; None otherwise (not a solid's triangle, an
    /// outward ray, or a grazing one).
    #[inline]
    pub(crate) fn bound(&self, from: u32, o: Vec3, d: Vec3) -> Option<(f32, usize)> {
        match self.of_triangle.get(from as usize) {
            // An opaque solid's rays never head inward (a reflection leaves its surface), so
            // none is worth the ball's exit.
            Some(&s) if (s as usize) < self.glass => {
                let t = self.solids[s as usize].exit(o, d);
                (t > 0.0).then_some((t, s as usize))
            }
            _ => None,
        }
    }

    /// The solid a ray from triangle `from` along `d` leaves, when `from` is a facet of one and
    /// `d` points out of it: ahead of the facet's plane by more than [`LEAVING_MARGIN`] of a
    /// right angle's cosine, which covers the f32 normal's rounding many times over (the test is
    /// in f64 on the f32 vertices). Such a ray cannot meet its solid again: the solid lies on or
    /// behind every facet's plane (within the hull test's allowance), the ray's points ahead of
    /// this one's. So its walk may skip the solid's subtrees ([`crate::accel::Accel::intersect_leaving`]).
    #[inline(always)]
    pub(crate) fn leaving(&self, mesh: &Mesh, from: u32, d: Vec3) -> Option<u32> {
        // Most rays start on no solid (a floor, a wall): answered here, without a call.
        let s = *self.of_triangle.get(from as usize)?;
        if s == NONE {
            return None;
        }
        self.leaving_solid(mesh, from, d, s)
    }

    /// [`Self::leaving`] for a ray from facet `from` of solid `s`.
    #[inline(never)]
    fn leaving_solid(&self, mesh: &Mesh, from: u32, d: Vec3, s: u32) -> Option<u32> {
        let [a, b, c] = mesh.vertices(from).map(|v| v.as_dvec3());
        let n = (b - a).cross(c - a) * self.solids[s as usize].outward;
        let (d, nd) = (d.as_dvec3(), n.dot(d.as_dvec3()));
        // n·d > margin·|n|·|d|, squared (no square root).
        (nd > 0.0 && nd * nd > LEAVING_MARGIN * LEAVING_MARGIN * n.length_squared() * d.length_squared()).then_some(s)
    }

    /// The solid triangle `t` is a facet of, if any.
    pub fn solid_of(&self, t: u32) -> Option<u32> {
        self.of_triangle.get(t as usize).copied().filter(|&s| s != NONE)
    }

    /// Marks the nodes of `accel` (the scene's BVH) by the solid their subtree belongs to, for
    /// [`Self::leaving`]'s walks ([`crate::accel::Accel::mark_solids`]; unmarked without solids).
    /// Again whenever the BVH is rebuilt: a new one starts unmarked.
    pub(crate) fn mark_nodes(&self, accel: &mut crate::accel::Accel) {
        accel.mark_solids(&self.of_triangle);
    }

    /// [`Self::bound`]'s distance, 0 where there is none.
    pub fn tmin(&self, from: u32, o: Vec3, d: Vec3) -> f32 {
        self.bound(from, o, d).map_or(0.0, |(t, _)| t)
    }

    /// The closest hit of a ray that [`Self::bound`] bounded by `tmin` inside solid `s`: its exit,
    /// found by walking the solid's surface where the walk is sure of it, else by walking the
    /// solid's own BVH from `tmin` on. Both give the hit the scene's walk gives.
    #[inline]
    pub(crate) fn closest(&self, s: usize, o: Vec3, d: Vec3, tmin: f32) -> Option<Hit> {
        let own = &self.accels[s];
        if let (false, Some(surface)) = (self.bvh_only, &self.surfaces[s]) {
            if let Some(hit) = surface.exit(o, d, o + d * tmin) {
                return Some(hit);
            }
        }
        own.intersect_from(o, d, tmin, f32::INFINITY)
    }

    /// [`Self::closest`]'s surface walk alone (None where it is not sure, or off): for tests.
    pub fn surface_exit(&self, from: u32, o: Vec3, d: Vec3) -> Option<Hit> {
        let (tmin, s) = self.bound(from, o, d)?;
        self.surfaces[s].as_ref()?.exit(o, d, o + d * tmin)
    }

    /// Turns the surface walk on or off (on by default; tests compare).
    pub fn set_surface_walk(&mut self, on: bool) {
        self.bvh_only = !on;
    }
}

impl Solid {
    /// See [`ConvexSolids::blocks`]. In f32 with margins: the inner ball was shrunk by a part in
    /// 10⁴ and the outer grown by one, far above these few operations' rounding.
    #[inline]
    fn blocks(&self, o: Vec3, d: Vec3, tmax: f32) -> bool {
        let oc = self.center32 - o;
        let dd = d.length_squared();
        if !(dd > 0.0) {
            return false;
        }
        // The segment's point nearest the centre.
        let t = oc.dot(d) / dd;
        if !(t > 0.0 && t < tmax) {
            return false;
        }
        let near = oc - d * t;
        if !(near.length_squared() < self.inner_sq) {
            return false;
        }
        // The far end outside the outer ball (an infinite ray always leaves it).
        tmax == f32::INFINITY || (o + d * tmax - self.center32).length_squared() > self.outer_sq
    }

    /// The far root of |o + t d − c|² = r², rounded down, when positive; else 0. In f64: the
    /// quadratic's cancellation for grazing rays would otherwise cost more than the ball's margin.
    #[inline]
    fn exit(&self, o: Vec3, d: Vec3) -> f32 {
        let (o, d) = (o.as_dvec3(), d.as_dvec3());
        let oc = o - self.center;
        let (a, b, c) = (d.length_squared(), d.dot(oc), oc.length_squared() - self.radius * self.radius);
        // From outside the ball, heading away from its centre: both roots are ≤ 0, and the
        // rounded ones too (`disc` ≤ b·b rounded, whose square root is b), so the answer is 0
        // without the square root and the division, whose latency a leaving ray waited for.
        if b >= 0.0 && c >= 0.0 {
            return 0.0;
        }
        far_root(a, b, c)
    }
}

/// The far root of a·t² + 2b·t + c = 0 (a ray's distances to a sphere: a = |d|², b = d·(o − c),
/// c = |o − c|² − r²), rounded down to f32, when positive; else 0.
#[inline(always)]
fn far_root(a: f64, b: f64, c: f64) -> f32 {
    let disc = b * b - a * c;
    if !(disc > 0.0 && a > 0.0) {
        return 0.0;
    }
    let t = (disc.sqrt() - b) / a;
    // f32 rounding may round up: step one ulp down (the ball's margin covers the rest).
    if t > 0.0 && t.is_finite() {
        (t as f32).next_down().max(0.0)
    } else {
        0.0
    }
}

/// The ball about the mean of the hull's vertices, of radius a little under the least distance
/// from there to a facet plane; None when that centre is not well inside.
pub(crate) fn inner_ball(mesh: &Mesh, tris: &[u32], hull: &Hull) -> Option<Solid> {
    let center = hull.verts.iter().fold(DVec3::ZERO, |s, v| s + v.as_dvec3()) / hull.verts.len().max(1) as f64;
    let mut least = f64::INFINITY;
    for &t in tris {
        let (n, d) = plane(mesh, t)?;
        // The centre's depth behind the plane, outward-facing.
        least = least.min(hull.outward * (d - n.dot(center)));
    }
    // Smaller by a part in 10⁴ and by the plane tests' allowance: a ray inside this ball is
    // well inside the hull.
    let radius = least * (1.0 - 1e-4) - 8.0 * hull.tol;
    let farthest = hull.verts.iter().map(|v| (v.as_dvec3() - center).length()).fold(0.0, f64::max);
    let outer = farthest * (1.0 + 1e-4) + 8.0 * hull.tol;
    let center32 = center.as_vec3();
    // The f32 centre is off by half an ulp of its coordinates: the radii allow for it.
    let slack = center32.as_dvec3().distance(center);
    let (inner, outer) = (radius * (1.0 - 1e-4) - slack, outer * (1.0 + 1e-4) + slack);
    (radius.is_finite() && inner > 0.0 && outer.is_finite()).then_some(Solid {
        center,
        radius,
        center32,
        inner_sq: ((inner * inner) as f32).next_down(),
        outer_sq: ((outer * outer) as f32).next_up(),
        outward: hull.outward,
    })
}

/// Whether triangle `v` cannot reach into `hull`'s interior: the hull lies on one side of the
/// triangle's plane, or the triangle in front of one of the hull's `facets` (within the
/// allowance).
fn apart(v: [DVec3; 3], hull: &Hull, facets: &[(DVec3, f64)]) -> bool {
    let n = (v[1] - v[0]).cross(v[2] - v[0]).normalize_or_zero();
    let own = n != DVec3::ZERO && {
        let (mut ahead, mut behind) = (0.0f64, 0.0f64);
        for p in &hull.verts {
            let h = n.dot(p.as_dvec3() - v[0]);
            (ahead, behind) = (ahead.max(h), behind.min(h));
        }
        ahead <= hull.tol || behind >= -hull.tol
    };
    own || facets.iter().any(|&(n, d)| v.iter().all(|p| hull.outward * (n.dot(*p) - d) >= -hull.tol))
}

#[cfg(test)]
mod tests {
    use super::*;

    use crate::testing::mesh_of;

    /// An icosphere of 320 faces (outward winding), each face its own vertex triple.
    fn ball(c: Vec3, r: f32) -> Vec<[Vec3; 3]> {
        crate::testing::icosphere_faces(c, r, 2)
    }

    fn solids(tris: &[[Vec3; 3]]) -> ConvexSolids {
        ConvexSolids::find(&mesh_of(tris), |_| true, |_| false)
    }

    /// The nearest hit of every triangle (Möller and Trumbore 1997), for the tests' exits.
    fn nearest(m: &Mesh, o: Vec3, d: Vec3) -> Option<f32> {
        (0..m.triangles.len() as u32)
            .filter_map(|t| {
                let [a, b, c] = m.vertices(t);
                let (e1, e2) = (b - a, c - a);
                let p = d.cross(e2);
                let det = e1.dot(p);
                if det.abs() < 1e-12 {
                    return None;
                }
                let s = o - a;
                let u = s.dot(p) / det;
                let q = s.cross(e1);
                let v = d.dot(q) / det;
                let t = e2.dot(q) / det;
                (u >= 0.0 && v >= 0.0 && u + v <= 1.0 && t > 0.0).then_some(t)
            })
            .min_by(f32::total_cmp)
    }

    /// The ball's exit with the shortcut is the full root's, bit for bit: origins inside, on and
    /// outside the ball (and far away), directions towards, away from and across it, tiny and
    /// huge ones, zero and NaN. Fails when the shortcut takes a ray heading in, or one from inside.
    #[test]
    fn the_balls_exit_shortcut_answers_as_the_full_root() {
        use crate::sampler::hash_unit as u;
        let c = Vec3::new(0.3, -0.2, 1.0);
        let s = solids(&ball(c, 0.5));
        let solid = &s.solids[0];
        let r = solid.radius as f32;
        let mut ahead = 0;
        for i in 0..20_000u64 {
            let dir = |k: u64| Vec3::new(u(k) - 0.5, u(k + 1) - 0.5, u(k + 2) - 0.5);
            let dist = [0.0, 0.5, 0.999, 1.0, 1.001, 2.0, 1e4][(i % 7) as usize] * r;
            let o = c + dir(8 * i).normalize_or_zero() * dist;
            let scale = [1.0, 1e-20, 1e20, 0.0, f32::NAN][(i / 7 % 5) as usize];
            let d = dir(8 * i + 3) * scale;
            let (od, dd) = (o.as_dvec3(), d.as_dvec3());
            let oc = od - solid.center;
            let c2 = oc.length_squared() - solid.radius * solid.radius;
            let (got, want) = (solid.exit(o, d), far_root(dd.length_squared(), dd.dot(oc), c2));
            assert_eq!(got.to_bits(), want.to_bits(), "o {o:?} d {d:?}");
            ahead += usize::from(want > 0.0);
        }
        assert!(ahead > 5_000, "only {ahead} rays have a root ahead");
    }

    #[test]
    fn a_closed_convex_ball_is_a_solid_and_inward_rays_start_at_its_inner_ball() {
        let c = Vec3::new(0.0, 0.5, 0.0);
        let mut tris = ball(c, 0.5);
        let n = tris.len();
        // A floor touching the ball's lowest point, and a wall across the room.
        tris.push([Vec3::new(-5.0, 0.0, -5.0), Vec3::new(0.0, 0.0, 5.0), Vec3::new(5.0, 0.0, -5.0)]);
        tris.push([Vec3::new(-5.0, 0.0, -3.0), Vec3::new(5.0, 0.0, -3.0), Vec3::new(0.0, 5.0, -3.0)]);
        let m = mesh_of(&tris);
        let s = ConvexSolids::find(&m, |_| true, |_| false);
        assert_eq!(s.len(), 1, "the ball is a solid; floor and wall are not closed groups");
        // From the centre of a face, inward: the bound lies short of the exit, close to it.
        for f in [0u32, 17, 101, 250] {
            let [a, b, cc] = m.vertices(f);
            let o = (a + b + cc) / 3.0;
            let d = (c - o).normalize();
            let t = s.tmin(f, o, d);
            let exit = nearest(&m, o + d * 1e-4, d).expect("the ray leaves the ball") + 1e-4;
            assert!(t > 0.9 * exit && t < exit, "face {f}: bound {t}, exit {exit}");
            // Outward, and from the floor: no bound.
            assert_eq!(s.tmin(f, o, -d), 0.0);
            assert_eq!(s.tmin(n as u32, o, d), 0.0);
        }
    }

    #[test]
    fn open_dented_or_crowded_groups_are_not_solids() {
        let c = Vec3::new(0.0, 2.0, 0.0);
        let whole = ball(c, 0.5);
        assert_eq!(solids(&whole).len(), 1);
        // A face missing: not closed.
        assert!(solids(&whole[1..]).is_empty());
        // A vertex pushed in: not convex.
        let first = whole[0][0];
        let dented: Vec<[Vec3; 3]> =
            whole.iter().map(|t| t.map(|p| if p == first { c + (p - c) * 0.7 } else { p })).collect();
        assert!(solids(&dented).is_empty());
        // Something inside: not isolated.
        let mut crowded = whole.clone();
        crowded.push([c, c + Vec3::X * 0.1, c + Vec3::Y * 0.1]);
        assert!(solids(&crowded).is_empty());
        // A triangle cutting through the hull: not isolated.
        let mut cut = whole.clone();
        cut.push([c + Vec3::new(-2.0, 0.1, -2.0), c + Vec3::new(2.0, 0.1, -2.0), c + Vec3::new(0.0, 0.1, 2.0)]);
        assert!(solids(&cut).is_empty());
        // Touching from outside (a tangent plane at the top): still a solid.
        let top = whole.iter().flatten().map(|p| p.y).fold(f32::MIN, f32::max);
        let mut touched = whole.clone();
        touched.push([Vec3::new(-2.0, top, -2.0), Vec3::new(0.0, top, 2.0), Vec3::new(2.0, top, -2.0)]);
        assert_eq!(solids(&touched).len(), 1);
        // Not glass: nothing looked for.
        assert!(ConvexSolids::find(&mesh_of(&whole), |_| false, |_| false).is_empty());
    }

    /// `blocks_lanes` answers each lane as `blocks` answers its ray, bit for bit, and only the
    /// lanes asked: rays through one ball, two, none, ending inside a ball or past it, unbounded,
    /// with zero, negative and NaN lengths, a zero direction, and more balls than are tried.
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    #[test]
    fn blocks_lanes_answer_as_blocks() {
        use crate::sampler::hash_unit as u;
        // Ten balls in a row (more than MAX_OCCLUDERS), of radii 0.3 to 0.48.
        let mut tris = Vec::new();
        let centers: Vec<Vec3> = (0..10).map(|i| Vec3::new(i as f32 * 1.5, 0.0, 0.0)).collect();
        for (i, &c) in centers.iter().enumerate() {
            tris.extend(ball(c, 0.3 + 0.02 * i as f32));
        }
        let s = solids(&tris);
        assert_eq!(s.glass_len(), 10);
        let (mut blocked, mut seen) = (0, 0);
        let mut r = 7u64 << 32;
        let mut next = || {
            r += 1;
            u(r)
        };
        for batch in 0..4000u32 {
            let (mut o, mut d, mut tmax) = ([Vec3::ZERO; 8], [Vec3::ZERO; 8], [0f32; 8]);
            for k in 0..8 {
                // From around the row towards a point near some ball's centre, or anywhere.
                let from = Vec3::new(next() * 16.0 - 1.5, next() * 4.0 - 2.0, next() * 4.0 - 2.0);
                let target =
                    centers[(next() * 10.0) as usize % 10] + Vec3::new(next() - 0.5, next() - 0.5, next() - 0.5) * 0.8;
                let to = if next() < 0.8 { target } else { Vec3::new(next(), next(), next()) * 20.0 - 10.0 };
                let scale = 0.25 + next() * 2.0;
                o[k] = from;
                d[k] = (to - from) * scale;
                // To the target's point (t = 1/scale), halfway there, or anywhere up to 3.
                tmax[k] = match (batch as usize + k) % 9 {
                    0 => f32::INFINITY,
                    1 => f32::NAN,
                    2 => 0.0,
                    3 => -1.0,
                    4 => 1.0 / scale,
                    5 => 0.5 / scale,
                    _ => next() * 3.0,
                };
                if (batch as usize + k).is_multiple_of(97) {
                    d[k] = Vec3::ZERO;
                }
                // Along the row, unbounded: the far end's other coordinates are 0·∞ (NaN).
                if (batch as usize + k).is_multiple_of(11) {
                    (o[k].y, o[k].z, d[k], tmax[k]) = (next() * 0.2, next() * 0.2, Vec3::X, f32::INFINITY);
                }
            }
            let lanes = if batch.is_multiple_of(5) { u32::from(next().to_bits() as u8) } else { 0xff };
            let got = s.blocks_lanes(&o, &d, &tmax, lanes);
            let want = (0..8).filter(|&k| lanes & (1 << k) != 0 && s.blocks(o[k], d[k], tmax[k]));
            let want = want.fold(0u32, |b, k| b | 1 << k);
            assert_eq!(got, want, "batch {batch}: {o:?} {d:?} {tmax:?}");
            blocked += want.count_ones();
            seen += lanes.count_ones();
        }
        // Both answers occur often.
        assert!(blocked > seen / 10 && blocked < seen * 9 / 10, "{blocked} of {seen}");
    }
}
