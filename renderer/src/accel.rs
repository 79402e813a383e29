//! Ray-triangle intersection over the whole scene: a compressed-wide BVH (CWBVH, 8-wide, SIMD node
//! tests) built and traversed by `obvhs`, with triangles stored in BVH leaf order and intersected by
//! our own Möller-Trumbore test (which also reports the barycentrics shading needs).
//!
//! Instancing makes it two-level: each prototype (a mesh several nodes place) gets its own BVH over
//! its object-space triangles, built once; the top level holds the world-space triangles and one
//! box per instance. A ray reaching an instance's box is carried into object space by the
//! instance's inverse transform, direction unnormalised, so the hit distance t is the same number
//! in both spaces and the closest-hit bound carries over unchanged. Memory follows unique geometry.

use crate::math::{Vec3, Vec3A};
use crate::mesh::Mesh;
use obvhs::cwbvh::CwBvh;
use obvhs::ray::Ray as BvhRay;

/// Precomputed triangle for intersection: a vertex and two edges (Möller & Trumbore 1997).
#[derive(Clone, Copy, Debug)]
pub struct RtTriangle {
    pub v0: Vec3A,
    pub e1: Vec3A,
    pub e2: Vec3A,
    /// Index into `Mesh::triangles`.
    pub id: u32,
}

impl RtTriangle {
    pub fn new(v: [Vec3; 3], id: u32) -> Self {
        let v0 = Vec3A::from(v[0]);
        RtTriangle { v0, e1: Vec3A::from(v[1]) - v0, e2: Vec3A::from(v[2]) - v0, id }
    }

    /// Returns (t, b1, b2) for a hit with `tmin < t < tmax`.
    #[inline(always)]
    pub fn intersect(&self, o: Vec3A, d: Vec3A, tmin: f32, tmax: f32) -> Option<(f32, f32, f32)> {
        let pvec = d.cross(self.e2);
        let det = self.e1.dot(pvec);
        if det == 0.0 || !det.is_finite() {
            return None;
        }
        let inv = 1.0 / det;
        let tvec = o - self.v0;
        let b1 = tvec.dot(pvec) * inv;
        if !(0.0..=1.0).contains(&b1) {
            return None;
        }
        let qvec = tvec.cross(self.e1);
        let b2 = d.dot(qvec) * inv;
        if b2 < 0.0 || b1 + b2 > 1.0 {
            return None;
        }
        let t = self.e2.dot(qvec) * inv;
        (t > tmin && t < tmax).then_some((t, b1, b2))
    }
}

#[derive(Clone, Copy, Debug)]
pub struct Hit {
    pub t: f32,
    pub triangle: u32,
    pub b1: f32,
    pub b2: f32,
    /// The instance hit (index into `Mesh::instances`), or [`NO_INSTANCE`] for world geometry.
    pub instance: u32,
}

/// `Hit::instance` of a world-space triangle.
pub const NO_INSTANCE: u32 = u32::MAX;

/// The top level of a scene with instances.
/// (Its BVH is `Accel::bvh`.)
struct TopLevel {
    /// Top-level leaves in `Accel::bvh.primitive_indices` order.
    prims: Vec<TopPrim>,
    /// One BVH per prototype (`Mesh::prototypes`), in object space.
    blas: Vec<Accel>,
}

#[derive(Clone, Copy)]
enum TopPrim {
    Triangle(RtTriangle),
    Instance { index: u32, prototype: u32, to_object: glam::Affine3A },
}

