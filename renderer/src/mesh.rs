//! World-space triangle soup: every glTF primitive instance is flattened into one vertex/triangle
//! list at load time, so the accelerator and the lights index one array.

use crate::math::{Vec2, Vec3, Vec4};
use crate::texture::TexCoords;

/// Per-triangle flags: which vertex attributes the source primitive had.
pub mod flags {
    pub const NORMALS: u8 = 1;
    pub const TANGENTS: u8 = 2;
    pub const UVS: u8 = 4;
    /// The primitive has TEXCOORD_1 (in `Mesh::uvs1`).
    pub const UVS1: u8 = 8;
    /// The primitive has COLOR_0 (in `Mesh::colors`).
    pub const COLORS: u8 = 16;
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
    pub normals: Vec<Vec3>,
    /// xyz tangent, w bitangent sign (glTF convention).
    pub tangents: Vec<Vec4>,
    pub uvs: Vec<Vec2>,
    /// TEXCOORD_1, allocated only once some primitive has it (then parallel to `positions`).
    pub uvs1: Vec<Vec2>,
    /// COLOR_0 (linear RGBA), allocated only once some primitive has it (then parallel to `positions`).
    pub colors: Vec<Vec4>,
    pub triangles: Vec<Triangle>,
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

    /// Both texture coordinate sets of triangle `t` at barycentrics (b1, b2).
    #[inline]
    fn tex_coords(&self, t: &Triangle, b1: f32, b2: f32) -> TexCoords {
        let b0 = 1.0 - b1 - b2;
        let [i0, i1, i2] = [t.v[0] as usize, t.v[1] as usize, t.v[2] as usize];
        let lerp = |v: &[Vec2]| v[i0] * b0 + v[i1] * b1 + v[i2] * b2;
        let uv0 = if t.flags & flags::UVS != 0 { lerp(&self.uvs) } else { Vec2::ZERO };
        let uv1 = if t.flags & flags::UVS1 != 0 { lerp(&self.uvs1) } else { Vec2::ZERO };
        TexCoords([uv0, uv1])
    }

    /// Surface point at barycentrics (b1, b2) of `tri` (b0 = 1 − b1 − b2).
    pub fn surface_point(&self, tri: u32, b1: f32, b2: f32) -> SurfacePoint {
        let t = &self.triangles[tri as usize];
        let b0 = 1.0 - b1 - b2;
        let [i0, i1, i2] = [t.v[0] as usize, t.v[1] as usize, t.v[2] as usize];
        let (p0, p1, p2) = (self.positions[i0], self.positions[i1], self.positions[i2]);
        // Position from the vertices (not o + t·d), relative to p0: the point stays on the triangle's plane to
        // within about one ulp of its coordinates, however far from the origin the scene is.
        let p = p0 + (p1 - p0) * b1 + (p2 - p0) * b2;
        let ng = (p1 - p0).cross(p2 - p0).normalize_or_zero();
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
        let tangent = (t.flags & flags::TANGENTS != 0)
            .then(|| self.tangents[i0] * b0 + self.tangents[i1] * b1 + self.tangents[i2] * b2);
        let color = if t.flags & flags::COLORS != 0 {
            self.colors[i0] * b0 + self.colors[i1] * b1 + self.colors[i2] * b2
        } else {
            Vec4::ONE
        };
        SurfacePoint { p, ng, ns, tangent, uv, color, triangle: tri }
    }

    /// Generates per-vertex tangents from UV derivatives for the triangles in `tris` (Lengyel 2001,
    /// "Computing Tangent Space Basis Vectors for an Arbitrary Mesh"), used when a primitive has a
    /// normal map but no TANGENT attribute.
    pub fn generate_tangents(&mut self, tris: std::ops::Range<usize>) {
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
