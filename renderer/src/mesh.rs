//! The scene's triangles: world-space triangle soup for geometry placed once (flattened at load
//! time, so the accelerator and the lights index one array), plus prototypes — meshes several
//! nodes place — stored once in object space and put in the world by their [`Instance`]s.

use crate::math::{Mat4, Vec2, Vec3, Vec4};
use crate::texture::TexCoords;
use glam::Mat3;

/// Per-triangle flags: which vertex attributes the source primitive had.
pub mod flags {
    pub const NORMALS: u8 = 1;
    pub const TANGENTS: u8 = 2;
    pub const UVS: u8 = 4;
    /// The primitive has TEXCOORD_1 (in `Mesh::uvs1`).
    pub const UVS1: u8 = 8;
    /// The primitive has COLOR_0 (in `Mesh::colors`).
    pub const COLORS: u8 = 16;
    /// The triangle belongs to a prototype: its vertices are in object space.
    pub const OBJECT_SPACE: u8 = 32;
}

/// The largest coordinate (in either sign, world or object space) a vertex may have. The renderer's
/// arithmetic multiplies up to four coordinates together (a triangle's area is the length of a
/// cross product of edges, the squared length of a product of two): at 10⁹ that is 10³⁶, inside
/// f32's 3.4·10³⁸, while a vertex at 3·10³⁸ (finite, but past every such product) made the BVH
/// builder index out of bounds. 10⁹ m is a million kilometres: no scene a camera frames needs
/// more, and beyond it an f32 position is coarser than 64 m anyway.
pub const MAX_COORDINATE: f32 = 1e9;

/// True when `p` is finite and within [`MAX_COORDINATE`] on every axis.
pub fn is_usable_position(p: Vec3) -> bool {
    p.is_finite() && p.abs().max_element() <= MAX_COORDINATE
}

/// One placement of a prototype (`Mesh::prototypes[prototype]`).
#[derive(Clone, Copy, Debug)]
pub struct Instance {
    pub prototype: u32,
    pub to_world: Mat4,
    pub to_object: Mat4,
    /// Inverse transpose of `to_world`'s linear part: object normals to world normals.
    pub normal_matrix: Mat3,
    /// An upper bound on how much `to_world` stretches a distance (its linear part's Frobenius
    /// norm): what an object-space [`SurfacePoint::plane_error`] becomes in world space.
    pub stretch: f32,
    /// False while an animation gives it a singular transform (scaled to nothing): not traced.
    pub visible: bool,
}

impl Instance {
    /// None when `to_world` is singular or not finite (nothing of it can be rendered).
    pub fn new(prototype: u32, to_world: Mat4) -> Option<Self> {
        let linear = Mat3::from_mat4(to_world);
        let det = linear.determinant();
        if !(det != 0.0 && det.is_finite() && to_world.is_finite()) {
            return None;
        }
        let to_object = to_world.inverse();
        let normal_matrix = linear.inverse().transpose();
        let stretch =
            (linear.x_axis.length_squared() + linear.y_axis.length_squared() + linear.z_axis.length_squared()).sqrt();
        (to_object.is_finite() && normal_matrix.is_finite()).then_some(Instance {
            prototype,
            to_world,
            to_object,
            normal_matrix,
            stretch,
            visible: true,
        })
    }
}

#[derive(Clone, Copy, Debug)]
pub struct Triangle {
    pub v: [u32; 3],
    pub material: u32,
    pub flags: u8,
}

#[derive(Default)]
pub struct Mesh {
    pub positions: Vec<Vec3>,
    /// NORMAL, TANGENT (xyz, w the bitangent sign: glTF convention) and TEXCOORD_0: each empty
    /// until some primitive has it, then parallel to `positions` (read only where the triangle's
    /// flags say its primitive had it).
    pub normals: Vec<Vec3>,
    pub tangents: Vec<Vec4>,
    pub uvs: Vec<Vec2>,
    /// TEXCOORD_1, allocated only once some primitive has it (then parallel to `positions`).
    pub uvs1: Vec<Vec2>,
    /// COLOR_0 (linear RGBA), allocated only once some primitive has it (then parallel to `positions`).
    pub colors: Vec<Vec4>,
    pub triangles: Vec<Triangle>,
    /// Prototype triangle ranges (their triangles flagged OBJECT_SPACE) and their placements.
    pub prototypes: Vec<std::ops::Range<u32>>,
    pub instances: Vec<Instance>,
}

