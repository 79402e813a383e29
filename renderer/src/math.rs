//! Small geometric helpers shared by every part of the renderer: orthonormal frames, luminance and the
//! self-intersection-free ray offset.

pub use glam::{Mat3, Mat4, Vec2, Vec3, Vec3A, Vec4};

pub const PI: f32 = std::f32::consts::PI;
pub const INV_PI: f32 = std::f32::consts::FRAC_1_PI;

/// Rec. 709 / sRGB luminance of a linear RGB triple. Used for light power, lobe weights and the
/// luminance statistics kept in [`crate::film::PartialSums`].
#[inline]
pub fn luminance(c: Vec3) -> f32 {
    0.2126 * c.x + 0.7152 * c.y + 0.0722 * c.z
}

/// An orthonormal basis whose `n` axis is a surface normal; BSDFs work in this local frame where
/// `cos θ = w.z`.
#[derive(Clone, Copy, Debug)]
pub struct Frame {
    pub s: Vec3,
    pub t: Vec3,
    pub n: Vec3,
}

impl Frame {
    /// Branchless ONB from a unit normal (Duff et al. 2017, "Building an Orthonormal Basis, Revisited").
    pub fn from_normal(n: Vec3) -> Self {
        let sign = 1.0f32.copysign(n.z);
        let a = -1.0 / (sign + n.z);
        let b = n.x * n.y * a;
        let s = Vec3::new(1.0 + sign * n.x * n.x * a, sign * b, -sign * n.x);
        let t = Vec3::new(b, sign + n.y * n.y * a, -n.y);
        Frame { s, t, n }
    }

    /// Frame from a unit normal and an approximate tangent (Gram-Schmidt); falls back to
    /// [`Frame::from_normal`] when the tangent is degenerate or parallel to the normal.
    pub fn from_normal_tangent(n: Vec3, tangent: Vec3) -> Self {
        let s = tangent - n * n.dot(tangent);
        let len2 = s.length_squared();
        if !(len2 > 1e-12) || !len2.is_finite() {
            return Frame::from_normal(n);
        }
        let s = s / len2.sqrt();
        Frame { s, t: n.cross(s), n }
    }

    #[inline]
    pub fn to_local(&self, v: Vec3) -> Vec3 {
        Vec3::new(v.dot(self.s), v.dot(self.t), v.dot(self.n))
    }

    #[inline]
    pub fn to_world(&self, v: Vec3) -> Vec3 {
        self.s * v.x + self.t * v.y + self.n * v.z
    }
}

/// Relative length by which a shadow ray to a point sampled on an area light stops short of it.
///
/// Offsetting the target off the light's surface (`offset_ray_origin`) is not enough on its own: that
/// offset is a few ulps of the *light's coordinates*, while the error of the hit distance `t` that the
/// triangle test computes is a few ulps of the *ray's length*. A small emitter near the origin (a
/// 0.3-radius bulb, ulp 3e-8) lit from 4 units away (ulp of t 5e-7) is then found as its own occluder,
/// or its coplanar neighbour is, for a large fraction of samples: next-event estimation came out 6-9 %
/// too dark under a finely tessellated sphere light (issue 10). Stopping 1e-4 short, as pbrt-v4 does
/// (`ShadowEpsilon`; Mitsuba 3 uses 1e-3), puts the end of the ray far outside that error.
pub const SHADOW_EPSILON: f32 = 1e-4;

/// Moves a ray origin off a surface along `n` (pointing to the side the ray leaves towards) by a few
/// ULPs of the position, so the new ray cannot re-hit the surface it starts on at any distance from the
/// origin. Wächter & Binder, "A Fast and Robust Method for Avoiding Self-Intersection", Ray Tracing
/// Gems ch. 6 (2019), with a smaller integer scale (16 ulps at most, not 256): our hit points are
/// interpolated relative to a vertex and carry about one ulp of error, and 256 ulps is already two
/// units at 1e5 from the origin — enough to push a ray through thin walls.
///
/// This is the form for a scene whose coordinates reach 1 or more; a scene's renders use
/// [`offset_ray_origin_scaled`] with its [`offset_scale`].
#[inline]
pub fn offset_ray_origin(p: Vec3, n: Vec3) -> Vec3 {
    offset_ray_origin_scaled(p, n, 1.0)
}

