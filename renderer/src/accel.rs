//! Ray-triangle intersection over the whole scene: a compressed-wide BVH (CWBVH, 8-wide, SIMD node
//! tests) built by `obvhs`, traversed by our loop (nearest child first, children beyond the
//! closest hit skipped) with our 8-wide node test, with triangles
//! stored in BVH leaf order in blocks of eight and intersected by our watertight test
//! (`triangle.rs`): the leaf triangles a node test reaches, a block (eight lanes) at a time.
//!
//! Instancing makes it two-level: each prototype (a mesh several nodes place) gets its own BVH over
//! its object-space triangles, built once; the top level holds the world-space triangles and one
//! box per instance. A ray reaching an instance's box is carried into object space by the
//! instance's inverse transform, direction unnormalised, so the hit distance t is the same number
//! in both spaces and the closest-hit bound carries over unchanged. Memory follows unique geometry.

use crate::math::{Vec3, Vec3A};
use crate::mesh::Mesh;
use crate::wide_node::WideNode;
use obvhs::cwbvh::node::CwBvhNode;
use obvhs::cwbvh::CwBvh;
use obvhs::ray::Ray as BvhRay;

use crate::triangle::{RtTriangle, TriangleBlocks, WatertightRay, LANES};
use std::mem::MaybeUninit;

#[derive(Clone, Copy, Debug)]
pub struct Hit {
    pub t: f32,
    pub triangle: u32,
    pub b1: f32,
    pub b2: f32,
    /// The instance hit (index into `Mesh::instances`), or [`NO_INSTANCE`] for world geometry.
    pub instance: u32,
}

/// `Hit::instance` of a world-space triangle.
pub const NO_INSTANCE: u32 = u32::MAX;

/// The top level of a scene with instances.
/// (Its BVH is `Accel::bvh`.)
struct TopLevel {
    /// Top-level leaves in `Accel::bvh.primitive_indices` order.
    prims: Vec<TopPrim>,
    /// One BVH per prototype (`Mesh::prototypes`), in object space.
    blas: Vec<Accel>,
}

#[derive(Clone, Copy)]
enum TopPrim {
    Triangle(RtTriangle),
    Instance { index: u32, prototype: u32, to_object: glam::Affine3A },
}

/// A leaf triangle's hit as the eight-wide test reports it: (t, slot in `Accel::tris`, b1, b2).
type LeafHit = (f32, usize, f32, f32);

/// A child the traversal has yet to visit: its node and, for closest hits, the distance at which
/// the ray enters its box.
#[derive(Clone, Copy)]
struct Deferred {
    node: u32,
    entry: f32,
}

/// Deferred children a traversal holds on the call stack. A node defers at most seven children
/// beyond the one it descends into, so a BVH `depth` levels deep needs at most `7·depth + 1`
/// entries: this serves every BVH up to 36 levels; a deeper (degenerate) one gets a heap stack
/// of its own size (`Accel::stack_len`).
const STACK: usize = 256;

/// obvhs' ray octant code (`CwBvh::new_traversal`): in every byte, bit 2, 1, 0 set for a
/// non-negative x, y, z direction component. XORed with a child's slot it gives the child's
/// traversal priority (the node test's hit-mask bit).
#[inline(always)]
fn octant_inv4(d: Vec3A) -> u32 {
    (if d.x < 0.0 { 0 } else { 0x0404_0404 })
        | (if d.y < 0.0 { 0 } else { 0x0202_0202 })
        | (if d.z < 0.0 { 0 } else { 0x0101_0101 })
}

/// The node index of the inner child in `slot` of `node`: inner children are stored from
/// `child_base_idx` in slot order.
#[inline(always)]
fn inner_child(node: &impl TraversalNode, slot: u32) -> u32 {
    let (child_base, _, imask) = node.links();
    child_base + (imask & ((1u32 << slot) - 1)).count_ones()
}

/// What the traversal loops need of a node: its test and where its children are. Implemented by
/// obvhs' compressed node and by its decompressed form ([`WideNode`]), so one loop serves both.
trait TraversalNode {
    /// The hit mask in obvhs' format and each child's entry distance by slot (see
    /// [`crate::cwbvh_node::intersect_entry`]).
    fn test(&self, ray: &BvhRay, inv_far: Vec3A, oct_inv4: u32) -> (u32, [f32; 8]);
    /// obvhs' `(child_base_idx, primitive_base_idx, imask)`.
    fn links(&self) -> (u32, u32, u32);
}

impl TraversalNode for CwBvhNode {
    #[inline(always)]
    fn test(&self, ray: &BvhRay, _: Vec3A, oct_inv4: u32) -> (u32, [f32; 8]) {
        crate::cwbvh_node::intersect_entry(self, ray, oct_inv4)
    }
    #[inline(always)]
    fn links(&self) -> (u32, u32, u32) {
        (self.child_base_idx, self.primitive_base_idx, self.imask as u32)
    }
}

impl TraversalNode for WideNode {
    #[inline(always)]
    fn test(&self, ray: &BvhRay, inv_far: Vec3A, oct_inv4: u32) -> (u32, [f32; 8]) {
        self.intersect(ray, inv_far, oct_inv4)
    }
    #[inline(always)]
    fn links(&self) -> (u32, u32, u32) {
        (self.child_base_idx, self.primitive_base_idx, self.imask)
    }
}