/// Geometry at a ray hit, before the material is applied.
#[derive(Clone, Copy, Debug)]
pub struct SurfacePoint {
    pub p: Vec3,
    /// Geometric normal from the winding order (counter-clockwise = front).
    pub ng: Vec3,
    /// Interpolated vertex normal (= ng when the primitive has none).
    pub ns: Vec3,
    /// Interpolated tangent (w = handedness), if the primitive has tangents.
    pub tangent: Option<Vec4>,
    /// TEXCOORD_0 and TEXCOORD_1.
    pub uv: TexCoords,
    /// COLOR_0 (white where the primitive has none): multiplies the base color.
    pub color: Vec4,
    pub triangle: u32,
    /// How far off the triangle's plane a ray leaving `p` must start so that the triangle test
    /// cannot find this triangle again ([`plane_error`]); the spawned ray's origin is lifted by
    /// this much before the ulp offset ([`crate::scene::Scene::spawn_origin`]).
    pub plane_error: f32,
}

/// Multiples of f32's unit roundoff (2⁻²⁴) of a triangle's extent by which a ray leaving it starts
/// off its plane. The triangle test's distance to the triangle's own plane, from an origin on it,
/// carries a rounding error that grows with the vertices' distances from the origin, that is with
/// the triangle's size, whatever the point's coordinates (pbrt-v4 §6.8.4 bounds it by a few tens of
/// ulps of the largest such distance, δt). The origin offset's 16 ulps of the point's coordinates
/// fall short of it wherever those are small next to the triangle: on the Veach scene's plate,
/// 8 units wide and straddling y = 0, 0.4 % of the rays leaving it hit it again
/// (`renderer/tests/self_intersection.rs`: 862 of about 2·10⁵ rays without the lift, 9 with 1
/// unit roundoff, none from 2; as an instance 100 times its size, 1 290, 2 and none; 32 leaves a
/// margin of 16 for slivers and grazing rays, and is still only 2·10⁻⁶ of the triangle's size).
pub const PLANE_ERROR_ULPS: f32 = 32.0;

/// [`SurfacePoint::plane_error`] of a triangle with edges `e1` and `e2` from its first vertex:
/// [`PLANE_ERROR_ULPS`] unit roundoffs of the largest coordinate extent, |e1| + |e2|.
#[inline(always)]
pub fn plane_error(e1: Vec3, e2: Vec3) -> f32 {
    PLANE_ERROR_ULPS * (f32::EPSILON / 2.0) * (e1.abs() + e2.abs()).max_element()
}

impl Mesh {
    #[inline]
    pub fn vertices(&self, tri: u32) -> [Vec3; 3] {
        let t = &self.triangles[tri as usize];
        [self.positions[t.v[0] as usize], self.positions[t.v[1] as usize], self.positions[t.v[2] as usize]]
    }

    pub fn area(&self, tri: u32) -> f32 {
        let [a, b, c] = self.vertices(tri);
        0.5 * (b - a).cross(c - a).length()
    }

    /// Position, geometric normal and UVs at barycentrics (b1, b2): what light sampling needs.
    #[inline]
    pub fn position_normal_uv(&self, tri: u32, b1: f32, b2: f32) -> (Vec3, Vec3, TexCoords) {
        let t = &self.triangles[tri as usize];
        let [i0, i1, i2] = [t.v[0] as usize, t.v[1] as usize, t.v[2] as usize];
        let (p0, p1, p2) = (self.positions[i0], self.positions[i1], self.positions[i2]);
        let ng = (p1 - p0).cross(p2 - p0).normalize_or_zero();
        let uv = self.tex_coords(t, b1, b2);
        (p0 + (p1 - p0) * b1 + (p2 - p0) * b2, if ng == Vec3::ZERO { Vec3::Z } else { ng }, uv)
    }

    /// The texture coordinates [`Self::surface_point`] gives at barycentrics (b1, b2) of `tri`
    /// (the eight-lane kernel resolves a textured material's BSDF with them).
    #[inline]
    pub fn tex_coords_at(&self, tri: u32, b1: f32, b2: f32) -> TexCoords {
        self.tex_coords(&self.triangles[tri as usize], b1, b2)
    }

    /// The interpolated tangent (xyz, handedness w) [`Self::surface_point`] gives at barycentrics
    /// (b1, b2) of `tri`: None for a triangle without tangents.
    #[inline]
    pub fn tangent_at(&self, tri: u32, b1: f32, b2: f32) -> Option<Vec4> {
        self.tangent(&self.triangles[tri as usize], b1, b2)
    }