/// The scale of [`offset_ray_origin_scaled`]'s absolute part for a scene whose coordinates stay
/// within `max_abs` of the origin: the largest power of two not above `max_abs`, and 1 from
/// `max_abs` = 1 up (so scenes that large keep Wächter & Binder's constants, and their images).
///
/// Why: near the origin (within 1/32) Wächter & Binder offset by an absolute 2⁻¹⁶, a distance
/// that is small only in a scene about 1 unit across or more. In a room a millimetre across (or
/// a Blender export scaled by 0.01) it is 1.5 % of the room's width, and the image came out
/// 5.5 % brighter than the same room at full size (`renderer/tests/scale.rs`). With the scale a
/// power of two, a scene scaled by a power of two is offset by its own offsets scaled exactly,
/// so its image is the same.
pub fn offset_scale(max_abs: f32) -> f32 {
    if !(max_abs < 1.0) || !(max_abs > 0.0) {
        return 1.0;
    }
    // Bounded below so the absolute offset (2⁻¹⁶ of this) stays a normal float.
    let exp = (max_abs.to_bits() >> 23) as i32 - 127;
    f32::from_bits(((exp.max(-100) + 127) as u32) << 23)
}

/// [`offset_ray_origin`] with its absolute part (the threshold near the origin and the offset
/// there) multiplied by `scale`, a power of two ([`offset_scale`]).
#[inline]
pub fn offset_ray_origin_scaled(p: Vec3, n: Vec3, scale: f32) -> Vec3 {
    const ORIGIN: f32 = 1.0 / 32.0;
    const FLOAT_SCALE: f32 = 1.0 / 65536.0;
    const INT_SCALE: f32 = 16.0;
    let (near, float_scale) = (ORIGIN * scale, FLOAT_SCALE * scale);
    let of_i = [(INT_SCALE * n.x) as i32, (INT_SCALE * n.y) as i32, (INT_SCALE * n.z) as i32];
    let offset = |p: f32, o: i32| -> f32 { f32::from_bits((p.to_bits() as i32 + if p < 0.0 { -o } else { o }) as u32) };
    let pi = Vec3::new(offset(p.x, of_i[0]), offset(p.y, of_i[1]), offset(p.z, of_i[2]));
    Vec3::new(
        if p.x.abs() < near { p.x + float_scale * n.x } else { pi.x },
        if p.y.abs() < near { p.y + float_scale * n.y } else { pi.y },
        if p.z.abs() < near { p.z + float_scale * n.z } else { pi.z },
    )
}

/// Mirror reflection of `w` about `n` (both unit, same hemisphere convention as pbrt: the result
/// points away from the surface when `w` does).
#[inline]
pub fn reflect(w: Vec3, n: Vec3) -> Vec3 {
    2.0 * w.dot(n) * n - w
}

/// Power heuristic with β = 2 (Veach 1997, §9.2.4), written so that an infinite pdf (delta) or
/// 0/0 never produces NaN.
#[inline]
pub fn power_heuristic(f: f32, g: f32) -> f32 {
    let (f2, g2) = (f * f, g * g);
    if f2.is_infinite() {
        return 1.0;
    }
    if f2 + g2 <= 0.0 {
        return 0.0;
    }
    f2 / (f2 + g2)
}

/// Balance heuristic (Veach 1997, §9.2.2).
#[inline]
pub fn balance_heuristic(f: f32, g: f32) -> f32 {
    if f.is_infinite() {
        return 1.0;
    }
    if f + g <= 0.0 {
        return 0.0;
    }
    f / (f + g)
}

