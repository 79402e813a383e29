//! A bounding-volume hierarchy over lights for many-light sampling: each node bounds its lights'
//! positions, total power and emission directions (a cone), and a light is chosen by walking down the
//! tree, picking a child in proportion to an importance estimate for the shading point (pbrt-v4
//! §12.6.3 `BVHLightSampler` and `LightBounds::Importance`; Conty & Kulla 2018, "Importance Sampling of
//! Many Lights with Adaptive Tree Splitting"). `pmf()` retraces the same walk, so MIS can ask for
//! the probability of any light at any point.

use crate::math::{Vec3, PI};

/// Spatial and directional bounds of one or more lights.
#[derive(Clone, Copy, Debug)]
pub struct LightBounds {
    pub min: Vec3,
    pub max: Vec3,
    /// Emitted power (luminance).
    pub phi: f32,
    /// Emission cone: axis, cos of its spread θo, and cos of the falloff θe beyond it.
    pub w: Vec3,
    pub cos_theta_o: f32,
    pub cos_theta_e: f32,
    pub two_sided: bool,
}

#[inline]
fn safe_sqrt(x: f32) -> f32 {
    x.max(0.0).sqrt()
}

/// cos(max(0, θa − θb)) from sines and cosines.
#[inline]
fn cos_sub_clamped(sin_a: f32, cos_a: f32, sin_b: f32, cos_b: f32) -> f32 {
    if cos_a > cos_b {
        1.0
    } else {
        cos_a * cos_b + sin_a * sin_b
    }
}

/// sin(max(0, θa − θb)).
#[inline]
fn sin_sub_clamped(sin_a: f32, cos_a: f32, sin_b: f32, cos_b: f32) -> f32 {
    if cos_a > cos_b {
        0.0
    } else {
        sin_a * cos_b - cos_a * sin_b
    }
}

/// Rotates `v` about the unit axis `k` by `angle` (Rodrigues).
fn rotate(v: Vec3, k: Vec3, angle: f32) -> Vec3 {
    let (s, c) = angle.sin_cos();
    v * c + k.cross(v) * s + k * k.dot(v) * (1.0 - c)
}

impl LightBounds {
    /// Union of two bounds (cones merged as in pbrt-v4 `DirectionCone::Union`).
    pub fn union(a: &LightBounds, b: &LightBounds) -> LightBounds {
        if a.phi == 0.0 {
            return *b;
        }
        if b.phi == 0.0 {
            return *a;
        }
        let (w, cos_theta_o) = {
            let (ta, tb) = (a.cos_theta_o.clamp(-1.0, 1.0).acos(), b.cos_theta_o.clamp(-1.0, 1.0).acos());
            let td = a.w.dot(b.w).clamp(-1.0, 1.0).acos();
            if (td + tb).min(PI) <= ta {
                (a.w, a.cos_theta_o)
            } else if (td + ta).min(PI) <= tb {
                (b.w, b.cos_theta_o)
            } else {
                let to = (ta + td + tb) / 2.0;
                let axis = a.w.cross(b.w);
                if to >= PI || axis.length_squared() < 1e-12 {
                    (a.w, -1.0)
                } else {
                    (rotate(a.w, axis.normalize(), to - ta).normalize(), to.cos())
                }
            }
        };
        LightBounds {
            min: a.min.min(b.min),
            max: a.max.max(b.max),
            phi: a.phi + b.phi,
            w,
            cos_theta_o,
            cos_theta_e: a.cos_theta_e.min(b.cos_theta_e),
            two_sided: a.two_sided || b.two_sided,
        }
    }

    pub fn centroid(&self) -> Vec3 {
        (self.min + self.max) * 0.5
    }