/// Closest-hit traversal of a BVH's `nodes` (compressed or wide, each tested 8 children at once). At a
/// node, its hit leaf primitives go to `group(ray, base, mask)` all at once (slots `base + i` for
/// the bits i of `mask`, at most 24), which returns the closest hit distance among them (∞ for
/// none) and so shortens the ray; then its hit inner children are deferred nearest on top, each
/// with its entry distance, and the nearest deferred child the ray still reaches is next.
///
/// Why not obvhs' loop (`obvhs::traverse!`, a GPU design): it defers a node's children as one
/// group in octant order and pops them without their distances, so a child lying wholly beyond a
/// hit found meanwhile still costs a node test, and children are visited in octant order rather
/// than by distance. Both test every leaf that can hold the closest hit, so the hits are the same
/// (a test compares them ray for ray against obvhs' loop).
#[inline(always)]
fn traverse_closest<N: TraversalNode>(
    nodes: &[N],
    stack: &mut [MaybeUninit<Deferred>],
    ray: BvhRay,
    mut group: impl FnMut(&BvhRay, usize, u32) -> f32,
) {
    if nodes.is_empty() {
        return;
    }
    let mut walk = ClosestWalk::new(ray);
    while walk.step(nodes, stack, &mut group) {}
}

/// [`traverse_closest`] for two rays at once, a node of each in turn: the two walks are
/// independent chains of loads and tests, so the core can overlap one's latency with the other's.
#[inline(always)]
fn traverse_closest_pair<N: TraversalNode>(
    nodes: &[N],
    stacks: (&mut [MaybeUninit<Deferred>], &mut [MaybeUninit<Deferred>]),
    rays: (BvhRay, BvhRay),
    mut group_a: impl FnMut(&BvhRay, usize, u32) -> f32,
    mut group_b: impl FnMut(&BvhRay, usize, u32) -> f32,
) {
    if nodes.is_empty() {
        return;
    }
    let (stack_a, stack_b) = stacks;
    let mut a = ClosestWalk::new(rays.0);
    let mut b = ClosestWalk::new(rays.1);
    let (mut live_a, mut live_b) = (true, true);
    while live_a && live_b {
        live_a = a.step(nodes, stack_a, &mut group_a);
        live_b = b.step(nodes, stack_b, &mut group_b);
    }
    while live_a {
        live_a = a.step(nodes, stack_a, &mut group_a);
    }
    while live_b {
        live_b = b.step(nodes, stack_b, &mut group_b);
    }
}

/// One ray's closest-hit traversal ([`traverse_closest`]) as a state advanced a node at a time.
/// Its stack is handed to each step, so a pair's two stacks are two plain borrows.
struct ClosestWalk {
    ray: BvhRay,
    inv_far: Vec3A,
    oct_inv4: u32,
    sp: usize,
    current: u32,
}

impl ClosestWalk {
    #[inline(always)]
    fn new(ray: BvhRay) -> Self {
        let oct_inv4 = octant_inv4(ray.direction);
        let inv_far = crate::wide_node::far_inverse(&ray);
        ClosestWalk { ray, inv_far, oct_inv4, sp: 0, current: 0 }
    }

    /// Visits the current node and picks the next; false when no node is left to visit.
    #[inline(always)]
    fn step<N: TraversalNode>(
        &mut self,
        nodes: &[N],
        stack: &mut [MaybeUninit<Deferred>],
        group: &mut impl FnMut(&BvhRay, usize, u32) -> f32,
    ) -> bool {
        let oct = self.oct_inv4 & 7;
        let node = &nodes[self.current as usize];
        let (hits, entry) = node.test(&self.ray, self.inv_far, self.oct_inv4);
        let prims = hits & 0x00ff_ffff;
        if prims != 0 {
            let t = group(&self.ray, node.links().1 as usize, prims);
            if t < self.ray.tmax {
                self.ray.tmax = t;
            }
        }
        // Inner children hit: bit 24 + p of the mask is the child in slot p ^ octant. Each is
        // inserted into this node's run at the top of the stack, farthest deepest.
        let mut inner = hits >> 24;
        let run = self.sp;
        let mut sp = self.sp;
        while inner != 0 && sp < stack.len() {
            let slot = inner.trailing_zeros() ^ oct;
            inner &= inner - 1;
            let d = Deferred { node: inner_child(node, slot), entry: entry[slot as usize] };
            let mut i = sp;
            // SAFETY: every entry below `sp` has been written.
            while i > run && unsafe { stack[i - 1].assume_init() }.entry < d.entry {
                stack[i] = stack[i - 1];
                i -= 1;
            }
            stack[i] = MaybeUninit::new(d);
            sp += 1;
        }
        // Next: the nearest deferred child that begins before the closest hit so far.
        loop {
            if sp == 0 {
                self.sp = 0;
                return false;
            }
            sp -= 1;
            // SAFETY: as above.
            let d = unsafe { stack[sp].assume_init() };
            if d.entry <= self.ray.tmax {
                self.current = d.node;
                self.sp = sp;
                return true;
            }
        }
    }
}