/// Closest-hit traversal of `bvh`: obvhs' traversal loop (`obvhs::traverse!`) with the 8-wide
/// AVX2 node test of [`crate::cwbvh_node`]. `prim(ray, i)` intersects primitive slot `i` and returns
/// its hit distance (∞ for a miss); a closer hit shortens the ray for the rest of the traversal.
#[inline(always)]
fn traverse_closest(bvh: &CwBvh, mut ray: BvhRay, mut prim: impl FnMut(&BvhRay, usize) -> f32) {
    use glam::UVec2;
    let mut state = bvh.new_traversal(ray.direction);
    let mut node;
    obvhs::traverse!(bvh, node, state, crate::cwbvh_node::intersect(node, &ray, state.oct_inv4), {
        let t = prim(&ray, state.primitive_id as usize);
        if t < ray.tmax {
            ray.tmax = t;
        }
    });
}

/// True when `prim(i)` reports a hit for some primitive slot `i` (traversal stops at the first).
#[inline(always)]
fn traverse_any(bvh: &CwBvh, ray: BvhRay, mut prim: impl FnMut(usize) -> bool) -> bool {
    use glam::UVec2;
    let mut state = bvh.new_traversal(ray.direction);
    let mut node;
    let mut hit = false;
    'outer: {
        obvhs::traverse!(bvh, node, state, crate::cwbvh_node::intersect(node, &ray, state.oct_inv4), {
            if prim(state.primitive_id as usize) {
                hit = true;
                break 'outer;
            }
        });
    }
    hit
}

/// obvhs's build quality for `n` triangles: "medium" (the best trace speed per build second at
/// ordinary sizes) up to LARGE_BUILD triangles, "fast" above, where the medium build's longer
/// PLOC search and reinsertion passes cost more seconds than the renders they speed up
/// (`tessera bench scale`, figures in ARCHITECTURE.md).
fn build_params(n: usize) -> obvhs::BvhBuildParams {
    if n > LARGE_BUILD {
        obvhs::BvhBuildParams::fast_build()
    } else {
        obvhs::BvhBuildParams::medium_build()
    }
}

/// See [`build_params`].
pub const LARGE_BUILD: usize = 4_000_000;

/// Which BVH answers ray queries. Both give the same hits; `Own` is kept to measure `Obvhs` against.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum AccelKind {
    #[default]
    Obvhs,
    Own,
}

crate::named_choices!(AccelKind, "accelerator", { "obvhs" => Self::Obvhs, "own" => Self::Own });

pub struct Accel {
    bvh: CwBvh,
    /// Triangles in `bvh.primitive_indices` order, so a leaf's primitives are contiguous in memory.
    tris: Vec<RtTriangle>,
    own: Option<crate::bvh::Bvh>,
    /// Set when the scene has instances (then `bvh`, `tris` and `own` are empty).
    top: Option<Box<TopLevel>>,
}

impl Accel {
    pub fn build(mesh: &Mesh) -> Self {
        Self::build_with(mesh, AccelKind::Obvhs)
    }

    pub fn build_with(mesh: &Mesh, kind: AccelKind) -> Self {
        if !mesh.instances.is_empty() {
            if kind == AccelKind::Own {
                tracing::warn!("the own BVH has no instancing: using obvhs for this instanced scene");
            }
            return Self::build_two_level(mesh);
        }
        Self::build_triangles(mesh, (0..mesh.triangles.len() as u32).collect(), kind)
    }

    /// A one-level BVH over the triangles `ids` of `mesh` (as they are stored).
    fn build_triangles(mesh: &Mesh, ids: Vec<u32>, kind: AccelKind) -> Self {
        if kind == AccelKind::Own {
            let tris = ids.iter().map(|&i| RtTriangle::new(mesh.vertices(i), i)).collect();
            return Accel {
                bvh: CwBvh::default(),
                tris: Vec::new(),
                own: Some(crate::bvh::Bvh::build(tris)),
                top: None,
            };
        }
        let prims: Vec<obvhs::triangle::Triangle> = ids
            .iter()
            .map(|&i| {
                let [a, b, c] = mesh.vertices(i);
                obvhs::triangle::Triangle { v0: a.into(), v1: b.into(), v2: c.into() }
            })
            .collect();
        if prims.is_empty() {
            return Accel { bvh: CwBvh::default(), tris: Vec::new(), own: None, top: None };
        }
        let bvh = obvhs::cwbvh::builder::build_cwbvh_from_tris(
            &prims,
            build_params(prims.len()),
            &mut std::time::Duration::default(),
        );
        let tris = bvh
            .primitive_indices
            .iter()
            .map(|&k| RtTriangle::new(mesh.vertices(ids[k as usize]), ids[k as usize]))
            .collect();
        Accel { bvh, tris, own: None, top: None }
    }

