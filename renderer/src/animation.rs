//! glTF animation: keyframe channels on node translation, rotation, scale and morph-target weights
//! (LINEAR with quaternion slerp, STEP, CUBICSPLINE), evaluated at any time; the node graph they
//! drive; and what a pose moves in a scene — instance transforms, skinned and morphed vertices,
//! cameras, punctual lights (glTF 2.0 §3.11 Animations, §3.7.3 Skins, §3.7.2.2 Morph targets).
//!
//! Posing is a pure function of the time: every frame starts from the rest data kept here, never
//! from the previous frame, so frame N renders the same whatever was rendered before it (the
//! determinism rule extends to frames). What does not move is not rebuilt: every mesh that neither
//! deforms nor emits is an instance whose BVH is built once; a pose updates instance transforms,
//! re-poses the deforming and emitting vertices, and rebuilds only the top-level BVH over them.

use crate::camera::Camera;
use crate::math::{Mat4, Vec3, Vec4};
use crate::mesh::{Instance, Mesh};
use crate::punctual::PunctualLight;
use glam::{Mat3, Quat};

/// Frames per second when the settings give none (Blender's default scene rate).
pub const DEFAULT_FPS: f32 = 24.0;

#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Interpolation {
    Linear,
    Step,
    CubicSpline,
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Property {
    Translation,
    Rotation,
    Scale,
    Weights,
}

/// One animated property of one node.
#[derive(Clone, Debug)]
pub struct Channel {
    pub node: usize,
    pub property: Property,
    pub interpolation: Interpolation,
    /// Key times, strictly increasing, finite.
    pub times: Vec<f32>,
    /// Key values, `width` floats a key (CUBICSPLINE: in-tangent, value, out-tangent per key).
    pub values: Vec<f32>,
    /// Floats per value: 3, 4, or the number of morph targets.
    pub width: usize,
}

impl Channel {
    /// The property's value at time `t` into `out` (`width` floats). Before the first key the first
    /// value holds, after the last the last (glTF: clamp).
    pub fn sample(&self, t: f32, out: &mut [f32]) {
        let w = self.width;
        let n = self.times.len();
        let stride = if self.interpolation == Interpolation::CubicSpline { 3 * w } else { w };
        // The value (not tangent) of key k.
        let value = |k: usize| {
            let at = k * stride + if self.interpolation == Interpolation::CubicSpline { w } else { 0 };
            &self.values[at..at + w]
        };
        if n == 1 || t <= self.times[0] {
            out.copy_from_slice(value(0));
            return;
        }
        if t >= self.times[n - 1] {
            out.copy_from_slice(value(n - 1));
            return;
        }
        // times[k] <= t < times[k + 1]
        let k = self.times.partition_point(|&x| x <= t) - 1;
        let (t0, t1) = (self.times[k], self.times[k + 1]);
        let td = t1 - t0;
        let s = if td > 0.0 { ((t - t0) / td).clamp(0.0, 1.0) } else { 0.0 };
        match self.interpolation {
            Interpolation::Step => out.copy_from_slice(value(k)),
            Interpolation::Linear if self.property == Property::Rotation => {
                let (a, b) = (value(k), value(k + 1));
                let q = Quat::from_xyzw(a[0], a[1], a[2], a[3])
                    .normalize()
                    .slerp(Quat::from_xyzw(b[0], b[1], b[2], b[3]).normalize(), s);
                out.copy_from_slice(&q.to_array());
            }
            Interpolation::Linear => {
                let (a, b) = (value(k), value(k + 1));
                for i in 0..w {
                    out[i] = a[i] + (b[i] - a[i]) * s;
                }
            }
            Interpolation::CubicSpline => {
                // Hermite spline (glTF 2.0 Appendix C): out-tangent of k, in-tangent of k + 1,
                // both scaled by the interval.
                let p0 = value(k);
                let p1 = value(k + 1);
                let m0 = &self.values[k * stride + 2 * w..k * stride + 3 * w];
                let m1 = &self.values[(k + 1) * stride..(k + 1) * stride + w];
                let (s2, s3) = (s * s, s * s * s);
                let (h00, h10, h01, h11) =
                    (2.0 * s3 - 3.0 * s2 + 1.0, s3 - 2.0 * s2 + s, -2.0 * s3 + 3.0 * s2, s3 - s2);
                for i in 0..w {
                    out[i] = h00 * p0[i] + h10 * td * m0[i] + h01 * p1[i] + h11 * td * m1[i];
                }
                if self.property == Property::Rotation {
                    let q = Quat::from_slice(out).normalize();
                    out.copy_from_slice(&q.to_array());
                }
            }
        }
    }
}

