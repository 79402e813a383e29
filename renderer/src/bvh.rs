//! Our own BVH: a binary tree built with binned SAH (Wald 2007, "On fast Construction of SAH-based
//! Bounding Volume Hierarchies"), traversed with a stack and near-child-first ordering. It exists to
//! measure `obvhs`'s CWBVH against (`tessera bench --accel own`), and as a fallback with no SIMD.

use crate::math::{Vec3, Vec3A};
use crate::triangle::RtTriangle;

#[derive(Clone, Copy, Debug)]
struct Node {
    min: Vec3A,
    max: Vec3A,
    /// Leaf: first triangle; interior: index of the left child (the right child follows it).
    first: u32,
    /// Number of triangles in a leaf, 0 for an interior node.
    count: u32,
}

pub struct Bvh {
    nodes: Vec<Node>,
    pub tris: Vec<RtTriangle>,
}

const BINS: usize = 16;
const MAX_LEAF: usize = 4;

#[derive(Clone, Copy)]
struct Bounds {
    min: Vec3A,
    max: Vec3A,
}

impl Bounds {
    const EMPTY: Bounds = Bounds { min: Vec3A::splat(f32::INFINITY), max: Vec3A::splat(f32::NEG_INFINITY) };
    fn grow(&mut self, p: Vec3A) {
        self.min = self.min.min(p);
        self.max = self.max.max(p);
    }
    fn join(&mut self, b: &Bounds) {
        self.min = self.min.min(b.min);
        self.max = self.max.max(b.max);
    }
    fn area(&self) -> f32 {
        let d = (self.max - self.min).max(Vec3A::ZERO);
        d.x * d.y + d.y * d.z + d.z * d.x
    }
}

fn tri_bounds(t: &RtTriangle) -> Bounds {
    let mut b = Bounds::EMPTY;
    t.v.iter().for_each(|&p| b.grow(p));
    b
}

impl Bvh {
    pub fn build(mut tris: Vec<RtTriangle>) -> Self {
        let bounds: Vec<Bounds> = tris.iter().map(tri_bounds).collect();
        let centroids: Vec<Vec3A> = bounds.iter().map(|b| (b.min + b.max) * 0.5).collect();
        let mut order: Vec<u32> = (0..tris.len() as u32).collect();
        let mut nodes = vec![Node { min: Vec3A::ZERO, max: Vec3A::ZERO, first: 0, count: 0 }];
        // Work list of (node, start, end) ranges in `order`.
        let mut work = vec![(0usize, 0usize, tris.len())];
        while let Some((ni, start, end)) = work.pop() {
            let mut nb = Bounds::EMPTY;
            let mut cb = Bounds::EMPTY;
            for &i in &order[start..end] {
                nb.join(&bounds[i as usize]);
                cb.grow(centroids[i as usize]);
            }
            nodes[ni].min = nb.min;
            nodes[ni].max = nb.max;
            let n = end - start;
            let split = if n <= MAX_LEAF {
                None
            } else {
                best_split(&order[start..end], &bounds, &centroids, &cb, nb.area(), n)
            };
            let Some((axis, pos)) = split else {
                nodes[ni].first = start as u32;
                nodes[ni].count = n as u32;
                continue;
            };
            let mid = start + partition(&mut order[start..end], |&i| centroids[i as usize][axis] < pos);
            let mid = if mid == start || mid == end { start + n / 2 } else { mid };
            let left = nodes.len();
            nodes.push(Node { min: Vec3A::ZERO, max: Vec3A::ZERO, first: 0, count: 0 });
            nodes.push(Node { min: Vec3A::ZERO, max: Vec3A::ZERO, first: 0, count: 0 });
            nodes[ni].first = left as u32;
            nodes[ni].count = 0;
            work.push((left, start, mid));
            work.push((left + 1, mid, end));
        }
        let reordered: Vec<RtTriangle> = order.iter().map(|&i| tris[i as usize]).collect();
        tris.clear();
        Bvh { nodes, tris: reordered }
    }

    #[inline]
    fn slab(min: Vec3A, max: Vec3A, o: Vec3A, inv: Vec3A, tmax: f32) -> f32 {
        let t0 = (min - o) * inv;
        let t1 = (max - o) * inv;
        let tn = t0.min(t1).max_element().max(0.0);
        let tf = t0.max(t1).min_element().min(tmax);
        if tn <= tf {
            tn
        } else {
            f32::INFINITY
        }
    }