/// True when `group(base, mask)` reports a hit for some group of primitive slots (as in
/// [`traverse_closest`]); traversal stops at the first. The ray never shortens, so children are
/// deferred in octant order and without their distances.
#[inline(always)]
fn traverse_any<N: TraversalNode>(
    nodes: &[N],
    stack: &mut [MaybeUninit<Deferred>],
    ray: BvhRay,
    mut group: impl FnMut(usize, u32) -> bool,
) -> bool {
    if nodes.is_empty() {
        return false;
    }
    let oct_inv4 = octant_inv4(ray.direction);
    let oct = oct_inv4 & 7;
    let inv_far = crate::wide_node::far_inverse(&ray);
    let (mut sp, mut current) = (0usize, 0u32);
    loop {
        let node = &nodes[current as usize];
        let hits = node.test(&ray, inv_far, oct_inv4).0;
        let prims = hits & 0x00ff_ffff;
        if prims != 0 && group(node.links().1 as usize, prims) {
            return true;
        }
        let mut inner = hits >> 24;
        while inner != 0 && sp < stack.len() {
            let slot = inner.trailing_zeros() ^ oct;
            inner &= inner - 1;
            stack[sp] = MaybeUninit::new(Deferred { node: inner_child(node, slot), entry: 0.0 });
            sp += 1;
        }
        if sp == 0 {
            return false;
        }
        sp -= 1;
        // SAFETY: every entry below `sp` has been written.
        current = unsafe { stack[sp].assume_init() }.node;
    }
}

/// Runs `f` with a traversal stack of `len` entries: on the call stack when that fits
/// [`STACK`], else on the heap.
#[inline(always)]
fn with_stack<R>(len: usize, f: impl FnOnce(&mut [MaybeUninit<Deferred>]) -> R) -> R {
    if len <= STACK {
        let mut stack: [MaybeUninit<Deferred>; STACK] = [const { MaybeUninit::uninit() }; STACK];
        f(&mut stack)
    } else {
        let mut stack = vec![MaybeUninit::uninit(); len];
        f(&mut stack)
    }
}

/// The traversal stack `bvh` needs: `7·depth + 1` entries for a BVH `depth` levels deep (see
/// [`STACK`]).
fn stack_len(bvh: &CwBvh) -> usize {
    let mut deepest = 0;
    let mut todo = if bvh.nodes.is_empty() { vec![] } else { vec![(0u32, 1usize)] };
    while let Some((n, d)) = todo.pop() {
        deepest = deepest.max(d);
        let node = &bvh.nodes[n as usize];
        for slot in 0..8 {
            if node.imask & (1 << slot) != 0 {
                todo.push((inner_child(node, slot), d + 1));
            }
        }
    }
    7 * deepest + 1
}

/// The bits i of `mask`, highest first (the order the traversal loop hands primitives over in).
#[inline(always)]
fn bits_descending(mut mask: u32) -> impl Iterator<Item = usize> {
    std::iter::from_fn(move || {
        (mask != 0).then(|| {
            let i = 31 - mask.leading_zeros();
            mask &= !(1 << i);
            i as usize
        })
    })
}

/// The next window for slots `base + i` (the bits i of a non-empty `mask`): the block of
/// [`LANES`] slots holding the highest one, as (the block's first slot, the lanes of that block
/// `mask` names), those bits taken out of `mask`. Taken highest first with a strictly shrinking
/// bound, windows pick the hit a one-at-a-time test from the highest slot down picks.
#[inline(always)]
fn next_window(base: usize, mask: &mut u32) -> (usize, u32) {
    let hi = 31 - mask.leading_zeros() as usize;
    let start = (base + hi) / LANES * LANES;
    // Bit i of `mask` is slot base + i and lane l of the block is slot start + l, which may lie
    // below base (start ≥ base − 7): shift in a u64 with LANES spare low bits.
    let shift = start + LANES - base;
    let lanes = ((((*mask as u64) << LANES) >> shift) & ((1 << LANES) - 1)) as u32;
    *mask &= !(((((1u64 << LANES) - 1) << shift) >> LANES) as u32);
    (start, lanes)
}

/// obvhs's build quality for `n` triangles: "medium" (the best trace speed per build second at
/// ordinary sizes) up to LARGE_BUILD triangles, "fast" above, where the medium build's longer
/// PLOC search and reinsertion passes cost more seconds than the renders they speed up
/// (`tessera bench scale`, figures in ARCHITECTURE.md).
fn build_params(n: usize) -> obvhs::BvhBuildParams {
    if n > LARGE_BUILD {
        obvhs::BvhBuildParams::fast_build()
    } else {
        obvhs::BvhBuildParams::medium_build()
    }
}

/// Above this many triangles (a one-level BVH) renders trace two paths' closest-hit rays together
/// ([`Accel::intersect_pair`]): there the walks wait on memory and two overlap their misses
/// (`tessera bench rays`: +3 % to +33 % closest-hit rays/s at 327 680 and 1 310 720
/// triangles); below, the BVH stays in cache and pairing costs more than it saves (−2 % to −21 %
/// on four suite scenes of 36 to 4 622 triangles). ARCHITECTURE.md has the figures.
pub const PAIR_RAYS_ABOVE: usize = WIDE_NODES_UP_TO;

/// See [`build_params`].
pub const LARGE_BUILD: usize = 4_000_000;