    /// After an animation moved instances or world vertices: a new top level over the prototype
    /// BVHs already built (they do not change), or a whole new BVH for a scene without instances.
    pub fn rebuild_top(&mut self, mesh: &Mesh) {
        match self.top.take() {
            Some(top) => *self = Self::top_level(mesh, top.blas),
            None => *self = Self::build(mesh),
        }
    }

    /// Prototype BVHs, then a top level over the world triangles and the instances' world boxes.
    fn build_two_level(mesh: &Mesh) -> Self {
        let blas: Vec<Accel> = mesh
            .prototypes
            .iter()
            .map(|r| Self::build_triangles(mesh, r.clone().collect(), AccelKind::Obvhs))
            .collect();
        Self::top_level(mesh, blas)
    }

    fn top_level(mesh: &Mesh, blas: Vec<Accel>) -> Self {
        let world: Vec<u32> = (0..mesh.triangles.len() as u32)
            .filter(|&i| mesh.triangles[i as usize].flags & crate::mesh::flags::OBJECT_SPACE == 0)
            .collect();
        let mut boxes: Vec<obvhs::aabb::Aabb> = Vec::with_capacity(world.len() + mesh.instances.len());
        let mut prims: Vec<TopPrim> = Vec::with_capacity(boxes.capacity());
        for &i in &world {
            let [a, b, c] = mesh.vertices(i);
            let (a, b, c) = (Vec3A::from(a), Vec3A::from(b), Vec3A::from(c));
            boxes.push(obvhs::aabb::Aabb { min: a.min(b).min(c), max: a.max(b).max(c) });
            prims.push(TopPrim::Triangle(RtTriangle::new(mesh.vertices(i), i)));
        }
        let proto_boxes = mesh.prototype_bounds();
        for (k, inst) in mesh.instances.iter().enumerate() {
            if !inst.visible {
                continue;
            }
            let Some(&bx) = proto_boxes.get(inst.prototype as usize) else { continue };
            let (lo, hi) = Mesh::instance_box(inst, bx);
            boxes.push(obvhs::aabb::Aabb { min: lo.into(), max: hi.into() });
            prims.push(TopPrim::Instance {
                index: k as u32,
                prototype: inst.prototype,
                to_object: glam::Affine3A::from_mat4(inst.to_object),
            });
        }
        if boxes.is_empty() {
            return Accel {
                bvh: CwBvh::default(),
                tris: Vec::new(),
                own: None,
                top: Some(Box::new(TopLevel { prims, blas })),
            };
        }
        let bvh =
            obvhs::cwbvh::builder::build_cwbvh(&boxes, obvhs::BvhBuildParams::medium_build(), &mut Default::default());
        // Leaf order, so a leaf's primitives sit together.
        let prims = bvh.primitive_indices.iter().map(|&i| prims[i as usize]).collect();
        Accel { bvh, tris: Vec::new(), own: None, top: Some(Box::new(TopLevel { prims, blas })) }
    }

    /// Closest hit along `o + t d`, `0 < t < tmax`.
    pub fn intersect(&self, o: Vec3, d: Vec3, tmax: f32) -> Option<Hit> {
        if let Some(top) = &self.top {
            return self.intersect_two_level(top, Vec3A::from(o), Vec3A::from(d), tmax);
        }
        if let Some(own) = &self.own {
            return own.intersect(o, d, tmax, false).map(|(t, i, b1, b2)| Hit {
                t,
                triangle: own.tris[i].id,
                b1,
                b2,
                instance: NO_INSTANCE,
            });
        }
        self.intersect_object(Vec3A::from(o), Vec3A::from(d), tmax)
    }

