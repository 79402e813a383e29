//! Image textures: 8-bit RGBA storage (4 bytes a texel keeps 2K PBR texture sets small), decoded to
//! linear on lookup, bilinear filtering and the glTF wrap modes.

use crate::math::{Vec2, Vec4};

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Wrap {
    Repeat,
    ClampToEdge,
    MirroredRepeat,
}

/// How a material refers to a texture: which one, and the sampler's wrap modes.
#[derive(Clone, Copy, Debug)]
pub struct TextureRef {
    pub texture: u32,
    pub wrap_s: Wrap,
    pub wrap_t: Wrap,
    /// Which TEXCOORD_n set the texture reads (0 or 1).
    pub set: u8,
    /// KHR_texture_transform as the 2×3 affine map uv' = [a b c; d e f]·(u, v, 1), if any.
    pub transform: Option<[f32; 6]>,
}

impl TextureRef {
    /// The coordinates this texture is sampled at for a point with texture coordinates `uv`.
    #[inline]
    pub fn coords(&self, uv: &TexCoords) -> Vec2 {
        let p = uv.0[(self.set as usize).min(1)];
        match self.transform {
            None => p,
            Some([a, b, c, d, e, f]) => Vec2::new(a * p.x + b * p.y + c, d * p.x + e * p.y + f),
        }
    }
}

/// The texture coordinate sets of a surface point: TEXCOORD_0 and TEXCOORD_1 (zero where the
/// primitive has none).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct TexCoords(pub [Vec2; 2]);

/// KHR_texture_transform's matrix T·R·S (offset, rotation in radians, scale), as the spec's GLSL
/// writes it: uv' = offset + R(rotation)·(scale ⊙ uv), R's columns (cos, sin) and (−sin, cos).
pub fn texture_transform(offset: [f32; 2], rotation: f32, scale: [f32; 2]) -> [f32; 6] {
    let (s, c) = rotation.sin_cos();
    [c * scale[0], -s * scale[1], offset[0], s * scale[0], c * scale[1], offset[1]]
}

pub struct Texture {
    pub width: u32,
    pub height: u32,
    /// Row-major, top row first (glTF UV (0,0) is the image's top-left corner).
    pub texels: Vec<[u8; 4]>,
    /// Color textures (base color, emissive, specular color) are sRGB-encoded; data textures
    /// (metallic-roughness, normal, specular) are linear.
    pub srgb: bool,
}

/// [`Texture::is_large`]'s threshold, in texels.
const LARGE_TEXELS: usize = 512 * 512;

/// sRGB EOTF for each 8-bit code (IEC 61966-2-1).
fn srgb_table() -> &'static [f32; 256] {
    static TABLE: std::sync::OnceLock<[f32; 256]> = std::sync::OnceLock::new();
    TABLE.get_or_init(|| {
        let mut t = [0.0f32; 256];
        for (i, v) in t.iter_mut().enumerate() {
            let c = i as f32 / 255.0;
            *v = if c <= 0.04045 { c / 12.92 } else { ((c + 0.055) / 1.055).powf(2.4) };
        }
        t
    })
}

#[inline]
fn wrap_coord(i: i64, n: u32, wrap: Wrap) -> u32 {
    let n = n as i64;
    // Inside the texture every mode leaves the coordinate as it is, without the remainder's
    // 64-bit division (four of them a bilinear lookup).
    if (0..n).contains(&i) {
        return i as u32;
    }
    match wrap {
        Wrap::Repeat => i.rem_euclid(n) as u32,
        Wrap::ClampToEdge => i.clamp(0, n - 1) as u32,
        Wrap::MirroredRepeat => {
            let period = 2 * n;
            let m = i.rem_euclid(period);
            (if m < n { m } else { period - 1 - m }) as u32
        }
    }
}

impl Texture {
    #[inline]
    fn texel(&self, x: u32, y: u32) -> Vec4 {
        self.texels_at([(x, y)])[0]
    }

    /// Texels (x, y) decoded to linear values, the sRGB table looked up once for all.
    #[inline(always)]
    fn texels_at<const N: usize>(&self, at: [(u32, u32); N]) -> [Vec4; N] {
        let w = self.width as usize;
        let raw = at.map(|(x, y)| self.texels[(y as usize) * w + x as usize]);
        if self.srgb {
            let table = srgb_table();
            raw.map(|t| {
                Vec4::new(table[t[0] as usize], table[t[1] as usize], table[t[2] as usize], t[3] as f32 / 255.0)
            })
        } else {
            raw.map(|t| Vec4::new(t[0] as f32, t[1] as f32, t[2] as f32, t[3] as f32) / 255.0)
        }
    }