    /// Conservative estimate of the light these bounds can send to `p` (on a surface with normal `n`,
    /// if given): power / distance², reduced by the angle between the cone and `p`.
    pub fn importance(&self, p: Vec3, n: Option<Vec3>) -> f32 {
        let pc = self.centroid();
        let diag = (self.max - self.min).length();
        let d2 = (p - pc).length_squared().max(diag / 2.0);
        let wi = (p - pc).normalize_or_zero();
        let mut cos_w = self.w.dot(wi);
        if self.two_sided {
            cos_w = cos_w.abs();
        }
        let sin_w = safe_sqrt(1.0 - cos_w * cos_w);
        // Angle subtended by the bounds' bounding sphere as seen from p.
        let r2 = (diag / 2.0) * (diag / 2.0);
        let dist2 = (p - pc).length_squared();
        let cos_b = if dist2 <= r2 { -1.0 } else { safe_sqrt(1.0 - r2 / dist2) };
        let sin_b = safe_sqrt(1.0 - cos_b * cos_b);
        let sin_o = safe_sqrt(1.0 - self.cos_theta_o * self.cos_theta_o);
        let cos_x = cos_sub_clamped(sin_w, cos_w, sin_o, self.cos_theta_o);
        let sin_x = sin_sub_clamped(sin_w, cos_w, sin_o, self.cos_theta_o);
        let cos_p = cos_sub_clamped(sin_x, cos_x, sin_b, cos_b);
        if cos_p <= self.cos_theta_e {
            return 0.0;
        }
        let mut importance = self.phi * cos_p / d2;
        if let Some(n) = n {
            let cos_i = wi.dot(n).abs();
            let sin_i = safe_sqrt(1.0 - cos_i * cos_i);
            importance *= cos_sub_clamped(sin_i, cos_i, sin_b, cos_b);
        }
        if importance.is_finite() {
            importance.max(0.0)
        } else {
            0.0
        }
    }
}

#[derive(Clone, Copy, Debug)]
struct Node {
    bounds: LightBounds,
    /// Interior: index of the first child (the second follows). Leaf: the light index.
    index: u32,
    leaf: bool,
}

pub struct LightTree {
    nodes: Vec<Node>,
    /// For each light: its leaf's node index.
    leaf_of: Vec<u32>,
    /// For each node: its parent (root: u32::MAX).
    parent: Vec<u32>,
}

impl LightTree {
    /// Builds the tree over `lights` (light index = position). Splits at the median of the longest
    /// centroid axis.
    pub fn build(lights: &[LightBounds]) -> Option<Self> {
        if lights.is_empty() {
            return None;
        }
        let mut tree = LightTree {
            nodes: Vec::with_capacity(2 * lights.len()),
            leaf_of: vec![0; lights.len()],
            parent: Vec::new(),
        };
        let mut idx: Vec<u32> = (0..lights.len() as u32).collect();
        tree.nodes.push(Node { bounds: lights[0], index: 0, leaf: true });
        tree.parent.push(u32::MAX);
        // (node, range in idx)
        let mut work = vec![(0usize, 0usize, lights.len())];
        while let Some((node, lo, hi)) = work.pop() {
            let mut b = lights[idx[lo] as usize];
            for &i in &idx[lo + 1..hi] {
                b = LightBounds::union(&b, &lights[i as usize]);
            }
            if hi - lo == 1 {
                tree.nodes[node] = Node { bounds: b, index: idx[lo], leaf: true };
                tree.leaf_of[idx[lo] as usize] = node as u32;
                continue;
            }
            let (mut cmin, mut cmax) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
            for &i in &idx[lo..hi] {
                let c = lights[i as usize].centroid();
                cmin = cmin.min(c);
                cmax = cmax.max(c);
            }
            let ext = cmax - cmin;
            let axis = if ext.x >= ext.y && ext.x >= ext.z {
                0
            } else if ext.y >= ext.z {
                1
            } else {
                2
            };
            let mid = (lo + hi) / 2;
            idx[lo..hi].select_nth_unstable_by(mid - lo, |a, b| {
                lights[*a as usize].centroid()[axis].total_cmp(&lights[*b as usize].centroid()[axis])
            });
            let first = tree.nodes.len();
            for _ in 0..2 {
                tree.nodes.push(Node { bounds: b, index: 0, leaf: true });
                tree.parent.push(node as u32);
            }
            tree.nodes[node] = Node { bounds: b, index: first as u32, leaf: false };
            work.push((first, lo, mid));
            work.push((first + 1, mid, hi));
        }
        Some(tree)
    }

    /// The two children's selection probabilities at interior `node` for point `p`.
    #[inline]
    fn child_probabilities(&self, node: &Node, p: Vec3, n: Option<Vec3>) -> Option<(f32, f32)> {
        let (a, b) = (&self.nodes[node.index as usize], &self.nodes[node.index as usize + 1]);
        let (ia, ib) = (a.bounds.importance(p, n), b.bounds.importance(p, n));
        if ia + ib <= 0.0 {
            return None;
        }
        Some((ia / (ia + ib), ib / (ia + ib)))
    }