/// A glTF animation: its name and channels.
#[derive(Clone, Debug)]
pub struct Clip {
    pub name: Option<String>,
    pub channels: Vec<Channel>,
}

/// A node's rest transform: TRS (animatable) or a matrix (not animatable, glTF §3.11).
#[derive(Clone, Copy, Debug)]
pub enum RestTransform {
    Trs { translation: Vec3, rotation: Quat, scale: Vec3 },
    Matrix(Mat4),
}

/// The node hierarchy: parents come before children in `order`.
#[derive(Clone, Debug, Default)]
pub struct NodeGraph {
    pub parent: Vec<Option<usize>>,
    pub rest: Vec<RestTransform>,
    /// Default morph weights per node (node's, else its mesh's), empty without targets.
    pub weights: Vec<Vec<f32>>,
    /// Nodes in an order where every parent precedes its children (only nodes of the scene).
    pub order: Vec<usize>,
}

/// World transforms and morph weights of every node at one time.
pub struct Pose {
    pub world: Vec<Mat4>,
    pub weights: Vec<Vec<f32>>,
}

/// Morph target deltas of one primitive (each parallel to its vertices; empty when absent).
#[derive(Clone, Debug, Default)]
pub struct MorphTarget {
    pub positions: Vec<Vec3>,
    pub normals: Vec<Vec3>,
    pub tangents: Vec<Vec3>,
}

/// A skin: joint nodes and their inverse bind matrices.
#[derive(Clone, Debug)]
pub struct Skin {
    pub joints: Vec<usize>,
    pub inverse_bind: Vec<Mat4>,
}

/// A primitive whose vertices a pose rewrites in `Mesh` (world-space storage): it deforms (skin,
/// morph targets) or emits light (lights are world-space triangles).
#[derive(Clone, Debug)]
pub struct Posed {
    pub node: usize,
    /// Its vertices in `Mesh`: `first..first + positions.len()`.
    pub first: usize,
    /// Rest (object-space) attributes; normals/tangents empty when the primitive has none.
    pub positions: Vec<Vec3>,
    pub normals: Vec<Vec3>,
    pub tangents: Vec<Vec4>,
    pub targets: Vec<MorphTarget>,
    /// Skin index, and up to 8 influences a vertex (JOINTS_0/1, WEIGHTS_0/1).
    pub skin: Option<usize>,
    pub influences: Vec<[(u16, f32); 8]>,
}

/// Everything a pose needs: the graph, the clips that play, and what they move.
#[derive(Clone, Debug, Default)]
pub struct Animator {
    pub graph: NodeGraph,
    pub clips: Vec<Clip>,
    /// Indices into `clips` that play (default: all, as Blender writes one per object).
    pub playing: Vec<usize>,
    pub skins: Vec<Skin>,
    /// Mesh instance k is placed by node `instance_nodes[k].0`, times the local transform `.1`
    /// (EXT_mesh_gpu_instancing's, else identity).
    pub instance_nodes: Vec<(usize, Mat4)>,
    pub posed: Vec<Posed>,
    /// Cameras: (node, yfov, aspect ratio), in `Scene::cameras` order.
    pub cameras: Vec<(usize, f32, Option<f32>)>,
    /// Punctual lights: (node, the light with position/direction at the node's origin and −Z).
    pub lights: Vec<(usize, PunctualLight)>,
}

/// Why a clip choice failed.
#[derive(Debug)]
pub struct NoSuchAnimation(pub String);

impl Animator {
    /// Whether anything moves or deforms at all.
    pub fn is_active(&self) -> bool {
        !self.playing.is_empty() || self.posed.iter().any(|p| p.skin.is_some() || !p.targets.is_empty())
    }

    /// Plays the clip named `choice` (or with that index), or all clips for `None`.
    pub fn select(&mut self, choice: Option<&str>) -> Result<(), NoSuchAnimation> {
        self.playing = match choice {
            None => (0..self.clips.len()).collect(),
            Some(c) => {
                let by_name = self.clips.iter().position(|clip| clip.name.as_deref() == Some(c));
                match by_name.or_else(|| c.parse::<usize>().ok().filter(|&i| i < self.clips.len())) {
                    Some(i) => vec![i],
                    None => {
                        let names: Vec<String> = self
                            .clips
                            .iter()
                            .enumerate()
                            .map(|(i, c)| format!("{i} '{}'", c.name.as_deref().unwrap_or("")))
                            .collect();
                        return Err(NoSuchAnimation(format!(
                            "no animation '{c}' (the file has {}: {})",
                            self.clips.len(),
                            names.join(", ")
                        )));
                    }
                }
            }
        };
        Ok(())
    }

