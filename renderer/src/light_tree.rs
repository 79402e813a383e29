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

/// The bounds below an interior node X, as the eight lanes of vectors: X's two children (lanes 0
/// and 1) and their children (lanes 2–3 under the first, 4–5 under the second; empty lanes are
/// zero bounds), with what `importance` derives from bounds alone (centroid, half diagonal,
/// sin θo) computed once, by the same operations. [`Family::importance`] runs
/// `LightBounds::importance` on all lanes at once (AVX), operation for operation, so every lane
/// is the one-at-a-time reference's number, bit for bit (a test checks it on random points,
/// normals and bounds), and one evaluation serves two levels of the walk: X's choice and its
/// chosen child's. Kept for the interior nodes at even depth, which is where walks from the
/// root evaluate: 384 bytes each, between a third and two thirds of the N − 1 interior nodes of
/// N lights, so 130–260 bytes a light beside the nodes' own ~120.
#[derive(Clone, Copy, Debug, Default)]
#[repr(C, align(32))]
struct Family {
    c: [[f32; 8]; 3],
    w: [[f32; 8]; 3],
    half_diag: [f32; 8],
    phi: [f32; 8],
    cos_o: [f32; 8],
    sin_o: [f32; 8],
    cos_e: [f32; 8],
    /// All bits set in a two-sided lane.
    two_sided: [u32; 8],
}

impl Family {
    fn new(lanes: [Option<&LightBounds>; 6]) -> Self {
        let mut f = Family::default();
        for (l, x) in lanes.into_iter().enumerate() {
            let Some(x) = x else { continue };
            let c = x.centroid();
            let diag = (x.max - x.min).length();
            for k in 0..3 {
                f.c[k][l] = c[k];
                f.w[k][l] = x.w[k];
            }
            f.half_diag[l] = diag / 2.0;
            f.phi[l] = x.phi;
            f.cos_o[l] = x.cos_theta_o;
            f.sin_o[l] = safe_sqrt(1.0 - x.cos_theta_o * x.cos_theta_o);
            f.cos_e[l] = x.cos_theta_e;
            f.two_sided[l] = if x.two_sided { u32::MAX } else { 0 };
        }
        f
    }