    #[inline(always)]
    fn tangent(&self, t: &Triangle, b1: f32, b2: f32) -> Option<Vec4> {
        let b0 = 1.0 - b1 - b2;
        let [i0, i1, i2] = [t.v[0] as usize, t.v[1] as usize, t.v[2] as usize];
        (t.flags & flags::TANGENTS != 0)
            .then(|| self.tangents[i0] * b0 + self.tangents[i1] * b1 + self.tangents[i2] * b2)
    }

    /// The interpolated vertex colour [`Self::surface_point`] gives at barycentrics (b1, b2) of
    /// `tri`: white for a triangle without colours.
    #[inline]
    pub fn color_at(&self, tri: u32, b1: f32, b2: f32) -> Vec4 {
        self.color(&self.triangles[tri as usize], b1, b2)
    }

    #[inline(always)]
    fn color(&self, t: &Triangle, b1: f32, b2: f32) -> Vec4 {
        let b0 = 1.0 - b1 - b2;
        let [i0, i1, i2] = [t.v[0] as usize, t.v[1] as usize, t.v[2] as usize];
        if t.flags & flags::COLORS != 0 {
            self.colors[i0] * b0 + self.colors[i1] * b1 + self.colors[i2] * b2
        } else {
            Vec4::ONE
        }
    }

    /// Both texture coordinate sets of triangle `t` at barycentrics (b1, b2).
    #[inline(always)]
    fn tex_coords(&self, t: &Triangle, b1: f32, b2: f32) -> TexCoords {
        let b0 = 1.0 - b1 - b2;
        let [i0, i1, i2] = [t.v[0] as usize, t.v[1] as usize, t.v[2] as usize];
        let lerp = |v: &[Vec2]| v[i0] * b0 + v[i1] * b1 + v[i2] * b2;
        let uv0 = if t.flags & flags::UVS != 0 { lerp(&self.uvs) } else { Vec2::ZERO };
        let uv1 = if t.flags & flags::UVS1 != 0 { lerp(&self.uvs1) } else { Vec2::ZERO };
        TexCoords([uv0, uv1])
    }

    /// Asks the cache for triangle `tri`'s record ([`Self::prefetch_vertices`] is the second
    /// half: a batch of hits calls this for all, then that for all, then shades them, so the
    /// misses of [`Self::surface_point`] overlap instead of following one another).
    #[inline(always)]
    pub fn prefetch_triangle(&self, tri: u32) {
        if let Some(t) = self.triangles.get(tri as usize) {
            crate::accel::prefetch(t);
        }
    }

    /// Asks the cache for the vertex attributes of triangle `tri` that [`Self::surface_point`]
    /// reads.
    #[inline(always)]
    pub fn prefetch_vertices(&self, tri: u32) {
        let Some(t) = self.triangles.get(tri as usize) else { return };
        for &i in &t.v {
            let i = i as usize;
            if let Some(p) = self.positions.get(i) {
                crate::accel::prefetch(p);
            }
            if t.flags & flags::NORMALS != 0 {
                if let Some(n) = self.normals.get(i) {
                    crate::accel::prefetch(n);
                }
            }
            if t.flags & flags::UVS != 0 {
                if let Some(uv) = self.uvs.get(i) {
                    crate::accel::prefetch(uv);
                }
            }
        }
    }

    /// Surface point at barycentrics (b1, b2) of `tri` (b0 = 1 − b1 − b2).
    pub fn surface_point(&self, tri: u32, b1: f32, b2: f32) -> SurfacePoint {
        let t = &self.triangles[tri as usize];
        let b0 = 1.0 - b1 - b2;
        let [i0, i1, i2] = [t.v[0] as usize, t.v[1] as usize, t.v[2] as usize];
        let (p0, p1, p2) = (self.positions[i0], self.positions[i1], self.positions[i2]);
        // Position from the vertices (not o + t·d), relative to p0: the point stays on the triangle's plane to
        // within about one ulp of its coordinates, however far from the origin the scene is.
        let (e1, e2) = (p1 - p0, p2 - p0);
        let p = p0 + e1 * b1 + e2 * b2;
        let ng = e1.cross(e2).normalize_or_zero();
        let ng = if ng == Vec3::ZERO { Vec3::Z } else { ng };
        let ns = if t.flags & flags::NORMALS != 0 {
            let n = self.normals[i0] * b0 + self.normals[i1] * b1 + self.normals[i2] * b2;
            let n = n.normalize_or_zero();
            if n == Vec3::ZERO || !n.is_finite() {
                ng
            } else {
                n
            }
        } else {
            ng
        };
        let uv = self.tex_coords(t, b1, b2);
        let tangent = self.tangent(t, b1, b2);
        let color = self.color(t, b1, b2);
        SurfacePoint { p, ng, ns, tangent, uv, color, triangle: tri, plane_error: plane_error(e1, e2) }
    }