    /// Node world transforms and weights at time `t` (seconds).
    pub fn pose(&self, t: f32) -> Pose {
        let g = &self.graph;
        let n = g.parent.len();
        let mut trs: Vec<Option<(Vec3, Quat, Vec3)>> = g
            .rest
            .iter()
            .map(|r| match *r {
                RestTransform::Trs { translation, rotation, scale } => Some((translation, rotation, scale)),
                RestTransform::Matrix(_) => None,
            })
            .collect();
        let mut weights = g.weights.clone();
        let mut buf = Vec::new();
        for &c in &self.playing {
            for ch in &self.clips[c].channels {
                buf.resize(ch.width, 0.0);
                ch.sample(t, &mut buf);
                match (ch.property, trs.get_mut(ch.node)) {
                    (Property::Translation, Some(Some(x))) => x.0 = Vec3::from_slice(&buf),
                    (Property::Rotation, Some(Some(x))) => x.1 = Quat::from_slice(&buf).normalize(),
                    (Property::Scale, Some(Some(x))) => x.2 = Vec3::from_slice(&buf),
                    (Property::Weights, _) => {
                        if let Some(w) = weights.get_mut(ch.node) {
                            w.clear();
                            w.extend_from_slice(&buf);
                        }
                    }
                    _ => {}
                }
            }
        }
        let mut world = vec![Mat4::IDENTITY; n];
        for &i in &g.order {
            let local = match (trs[i], g.rest[i]) {
                (Some((t, r, s)), _) => Mat4::from_scale_rotation_translation(s, r, t),
                (None, RestTransform::Matrix(m)) => m,
                (None, RestTransform::Trs { .. }) => Mat4::IDENTITY,
            };
            world[i] = match g.parent[i] {
                Some(p) => world[p] * local,
                None => local,
            };
        }
        Pose { world, weights }
    }

    /// Applies the pose at time `t`: instance transforms, posed vertices, cameras, lights.
    /// Returns the lights (the caller rebuilds the light set and the top-level BVH).
    pub fn apply(&self, t: f32, mesh: &mut Mesh, cameras: &mut [Camera]) -> Vec<PunctualLight> {
        let pose = self.pose(t);
        for (k, &(node, local)) in self.instance_nodes.iter().enumerate() {
            if let Some(inst) = mesh.instances.get_mut(k) {
                match Instance::new(inst.prototype, pose.world[node] * local) {
                    Some(new) => *inst = new,
                    // A singular transform (a scale animated to 0 hides an object): not drawn.
                    None => inst.visible = false,
                }
            }
        }
        // A pose that carries an instance past the usable range hides it, as a singular one does.
        if !self.instance_nodes.is_empty() {
            let boxes = mesh.prototype_bounds();
            for inst in mesh.instances.iter_mut().take(self.instance_nodes.len()) {
                if boxes.get(inst.prototype as usize).is_some_and(|&bx| Mesh::instance_box(inst, bx).is_none()) {
                    inst.visible = false;
                }
            }
        }
        for p in &self.posed {
            self.apply_posed(p, &pose, mesh);
        }
        for (c, &(node, yfov, aspect)) in cameras.iter_mut().zip(&self.cameras) {
            if let Some(cam) = Camera::from_matrix(pose.world[node], yfov, aspect) {
                *c = cam;
            }
        }
        self.lights
            .iter()
            .map(|&(node, l)| {
                let m = pose.world[node];
                let direction = m.transform_vector3(-Vec3::Z).normalize_or(l.direction);
                PunctualLight { position: m.transform_point3(Vec3::ZERO), direction, ..l }
            })
            .collect()
    }