    /// The importance of every lane's bounds at `p` (normal `n`): see `LightBounds::importance`,
    /// whose steps these are, in the same order.
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    #[inline]
    fn importance(&self, p: Vec3, n: Option<Vec3>) -> [f32; 8] {
        // SAFETY: AVX2 is enabled at compile time; every load reads a 32-byte-aligned [f32; 8].
        unsafe { self.importance_avx(p, n) }
    }

    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    #[inline(always)]
    unsafe fn importance_avx(&self, p: Vec3, n: Option<Vec3>) -> [f32; 8] {
        use std::arch::x86_64::*;
        let ld = |a: &[f32; 8]| _mm256_load_ps(a.as_ptr());
        let splat = _mm256_set1_ps;
        let (zero, one) = (_mm256_setzero_ps(), splat(1.0));
        // safe_sqrt: max(x, 0) first (VMAXPS returns its second operand for a NaN, as f32::max does).
        let safe_sqrt = |x: __m256| _mm256_sqrt_ps(_mm256_max_ps(x, zero));
        let select = |m: __m256, a: __m256, b: __m256| _mm256_blendv_ps(b, a, m);
        let dot = |ax: __m256, ay: __m256, az: __m256, bx: __m256, by: __m256, bz: __m256| {
            _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(ax, bx), _mm256_mul_ps(ay, by)), _mm256_mul_ps(az, bz))
        };
        let gt = |a: __m256, b: __m256| _mm256_cmp_ps::<_CMP_GT_OQ>(a, b);
        // cos(max(0, θa − θb)) and sin(max(0, θa − θb)).
        let cos_sub = |sa: __m256, ca: __m256, sb: __m256, cb: __m256| {
            select(gt(ca, cb), one, _mm256_add_ps(_mm256_mul_ps(ca, cb), _mm256_mul_ps(sa, sb)))
        };
        let sin_sub = |sa: __m256, ca: __m256, sb: __m256, cb: __m256| {
            select(gt(ca, cb), zero, _mm256_sub_ps(_mm256_mul_ps(sa, cb), _mm256_mul_ps(ca, sb)))
        };
        let (vx, vy, vz) = (
            _mm256_sub_ps(splat(p.x), ld(&self.c[0])),
            _mm256_sub_ps(splat(p.y), ld(&self.c[1])),
            _mm256_sub_ps(splat(p.z), ld(&self.c[2])),
        );
        let dist2 = dot(vx, vy, vz, vx, vy, vz);
        let half_diag = ld(&self.half_diag);
        let d2 = _mm256_max_ps(dist2, half_diag);
        // normalize_or_zero: v · (1 / |v|) where that reciprocal is finite and positive.
        let rcp = _mm256_div_ps(one, _mm256_sqrt_ps(dist2));
        let abs = |x: __m256| _mm256_andnot_ps(splat(-0.0), x);
        let ok = _mm256_and_ps(_mm256_cmp_ps::<_CMP_LT_OQ>(abs(rcp), splat(f32::INFINITY)), gt(rcp, zero));
        let (wx, wy, wz) = (
            _mm256_and_ps(ok, _mm256_mul_ps(vx, rcp)),
            _mm256_and_ps(ok, _mm256_mul_ps(vy, rcp)),
            _mm256_and_ps(ok, _mm256_mul_ps(vz, rcp)),
        );
        let cos_w = dot(ld(&self.w[0]), ld(&self.w[1]), ld(&self.w[2]), wx, wy, wz);
        let two_sided = _mm256_castsi256_ps(_mm256_load_si256(self.two_sided.as_ptr() as *const __m256i));
        let cos_w = select(two_sided, abs(cos_w), cos_w);
        let sin_w = safe_sqrt(_mm256_sub_ps(one, _mm256_mul_ps(cos_w, cos_w)));
        let r2 = _mm256_mul_ps(half_diag, half_diag);
        let inside = _mm256_cmp_ps::<_CMP_LE_OQ>(dist2, r2);
        let cos_b = select(inside, splat(-1.0), safe_sqrt(_mm256_sub_ps(one, _mm256_div_ps(r2, dist2))));
        let sin_b = safe_sqrt(_mm256_sub_ps(one, _mm256_mul_ps(cos_b, cos_b)));
        let (sin_o, cos_o) = (ld(&self.sin_o), ld(&self.cos_o));
        let cos_x = cos_sub(sin_w, cos_w, sin_o, cos_o);
        let sin_x = sin_sub(sin_w, cos_w, sin_o, cos_o);
        let cos_p = cos_sub(sin_x, cos_x, sin_b, cos_b);
        let lit = gt(cos_p, ld(&self.cos_e));
        let mut imp = _mm256_div_ps(_mm256_mul_ps(ld(&self.phi), cos_p), d2);
        if let Some(n) = n {
            let cos_i = abs(dot(wx, wy, wz, splat(n.x), splat(n.y), splat(n.z)));
            let sin_i = safe_sqrt(_mm256_sub_ps(one, _mm256_mul_ps(cos_i, cos_i)));
            imp = _mm256_mul_ps(imp, cos_sub(sin_i, cos_i, sin_b, cos_b));
        }
        let finite = _mm256_cmp_ps::<_CMP_LT_OQ>(abs(imp), splat(f32::INFINITY));
        let imp = _mm256_and_ps(_mm256_and_ps(lit, finite), _mm256_max_ps(imp, zero));
        let mut out = [0f32; 8];
        _mm256_storeu_ps(out.as_mut_ptr(), imp);
        out
    }
}

