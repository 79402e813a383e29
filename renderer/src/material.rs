//! glTF metallic-roughness materials and their resolution to a [`Bsdf`] at a shading point.

use crate::bsdf::Bsdf;
use crate::clearcoat::Clearcoat;
use crate::math::{Vec3, Vec4};
use crate::microfacet::Ggx;
use crate::sheen::Sheen;
use crate::texture::{TexCoords, Texture, TextureRef};

#[derive(Clone, Debug)]
pub struct Material {
    pub name: String,
    pub base_color: Vec4,
    pub base_color_texture: Option<TextureRef>,
    pub metallic: f32,
    pub roughness: f32,
    /// glTF packs roughness in G and metallic in B.
    pub metallic_roughness_texture: Option<TextureRef>,
    pub normal_texture: Option<TextureRef>,
    pub normal_scale: f32,
    /// emissiveFactor × KHR_materials_emissive_strength.
    pub emissive: Vec3,
    pub emissive_texture: Option<TextureRef>,
    /// KHR_materials_specular.
    pub specular: f32,
    pub specular_texture: Option<TextureRef>,
    pub specular_color: Vec3,
    pub specular_color_texture: Option<TextureRef>,
    /// KHR_materials_ior (glTF default 1.5).
    pub ior: f32,
    /// KHR_materials_transmission factor (and texture, red channel).
    pub transmission: f32,
    pub transmission_texture: Option<TextureRef>,
    /// KHR_materials_clearcoat: factor (× texture R), roughness (× texture G), its own normal map.
    pub clearcoat: f32,
    pub clearcoat_texture: Option<TextureRef>,
    pub clearcoat_roughness: f32,
    pub clearcoat_roughness_texture: Option<TextureRef>,
    pub clearcoat_normal_texture: Option<TextureRef>,
    pub clearcoat_normal_scale: f32,
    /// KHR_materials_sheen: color (× texture RGB), roughness (× texture A). Black = no sheen.
    pub sheen_color: Vec3,
    pub sheen_color_texture: Option<TextureRef>,
    pub sheen_roughness: f32,
    pub sheen_roughness_texture: Option<TextureRef>,
    /// KHR_materials_volume as an absorption coefficient σa = −ln(attenuationColor) /
    /// attenuationDistance (per scene unit) inside the mesh; zero = clear, and zero for a thin
    /// wall (`thicknessFactor` 0, the extension's default: no volume behind the surface).
    /// Beer–Lambert along the real path length (a positive thickness's value is a rasteriser's
    /// hint and is not used).
    pub absorption: Vec3,
    /// KHR_materials_unlit: the surface shows its base color whatever the lighting. In a path
    /// tracer that is an emitter of radiance baseColor that does not scatter (as Blender's exporter
    /// writes an Emission/Background shader), seen by every ray but not sampled by NEE.
    pub unlit: bool,
    /// glTF `doubleSided`: here it decides whether an emissive surface emits from its back face too.
    pub double_sided: bool,
    pub alpha_mode: AlphaMode,
}

/// glTF `alphaMode`: MASK cuts out where alpha < cutoff; BLEND is treated as stochastic transparency
/// (a ray passes with probability 1 − alpha; shadow rays are attenuated by 1 − alpha).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum AlphaMode {
    Opaque,
    Mask(f32),
    Blend,
}

impl Default for Material {
    /// The glTF default material (spec §3.9.6): white, fully metallic, fully rough.
    fn default() -> Self {
        Material {
            name: "default".into(),
            base_color: Vec4::ONE,
            base_color_texture: None,
            metallic: 1.0,
            roughness: 1.0,
            metallic_roughness_texture: None,
            normal_texture: None,
            normal_scale: 1.0,
            emissive: Vec3::ZERO,
            emissive_texture: None,
            specular: 1.0,
            specular_texture: None,
            specular_color: Vec3::ONE,
            specular_color_texture: None,
            ior: 1.5,
            transmission: 0.0,
            transmission_texture: None,
            clearcoat: 0.0,
            clearcoat_texture: None,
            clearcoat_roughness: 0.0,
            clearcoat_roughness_texture: None,
            clearcoat_normal_texture: None,
            clearcoat_normal_scale: 1.0,
            sheen_color: Vec3::ZERO,
            sheen_color_texture: None,
            sheen_roughness: 0.0,
            sheen_roughness_texture: None,
            absorption: Vec3::ZERO,
            unlit: false,
            double_sided: false,
            alpha_mode: AlphaMode::Opaque,
        }
    }
}