    fn apply_posed(&self, p: &Posed, pose: &Pose, mesh: &mut Mesh) {
        let n = p.positions.len();
        let weights = pose.weights.get(p.node).map(Vec::as_slice).unwrap_or(&[]);
        // Morph targets first (in object space), then the skin or the node transform.
        let mut pos = p.positions.clone();
        let mut nrm = p.normals.clone();
        let mut tan: Vec<Vec3> = p.tangents.iter().map(|t| t.truncate()).collect();
        for (target, &w) in p.targets.iter().zip(weights) {
            if w == 0.0 || !w.is_finite() {
                continue;
            }
            for (v, d) in pos.iter_mut().zip(&target.positions) {
                *v += w * *d;
            }
            for (v, d) in nrm.iter_mut().zip(&target.normals) {
                *v += w * *d;
            }
            for (v, d) in tan.iter_mut().zip(&target.tangents) {
                *v += w * *d;
            }
        }
        let skin = p.skin.and_then(|s| self.skins.get(s));
        let joint_matrices: Vec<Mat4> = match skin {
            Some(s) => s
                .joints
                .iter()
                .zip(&s.inverse_bind)
                .map(|(&j, ibm)| pose.world.get(j).copied().unwrap_or(Mat4::IDENTITY) * *ibm)
                .collect(),
            None => Vec::new(),
        };
        let node_world = pose.world[p.node];
        #[allow(clippy::needless_range_loop)] // i indexes six parallel arrays and the mesh storage
        for i in 0..n {
            let m = if skin.is_some() {
                // Σ wᵢ · joint matrix ᵢ (glTF §3.7.3.3); weights renormalised against rounding.
                let mut m = Mat4::ZERO;
                let mut total = 0.0;
                for &(j, w) in &p.influences[i] {
                    if w > 0.0 {
                        if let Some(jm) = joint_matrices.get(j as usize) {
                            m += *jm * w;
                            total += w;
                        }
                    }
                }
                if total > 0.0 {
                    m * (1.0 / total)
                } else {
                    node_world
                }
            } else {
                node_world
            };
            let out = p.first + i;
            let wp = m.transform_point3(pos[i]);
            // A pose that throws a vertex past the usable range keeps its last position (as a
            // non-finite one does): the BVH and the lights' areas need bounded coordinates.
            if crate::mesh::is_usable_position(wp) {
                mesh.positions[out] = wp;
            }
            if !nrm.is_empty() || !tan.is_empty() {
                let linear = Mat3::from_mat4(m);
                if let Some(nv) = nrm.get(i) {
                    let normal_m = linear.inverse().transpose();
                    let w = (normal_m * *nv).normalize_or_zero();
                    if w.is_finite() && out < mesh.normals.len() {
                        mesh.normals[out] = w;
                    }
                }
                if let (Some(tv), Some(rest)) = (tan.get(i), p.tangents.get(i)) {
                    let w = (linear * *tv).normalize_or_zero();
                    if w.is_finite() && out < mesh.tangents.len() {
                        mesh.tangents[out] = w.extend(rest.w);
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn channel(
        property: Property,
        interpolation: Interpolation,
        times: &[f32],
        values: &[f32],
        width: usize,
    ) -> Channel {
        Channel { node: 0, property, interpolation, times: times.to_vec(), values: values.to_vec(), width }
    }

    #[test]
    fn linear_step_and_clamping() {
        let c = channel(Property::Translation, Interpolation::Linear, &[1.0, 3.0], &[0.0, 0.0, 0.0, 4.0, 2.0, 0.0], 3);
        let mut out = [0.0; 3];
        c.sample(2.0, &mut out);
        assert_eq!(out, [2.0, 1.0, 0.0]);
        c.sample(0.0, &mut out);
        assert_eq!(out, [0.0, 0.0, 0.0], "before the first key: the first value");
        c.sample(9.0, &mut out);
        assert_eq!(out, [4.0, 2.0, 0.0], "after the last key: the last value");
        let s = Channel { interpolation: Interpolation::Step, ..c };
        s.sample(2.9, &mut out);
        assert_eq!(out, [0.0, 0.0, 0.0]);
        s.sample(3.0, &mut out);
        assert_eq!(out, [4.0, 2.0, 0.0]);
    }

    #[test]
    fn rotations_slerp_at_constant_angular_speed() {
        let a = Quat::IDENTITY;
        let b = Quat::from_rotation_y(2.0);
        let v: Vec<f32> = a.to_array().into_iter().chain(b.to_array()).collect();
        let c = channel(Property::Rotation, Interpolation::Linear, &[0.0, 1.0], &v, 4);
        let mut out = [0.0; 4];
        c.sample(0.25, &mut out);
        let q = Quat::from_slice(&out);
        assert!(q.angle_between(Quat::from_rotation_y(0.5)) < 1e-5, "{q:?}");
    }

    #[test]
    fn cubic_spline_is_hermite() {
        // One scalar weight: keys at 0 and 2, values 0 and 1, out-tangent 1 at the first, in-tangent
        // 0 at the second. p(s) = h10·td·m0 + h01·p1 with td = 2.
        let v = [0.0, 0.0, 1.0, 0.0, 1.0, 0.0];
        let c = channel(Property::Weights, Interpolation::CubicSpline, &[0.0, 2.0], &v, 1);
        let mut out = [0.0];
        c.sample(1.0, &mut out);
        let s = 0.5f32;
        let expect = (s * s * s - 2.0 * s * s + s) * 2.0 * 1.0 + (-2.0 * s * s * s + 3.0 * s * s);
        assert!((out[0] - expect).abs() < 1e-6, "{} vs {expect}", out[0]);
        c.sample(2.0, &mut out);
        assert_eq!(out[0], 1.0);
    }
}