/// Cosine-weighted hemisphere sample via Shirley-Chiu concentric mapping (pbrt-v4 §A.5.3).
#[inline]
pub fn sample_cosine_hemisphere(u: Vec2) -> Vec3 {
    let d = sample_uniform_disk_concentric(u);
    let z = (1.0 - d.x * d.x - d.y * d.y).max(0.0).sqrt();
    Vec3::new(d.x, d.y, z)
}

#[inline]
pub fn cosine_hemisphere_pdf(cos_theta: f32) -> f32 {
    cos_theta.max(0.0) * INV_PI
}

/// Shirley-Chiu concentric square-to-disk mapping (pbrt-v4 §A.5.1). Both wedges need sin and cos
/// of an angle within π/4 of an axis: θ = (π/4)·(y/x), or π/2 − (π/4)·(x/y) whose cosine and sine
/// are the sine and cosine of (π/4)·(x/y), so [`sin_cos_quarter`] serves without range reduction.
#[inline]
pub fn sample_uniform_disk_concentric(u: Vec2) -> Vec2 {
    let o = 2.0 * u - Vec2::ONE;
    if o.x == 0.0 && o.y == 0.0 {
        return Vec2::ZERO;
    }
    if o.x.abs() > o.y.abs() {
        let (s, c) = sin_cos_quarter((PI / 4.0) * (o.y / o.x));
        o.x * Vec2::new(c, s)
    } else {
        let (s, c) = sin_cos_quarter((PI / 4.0) * (o.x / o.y));
        o.y * Vec2::new(s, c)
    }
}

/// (sin x, cos x) for |x| ≤ π/4 by the minimax polynomials of Cephes' `sinf`/`cosf` (Moshier
/// 1989; within about 1 ulp there). libm's `sincosf` handles any argument and showed up as 2.4 %
/// of a Cornell render's time; sampling only ever asks for small or easily reduced angles.
#[inline]
pub fn sin_cos_quarter(x: f32) -> (f32, f32) {
    let z = x * x;
    let s = ((-1.951_529_6e-4 * z + 8.332_161e-3) * z - 1.666_665_5e-1) * z * x + x;
    let c = ((2.443_315_7e-5 * z - 1.388_731_6e-3) * z + 4.166_664_6e-2) * z * z - 0.5 * z + 1.0;
    (s, c)
}

/// (sin x, cos x) for 0 ≤ x ≤ 2π (an azimuth): reduced to the nearest multiple of π/2 and
/// [`sin_cos_quarter`], then rotated by that quadrant.
#[inline]
pub fn sin_cos_azimuth(x: f32) -> (f32, f32) {
    let k = (x * (2.0 / PI)).round();
    let (s, c) = sin_cos_quarter(x - k * (PI / 2.0));
    match (k as i32) & 3 {
        0 => (s, c),
        1 => (c, -s),
        2 => (-s, -c),
        _ => (-c, s),
    }
}