    /// Object-space bounds of each prototype.
    pub fn prototype_bounds(&self) -> Vec<(Vec3, Vec3)> {
        self.prototypes
            .iter()
            .map(|r| {
                let (mut a, mut b) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
                for t in r.clone() {
                    for p in self.vertices(t) {
                        a = a.min(p);
                        b = b.max(p);
                    }
                }
                (a, b)
            })
            .collect()
    }

    /// World-space box of an instance whose prototype's object box is `(a, b)`: the box around
    /// its 8 transformed corners (conservative, and 8 transforms instead of one per vertex).
    /// None when the prototype is empty (an inverted box) or the placement reaches past
    /// [`MAX_COORDINATE`]: such an instance has nothing a ray can hit, and is not traced.
    pub fn instance_box(inst: &Instance, (a, b): (Vec3, Vec3)) -> Option<(Vec3, Vec3)> {
        let (mut lo, mut hi) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
        if !(a.cmple(b).all()) {
            return None;
        }
        for k in 0..8 {
            let c = Vec3::new(
                if k & 1 != 0 { b.x } else { a.x },
                if k & 2 != 0 { b.y } else { a.y },
                if k & 4 != 0 { b.z } else { a.z },
            );
            let w = inst.to_world.transform_point3(c);
            lo = lo.min(w);
            hi = hi.max(w);
        }
        (is_usable_position(lo) && is_usable_position(hi)).then_some((lo, hi))
    }

    /// World-space bounds of everything: world triangles and every instance.
    pub fn world_bounds(&self) -> Option<(Vec3, Vec3)> {
        let (mut lo, mut hi) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
        for (i, t) in self.triangles.iter().enumerate() {
            if t.flags & flags::OBJECT_SPACE == 0 {
                for p in self.vertices(i as u32) {
                    lo = lo.min(p);
                    hi = hi.max(p);
                }
            }
        }
        // Each prototype's object box once, then its 8 corners per instance (not every vertex).
        let boxes = self.prototype_bounds();
        for inst in self.instances.iter().filter(|i| i.visible) {
            let Some(&bx) = boxes.get(inst.prototype as usize) else { continue };
            let Some((a, b)) = Self::instance_box(inst, bx) else { continue };
            lo = lo.min(a);
            hi = hi.max(b);
        }
        (lo.x <= hi.x).then_some((lo, hi))
    }

    /// A surface point of an instance: the prototype's object-space point carried to the world
    /// (positions by the transform, normals by its inverse transpose, tangents by its linear part).
    pub fn instance_surface_point(&self, inst: &Instance, tri: u32, b1: f32, b2: f32) -> SurfacePoint {
        let mut sp = self.surface_point(tri, b1, b2);
        sp.p = inst.to_world.transform_point3(sp.p);
        // The bound holds in object space, where the instance's triangle test runs; a world
        // distance of it times the transform's largest stretch is at least that far off the plane
        // there.
        sp.plane_error *= inst.stretch;
        let n = |v: Vec3, fallback: Vec3| {
            let w = (inst.normal_matrix * v).normalize_or_zero();
            if w == Vec3::ZERO || !w.is_finite() {
                fallback
            } else {
                w
            }
        };
        sp.ng = n(sp.ng, Vec3::Z);
        sp.ns = n(sp.ns, sp.ng);
        if let Some(t) = sp.tangent {
            let w = inst.to_world.transform_vector3(t.truncate()).normalize_or_zero();
            sp.tangent = Some(w.extend(t.w));
        }
        sp
    }

    /// Clears [`flags::NORMALS`] of the triangles in `tris` whose three vertex normals are the same
    /// vector and that vector is the triangle's winding normal (to within 10⁻⁶ of cos 0°, 0.08°):
    /// interpolating and normalising them gives that normal again, so [`Self::surface_point`] can
    /// take the geometric normal instead, one square root and one division fewer per hit. Exporters
    /// write a normal per corner even for flat faces (Blender does, and every wall of the Cornell
    /// box has them). Triangles with tangents keep theirs: a normal map is applied in their frame.
    pub fn drop_flat_normals(&mut self, tris: std::ops::Range<usize>) {
        for t in &mut self.triangles[tris] {
            if t.flags & flags::NORMALS == 0 || t.flags & flags::TANGENTS != 0 {
                continue;
            }
            // The loader has checked every index, and a triangle with NORMALS has its normals.
            let [n0, n1, n2] = t.v.map(|i| self.normals[i as usize]);
            let [p0, p1, p2] = t.v.map(|i| self.positions[i as usize]);
            let ng = (p1 - p0).cross(p2 - p0).normalize_or_zero();
            if n0 == n1 && n1 == n2 && n0.normalize_or_zero().dot(ng) >= 1.0 - 1e-6 {
                t.flags &= !flags::NORMALS;
            }
        }
    }

