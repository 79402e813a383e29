//! Inward rays in closed convex glass find their exit by walking the solid's surface
//! (`renderer::solid_surface`) or start their node tests where they leave the solid's inner ball
//! (`renderer::convex_solid`, `Scene::intersect_surface`): the hits are the full walks' own, and
//! renders are the same bits with the bound and the walk and without.

use glam::Vec3;
use renderer::film::Rect;
use renderer::material::Material;
use renderer::render::render_tile_counted;
use renderer::sampler::hash_unit as u;
use renderer::scene::Scene;
use renderer::testing::{emitter, lambert, SceneBuilder};
use renderer::{Counters, RenderSettings};

fn glass(roughness: f32) -> Material {
    Material { name: "glass".into(), transmission: 1.0, ior: 1.5, metallic: 0.0, roughness, ..Material::default() }
}

/// A floor with three glass objects on it: an icosphere resting on the floor (touching it), a
/// UV sphere, and an icosphere with a small plate inside (not isolated: no solid); a lamp above.
fn scene() -> Scene {
    scene_wound(false)
}

/// [`scene`], with the first sphere's winding turned inward when `inward` (a solid is a solid
/// whichever way its triangles face).
fn scene_wound(inward: bool) -> Scene {
    let mut b = SceneBuilder::default();
    let floor = b.material(lambert(Vec3::splat(0.6)));
    let smooth = b.material(glass(0.0));
    let rough = b.material(glass(0.3));
    let lamp = b.material(emitter(Vec3::splat(20.0)));
    b.quad(Vec3::ZERO, Vec3::new(4.0, 0.0, 0.0), Vec3::new(0.0, 0.0, -4.0), floor);
    b.sphere(Vec3::new(-1.0, 0.5, 0.0), 0.5, 3, inward, smooth);
    b.uv_sphere(Vec3::new(0.3, 0.6, -0.4), 0.4, 32, 16, rough);
    b.sphere(Vec3::new(1.3, 0.5, 0.6), 0.4, 2, false, smooth);
    b.quad(Vec3::new(1.3, 0.5, 0.6), Vec3::new(0.05, 0.0, 0.0), Vec3::new(0.0, 0.0, -0.05), floor);
    b.quad(Vec3::new(0.0, 3.0, 0.0), Vec3::new(0.5, 0.0, 0.0), Vec3::new(0.0, 0.0, 0.5), lamp);
    b.look_at(Vec3::new(0.0, 1.6, 4.0), Vec3::new(0.0, 0.4, 0.0), 40.0);
    b.build()
}

/// A hit as bits (triangle, t, barycentrics), to compare walks exactly.
fn key(h: Option<renderer::accel::Hit>) -> Option<(u32, u32, u32, u32)> {
    h.map(|h| (h.triangle, h.t.to_bits(), h.b1.to_bits(), h.b2.to_bits()))
}

/// Ray `i`'s start: a random one of triangles `tris`, a random point of it, its unit winding
/// normal (random numbers 5i to 5i + 2; the caller's direction may take 5i + 3 and 5i + 4).
fn point_on(s: &Scene, tris: &[u32], i: u64) -> (u32, Vec3, Vec3) {
    let tri = tris[((u(5 * i) * tris.len() as f32) as usize).min(tris.len() - 1)];
    let [a, b, c] = s.mesh.vertices(tri);
    let (b1, b2) = (u(5 * i + 1), u(5 * i + 2));
    let (b1, b2) = if b1 + b2 > 1.0 { (1.0 - b1, 1.0 - b2) } else { (b1, b2) };
    (tri, a + (b - a) * b1 + (c - a) * b2, (b - a).cross(c - a).normalize())
}