/// Up to this many primitives a BVH's nodes are decompressed ([`WideNode`]: 256 bytes a node
/// against 80). Small BVHs stay in cache either way and the shorter node test wins; large ones
/// miss cache, and three times the bytes a node costs more than the test saves. `tessera bench
/// rays` on this 2-core EPYC (512 KiB L2 a core), wide against compressed, closest / occluded
/// Mrays/s, medians of three runs: 5 120 triangles +13 % / +17 %, 20 480 +4 % / +7 %, 81 920
/// −11 % / −4 %, 327 680 +1 % / −1 % (2026-11-23; an earlier round gave −15 % / −19 % there).
pub const WIDE_NODES_UP_TO: usize = 65_536;

/// `bvh` with its nodes taken out and decompressed when it holds at most `wide_up_to`
/// primitives ([`WIDE_NODES_UP_TO`]), else unchanged with no wide nodes.
fn decompress(mut bvh: CwBvh, primitives: usize, wide_up_to: usize) -> (CwBvh, Vec<WideNode>) {
    if primitives > wide_up_to {
        return (bvh, Vec::new());
    }
    let wide = bvh.nodes.iter().map(WideNode::from_compressed).collect();
    bvh.nodes = Vec::new();
    (bvh, wide)
}

/// Which BVH answers ray queries. All give the same hits; `ObvhsCompressed` and `Own` are kept to
/// measure `Obvhs` against.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum AccelKind {
    /// obvhs' CWBVH, nodes decompressed up to [`WIDE_NODES_UP_TO`] primitives (the default).
    #[default]
    Obvhs,
    /// obvhs' CWBVH with its compressed nodes at every size.
    ObvhsCompressed,
    /// Our binned-SAH BVH2.
    Own,
}

impl AccelKind {
    /// Up to how many primitives this kind's BVHs traverse decompressed nodes.
    fn wide_up_to(self) -> usize {
        match self {
            AccelKind::ObvhsCompressed => 0,
            _ => WIDE_NODES_UP_TO,
        }
    }

    /// The name `FromStr` takes.
    pub fn name(self) -> &'static str {
        match self {
            AccelKind::Obvhs => "obvhs",
            AccelKind::ObvhsCompressed => "obvhs-compressed",
            AccelKind::Own => "own",
        }
    }
}

crate::named_choices!(AccelKind, "accelerator", {
    "obvhs" => Self::Obvhs,
    "obvhs-compressed" => Self::ObvhsCompressed,
    "own" => Self::Own,
});

#[derive(Default)]
pub struct Accel {
    /// obvhs' BVH. Its compressed nodes are traversed only above [`WIDE_NODES_UP_TO`] primitives;
    /// below, they are dropped after the build in favour of `wide`.
    bvh: CwBvh,
    /// `bvh`'s nodes decompressed ([`WideNode`]), or empty.
    wide: Vec<WideNode>,
    /// What was asked for (kept for [`Accel::rebuild_top`]).
    kind: AccelKind,
    /// The traversal stack `bvh` needs ([`stack_len`]).
    stack_len: usize,
    /// Triangles in `bvh.primitive_indices` order, so a node's leaf primitives are consecutive slots.
    tris: TriangleBlocks,
    /// Test leaf triangles one at a time (`TriangleBlocks::intersect8_scalar`): the reference the
    /// eight-wide test is held to (same hits, same images), off except in tests.
    scalar_reference: bool,
    /// Renders trace two paths' rays together ([`Accel::pairs_rays`]).
    pair_rays: bool,
    own: Option<crate::bvh::Bvh>,
    /// Set when the scene has instances (then `bvh`, `tris` and `own` are empty).
    top: Option<Box<TopLevel>>,
}

impl Accel {
    pub fn build(mesh: &Mesh) -> Self {
        Self::build_with(mesh, AccelKind::Obvhs)
    }

    pub fn build_with(mesh: &Mesh, kind: AccelKind) -> Self {
        if !mesh.instances.is_empty() {
            if kind == AccelKind::Own {
                tracing::warn!("the own BVH has no instancing: using obvhs for this instanced scene");
            }
            return Self::build_two_level(mesh, kind);
        }
        Self::build_triangles(mesh, (0..mesh.triangles.len() as u32).collect(), kind)
    }

    /// A one-level BVH over the triangles `ids` of `mesh` (as they are stored).
    fn build_triangles(mesh: &Mesh, ids: Vec<u32>, kind: AccelKind) -> Self {
        if kind == AccelKind::Own {
            let tris = ids.iter().map(|&i| RtTriangle::new(mesh.vertices(i), i)).collect();
            return Accel {
                bvh: CwBvh::default(),
                wide: Vec::new(),
                kind,
                stack_len: 0,
                tris: TriangleBlocks::default(),
                scalar_reference: false,
                pair_rays: false,
                own: Some(crate::bvh::Bvh::build(tris)),
                top: None,
            };
        }
        let prims: Vec<obvhs::triangle::Triangle> = ids
            .iter()
            .map(|&i| {
                let [a, b, c] = mesh.vertices(i);
                obvhs::triangle::Triangle { v0: a.into(), v1: b.into(), v2: c.into() }
            })
            .collect();
        if prims.is_empty() {
            return Accel { kind, ..Accel::default() };
        }
        let bvh = obvhs::cwbvh::builder::build_cwbvh_from_tris(
            &prims,
            build_params(prims.len()),
            &mut std::time::Duration::default(),
        );
        let stack_len = stack_len(&bvh);
        let tris = TriangleBlocks::new(
            bvh.primitive_indices.iter().map(|&k| RtTriangle::new(mesh.vertices(ids[k as usize]), ids[k as usize])),
        );
        let (bvh, wide) = decompress(bvh, prims.len(), kind.wide_up_to());
        let pair_rays = prims.len() > PAIR_RAYS_ABOVE;
        Accel { stack_len, bvh, wide, kind, tris, scalar_reference: false, pair_rays, own: None, top: None }
    }