    /// Closest hit: (t, triangle slot in `tris`, b1, b2).
    pub fn intersect(&self, o: Vec3, d: Vec3, mut tmax: f32, any: bool) -> Option<(f32, usize, f32, f32)> {
        if self.tris.is_empty() {
            return None;
        }
        let (o, d) = (Vec3A::from(o), Vec3A::from(d));
        let inv = Vec3A::ONE / d;
        let wray = crate::triangle::WatertightRay::new(o, d);
        let mut stack = [0u32; 64];
        let mut sp = 0usize;
        let mut node = 0usize;
        let mut best = None;
        loop {
            let n = &self.nodes[node];
            if n.count > 0 {
                for i in n.first as usize..(n.first + n.count) as usize {
                    if let Some((t, b1, b2)) = self.tris[i].intersect(&wray, tmax) {
                        tmax = t;
                        best = Some((t, i, b1, b2));
                        if any {
                            return best;
                        }
                    }
                }
            } else {
                let (l, r) = (n.first as usize, n.first as usize + 1);
                let (nl, nr) = (&self.nodes[l], &self.nodes[r]);
                let tl = Self::slab(nl.min, nl.max, o, inv, tmax);
                let tr = Self::slab(nr.min, nr.max, o, inv, tmax);
                let (near, far, tnear, tfar) = if tl <= tr { (l, r, tl, tr) } else { (r, l, tr, tl) };
                if tnear.is_finite() {
                    if tfar.is_finite() && sp < stack.len() {
                        stack[sp] = far as u32;
                        sp += 1;
                    }
                    node = near;
                    continue;
                }
            }
            if sp == 0 {
                break;
            }
            sp -= 1;
            node = stack[sp] as usize;
        }
        best
    }
}

fn partition<T>(v: &mut [T], pred: impl Fn(&T) -> bool) -> usize {
    let mut i = 0;
    for j in 0..v.len() {
        if pred(&v[j]) {
            v.swap(i, j);
            i += 1;
        }
    }
    i
}

#[allow(clippy::needless_range_loop)] // `axis` indexes three arrays at once
/// Binned SAH: the best (axis, position) split, or None when a leaf is cheaper.
fn best_split(
    items: &[u32],
    bounds: &[Bounds],
    centroids: &[Vec3A],
    cb: &Bounds,
    parent_area: f32,
    n: usize,
) -> Option<(usize, f32)> {
    let mut best: Option<(f32, usize, f32)> = None;
    for axis in 0..3 {
        let (lo, hi) = (cb.min[axis], cb.max[axis]);
        if !(hi > lo) {
            continue;
        }
        let scale = BINS as f32 / (hi - lo);
        let mut bins = [(Bounds::EMPTY, 0usize); BINS];
        for &i in items {
            let b = (((centroids[i as usize][axis] - lo) * scale) as usize).min(BINS - 1);
            bins[b].0.join(&bounds[i as usize]);
            bins[b].1 += 1;
        }
        let mut right_area = [0.0f32; BINS];
        let mut right_count = [0usize; BINS];
        let (mut acc, mut cnt) = (Bounds::EMPTY, 0);
        for k in (1..BINS).rev() {
            acc.join(&bins[k].0);
            cnt += bins[k].1;
            right_area[k] = acc.area();
            right_count[k] = cnt;
        }
        let (mut acc, mut cnt) = (Bounds::EMPTY, 0);
        for k in 1..BINS {
            acc.join(&bins[k - 1].0);
            cnt += bins[k - 1].1;
            if cnt == 0 || right_count[k] == 0 {
                continue;
            }
            let cost = acc.area() * cnt as f32 + right_area[k] * right_count[k] as f32;
            if best.is_none_or(|b| cost < b.0) {
                best = Some((cost, axis, lo + k as f32 / scale));
            }
        }
    }
    let (cost, axis, pos) = best?;
    // Leaf cost n·A vs. traversal (≈ one triangle test) + children.
    (cost / parent_area.max(1e-30) + 1.0 < n as f32).then_some((axis, pos))
}