#[inline]
fn lookup(textures: &[Texture], r: &Option<TextureRef>, uv: TexCoords) -> Option<Vec4> {
    r.as_ref().map(|r| textures[r.texture as usize].sample(r.coords(&uv), r))
}

/// Whether some material is alpha-blended (BLEND: it passes a ray by the sample's numbers and
/// shadow rays in part).
pub fn any_blends(materials: &[Material]) -> bool {
    materials.iter().any(|m| m.alpha_mode == AlphaMode::Blend)
}

impl Material {
    pub fn is_emissive(&self) -> bool {
        self.emissive.max_element() > 0.0
    }

    /// Coverage at `uv` for MASK and BLEND materials (base color alpha × texture alpha × COLOR_0
    /// alpha), in [0, 1].
    pub fn alpha(&self, textures: &[Texture], uv: TexCoords, color: Vec4) -> f32 {
        let mut a = self.base_color.w * color.w;
        if let Some(t) = lookup(textures, &self.base_color_texture, uv) {
            a *= t.w;
        }
        if a.is_finite() {
            a.clamp(0.0, 1.0)
        } else {
            1.0
        }
    }

    /// Emitted radiance at `uv` (front face; the caller decides sidedness). Inlined: the
    /// kernel asks it per lane of every light sample, where an untextured emitter's answer is
    /// one load (callgrind, Cornell: 18 instructions a call when it was not).
    #[inline]
    pub fn emission(&self, textures: &[Texture], uv: TexCoords) -> Vec3 {
        match lookup(textures, &self.emissive_texture, uv) {
            Some(t) => self.emissive * t.truncate(),
            None => self.emissive,
        }
    }

    /// Base color × texture × vertex color (COLOR_0), RGB clamped to [0, 1].
    pub fn base_color_at(&self, textures: &[Texture], uv: TexCoords, color: Vec4) -> Vec3 {
        let mut base = self.base_color * color;
        if let Some(t) = lookup(textures, &self.base_color_texture, uv) {
            base *= t;
        }
        Vec3::new(sanitize(base.x), sanitize(base.y), sanitize(base.z))
    }

    /// BSDF parameters at `uv` (with the vertex color `color`), with every input clamped to its
    /// valid range so that no texture or factor can produce NaN or energy gain. A clearcoat's normal
    /// is the shading normal here; the integrator replaces it when the coat has its own normal map.
    pub fn bsdf(&self, textures: &[Texture], uv: TexCoords, color: Vec4) -> Bsdf {
        let base_color = self.base_color_at(textures, uv, color);
        let (mut metallic, mut roughness) = (self.metallic, self.roughness);
        if let Some(t) = lookup(textures, &self.metallic_roughness_texture, uv) {
            roughness *= t.y;
            metallic *= t.z;
        }
        let mut specular = self.specular;
        if let Some(t) = lookup(textures, &self.specular_texture, uv) {
            specular *= t.w;
        }
        let mut specular_color = self.specular_color;
        if let Some(t) = lookup(textures, &self.specular_color_texture, uv) {
            specular_color *= t.truncate();
        }
        let coat = (self.clearcoat > 0.0).then(|| {
            let mut c = self.clearcoat;
            if let Some(t) = lookup(textures, &self.clearcoat_texture, uv) {
                c *= t.x;
            }
            let mut r = self.clearcoat_roughness;
            if let Some(t) = lookup(textures, &self.clearcoat_roughness_texture, uv) {
                r *= t.y;
            }
            Clearcoat { weight: sanitize(c), ggx: Ggx::from_roughness(sanitize(r)), normal: Vec3::Z }
        });
        let sheen = (self.sheen_color.max_element() > 0.0).then(|| {
            let mut c = self.sheen_color;
            if let Some(t) = lookup(textures, &self.sheen_color_texture, uv) {
                c *= t.truncate();
            }
            let mut r = self.sheen_roughness;
            if let Some(t) = lookup(textures, &self.sheen_roughness_texture, uv) {
                r *= t.w;
            }
            Sheen::new(Vec3::new(sanitize(c.x), sanitize(c.y), sanitize(c.z)), sanitize(r))
        });
        Bsdf {
            base_color,
            metallic: sanitize(metallic),
            ggx: Ggx::from_roughness(sanitize(roughness)),
            specular: sanitize(specular),
            f0_dielectric: Bsdf::f0_from_ior(
                if self.ior.is_finite() { self.ior.max(1.0) } else { 1.5 },
                specular_color.max(Vec3::ZERO),
            ),
            transmission: {
                let mut t = self.transmission;
                if let Some(tex) = lookup(textures, &self.transmission_texture, uv) {
                    t *= tex.x;
                }
                sanitize(t)
            },
            eta: if self.ior.is_finite() { self.ior.max(1.0) } else { 1.5 },
            coat: coat.filter(|c| c.weight > 0.0),
            sheen: sheen.filter(|s| s.color.max_element() > 0.0),
        }
    }