/// Uniform barycentrics on a triangle (Heitz 2019, "A Low-Distortion Map Between Triangle and
/// Square"); returns (b0, b1, b2).
#[inline]
pub fn sample_uniform_triangle(u: Vec2) -> Vec3 {
    let (b0, b1);
    if u.x < u.y {
        b0 = u.x / 2.0;
        b1 = u.y - b0;
    } else {
        b1 = u.y / 2.0;
        b0 = u.x - b1;
    }
    Vec3::new(b0, b1, 1.0 - b0 - b1)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The polynomial sine and cosine agree with libm to a few ulp over the sampling ranges
    /// (the azimuth's quadrant reduction included, at its seams and ends).
    #[test]
    fn polynomial_sin_cos_match_libm() {
        let mut worst = 0.0f32;
        for i in 0..=100_000 {
            let x = (i as f32 / 100_000.0 - 0.5) * (PI / 2.0);
            let (s, c) = sin_cos_quarter(x);
            worst = worst.max((s - x.sin()).abs()).max((c - x.cos()).abs());
            let a = i as f32 / 100_000.0 * 2.0 * PI;
            let (s, c) = sin_cos_azimuth(a);
            worst = worst.max((s - a.sin()).abs()).max((c - a.cos()).abs());
        }
        for a in [0.0, PI / 4.0, PI / 2.0, PI, 1.5 * PI, 2.0 * PI, 7.0 * PI / 4.0, 2.0 * PI - 1e-6] {
            let (s, c) = sin_cos_azimuth(a);
            worst = worst.max((s - a.sin()).abs()).max((c - a.cos()).abs());
        }
        assert!(worst < 4.0 * f32::EPSILON, "worst absolute error {worst:e}");
    }

    #[test]
    fn frame_is_orthonormal_for_all_normals() {
        for n in [
            Vec3::Z,
            -Vec3::Z,
            Vec3::X,
            Vec3::new(0.3, -0.4, 0.866).normalize(),
            Vec3::new(1e-7, 1e-7, -1.0).normalize(),
        ] {
            let f = Frame::from_normal(n);
            assert!((f.s.length() - 1.0).abs() < 1e-5);
            assert!((f.t.length() - 1.0).abs() < 1e-5);
            assert!(f.s.dot(f.t).abs() < 1e-5 && f.s.dot(n).abs() < 1e-5 && f.t.dot(n).abs() < 1e-5);
            let v = Vec3::new(0.2, -0.7, 0.4);
            assert!((f.to_world(f.to_local(v)) - v).length() < 1e-5);
        }
    }

    #[test]
    fn offset_moves_to_the_requested_side_at_any_scale() {
        for scale in [0.0f32, 1e-3, 1.0, 1e5, -1e5] {
            let p = Vec3::splat(scale);
            let n = Vec3::new(0.0, 1.0, 0.0);
            let q = offset_ray_origin(p, n);
            assert!(q.y > p.y, "scale {scale}: {q:?} not above {p:?}");
            assert_eq!(q.x, p.x);
        }
    }

    #[test]
    fn offset_scale_is_a_power_of_two_below_one() {
        assert_eq!(offset_scale(1.0), 1.0);
        assert_eq!(offset_scale(37.0), 1.0);
        assert_eq!(offset_scale(f32::INFINITY), 1.0);
        assert_eq!(offset_scale(f32::NAN), 1.0);
        assert_eq!(offset_scale(0.0), 1.0);
        assert_eq!(offset_scale(0.8), 0.5);
        assert_eq!(offset_scale(0.5), 0.5);
        assert_eq!(offset_scale(0.8 / 1024.0), 1.0 / 2048.0);
        assert_eq!(offset_scale(1e-38), 2f32.powi(-100));
        // A scene scaled by a power of two is offset by the same points scaled.
        for (i, &p) in [0.01f32, -0.02, 0.3, 0.7, -0.0001].iter().enumerate() {
            let (p, n) = (Vec3::new(p, 0.5 * p, 0.02), Vec3::new(0.6, -0.8, 0.0));
            let k = 2f32.powi(-(3 * i as i32 + 4));
            let s = offset_scale(0.8);
            assert_eq!(offset_ray_origin_scaled(p * k, n, s * k), offset_ray_origin_scaled(p, n, s) * k);
        }
        // Scale 1 is Wächter & Binder's constants.
        let p = Vec3::new(0.01, -0.5, 3.0);
        assert_eq!(offset_ray_origin_scaled(p, Vec3::Y, 1.0), offset_ray_origin(p, Vec3::Y));
    }

    #[test]
    fn heuristics_handle_delta_and_zero() {
        assert_eq!(power_heuristic(f32::INFINITY, 1.0), 1.0);
        assert_eq!(power_heuristic(0.0, 0.0), 0.0);
        assert!((power_heuristic(1.0, 1.0) - 0.5).abs() < 1e-6);
        assert_eq!(balance_heuristic(0.0, 0.0), 0.0);
    }
}