#[test]
fn inward_rays_bounded_by_a_solids_ball_find_what_the_full_walks_find() {
    let s = scene();
    assert_eq!(s.convex_solids(), 2, "the two isolated spheres; the third holds a plate");
    let glass: Vec<u32> =
        (0..s.mesh.triangles.len() as u32).filter(|&t| s.mesh.triangles[t as usize].material != 0).collect();
    let (mut bounded, mut hits, mut tighter_differs, mut walked) = (0u32, 0u32, 0u32, 0u32);
    let n = 40_000u64;
    for i in 0..n {
        // A random point of a random glass triangle, a direction into the inside (refraction
        // and internal reflection go there), the origin offset as the integrator offsets it.
        let (tri, p, ng) = point_on(&s, &glass, i);
        let (z, phi) = (u(5 * i + 3), std::f32::consts::TAU * u(5 * i + 4));
        let frame = renderer::math::Frame::from_normal(-ng);
        let r = (1.0 - z * z).max(0.0).sqrt();
        let d = frame.to_world(Vec3::new(r * phi.cos(), r * phi.sin(), z)).normalize();
        let o = s.offset_ray_origin(p, -ng);
        let tmin = s.solid_tmin(tri, o, d);
        let full = s.accel.intersect(o, d, f32::INFINITY);
        let cut = s.intersect_surface(o, d, 0, tri);
        assert_eq!(key(full), key(cut), "ray {i} from triangle {tri}: bound {tmin}");
        if tmin > 0.0 {
            bounded += 1;
            let h = full.expect("a ray inside a closed solid leaves it");
            assert!(h.t > tmin, "ray {i}: the hit at {} lies before the bound {tmin}", h.t);
            // A bound a tenth farther on skips the exit's boxes for some rays: the bound is
            // what decides, and this test would see a wrong one.
            if key(s.accel.intersect_from(o, d, h.t * 1.1, f32::INFINITY)) != key(full) {
                tighter_differs += 1;
            }
            // The surface walk (`renderer::solid_surface`), where it answers, answers the same.
            if let Some(exit) = s.solid_surface_exit(tri, o, d) {
                assert_eq!(key(Some(exit)), key(full), "ray {i}: the surface walk's exit");
                walked += 1;
            }
        }
        hits += full.is_some() as u32;
        // The other way, outward from the same point: never bounded.
        let out = s.offset_ray_origin(p, ng);
        assert_eq!(s.solid_tmin(tri, out, -d), 0.0, "ray {i}: an outward ray got a bound");
    }
    eprintln!(
        "{bounded} of {n} inward rays bounded ({walked} answered by the surface walk), {hits} hit, \
         {tighter_differs} differ with a bound past the exit"
    );
    assert!(walked * 100 > bounded * 95, "the surface walk answered {walked} of {bounded}");
    // Two thirds of the glass triangles are in solids, and nearly every inward ray but a
    // grazing one crosses the inner ball.
    assert!(bounded as u64 > n / 2, "{bounded} of {n} rays bounded");
    assert!(tighter_differs > bounded / 2, "{tighter_differs} of {bounded}: a bound past the exit must show");
}

#[test]
fn segments_a_solid_blocks_are_blocked_by_its_triangles() {
    let s = scene();
    let (mut blocked_by_solid, mut occluded) = (0u32, 0u32);
    let n = 40_000u64;
    for i in 0..n {
        // From a point above the floor to a point in the room: through the spheres, ending
        // inside them, beside them, or short of them.
        let a = Vec3::new(-2.0 + 4.0 * u(6 * i), 0.01 + 1.5 * u(6 * i + 1), -2.0 + 4.0 * u(6 * i + 2));
        let b = Vec3::new(-2.0 + 4.0 * u(6 * i + 3), 0.01 + 3.0 * u(6 * i + 4), -2.0 + 4.0 * u(6 * i + 5));
        let (d, len) = ((b - a).normalize(), (b - a).length());
        let walk = s.accel.occluded(a, d, len);
        let solid = s.solid_blocks(a, d, len);
        assert!(!solid || walk, "segment {i}: a solid blocks it, the walk finds nothing");
        blocked_by_solid += solid as u32;
        occluded += walk as u32;
        // Infinite rays too (a light at infinity).
        assert!(!s.solid_blocks(a, d, f32::INFINITY) || s.accel.occluded(a, d, f32::INFINITY));
    }
    eprintln!("{blocked_by_solid} of {n} segments blocked by a solid, {occluded} by the walk");
    assert!(blocked_by_solid > n as u32 / 20, "{blocked_by_solid} of {n}: the test must exercise the shortcut");
    // A segment ending inside a solid, or passing beside it, is not the solid's to block.
    let c = Vec3::new(-1.0, 0.5, 0.0);
    assert!(!s.solid_blocks(c + Vec3::X * 2.0, -Vec3::X, 1.9));
    assert!(s.solid_blocks(c + Vec3::X * 2.0, -Vec3::X, 3.0));
    assert!(!s.solid_blocks(c + Vec3::new(2.0, 0.0, 0.6), -Vec3::X, 4.0));
}