    /// The four texels (columns xa, xb; rows ya, yb) a bilinear lookup at `uv` blends and its
    /// weights (fx, fy); None for non-finite coordinates (the lookup then reads texel (0, 0)).
    #[inline(always)]
    fn footprint(&self, uv: Vec2, r: &TextureRef) -> Option<([u32; 4], f32, f32)> {
        let x = uv.x * self.width as f32 - 0.5;
        let y = uv.y * self.height as f32 - 0.5;
        if !x.is_finite() || !y.is_finite() {
            return None;
        }
        let (x0, y0) = (x.floor(), y.floor());
        let (fx, fy) = (x - x0, y - y0);
        let (x0, y0) = (x0 as i64, y0 as i64);
        let xa = wrap_coord(x0, self.width, r.wrap_s);
        let xb = wrap_coord(x0 + 1, self.width, r.wrap_s);
        let ya = wrap_coord(y0, self.height, r.wrap_t);
        let yb = wrap_coord(y0 + 1, self.height, r.wrap_t);
        Some(([xa, xb, ya, yb], fx, fy))
    }

    /// Bilinear lookup in linear space (decode first, then filter, as GPUs do for sRGB formats).
    pub fn sample(&self, uv: Vec2, r: &TextureRef) -> Vec4 {
        let Some(([xa, xb, ya, yb], fx, fy)) = self.footprint(uv, r) else { return self.texel(0, 0) };
        let [a, b, c, d] = self.texels_at([(xa, ya), (xb, ya), (xa, yb), (xb, yb)]);
        let top = a * (1.0 - fx) + b * fx;
        let bottom = c * (1.0 - fx) + d * fx;
        top * (1.0 - fy) + bottom * fy
    }

    /// Whether the texture is large enough (a megabyte, 512 × 512 texels) that lookups where rays
    /// land mostly miss the cache: the kernel asks for such textures' texels ahead
    /// ([`Self::prefetch`]); below it, asking cost more than it saved (a 64² grid, 16 KiB: 1.064
    /// times the time of `scenes/blender/materials.glb`).
    pub fn is_large(&self) -> bool {
        self.texels.len() >= LARGE_TEXELS
    }