/// Where a decision node's two child importances are found: the family evaluated (index into
/// `LightTree::families`) and the first of its two lanes.
#[derive(Clone, Copy, Debug)]
struct Lanes {
    family: u32,
    first: u8,
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
    /// The families ([`Family`]) of the interior nodes at even depth, and for each node where the
    /// importances of its children are found: the walk's hot loop (it was 42 % of a render of
    /// `scenes/sphere_lights`, 4608 emissive triangles) evaluates one family per two levels.
    families: Vec<Family>,
    lanes: Vec<Lanes>,
    /// Evaluate children one at a time with `LightBounds::importance` (the reference the family
    /// evaluation is held to, bit for bit); off except in tests.
    scalar_reference: bool,
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
            families: Vec::new(),
            lanes: Vec::new(),
            scalar_reference: false,
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
        tree.build_families();
        Some(tree)
    }

    /// Families at the even-depth interior nodes; each interior node's lanes: its own family's
    /// 0–1 at even depth, else its parent's 2–3 (first child) or 4–5 (second).
    fn build_families(&mut self) {
        let mut depth = vec![0u32; self.nodes.len()];
        // Children are pushed after their parents, so one forward pass sets every depth.
        for i in 1..self.nodes.len() {
            depth[i] = depth[self.parent[i] as usize] + 1;
        }
        self.lanes = vec![Lanes { family: u32::MAX, first: 0 }; self.nodes.len()];
        for (i, &d) in depth.iter().enumerate() {
            let node = self.nodes[i];
            if node.leaf || d % 2 == 1 {
                continue;
            }
            let kids = [node.index as usize, node.index as usize + 1];
            let grandkids = |k: usize| {
                let c = &self.nodes[k];
                match c.leaf {
                    true => [None, None],
                    false => {
                        [Some(&self.nodes[c.index as usize].bounds), Some(&self.nodes[c.index as usize + 1].bounds)]
                    }
                }
            };
            let [g0, g1] = grandkids(kids[0]);
            let [g2, g3] = grandkids(kids[1]);
            let lanes = [Some(&self.nodes[kids[0]].bounds), Some(&self.nodes[kids[1]].bounds), g0, g1, g2, g3];
            let family = self.families.len() as u32;
            self.families.push(Family::new(lanes));
            self.lanes[i] = Lanes { family, first: 0 };
            for (k, &c) in kids.iter().enumerate() {
                if !self.nodes[c].leaf {
                    self.lanes[c] = Lanes { family, first: 2 + 2 * k as u8 };
                }
            }
        }
    }

    /// Makes the walk evaluate each child alone with `LightBounds::importance` (tests compare).
    pub fn set_scalar_reference(&mut self, on: bool) {
        self.scalar_reference = on;
    }

    /// The importances of interior `node`'s two children at `p`, by the reference (one at a time).
    fn child_importances_scalar(&self, node: usize, p: Vec3, n: Option<Vec3>) -> (f32, f32) {
        let first = self.nodes[node].index as usize;
        (self.nodes[first].bounds.importance(p, n), self.nodes[first + 1].bounds.importance(p, n))
    }

    /// The two children's selection probabilities from their importances.
    #[inline]
    fn probabilities((ia, ib): (f32, f32)) -> Option<(f32, f32)> {
        if ia + ib <= 0.0 {
            return None;
        }
        Some((ia / (ia + ib), ib / (ia + ib)))
    }

    /// The importances of interior `node`'s children at `p`, from its family's evaluation, made
    /// now or kept in `cache` (family index, lanes) from the level above.
    #[inline]
    fn child_importances(&self, node: usize, p: Vec3, n: Option<Vec3>, cache: &mut (u32, [f32; 8])) -> (f32, f32) {
        #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
        if !self.scalar_reference {
            let Lanes { family, first } = self.lanes[node];
            if cache.0 != family {
                *cache = (family, self.families[family as usize].importance(p, n));
            }
            return (cache.1[first as usize], cache.1[first as usize + 1]);
        }
        let _ = cache;
        self.child_importances_scalar(node, p, n)
    }

    /// Chooses a light for point `p`: (light index, probability).
    pub fn sample(&self, p: Vec3, n: Option<Vec3>, mut u: f32) -> Option<(usize, f32)> {
        let root = &self.nodes[0];
        if root.leaf {
            return (root.bounds.importance(p, n) > 0.0).then_some((root.index as usize, 1.0));
        }
        let (mut at, mut pmf) = (0usize, 1.0f32);
        let mut cache = (u32::MAX, [0f32; 8]);
        loop {
            let (pa, _) = Self::probabilities(self.child_importances(at, p, n, &mut cache))?;
            let first = self.nodes[at].index as usize;
            at = if u < pa {
                u = (u / pa).min(1.0 - f32::EPSILON);
                pmf *= pa;
                first
            } else {
                u = ((u - pa) / (1.0 - pa)).min(1.0 - f32::EPSILON);
                pmf *= 1.0 - pa;
                first + 1
            };
            let node = &self.nodes[at];
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
        let mut cache = (u32::MAX, [0f32; 8]);
        while self.parent[child as usize] != u32::MAX {
            let parent = self.parent[child as usize];
            let node = &self.nodes[parent as usize];
            let Some((pa, pb)) = Self::probabilities(self.child_importances(parent as usize, p, n, &mut cache)) else {
                return 0.0;
            };
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

    /// The family (AVX) importance of both children equals `LightBounds::importance` of each, bit
    /// for bit, and so do whole walks (`sample`, `pmf`), over random bounds of every kind.
    #[test]
    fn family_importance_equals_one_at_a_time() {
        let u = crate::sampler::hash_unit;
        let v = |i: u64| Vec3::new(u(i), u(i + 1), u(i + 2)) * 2.0 - 1.0;
        let mut lights = Vec::new();
        for i in 0..300u64 {
            let c = v(20 * i) * 4.0;
            let ext = match i % 4 {
                0 => Vec3::ZERO, // a point light's bounds
                1 => Vec3::splat(0.01),
                _ => (v(20 * i + 3) + 1.0) * 0.5,
            };
            let w = v(20 * i + 6).normalize_or(Vec3::Y);
            lights.push(LightBounds {
                min: c - ext,
                max: c + ext,
                phi: u(20 * i + 9) * 10.0,
                w,
                cos_theta_o: if i % 5 == 0 { -1.0 } else { u(20 * i + 10) * 2.0 - 1.0 },
                cos_theta_e: if i % 3 == 0 { 0.0 } else { u(20 * i + 11) - 1.0 },
                two_sided: i % 7 == 0,
            });
        }
        let mut tree = LightTree::build(&lights).unwrap();
        let (mut compared, mut nonzero) = (0usize, 0usize);
        for k in 0..2000u64 {
            let p = if k % 50 == 0 { lights[k as usize % 300].centroid() } else { v(7 * k + 100_000) * 5.0 };
            let n = (k % 3 != 0).then(|| v(7 * k + 200_000).normalize_or(Vec3::Z));
            for (i, node) in tree.nodes.iter().enumerate() {
                if node.leaf {
                    continue;
                }
                let (a, b) = (&tree.nodes[node.index as usize].bounds, &tree.nodes[node.index as usize + 1].bounds);
                let (pa, pb) = tree.child_importances(i, p, n, &mut (u32::MAX, [0.0; 8]));
                let (sa, sb) = (a.importance(p, n), b.importance(p, n));
                // Equal as numbers (0 and −0 alike) and as bits where non-zero.
                assert!(pa == sa && (pa == 0.0 || pa.to_bits() == sa.to_bits()), "node {i}: {pa} vs {sa}");
                assert!(pb == sb && (pb == 0.0 || pb.to_bits() == sb.to_bits()), "node {i}: {pb} vs {sb}");
                compared += 2;
                nonzero += (sa > 0.0) as usize + (sb > 0.0) as usize;
            }
            let uu = u(7 * k + 5);
            let family = (tree.sample(p, n, uu), (0..300).map(|l| tree.pmf(p, n, l).to_bits()).collect::<Vec<_>>());
            tree.set_scalar_reference(true);
            let scalar = (tree.sample(p, n, uu), (0..300).map(|l| tree.pmf(p, n, l).to_bits()).collect::<Vec<_>>());
            tree.set_scalar_reference(false);
            assert_eq!(family.0.map(|(l, q)| (l, q.to_bits())), scalar.0.map(|(l, q)| (l, q.to_bits())), "point {k}");
            assert_eq!(family.1, scalar.1, "point {k}");
        }
        assert!(compared > 500_000 && nonzero > compared / 4, "{compared} compared, {nonzero} non-zero");
    }

    /// The memory figures `Family`'s doc gives: 384 bytes a family, ~60 a node.
    #[test]
    fn family_and_node_sizes() {
        assert_eq!(std::mem::size_of::<Family>(), 384);
        let node = std::mem::size_of::<Node>();
        assert!((56..=64).contains(&node), "{node} bytes a node");
    }
}