/// The same image bits with the bound and without, with the eight-lane kernel and without, with
/// rays walked one at a time and in batches (`Scene::intersect_surface_batch`'s batched path,
/// which this small scene only takes when told to).
#[test]
fn renders_are_the_same_bits_with_the_solids_bound_or_without() {
    let mut s = scene();
    for (lanes, batched) in [(true, false), (false, false), (true, true), (false, true)] {
        s.set_lanes(lanes);
        s.set_batch_rays(batched);
        assert_eq!(s.batches_rays(), batched);
        s.set_convex_solids(true);
        assert_eq!(s.convex_solids(), 2);
        let with = render_bits(&s, 3);
        // The solids' BVHs alone, without the surface walk.
        s.set_solid_surface_walk(false);
        assert!(with == render_bits(&s, 3), "lanes {lanes}, batched {batched}: the surface walk changed the image");
        s.set_convex_solids(false);
        assert_eq!(s.convex_solids(), 0);
        assert!(with == render_bits(&s, 3), "lanes {lanes}, batched {batched}: the bound changed the image");
    }
}

/// A 40×30 render of `s` at 8 spp (seed `seed`): its sums and squared luminances as bits.
/// Fails on a black or broken image, which would test nothing.
fn render_bits(s: &Scene, seed: u64) -> Vec<u64> {
    let settings = RenderSettings { width: 40, height: 30, spp: 8, seed, ..RenderSettings::default() };
    let rect = Rect { x0: 0, y0: 0, width: settings.width, height: settings.height };
    let p = render_tile_counted(s, &settings, rect, 0..settings.spp, &Counters::default());
    let total: f64 = p.sum_rgb.iter().flatten().sum();
    assert!(total > 0.0 && total.is_finite(), "a black or broken image tests nothing");
    p.sum_rgb.iter().flatten().chain(&p.sum_lum_sq).map(|v| v.to_bits()).collect()
}

/// Rays leaving a solid through one of its facets skip the solid's subtrees
/// (`Accel::intersect_leaving`): they find what the full walk finds. And the skip is real: the
/// same directions from points just inside the facets, where a full walk meets the solid's own
/// triangles, rarely do (only where a BVH leaf holds the solid's triangles with others'). With
/// a sphere wound either way, over decompressed and compressed nodes.
#[test]
fn rays_leaving_a_solid_find_what_the_full_walks_find() {
    use renderer::accel::AccelKind;
    for inward in [false, true] {
        for kind in [AccelKind::Obvhs, AccelKind::ObvhsCompressed] {
            let mut s = scene_wound(inward);
            s.use_accel(kind);
            leaving_rays_in(&s, &format!("inward winding {inward}, {kind:?}"));
        }
    }
}