    /// Asks the cache for the texels [`Self::sample`]`(uv, r)` reads. A texture of megabytes read
    /// where rays land misses the cache at nearly every lookup; the kernel asks for all its lanes'
    /// texels before it reads the first, so their misses overlap instead of following each other.
    #[inline]
    pub fn prefetch(&self, uv: Vec2, r: &TextureRef) {
        let Some(([xa, xb, ya, yb], ..)) = self.footprint(uv, r) else { return };
        let w = self.width as usize;
        for i in [
            ya as usize * w + xa as usize,
            ya as usize * w + xb as usize,
            yb as usize * w + xa as usize,
            yb as usize * w + xb as usize,
        ] {
            self.texels.get(i).map(crate::accel::prefetch);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn checker() -> Texture {
        Texture {
            width: 2,
            height: 2,
            texels: vec![[0, 0, 0, 255], [255, 255, 255, 255], [255, 255, 255, 255], [0, 0, 0, 255]],
            srgb: false,
        }
    }

    #[test]
    fn wrap_modes() {
        assert_eq!(wrap_coord(-1, 4, Wrap::Repeat), 3);
        assert_eq!(wrap_coord(4, 4, Wrap::ClampToEdge), 3);
        assert_eq!(wrap_coord(-1, 4, Wrap::ClampToEdge), 0);
        assert_eq!(wrap_coord(4, 4, Wrap::MirroredRepeat), 3);
        assert_eq!(wrap_coord(-1, 4, Wrap::MirroredRepeat), 0);
    }

    /// The in-range shortcut answers as each mode's rule does everywhere: the remainder for
    /// repeat, the clamp, the mirrored remainder.
    #[test]
    fn wrap_coord_is_each_modes_rule() {
        for n in [1u32, 2, 3, 7, 16] {
            let m = n as i64;
            for i in -4 * m..4 * m {
                let mirrored = {
                    let r = i.rem_euclid(2 * m);
                    if r < m {
                        r
                    } else {
                        2 * m - 1 - r
                    }
                };
                assert_eq!(wrap_coord(i, n, Wrap::Repeat) as i64, i.rem_euclid(m), "repeat {i} in {n}");
                assert_eq!(wrap_coord(i, n, Wrap::ClampToEdge) as i64, i.clamp(0, m - 1), "clamp {i} in {n}");
                assert_eq!(wrap_coord(i, n, Wrap::MirroredRepeat) as i64, mirrored, "mirror {i} in {n}");
            }
        }
    }

    /// Asking for a lookup's texels reads inside the texture wherever the coordinates are (far
    /// outside, negative, non-finite, at the edges) and in every wrap mode, and a texture is
    /// large from 512 × 512 texels on.
    #[test]
    fn prefetch_stays_inside_and_large_starts_at_a_megabyte() {
        let t = Texture { width: 3, height: 2, texels: vec![[9, 9, 9, 9]; 6], srgb: true };
        for wrap in [Wrap::Repeat, Wrap::ClampToEdge, Wrap::MirroredRepeat] {
            let r = TextureRef { texture: 0, wrap_s: wrap, wrap_t: wrap, set: 0, transform: None };
            for u in [-1e9, -2.5, -0.01, 0.0, 0.5, 0.999, 1.0, 7.25, 1e9, f32::NAN, f32::INFINITY] {
                for v in [-3.0, 0.0, 0.75, 1.0, 4.5, f32::NEG_INFINITY] {
                    let ([xa, xb, ya, yb], ..) = t.footprint(Vec2::new(u, v), &r).unwrap_or(([0; 4], 0.0, 0.0));
                    assert!(xa < 3 && xb < 3 && ya < 2 && yb < 2, "{wrap:?} ({u}, {v})");
                    t.prefetch(Vec2::new(u, v), &r);
                }
            }
        }
        assert!(!t.is_large());
        let side = |n: u32| Texture { width: n, height: n, texels: vec![[0; 4]; (n * n) as usize], srgb: false };
        assert!(!side(511).is_large());
        assert!(side(512).is_large());
    }

    #[test]
    fn bilinear_hits_texel_centres_and_blends_between() {
        let t = checker();
        let r =
            TextureRef { texture: 0, wrap_s: Wrap::ClampToEdge, wrap_t: Wrap::ClampToEdge, set: 0, transform: None };
        assert_eq!(t.sample(Vec2::new(0.25, 0.25), &r).x, 0.0);
        assert_eq!(t.sample(Vec2::new(0.75, 0.25), &r).x, 1.0);
        assert!((t.sample(Vec2::new(0.5, 0.25), &r).x - 0.5).abs() < 1e-6);
    }

    #[test]
    fn srgb_decode() {
        let t = Texture { width: 1, height: 1, texels: vec![[188, 0, 255, 255]], srgb: true };
        let r = TextureRef { texture: 0, wrap_s: Wrap::Repeat, wrap_t: Wrap::Repeat, set: 0, transform: None };
        let v = t.sample(Vec2::splat(0.5), &r);
        assert!((v.x - 0.5029).abs() < 1e-3, "{v:?}");
        assert_eq!(v.y, 0.0);
        assert!((v.z - 1.0).abs() < 1e-6);
    }

    /// KHR_texture_transform as the spec's GLSL writes it: T·R·S, R with columns (cos, sin) and
    /// (−sin, cos); and the texCoord set chosen per texture.
    #[test]
    fn texture_transform_follows_the_spec() {
        let m = texture_transform([0.5, 0.0], std::f32::consts::FRAC_PI_2, [2.0, 1.0]);
        let r = TextureRef { texture: 0, wrap_s: Wrap::Repeat, wrap_t: Wrap::Repeat, set: 1, transform: Some(m) };
        // (1, 0) on set 1: scaled to (2, 0), rotated to (0, 2), offset to (0.5, 2).
        let p = r.coords(&TexCoords([Vec2::new(9.0, 9.0), Vec2::new(1.0, 0.0)]));
        assert!((p - Vec2::new(0.5, 2.0)).length() < 1e-6, "{p:?}");
        let plain = TextureRef { set: 0, transform: None, ..r };
        assert_eq!(plain.coords(&TexCoords([Vec2::new(0.25, 0.75), Vec2::ZERO])), Vec2::new(0.25, 0.75));
    }
}