    /// After an animation moved instances or world vertices: a new top level over the prototype
    /// BVHs already built (they do not change), or a whole new BVH for a scene without instances.
    pub fn rebuild_top(&mut self, mesh: &Mesh) {
        match self.top.take() {
            Some(top) => *self = Self::top_level(mesh, top.blas, self.kind),
            None => *self = Self::build_with(mesh, self.kind),
        }
    }

    /// Prototype BVHs, then a top level over the world triangles and the instances' world boxes.
    /// The prototypes are obvhs' (the own BVH has no instancing), with `kind`'s node form.
    fn build_two_level(mesh: &Mesh, kind: AccelKind) -> Self {
        let blas_kind = if kind == AccelKind::Own { AccelKind::Obvhs } else { kind };
        let blas: Vec<Accel> =
            mesh.prototypes.iter().map(|r| Self::build_triangles(mesh, r.clone().collect(), blas_kind)).collect();
        Self::top_level(mesh, blas, kind)
    }

    fn top_level(mesh: &Mesh, blas: Vec<Accel>, kind: AccelKind) -> Self {
        let world: Vec<u32> = (0..mesh.triangles.len() as u32)
            .filter(|&i| mesh.triangles[i as usize].flags & crate::mesh::flags::OBJECT_SPACE == 0)
            .collect();
        let mut boxes: Vec<obvhs::aabb::Aabb> = Vec::with_capacity(world.len() + mesh.instances.len());
        let mut prims: Vec<TopPrim> = Vec::with_capacity(boxes.capacity());
        for &i in &world {
            let [a, b, c] = mesh.vertices(i);
            let (a, b, c) = (Vec3A::from(a), Vec3A::from(b), Vec3A::from(c));
            boxes.push(obvhs::aabb::Aabb { min: a.min(b).min(c), max: a.max(b).max(c) });
            prims.push(TopPrim::Triangle(RtTriangle::new(mesh.vertices(i), i)));
        }
        let proto_boxes = mesh.prototype_bounds();
        for (k, inst) in mesh.instances.iter().enumerate() {
            if !inst.visible {
                continue;
            }
            let Some(&bx) = proto_boxes.get(inst.prototype as usize) else { continue };
            let (lo, hi) = Mesh::instance_box(inst, bx);
            boxes.push(obvhs::aabb::Aabb { min: lo.into(), max: hi.into() });
            prims.push(TopPrim::Instance {
                index: k as u32,
                prototype: inst.prototype,
                to_object: glam::Affine3A::from_mat4(inst.to_object),
            });
        }
        if boxes.is_empty() {
            return Accel { top: Some(Box::new(TopLevel { prims, blas })), ..Accel::default() };
        }
        let bvh =
            obvhs::cwbvh::builder::build_cwbvh(&boxes, obvhs::BvhBuildParams::medium_build(), &mut Default::default());
        // Leaf order, so a leaf's primitives sit together.
        let prims: Vec<TopPrim> = bvh.primitive_indices.iter().map(|&i| prims[i as usize]).collect();
        let stack_len = stack_len(&bvh);
        let (bvh, wide) = decompress(bvh, prims.len(), kind.wide_up_to());
        Accel { stack_len, bvh, wide, kind, top: Some(Box::new(TopLevel { prims, blas })), ..Accel::default() }
    }

    /// [`traverse_closest`] over this BVH's nodes, wide or compressed.
    #[inline(always)]
    fn closest(&self, ray: BvhRay, group: impl FnMut(&BvhRay, usize, u32) -> f32) {
        with_stack(self.stack_len, |stack| {
            if self.wide.is_empty() {
                traverse_closest(&self.bvh.nodes, stack, ray, group)
            } else {
                traverse_closest(&self.wide, stack, ray, group)
            }
        })
    }

    /// [`traverse_any`] over this BVH's nodes, wide or compressed.
    #[inline(always)]
    fn any(&self, ray: BvhRay, group: impl FnMut(usize, u32) -> bool) -> bool {
        with_stack(self.stack_len, |stack| {
            if self.wide.is_empty() {
                traverse_any(&self.bvh.nodes, stack, ray, group)
            } else {
                traverse_any(&self.wide, stack, ray, group)
            }
        })
    }

    /// Makes every leaf triangle test the one-at-a-time reference (prototypes included).
    pub fn set_scalar_reference(&mut self, on: bool) {
        self.scalar_reference = on;
        if let Some(top) = &mut self.top {
            top.blas.iter_mut().for_each(|b| b.set_scalar_reference(on));
        }
    }