fn leaving_rays_in(s: &Scene, case: &str) {
    assert_eq!(s.convex_solids(), 2, "{case}");
    let glass: Vec<u32> = (0..s.mesh.triangles.len() as u32).filter(|&t| s.solid_of(t).is_some()).collect();
    assert!(!glass.is_empty());
    let (mut leaving, mut hits, mut own_from_inside, mut own_skipping) = (0u32, 0u32, 0u32, 0u32);
    let n = 40_000u64;
    for i in 0..n {
        let (tri, p, ng) = point_on(s, &glass, i);
        // Any direction: the test sorts out which leave.
        let (z, phi) = (2.0 * u(5 * i + 3) - 1.0, std::f32::consts::TAU * u(5 * i + 4));
        let r = (1.0 - z * z).max(0.0).sqrt();
        let d = Vec3::new(r * phi.cos(), r * phi.sin(), z);
        let front = if ng.dot(d) > 0.0 { ng } else { -ng };
        let o = s.offset_ray_origin(p, front);
        let full = s.accel.intersect(o, d, f32::INFINITY);
        assert_eq!(key(full), key(s.intersect_surface(o, d, 0, tri)), "{case}: ray {i} from triangle {tri}");
        let Some(solid) = s.solid_left(tri, d) else { continue };
        assert_eq!(s.solid_of(tri), Some(solid));
        assert_eq!(s.solid_tmin(tri, o, d), 0.0, "ray {i}: a leaving ray got an inward bound");
        leaving += 1;
        hits += full.is_some() as u32;
        assert!(full.is_none_or(|h| s.solid_of(h.triangle) != Some(solid)), "ray {i}: a leaving ray met its solid");
        // From just behind the facet the full walk may meet the solid; the skipping one seldom.
        let inside = s.offset_ray_origin(p, -front);
        let own = |h: Option<renderer::accel::Hit>| h.is_some_and(|h| s.solid_of(h.triangle) == Some(solid));
        own_from_inside += own(s.accel.intersect(inside, d, f32::INFINITY)) as u32;
        own_skipping += own(s.intersect_surface(inside, d, 0, tri)) as u32;
    }
    eprintln!(
        "{case}: {leaving} of {n} rays leave a solid, {hits} of them hit something; from \
         inside, {own_from_inside} full walks and {own_skipping} skipping ones meet the solid"
    );
    assert!(leaving as u64 > n / 3, "{leaving} of {n}: about half the directions leave");
    assert!(hits > leaving / 10, "{hits} of {leaving}: the floor and the other spheres must be hit");
    assert!(own_from_inside > leaving / 10, "{own_from_inside} full walks from inside met their solid");
    assert!(own_skipping * 10 < own_from_inside, "{own_skipping} skipping walks met their solid: nothing was skipped");
}

/// envlit's kind of scene: an opaque Lambert icosphere resting on a floor, a rough metal UV
/// sphere, and a glowing sphere (an emitter: left out), under a lamp.
fn opaque_scene() -> Scene {
    let mut b = SceneBuilder::default();
    let floor = b.material(lambert(Vec3::splat(0.6)));
    let white = b.material(lambert(Vec3::splat(0.8)));
    let metal = b.material(renderer::testing::metal(Vec3::splat(0.9), 0.3));
    let glow = b.material(emitter(Vec3::splat(4.0)));
    let lamp = b.material(emitter(Vec3::splat(20.0)));
    b.quad(Vec3::ZERO, Vec3::new(4.0, 0.0, 0.0), Vec3::new(0.0, 0.0, -4.0), floor);
    b.sphere(Vec3::new(-1.0, 0.5, 0.0), 0.5, 3, false, white);
    b.uv_sphere(Vec3::new(0.3, 0.6, -0.4), 0.4, 32, 16, metal);
    b.sphere(Vec3::new(1.3, 0.4, 0.6), 0.3, 2, false, glow);
    b.quad(Vec3::new(0.0, 3.0, 0.0), Vec3::new(0.5, 0.0, 0.0), Vec3::new(0.0, 0.0, 0.5), lamp);
    b.look_at(Vec3::new(0.0, 1.6, 4.0), Vec3::new(0.0, 0.4, 0.0), 40.0);
    b.build()
}