    /// Generates per-vertex tangents from UV derivatives for the triangles in `tris` (Lengyel 2001,
    /// "Computing Tangent Space Basis Vectors for an Arbitrary Mesh"), used when a primitive has a
    /// normal map but no TANGENT attribute.
    pub fn generate_tangents(&mut self, tris: std::ops::Range<usize>) {
        // Tangent storage is allocated lazily (see the loader): make room for these vertices.
        if self.tangents.len() < self.positions.len() {
            self.tangents.resize(self.positions.len(), Vec4::ZERO);
        }
        let mut tan = std::collections::HashMap::<u32, (Vec3, Vec3)>::new();
        for t in &self.triangles[tris.clone()] {
            let [i0, i1, i2] = t.v;
            let (p0, p1, p2) = (self.positions[i0 as usize], self.positions[i1 as usize], self.positions[i2 as usize]);
            let (w0, w1, w2) = (self.uvs[i0 as usize], self.uvs[i1 as usize], self.uvs[i2 as usize]);
            let (e1, e2) = (p1 - p0, p2 - p0);
            let (d1, d2) = (w1 - w0, w2 - w0);
            let det = d1.x * d2.y - d2.x * d1.y;
            if det.abs() < 1e-20 {
                continue;
            }
            let r = 1.0 / det;
            let sdir = (e1 * d2.y - e2 * d1.y) * r;
            let tdir = (e2 * d1.x - e1 * d2.x) * r;
            if !sdir.is_finite() || !tdir.is_finite() {
                continue;
            }
            for i in t.v {
                let e = tan.entry(i).or_insert((Vec3::ZERO, Vec3::ZERO));
                e.0 += sdir;
                e.1 += tdir;
            }
        }
        for (i, (s, t)) in tan {
            let n = self.normals.get(i as usize).copied().unwrap_or(Vec3::Z);
            let s_ortho = (s - n * n.dot(s)).normalize_or_zero();
            let w = if n.cross(s).dot(t) < 0.0 { -1.0 } else { 1.0 };
            self.tangents[i as usize] = s_ortho.extend(w);
        }
        for t in &mut self.triangles[tris] {
            t.flags |= flags::TANGENTS;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// One triangle of `normals` (one per corner) on the plane z = 0, wound counter-clockwise (+z).
    fn triangle(normals: [Vec3; 3], flags: u8) -> Mesh {
        let mut m = Mesh {
            positions: vec![Vec3::ZERO, Vec3::new(2.0, 0.0, 0.0), Vec3::new(0.0, 3.0, 0.0)],
            normals: normals.to_vec(),
            ..Mesh::default()
        };
        m.triangles.push(Triangle { v: [0, 1, 2], material: 0, flags });
        m.drop_flat_normals(0..1);
        m
    }

    #[test]
    fn flat_vertex_normals_give_way_to_the_geometric_normal() {
        let has_normals = |m: &Mesh| m.triangles[0].flags & flags::NORMALS != 0;
        // The winding normal at every corner: dropped, and the surface point's normal is the same.
        let flat = triangle([Vec3::Z; 3], flags::NORMALS);
        assert!(!has_normals(&flat));
        assert_eq!(flat.surface_point(0, 0.3, 0.2).ns, Vec3::Z);
        // Kept: smooth normals, one corner off by 0.1°, the normals facing the other way, and a
        // triangle with tangents (a normal map turns its frame).
        let tilt = Vec3::new(0.1f32.to_radians().sin(), 0.0, 0.1f32.to_radians().cos());
        for (normals, flags) in [
            ([Vec3::Z, Vec3::new(0.0, 0.6, 0.8), Vec3::Z], flags::NORMALS),
            ([tilt; 3], flags::NORMALS),
            ([-Vec3::Z; 3], flags::NORMALS),
            ([Vec3::Z; 3], flags::NORMALS | flags::TANGENTS),
        ] {
            assert!(has_normals(&triangle(normals, flags)), "{normals:?} (flags {flags})");
        }
    }
}