    /// Closest hit along `o + t d`, `0 < t < tmax`.
    pub fn intersect(&self, o: Vec3, d: Vec3, tmax: f32) -> Option<Hit> {
        if let Some(top) = &self.top {
            return self.intersect_two_level(top, Vec3A::from(o), Vec3A::from(d), tmax);
        }
        if let Some(own) = &self.own {
            return own.intersect(o, d, tmax, false).map(|(t, i, b1, b2)| Hit {
                t,
                triangle: own.tris[i].id,
                b1,
                b2,
                instance: NO_INSTANCE,
            });
        }
        self.intersect_object(Vec3A::from(o), Vec3A::from(d), tmax)
    }

    fn intersect_two_level(&self, top: &TopLevel, oa: Vec3A, da: Vec3A, tmax: f32) -> Option<Hit> {
        if top.prims.is_empty() || !da.is_finite() || !oa.is_finite() {
            return None;
        }
        let ray = BvhRay::new(oa, da, 0.0, tmax);
        let wray = WatertightRay::new(oa, da);
        let mut best: Option<Hit> = None;
        self.closest(ray, |r, base, mask| {
            let mut bound = r.tmax;
            // Highest slot first with a shrinking bound, as the traversal loop hands them over.
            for i in bits_descending(mask) {
                match &top.prims[base + i] {
                    TopPrim::Triangle(tri) => {
                        if let Some((t, b1, b2)) = tri.intersect(&wray, bound) {
                            best = Some(Hit { t, triangle: tri.id, b1, b2, instance: NO_INSTANCE });
                            bound = t;
                        }
                    }
                    TopPrim::Instance { index, prototype, to_object } => {
                        let (oo, dd) = (to_object.transform_point3a(oa), to_object.transform_vector3a(da));
                        if let Some(mut h) = top.blas[*prototype as usize].intersect_object(oo, dd, bound) {
                            h.instance = *index;
                            best = Some(h);
                            bound = h.t;
                        }
                    }
                }
            }
            bound
        });
        best
    }

    /// Closest hit in a one-level BVH (the scene's, or a prototype's with the ray already in object
    /// space, direction unnormalised).
    fn intersect_object(&self, oa: Vec3A, da: Vec3A, tmax: f32) -> Option<Hit> {
        if self.tris.is_empty() || !da.is_finite() || !oa.is_finite() {
            return None;
        }
        let ray = BvhRay::new(oa, da, 0.0, tmax);
        let wray = WatertightRay::new(oa, da);
        let mut best = None;
        self.closest(ray, |r, base, mask| self.closest_in_group(&wray, &mut best, r.tmax, base, mask));
        best.map(|leaf| self.leaf_hit(leaf))
    }

    /// The closest of a group's leaf triangles (as in [`traverse_closest`]) on the ray before
    /// `bound`, into `best`; returns the new bound (`bound` when none is closer).
    #[inline(always)]
    fn closest_in_group(
        &self,
        wray: &WatertightRay,
        best: &mut Option<LeafHit>,
        bound: f32,
        base: usize,
        mask: u32,
    ) -> f32 {
        let (mut bound, mut mask) = (bound, mask);
        while mask != 0 {
            let (start, lanes) = next_window(base, &mut mask);
            let hit = if self.scalar_reference {
                self.tris.intersect8_scalar(wray, start, lanes, bound)
            } else {
                self.tris.intersect8(wray, start, lanes, bound)
            };
            if let Some(h) = hit {
                bound = h.0;
                *best = Some(h);
            }
        }
        bound
    }

    #[inline(always)]
    fn leaf_hit(&self, (t, slot, b1, b2): LeafHit) -> Hit {
        Hit { t, triangle: self.tris.ids[slot], b1, b2, instance: NO_INSTANCE }
    }

    /// Whether renders should trace two paths' rays together ([`PAIR_RAYS_ABOVE`]; only a
    /// one-level obvhs BVH pairs).
    pub fn pairs_rays(&self) -> bool {
        self.pair_rays && self.top.is_none() && self.own.is_none() && !self.tris.is_empty()
    }

    /// Overrides [`Self::pairs_rays`]' size rule (tests hold paired renders to single ones on
    /// small scenes; images are the same either way).
    pub fn set_pair_rays(&mut self, on: bool) {
        self.pair_rays = on;
    }

    /// [`Self::intersect`] for two rays at once (interleaved traversal, the same hits).
    pub fn intersect_pair(&self, o: [Vec3; 2], d: [Vec3; 2], tmax: f32) -> [Option<Hit>; 2] {
        let (oa, da) = (o.map(Vec3A::from), d.map(Vec3A::from));
        if self.top.is_some()
            || self.own.is_some()
            || self.tris.is_empty()
            || !(oa[0].is_finite() && oa[1].is_finite() && da[0].is_finite() && da[1].is_finite())
        {
            return [self.intersect(o[0], d[0], tmax), self.intersect(o[1], d[1], tmax)];
        }
        let rays = (BvhRay::new(oa[0], da[0], 0.0, tmax), BvhRay::new(oa[1], da[1], 0.0, tmax));
        let wrays = [WatertightRay::new(oa[0], da[0]), WatertightRay::new(oa[1], da[1])];
        let mut best = [None, None];
        let [best_a, best_b] = &mut best;
        with_stack(self.stack_len, |sa| {
            with_stack(self.stack_len, |sb| {
                let ga = |r: &BvhRay, base, mask| self.closest_in_group(&wrays[0], best_a, r.tmax, base, mask);
                let gb = |r: &BvhRay, base, mask| self.closest_in_group(&wrays[1], best_b, r.tmax, base, mask);
                if self.wide.is_empty() {
                    traverse_closest_pair(&self.bvh.nodes, (sa, sb), rays, ga, gb)
                } else {
                    traverse_closest_pair(&self.wide, (sa, sb), rays, ga, gb)
                }
            })
        });
        best.map(|b| b.map(|leaf| self.leaf_hit(leaf)))
    }