    /// The BSDF when no texture feeds it, so that it is the same at every point of every surface
    /// without vertex colours: what [`Self::bsdf`] gives there, computed once per scene rather
    /// than at every path vertex (the clamps, `Ggx::from_roughness` and F0's division were 4.5 %
    /// of a Cornell-box render). None when a texture does feed it.
    pub fn uniform_bsdf(&self) -> Option<Bsdf> {
        self.base_color_texture.is_none().then(|| self.bsdf_but_base_colour()).flatten()
    }

    /// The BSDF when no texture but the base colour's feeds it: what [`Self::bsdf`] gives
    /// everywhere but in `base_color` (which [`Self::base_color_at`] gives at a point: nothing
    /// else of the BSDF reads the base colour texture or the vertex colour). None when another
    /// texture feeds it.
    pub fn bsdf_but_base_colour(&self) -> Option<Bsdf> {
        let feeds = [
            &self.metallic_roughness_texture,
            &self.specular_texture,
            &self.specular_color_texture,
            &self.transmission_texture,
            &self.clearcoat_texture,
            &self.clearcoat_roughness_texture,
            &self.sheen_color_texture,
            &self.sheen_roughness_texture,
        ];
        let untextured = || Material { base_color_texture: None, ..self.clone() };
        feeds.iter().all(|t| t.is_none()).then(|| untextured().bsdf(&[], TexCoords::default(), Vec4::ONE))
    }

    /// Every texture a hit on this material may read (the emissive one included).
    fn texture_refs(&self) -> [&Option<TextureRef>; 12] {
        [
            &self.base_color_texture,
            &self.metallic_roughness_texture,
            &self.normal_texture,
            &self.emissive_texture,
            &self.specular_texture,
            &self.specular_color_texture,
            &self.transmission_texture,
            &self.clearcoat_texture,
            &self.clearcoat_roughness_texture,
            &self.clearcoat_normal_texture,
            &self.sheen_color_texture,
            &self.sheen_roughness_texture,
        ]
    }

    /// Whether a hit on this material may read a texture too large to stay cached
    /// ([`Texture::is_large`]).
    pub fn reads_large_texture(&self, textures: &[Texture]) -> bool {
        self.texture_refs()
            .into_iter()
            .flatten()
            .any(|r| textures.get(r.texture as usize).is_some_and(Texture::is_large))
    }

    /// Asks the cache for the texels a hit at `uv` on this material may read from its large
    /// textures (each one's bilinear footprint, [`Texture::prefetch`]).
    pub fn prefetch_texels(&self, textures: &[Texture], uv: TexCoords) {
        for r in self.texture_refs().into_iter().flatten() {
            if let Some(t) = textures.get(r.texture as usize).filter(|t| t.is_large()) {
                t.prefetch(r.coords(&uv), r);
            }
        }
    }

    /// Tangent-space normal from the normal texture (scaled as the glTF spec defines), or None.
    pub fn tangent_space_normal(&self, textures: &[Texture], uv: TexCoords) -> Option<Vec3> {
        decode_normal(lookup(textures, &self.normal_texture, uv)?, self.normal_scale)
    }

