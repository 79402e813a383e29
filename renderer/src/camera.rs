//! Pinhole perspective camera with glTF conventions: looks down its local −Z, +Y up, `yfov` is the
//! full vertical field of view. The horizontal extent follows the *image* aspect ratio (as Blender
//! and Mitsuba with `fov_axis = y` do), so a `--width/--height` that differs from the file's
//! `aspectRatio` widens or narrows the view instead of stretching it.

use crate::math::{Mat4, Vec2, Vec3};

#[derive(Clone, Copy, Debug)]
pub struct Camera {
    pub origin: Vec3,
    /// Orthonormal camera axes in world space.
    pub right: Vec3,
    pub up: Vec3,
    pub forward: Vec3,
    pub yfov: f32,
    /// aspectRatio from the file, if any (used only to choose a default image size).
    pub aspect_ratio: Option<f32>,
}

impl Camera {
    /// From a node's world matrix (scale is removed: glTF says camera nodes should not be scaled,
    /// and a scaled one must not skew rays).
    pub fn from_matrix(world: Mat4, yfov: f32, aspect_ratio: Option<f32>) -> Option<Self> {
        let origin = world.w_axis.truncate();
        let right = world.x_axis.truncate().normalize_or_zero();
        let up0 = world.y_axis.truncate();
        let forward = (-world.z_axis.truncate()).normalize_or_zero();
        if right == Vec3::ZERO || forward == Vec3::ZERO || !origin.is_finite() {
            return None;
        }
        // Re-orthogonalize so a slightly sheared matrix still yields an orthonormal basis.
        let up = (up0 - forward * forward.dot(up0)).normalize_or_zero();
        let up = if up == Vec3::ZERO { right.cross(forward) } else { up };
        let right = forward.cross(up);
        if !(yfov > 0.0 && yfov < std::f32::consts::PI) {
            return None;
        }
        Some(Camera { origin, right, up, forward, yfov, aspect_ratio })
    }

    /// A default view of a bounding box: from +Z (the glTF "front"), slightly above, framing the
    /// bounding sphere with a 40° vertical field of view.
    pub fn framing(min: Vec3, max: Vec3) -> Self {
        let center = (min + max) * 0.5;
        let radius = ((max - min).length() * 0.5).max(1e-3);
        let yfov = 40f32.to_radians();
        let dist = radius / (yfov * 0.5).sin() * 1.05;
        let dir = Vec3::new(0.0, 0.25, 1.0).normalize();
        let origin = center + dir * dist;
        let forward = (center - origin).normalize();
        let right = forward.cross(Vec3::Y).normalize();
        let up = right.cross(forward);
        Camera { origin, right, up, forward, yfov, aspect_ratio: None }
    }

    /// Primary ray direction (unit) through film position `film` in pixels, (0,0) = top-left corner.
    #[inline]
    pub fn ray_direction(&self, film: Vec2, width: u32, height: u32) -> Vec3 {
        self.raster(width, height).direction(film)
    }

    /// [`Self::ray_direction`] for many rays of one image: the field of view's tangent (a libm
    /// call) and the aspect ratio taken once.
    pub fn raster(&self, width: u32, height: u32) -> Raster {
        Raster {
            camera: *self,
            tan_half: (self.yfov * 0.5).tan(),
            aspect: width as f32 / height as f32,
            width: width as f32,
            height: height as f32,
        }
    }
}

/// A camera seen through an image of a given size (see [`Camera::raster`]).
#[derive(Clone, Copy, Debug)]
pub struct Raster {
    camera: Camera,
    tan_half: f32,
    aspect: f32,
    width: f32,
    height: f32,
}

impl Raster {
    /// The unit direction through film position `film` (pixels from the top-left corner).
    #[inline]
    pub fn direction(&self, film: Vec2) -> Vec3 {
        let c = &self.camera;
        let x = (2.0 * film.x / self.width - 1.0) * self.tan_half * self.aspect;
        let y = (1.0 - 2.0 * film.y / self.height) * self.tan_half;
        (c.forward + c.right * x + c.up * y).normalize()
    }

    /// [`Self::direction`] for eight film positions, each lane in its operations and order
    /// (glam's `normalize`: times 1/√(x² + y² + z²)), so the same bits.
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    #[inline(always)]
    pub(crate) fn directions8(&self, fx: crate::lanes::F8, fy: crate::lanes::F8) -> crate::lanes::V8 {
        use crate::lanes::{F8, V8};
        use std::ops::Add;
        let c = &self.camera;
        let (one, two) = (F8::splat(1.0), F8::splat(2.0));
        let x = (two * fx / F8::splat(self.width) - one) * F8::splat(self.tan_half) * F8::splat(self.aspect);
        let y = (one - two * fy / F8::splat(self.height)) * F8::splat(self.tan_half);
        let d = V8::splat(c.forward).add(V8::splat(c.right).scale(x)).add(V8::splat(c.up).scale(y));
        d.scale(one / d.dot(d).sqrt())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn centre_pixel_looks_forward_and_corners_match_fov() {
        let cam = Camera::from_matrix(Mat4::IDENTITY, 90f32.to_radians(), None).unwrap();
        let d = cam.ray_direction(Vec2::new(50.0, 50.0), 100, 100);
        assert!((d - Vec3::new(0.0, 0.0, -1.0)).length() < 1e-6);
        let top = cam.ray_direction(Vec2::new(50.0, 0.0), 100, 100);
        assert!((top.y - top.z.abs()).abs() < 1e-5, "45° half angle: {top:?}");
        let left = cam.ray_direction(Vec2::new(0.0, 50.0), 200, 100);
        assert!((left.x + 2.0 * left.z.abs()).abs() < 1e-5, "aspect 2: {left:?}");
    }

    #[test]
    fn framing_sees_the_box_centre() {
        let cam = Camera::framing(Vec3::splat(-1.0), Vec3::splat(1.0));
        assert!((cam.forward - (-cam.origin).normalize()).length() < 1e-4);
    }
}