    /// Whether any leaf triangle of the group (`traverse_any`) lies on the ray before `tmax`.
    #[inline(always)]
    fn any_in_group(&self, wray: &WatertightRay, base: usize, mask: u32, tmax: f32) -> bool {
        let mut mask = mask;
        while mask != 0 {
            let (start, lanes) = next_window(base, &mut mask);
            let hit = if self.scalar_reference {
                self.tris.intersect8_scalar(wray, start, lanes, tmax).is_some()
            } else {
                self.tris.any8(wray, start, lanes, tmax)
            };
            if hit {
                return true;
            }
        }
        false
    }

    /// True when anything lies on `o + t d` for `0 < t < tmax`.
    pub fn occluded(&self, o: Vec3, d: Vec3, tmax: f32) -> bool {
        let (oa, da) = (Vec3A::from(o), Vec3A::from(d));
        if let Some(top) = &self.top {
            if top.prims.is_empty() || !oa.is_finite() || !da.is_finite() {
                return false;
            }
            let ray = BvhRay::new(oa, da, 0.0, tmax);
            let wray = WatertightRay::new(oa, da);
            return self.any(ray, |base, mask| {
                bits_descending(mask).any(|i| match &top.prims[base + i] {
                    TopPrim::Triangle(tri) => tri.intersect(&wray, tmax).is_some(),
                    TopPrim::Instance { prototype, to_object, .. } => top.blas[*prototype as usize].occluded_object(
                        to_object.transform_point3a(oa),
                        to_object.transform_vector3a(da),
                        tmax,
                    ),
                })
            });
        }
        if let Some(own) = &self.own {
            return own.intersect(o, d, tmax, true).is_some();
        }
        self.occluded_object(oa, da, tmax)
    }