    fn intersect_two_level(&self, top: &TopLevel, oa: Vec3A, da: Vec3A, tmax: f32) -> Option<Hit> {
        if top.prims.is_empty() {
            return None;
        }
        let ray = BvhRay::new(oa, da, 0.0, tmax);
        let mut best: Option<Hit> = None;
        traverse_closest(&self.bvh, ray, |r, id| match &top.prims[id] {
            TopPrim::Triangle(tri) => match tri.intersect(oa, da, 0.0, r.tmax) {
                Some((t, b1, b2)) => {
                    best = Some(Hit { t, triangle: tri.id, b1, b2, instance: NO_INSTANCE });
                    t
                }
                None => f32::INFINITY,
            },
            TopPrim::Instance { index, prototype, to_object } => {
                let (oo, dd) = (to_object.transform_point3a(oa), to_object.transform_vector3a(da));
                match top.blas[*prototype as usize].intersect_object(oo, dd, r.tmax) {
                    Some(mut h) => {
                        h.instance = *index;
                        best = Some(h);
                        h.t
                    }
                    None => f32::INFINITY,
                }
            }
        });
        best
    }

    /// Closest hit in a one-level BVH (the scene's, or a prototype's with the ray already in object
    /// space, direction unnormalised).
    fn intersect_object(&self, oa: Vec3A, da: Vec3A, tmax: f32) -> Option<Hit> {
        if self.tris.is_empty() || !da.is_finite() || !oa.is_finite() {
            return None;
        }
        let ray = BvhRay::new(oa, da, 0.0, tmax);
        let mut best: Option<Hit> = None;
        traverse_closest(&self.bvh, ray, |r, id| {
            let tri = &self.tris[id];
            match tri.intersect(oa, da, 0.0, r.tmax) {
                Some((t, b1, b2)) => {
                    best = Some(Hit { t, triangle: tri.id, b1, b2, instance: NO_INSTANCE });
                    t
                }
                None => f32::INFINITY,
            }
        });
        best
    }

    /// True when anything lies on `o + t d` for `0 < t < tmax`.
    pub fn occluded(&self, o: Vec3, d: Vec3, tmax: f32) -> bool {
        if let Some(top) = &self.top {
            if top.prims.is_empty() {
                return false;
            }
            let (oa, da) = (Vec3A::from(o), Vec3A::from(d));
            let ray = BvhRay::new(oa, da, 0.0, tmax);
            return traverse_any(&self.bvh, ray, |id| match &top.prims[id] {
                TopPrim::Triangle(tri) => tri.intersect(oa, da, 0.0, tmax).is_some(),
                TopPrim::Instance { prototype, to_object, .. } => {
                    let blas = &top.blas[*prototype as usize];
                    let (oo, dd) = (to_object.transform_point3a(oa), to_object.transform_vector3a(da));
                    if blas.tris.is_empty() || !oo.is_finite() || !dd.is_finite() {
                        return false;
                    }
                    let r = BvhRay::new(oo, dd, 0.0, tmax);
                    traverse_any(&blas.bvh, r, |j| blas.tris[j].intersect(oo, dd, 0.0, tmax).is_some())
                }
            });
        }
        if let Some(own) = &self.own {
            return own.intersect(o, d, tmax, true).is_some();
        }
        if self.tris.is_empty() {
            return false;
        }
        let (oa, da) = (Vec3A::from(o), Vec3A::from(d));
        let ray = BvhRay::new(oa, da, 0.0, tmax);
        traverse_any(&self.bvh, ray, |id| self.tris[id].intersect(oa, da, 0.0, tmax).is_some())
    }
}