/// Opaque closed convex solids only skip themselves when a ray leaves them: bounce rays
/// (`Scene::intersect_surface`) and shadow rays (`Scene::visibility_from`,
/// `Accel::occluded_leaving`) find what the full walks find, and the skip is real (from just
/// behind the facets the full walks meet the solid, the skipping ones do not). No inward bound
/// and no occlusion shortcut: an opaque solid's rays never head inward.
#[test]
fn rays_leaving_an_opaque_solid_find_what_the_full_walks_find() {
    let s = opaque_scene();
    assert_eq!(s.convex_solids(), 0, "no glass");
    assert_eq!(s.opaque_solids(), 2, "the Lambert and metal spheres; the glowing one is an emitter");
    let on_solids: Vec<u32> = (0..s.mesh.triangles.len() as u32).filter(|&t| s.solid_of(t).is_some()).collect();
    let (mut leaving, mut blocked, mut own_from_inside, mut own_skipping) = (0u32, 0u32, 0u32, 0u32);
    let n = 40_000u64;
    for i in 0..n {
        let (tri, p, ng) = point_on(&s, &on_solids, i);
        let (z, phi) = (2.0 * u(5 * i + 3) - 1.0, std::f32::consts::TAU * u(5 * i + 4));
        let r = (1.0 - z * z).max(0.0).sqrt();
        let d = Vec3::new(r * phi.cos(), r * phi.sin(), z);
        let front = if ng.dot(d) > 0.0 { ng } else { -ng };
        let o = s.offset_ray_origin(p, front);
        assert_eq!(s.solid_tmin(tri, o, d), 0.0, "ray {i}: an opaque solid bounded a ray");
        assert!(!s.solid_blocks(o, d, 10.0), "ray {i}: an opaque solid blocked a shadow ray without a walk");
        let full = s.accel.intersect(o, d, f32::INFINITY);
        assert_eq!(key(full), key(s.intersect_surface(o, d, 0, tri)), "ray {i} from triangle {tri}");
        // A shadow ray to a point 0.5–3 away, and one to infinity.
        for tmax in [0.5 + 2.5 * u(5 * i + 3), f32::INFINITY] {
            assert_eq!(
                s.visibility(o, d, tmax),
                s.visibility_from(o, d, tmax, tri),
                "shadow ray {i} from triangle {tri} to {tmax}"
            );
        }
        let Some(solid) = s.solid_left(tri, d) else { continue };
        leaving += 1;
        blocked += s.accel.occluded(o, d, f32::INFINITY) as u32;
        // From just behind the facet the full walk meets the solid; the skipping one must not.
        let inside = s.offset_ray_origin(p, -front);
        own_from_inside += s.accel.occluded(inside, d, 0.05) as u32;
        own_skipping += s.accel.occluded_leaving(inside, d, 0.05, solid) as u32;
    }
    eprintln!(
        "{leaving} of {n} rays leave a solid, {blocked} of them blocked; from inside, within 0.05, \
         {own_from_inside} full walks and {own_skipping} skipping ones are blocked"
    );
    assert!(leaving as u64 > n / 3, "{leaving} of {n}: about half the directions leave");
    assert!(blocked > leaving / 20, "{blocked} of {leaving}: the floor and the other sphere must block some");
    assert!(own_from_inside > leaving / 2, "{own_from_inside} full walks from inside met their solid");
    assert!(own_skipping * 10 < own_from_inside, "{own_skipping} skipping walks met their solid: nothing was skipped");
}

/// Renders of the opaque scene are the same bits with its solids and without, with the kernel
/// and without, rays batched or not.
#[test]
fn opaque_solids_leave_renders_the_same_bits() {
    let mut s = opaque_scene();
    for (lanes, batched) in [(true, false), (false, false), (true, true), (false, true)] {
        s.set_lanes(lanes);
        s.set_batch_rays(batched);
        s.set_convex_solids(true);
        assert_eq!(s.opaque_solids(), 2);
        let with = render_bits(&s, 5);
        s.set_convex_solids(false);
        assert_eq!(s.opaque_solids(), 0);
        assert!(with == render_bits(&s, 5), "lanes {lanes}, batched {batched}: the opaque solids changed the image");
    }
}
