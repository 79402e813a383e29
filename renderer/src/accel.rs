//! Ray-triangle intersection over the whole scene: a compressed-wide BVH (CWBVH, 8-wide, SIMD node
//! tests) built and traversed by `obvhs`, with triangles stored in BVH leaf order and intersected by
//! our own Möller-Trumbore test (which also reports the barycentrics shading needs).

use crate::math::{Vec3, Vec3A};
use crate::mesh::Mesh;
use obvhs::cwbvh::CwBvh;
use obvhs::ray::{Ray as BvhRay, RayHit};

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
}

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
}

impl Accel {
    pub fn build(mesh: &Mesh) -> Self {
        Self::build_with(mesh, AccelKind::Obvhs)
    }

    pub fn build_with(mesh: &Mesh, kind: AccelKind) -> Self {
        if kind == AccelKind::Own {
            let tris = (0..mesh.triangles.len() as u32).map(|i| RtTriangle::new(mesh.vertices(i), i)).collect();
            return Accel { bvh: CwBvh::default(), tris: Vec::new(), own: Some(crate::bvh::Bvh::build(tris)) };
        }
        let prims: Vec<obvhs::triangle::Triangle> = (0..mesh.triangles.len() as u32)
            .map(|i| {
                let [a, b, c] = mesh.vertices(i);
                obvhs::triangle::Triangle { v0: a.into(), v1: b.into(), v2: c.into() }
            })
            .collect();
        if prims.is_empty() {
            return Accel { bvh: CwBvh::default(), tris: Vec::new(), own: None };
        }
        let bvh = obvhs::cwbvh::builder::build_cwbvh_from_tris(
            &prims,
            obvhs::BvhBuildParams::medium_build(),
            &mut std::time::Duration::default(),
        );
        let tris = bvh.primitive_indices.iter().map(|&i| RtTriangle::new(mesh.vertices(i), i)).collect();
        Accel { bvh, tris, own: None }
    }

    /// Closest hit along `o + t d`, `0 < t < tmax`.
    pub fn intersect(&self, o: Vec3, d: Vec3, tmax: f32) -> Option<Hit> {
        if let Some(own) = &self.own {
            return own.intersect(o, d, tmax, false).map(|(t, i, b1, b2)| Hit { t, triangle: own.tris[i].id, b1, b2 });
        }
        if self.tris.is_empty() {
            return None;
        }
        let (oa, da) = (Vec3A::from(o), Vec3A::from(d));
        let ray = BvhRay::new(oa, da, 0.0, tmax);
        let mut hit = RayHit::none();
        let mut best: Option<Hit> = None;
        self.bvh.ray_traverse(ray, &mut hit, |r, id| {
            let tri = &self.tris[id];
            match tri.intersect(oa, da, 0.0, r.tmax) {
                Some((t, b1, b2)) => {
                    best = Some(Hit { t, triangle: tri.id, b1, b2 });
                    t
                }
                None => f32::INFINITY,
            }
        });
        best
    }

    /// True when anything lies on `o + t d` for `0 < t < tmax`.
    pub fn occluded(&self, o: Vec3, d: Vec3, tmax: f32) -> bool {
        if let Some(own) = &self.own {
            return own.intersect(o, d, tmax, true).is_some();
        }
        if self.tris.is_empty() {
            return false;
        }
        let (oa, da) = (Vec3A::from(o), Vec3A::from(d));
        let ray = BvhRay::new(oa, da, 0.0, tmax);
        !self
            .bvh
            .ray_traverse_miss(ray, |_, id| self.tris[id].intersect(oa, da, 0.0, tmax).map_or(f32::INFINITY, |h| h.0))
    }
}