    /// Chooses a light for point `p`: (light index, probability).
    pub fn sample(&self, p: Vec3, n: Option<Vec3>, mut u: f32) -> Option<(usize, f32)> {
        let mut node = &self.nodes[0];
        let mut pmf = 1.0f32;
        if node.leaf {
            return (node.bounds.importance(p, n) > 0.0).then_some((node.index as usize, 1.0));
        }
        loop {
            let (pa, _) = self.child_probabilities(node, p, n)?;
            let child = if u < pa {
                u = (u / pa).min(1.0 - f32::EPSILON);
                pmf *= pa;
                node.index as usize
            } else {
                u = ((u - pa) / (1.0 - pa)).min(1.0 - f32::EPSILON);
                pmf *= 1.0 - pa;
                node.index as usize + 1
            };
            node = &self.nodes[child];
            if node.leaf {
                return (pmf > 0.0).then_some((node.index as usize, pmf));
            }
        }
    }

    /// Probability that `sample(p, n, ·)` picks `light`.
    pub fn pmf(&self, p: Vec3, n: Option<Vec3>, light: usize) -> f32 {
        let Some(&leaf) = self.leaf_of.get(light) else { return 0.0 };
        if self.nodes[0].leaf {
            return if self.nodes[0].bounds.importance(p, n) > 0.0 { 1.0 } else { 0.0 };
        }
        let mut pmf = 1.0f32;
        let mut child = leaf;
        while self.parent[child as usize] != u32::MAX {
            let parent = self.parent[child as usize];
            let node = &self.nodes[parent as usize];
            let Some((pa, pb)) = self.child_probabilities(node, p, n) else { return 0.0 };
            pmf *= if child == node.index { pa } else { pb };
            child = parent;
        }
        pmf
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tri_light(c: Vec3, normal: Vec3, phi: f32) -> LightBounds {
        LightBounds {
            min: c - Vec3::splat(0.05),
            max: c + Vec3::splat(0.05),
            phi,
            w: normal,
            cos_theta_o: 1.0,
            cos_theta_e: 0.0,
            two_sided: false,
        }
    }

    #[test]
    fn pmf_sums_to_one_and_matches_sampling_frequencies() {
        let mut lights = Vec::new();
        for i in 0..37 {
            let a = i as f32 * 0.7;
            lights.push(tri_light(
                Vec3::new(a.cos() * 3.0, 2.0 + (i % 5) as f32 * 0.3, a.sin() * 3.0),
                -Vec3::Y,
                1.0 + (i % 7) as f32,
            ));
        }
        let tree = LightTree::build(&lights).unwrap();
        for p in [Vec3::ZERO, Vec3::new(2.5, 0.0, 0.3), Vec3::new(0.0, 1.0, -2.0)] {
            let n = Some(Vec3::Y);
            let total: f32 = (0..lights.len()).map(|l| tree.pmf(p, n, l)).sum();
            assert!((total - 1.0).abs() < 1e-4, "pmf sums to {total}");
            let m = 200_000;
            let mut counts = vec![0usize; lights.len()];
            for k in 0..m {
                let (l, pmf) = tree.sample(p, n, (k as f32 + 0.5) / m as f32).unwrap();
                assert!((pmf - tree.pmf(p, n, l)).abs() <= 1e-5 * pmf.max(1e-3));
                counts[l] += 1;
            }
            for (l, &c) in counts.iter().enumerate() {
                let f = c as f32 / m as f32;
                assert!((f - tree.pmf(p, n, l)).abs() < 2e-3, "light {l}: {f} vs {}", tree.pmf(p, n, l));
            }
        }
    }

    #[test]
    fn lights_facing_away_get_no_samples_and_near_lights_more() {
        let p = Vec3::ZERO;
        let near_far = LightTree::build(&[
            tri_light(Vec3::new(0.0, 1.0, 0.0), -Vec3::Y, 1.0),
            tri_light(Vec3::new(0.0, 10.0, 0.0), -Vec3::Y, 1.0),
        ])
        .unwrap();
        assert!(
            near_far.pmf(p, Some(Vec3::Y), 0) > 10.0 * near_far.pmf(p, Some(Vec3::Y), 1),
            "the near light dominates"
        );
        let away = LightTree::build(&[
            tri_light(Vec3::new(0.0, 1.0, 0.0), -Vec3::Y, 1.0),
            tri_light(Vec3::new(0.5, 2.0, 0.0), Vec3::Y, 50.0),
        ])
        .unwrap();
        assert_eq!(away.pmf(p, Some(Vec3::Y), 1), 0.0, "a one-sided light facing away");
        assert_eq!(away.pmf(p, Some(Vec3::Y), 0), 1.0);
    }
}