    /// Whether anything lies on the ray before `tmax` in a one-level BVH (the scene's, or a
    /// prototype's with the ray in object space), as [`Self::intersect_object`] for closest hits.
    fn occluded_object(&self, oa: Vec3A, da: Vec3A, tmax: f32) -> bool {
        if self.tris.is_empty() || !oa.is_finite() || !da.is_finite() {
            return false;
        }
        let wray = WatertightRay::new(oa, da);
        self.any(BvhRay::new(oa, da, 0.0, tmax), |base, mask| self.any_in_group(&wray, base, mask, tmax))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// obvhs' own traversal loop (`obvhs::traverse!`, as Tessera used it before its own loop) with
    /// one leaf triangle at a time and a shrinking bound: the reference for [`traverse_closest`].
    fn obvhs_closest(a: &Accel, o: Vec3A, d: Vec3A, tmax: f32) -> Option<(f32, u32)> {
        use glam::UVec2;
        let mut ray = BvhRay::new(o, d, 0.0, tmax);
        let wray = WatertightRay::new(o, d);
        let mut state = a.bvh.new_traversal(ray.direction);
        let mut node;
        let mut best = None;
        obvhs::traverse!(a.bvh, node, state, crate::cwbvh_node::intersect(node, &ray, state.oct_inv4), {
            let slot = state.primitive_id as usize;
            if let Some((t, _, _)) = a.tris.get(slot).intersect(&wray, ray.tmax) {
                ray.tmax = t;
                best = Some((t, a.tris.ids[slot]));
            }
        });
        best
    }

    /// Twelve spheres of mixed sizes and subdivisions inside a large inward-facing one, and the
    /// ids of all their triangles: a BVH deep enough for the traversal tests.
    fn sphere_cluster() -> (crate::testing::SceneBuilder, Vec<u32>) {
        let mut b = crate::testing::SceneBuilder::default();
        let m = b.material(crate::testing::lambert(Vec3::splat(0.5)));
        b.sphere(Vec3::ZERO, 6.0, 3, true, m);
        for k in 0..12u64 {
            let u = |j: u64| crate::sampler::hash_unit(16 * k + j);
            let c = Vec3::new(u(0), u(1), u(2)) * 6.0 - 3.0;
            b.sphere(c, 0.2 + u(3), 2 + (k % 3) as u32, false, m);
        }
        let all = (0..b.mesh.triangles.len() as u32).collect();
        (b, all)
    }

    /// The distance-ordered loop with its culling finds the hit obvhs' loop finds, ray for ray (the
    /// same distance to the bit and the same triangle, or a triangle the ray hits at that same
    /// distance: a ray through a shared edge), over compressed and over decompressed nodes, also
    /// with the heap stack a deep BVH gets; any-hit queries agree with the closest hit.
    #[test]
    fn own_traversal_finds_the_hits_of_obvhs_loop() {
        let (b, all) = sphere_cluster();
        // The reference keeps obvhs' compressed nodes.
        let reference = Accel::build_triangles(&b.mesh, all.clone(), AccelKind::ObvhsCompressed);
        assert!(reference.wide.is_empty() && reference.bvh.nodes.len() > 20 && reference.stack_len > 8);
        let (mut hits, mut ties) = (0usize, 0usize);
        for (wide, heap) in [(false, false), (true, false), (true, true)] {
            let kind = if wide { AccelKind::Obvhs } else { AccelKind::ObvhsCompressed };
            let mut accel = Accel::build_triangles(&b.mesh, all.clone(), kind);
            assert_eq!(accel.wide.is_empty(), !wide);
            if heap {
                accel.stack_len = STACK + 1;
            }
            for i in 0..20_000u64 {
                let u = |j: u64| crate::sampler::hash_unit(8 * i + j);
                let o = Vec3A::new(u(0), u(1), u(2)) * 8.0 - 4.0;
                let d = Vec3A::new(u(3), u(4), u(5)) * 2.0 - 1.0;
                if d.length_squared() == 0.0 {
                    continue;
                }
                let tmax = if i % 4 == 0 { 3.0 * u(6) } else { f32::INFINITY };
                let want = obvhs_closest(&reference, o, d, tmax);
                let got = accel.intersect(o.into(), d.into(), tmax);
                let case = format!("ray {i} (wide nodes {wide}, heap stack {heap})");
                match (want, got) {
                    (None, None) => {}
                    (Some((t, tri)), Some(h)) => {
                        hits += 1;
                        assert_eq!(t.to_bits(), h.t.to_bits(), "{case}: t {t} vs {}", h.t);
                        if tri != h.triangle {
                            let slot = accel.tris.ids.iter().position(|&x| x == h.triangle).unwrap();
                            let again = accel.tris.get(slot).intersect(&WatertightRay::new(o, d), f32::INFINITY);
                            assert_eq!(again.map(|x| x.0.to_bits()), Some(t.to_bits()), "{case}: triangle");
                            ties += 1;
                        }
                    }
                    other => panic!("{case}: {other:?}"),
                }
                assert_eq!(accel.occluded(o.into(), d.into(), tmax), want.is_some(), "{case}");
            }
        }
        eprintln!("{hits} hits, {ties} ties on shared edges");
        assert!(hits > 30_000, "the test rays must hit ({hits})");
    }

    /// Two rays traversed interleaved find what each finds alone, bit for bit, with compressed and
    /// wide nodes and a heap stack, and where a ray ends (tmax) or leaves everything early.
    #[test]
    fn paired_traversal_finds_each_rays_own_hit() {
        let (b, all) = sphere_cluster();
        let key = |h: Option<Hit>| h.map(|h| (h.t.to_bits(), h.triangle, h.b1.to_bits(), h.b2.to_bits()));
        let mut hits = 0usize;
        for (kind, heap) in [(AccelKind::ObvhsCompressed, false), (AccelKind::Obvhs, false), (AccelKind::Obvhs, true)] {
            let mut accel = Accel::build_triangles(&b.mesh, all.clone(), kind);
            if heap {
                accel.stack_len = STACK + 1;
            }
            let ray = |i: u64| {
                let u = |j: u64| crate::sampler::hash_unit(8 * i + j);
                // Every third ray starts outside the enclosing sphere pointing away: it ends at
                // the root while its partner walks on.
                let o = Vec3::new(u(0), u(1), u(2)) * 8.0 - 4.0;
                let o = if i.is_multiple_of(3) { o.normalize_or_zero() * 20.0 } else { o };
                let d = if i.is_multiple_of(3) { o } else { Vec3::new(u(3), u(4), u(5)) * 2.0 - 1.0 };
                (o, d)
            };
            for i in 0..10_000u64 {
                let ((oa, da), (ob, db)) = (ray(2 * i), ray(2 * i + 1));
                let tmax = if i % 4 == 0 { 3.0 * crate::sampler::hash_unit(7 * i) } else { f32::INFINITY };
                let got = accel.intersect_pair([oa, ob], [da, db], tmax);
                let want = [accel.intersect(oa, da, tmax), accel.intersect(ob, db, tmax)];
                assert_eq!(key(got[0]), key(want[0]), "pair {i}, first ray ({kind:?}, heap {heap})");
                assert_eq!(key(got[1]), key(want[1]), "pair {i}, second ray ({kind:?}, heap {heap})");
                hits += want.iter().filter(|h| h.is_some()).count();
            }
        }
        assert!(hits > 25_000, "the test rays must hit ({hits})");
    }

    /// Windows cover exactly the slots a group names, block-aligned, highest block first.
    #[test]
    fn windows_cover_the_group_block_by_block() {
        for base in 0..40usize {
            for k in 0..500u64 {
                let mask0 = (crate::sampler::hash_u64(k * 131 + base as u64) as u32) & 0x00ff_ffff | 1 << (k % 24);
                let mut want: Vec<usize> = (0..24).filter(|i| mask0 & (1 << i) != 0).map(|i| base + i).collect();
                let (mut mask, mut got, mut last) = (mask0, Vec::new(), usize::MAX);
                while mask != 0 {
                    let (start, lanes) = next_window(base, &mut mask);
                    assert!(start.is_multiple_of(LANES) && start < last && lanes != 0, "base {base} mask {mask0:#x}");
                    last = start;
                    got.extend((0..LANES).filter(|l| lanes & (1 << l) != 0).map(|l| start + l));
                }
                got.sort_unstable();
                want.sort_unstable();
                assert_eq!(got, want, "base {base} mask {mask0:#x}");
            }
        }
    }
}