    /// Tangent-space normal of the clearcoat's own normal map, or None (the coat then uses the
    /// interpolated vertex normal, not the base's mapped one: KHR_materials_clearcoat).
    pub fn clearcoat_tangent_space_normal(&self, textures: &[Texture], uv: TexCoords) -> Option<Vec3> {
        decode_normal(lookup(textures, &self.clearcoat_normal_texture, uv)?, self.clearcoat_normal_scale)
    }
}

/// A normal-map texel to a unit tangent-space normal (glTF: xy scaled by `scale`).
fn decode_normal(t: Vec4, scale: f32) -> Option<Vec3> {
    let n = Vec3::new((2.0 * t.x - 1.0) * scale, (2.0 * t.y - 1.0) * scale, 2.0 * t.z - 1.0).normalize_or_zero();
    (n != Vec3::ZERO && n.is_finite()).then_some(n)
}

#[inline]
fn sanitize(x: f32) -> f32 {
    if x.is_finite() {
        x.clamp(0.0, 1.0)
    } else {
        0.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::Vec2;
    use crate::texture::Wrap;

    /// `uniform_bsdf` is `bsdf` bit for bit wherever nothing varies it (no texture, colour of
    /// ones), over materials with every factor drawn at random (coat and sheen on and off, ior
    /// from 1 up); and it declines whenever any one texture feeds the BSDF, so a texture it
    /// forgot would be caught.
    #[test]
    fn uniform_bsdf_is_bsdf_where_nothing_varies_it() {
        let u = |i: u64| crate::sampler::hash_unit(i);
        for k in 0..2000u64 {
            let r = |j: u64| u(16 * k + j);
            let m = Material {
                base_color: Vec4::new(r(0), r(1) * 1.5, r(2), r(3)),
                metallic: r(4),
                roughness: r(5) * 1.2 - 0.1,
                specular: r(6),
                specular_color: Vec3::new(r(7), r(8) * 2.0, r(9)),
                ior: 1.0 + r(10) * 2.0,
                transmission: if k % 3 == 0 { r(11) } else { 0.0 },
                clearcoat: if k % 2 == 0 { r(12) } else { 0.0 },
                clearcoat_roughness: r(13),
                sheen_color: if k % 4 == 1 { Vec3::splat(r(14)) } else { Vec3::ZERO },
                sheen_roughness: r(15),
                ..Material::default()
            };
            let uv = TexCoords([Vec2::new(r(1), r(2)), Vec2::new(r(3), r(4))]);
            let uniform = m.uniform_bsdf().expect("no texture: uniform");
            assert_eq!(format!("{uniform:?}"), format!("{:?}", m.bsdf(&[], uv, Vec4::ONE)), "material {k}");
        }
        let texture = Texture { width: 1, height: 1, texels: vec![[128, 64, 200, 100]], srgb: false };
        let t = Some(TextureRef { texture: 0, wrap_s: Wrap::Repeat, wrap_t: Wrap::Repeat, set: 0, transform: None });
        let slots: [fn(&mut Material) -> &mut Option<TextureRef>; 9] = [
            |m| &mut m.base_color_texture,
            |m| &mut m.metallic_roughness_texture,
            |m| &mut m.specular_texture,
            |m| &mut m.specular_color_texture,
            |m| &mut m.transmission_texture,
            |m| &mut m.clearcoat_texture,
            |m| &mut m.clearcoat_roughness_texture,
            |m| &mut m.sheen_color_texture,
            |m| &mut m.sheen_roughness_texture,
        ];
        for (i, slot) in slots.iter().enumerate() {
            let mut m = Material {
                clearcoat: 0.5,
                clearcoat_roughness: 0.5,
                sheen_color: Vec3::splat(0.5),
                sheen_roughness: 0.5,
                transmission: 0.5,
                ..Material::default()
            };
            *slot(&mut m) = t;
            assert!(m.uniform_bsdf().is_none(), "texture slot {i} feeds the BSDF");
            // ... and it does change it (else the slot would not need to be listed).
            let mut untextured = m.clone();
            *slot(&mut untextured) = None;
            assert_ne!(
                format!("{:?}", m.bsdf(std::slice::from_ref(&texture), TexCoords::default(), Vec4::ONE)),
                format!("{:?}", untextured.bsdf(&[], TexCoords::default(), Vec4::ONE)),
                "texture slot {i}"
            );
        }
    }
}
