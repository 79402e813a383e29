// Embree 3 (the libembree3 Mitsuba 3 ships, the one its llvm_ad_rgb wavefronts run on) on the rays
// `tessera bench rays --dump DIR` wrote: one ray at a time (rtcIntersect1 / rtcOccluded1) and in
// packets of 8 and 16 consecutive rays (rtcIntersect8/16, rtcOccluded8/16), one thread, from C++ so
// no wrapper's per-ray cost is counted. Built and run by bench_embree_packets.py, which explains why.
//
//   embree_packets DIR RUNS   ->  one line per query kind: "name Mrays/s hits" (the median of RUNS)
#include <embree3/rtcore.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <functional>
#include <string>
#include <vector>

#ifdef RTC_NAMESPACE
using namespace RTC_NAMESPACE;
#endif

static std::vector<float> load(const std::string &dir, const char *name) {
    std::string path = dir + "/" + name;
    FILE *f = std::fopen(path.c_str(), "rb");
    if (!f) {
        std::fprintf(stderr, "cannot open %s\n", path.c_str());
        std::exit(1);
    }
    std::fseek(f, 0, SEEK_END);
    long bytes = std::ftell(f);
    std::fseek(f, 0, SEEK_SET);
    std::vector<float> v(bytes / 4);
    if (std::fread(v.data(), 4, v.size(), f) != v.size()) {
        std::fprintf(stderr, "short read of %s\n", path.c_str());
        std::exit(1);
    }
    std::fclose(f);
    return v;
}

struct Rays {
    std::vector<float> o, d, sd, st;
    size_t n() const { return o.size() / 3; }
};

// One timed pass of `query` (which returns how many rays it found a hit for); Mrays/s and hits.
template <typename F> static std::pair<double, size_t> timed(size_t n, F query) {
    auto t0 = std::chrono::steady_clock::now();
    size_t hits = query();
    double s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    return {n / s / 1e6, hits};
}

// Ray i of `r` into a ray, or into lane k of a packet (`at` picks the lane's element, or the
// field itself for a single ray): closest-hit rays go along `r.d` to infinity, occlusion rays
// (`shadow`) along `r.sd` to `r.st`.
template <typename Ray, typename At>
static void set_ray(Ray &ray, At at, const Rays &r, size_t i, bool shadow) {
    const std::vector<float> &d = shadow ? r.sd : r.d;
    at(ray.org_x) = r.o[3 * i], at(ray.org_y) = r.o[3 * i + 1], at(ray.org_z) = r.o[3 * i + 2];
    at(ray.dir_x) = d[3 * i], at(ray.dir_y) = d[3 * i + 1], at(ray.dir_z) = d[3 * i + 2];
    at(ray.tfar) = shadow ? r.st[i] : INFINITY;
    at(ray.mask) = ~0u;
}

// Ray i of a packet of W starting at ray `first`, for lane k: past the rays' end, the first ray
// again (its lane marked invalid by the caller).
static size_t lane_ray(size_t first, int k, size_t n) { return first + k < n ? first + k : first; }

// What a query needs of its ray structure, a single ray's or a packet's (`at` picks a packet
// lane's element, or the field itself): the rays it traces, the part holding the ray, what to
// clear before the call and whether the query found something.
struct Closest {
    static constexpr bool shadow = false;
    template <class P> static auto &ray(P &p) { return p.ray; }
    template <class P, class At> static void clear(P &p, At at) { at(p.hit.geomID) = RTC_INVALID_GEOMETRY_ID; }
    template <class P, class At> static bool found(P &p, At at) { return at(p.hit.geomID) != RTC_INVALID_GEOMETRY_ID; }
};
struct Occluded {
    static constexpr bool shadow = true;
    template <class P> static P &ray(P &p) { return p; }
    template <class P, class At> static void clear(P &, At) {}
    template <class P, class At> static bool found(P &p, At at) { return at(p.tfar) < 0.0f; }
};

// Every ray one at a time (`query` is rtcIntersect1 or rtcOccluded1 on `P`): how many found something.
template <class Kind, class P, class Query> static size_t singles(RTCScene scene, const Rays &r, Query query) {
    RTCIntersectContext ctx;
    rtcInitIntersectContext(&ctx);
    auto field = [](auto &f) -> auto & { return f; };
    size_t found = 0;
    for (size_t i = 0; i < r.n(); i++) {
        P p;
        std::memset(&p, 0, sizeof p);
        set_ray(Kind::ray(p), field, r, i, Kind::shadow);
        Kind::clear(p, field);
        query(scene, &ctx, &p);
        found += Kind::found(p, field);
    }
    return found;
}

// The rays in packets of W consecutive ones (`query` is rtcIntersectW or rtcOccludedW on `P`),
// lanes past the end invalid: how many found something.
template <class Kind, int W, class P, class Query> static size_t packets(RTCScene scene, const Rays &r, Query query) {
    RTCIntersectContext ctx;
    rtcInitIntersectContext(&ctx);
    auto lane = [](int k) { return [k](auto &f) -> auto & { return f[k]; }; };
    size_t found = 0, n = r.n();
    for (size_t i = 0; i < n; i += W) {
        alignas(64) P p;
        alignas(64) int valid[W];
        std::memset(&p, 0, sizeof p);
        for (int k = 0; k < W; k++) {
            valid[k] = i + k < n ? -1 : 0;
            set_ray(Kind::ray(p), lane(k), r, lane_ray(i, k, n), Kind::shadow);
            Kind::clear(p, lane(k));
        }
        query(valid, scene, &ctx, &p);
        for (int k = 0; k < W; k++) found += valid[k] && Kind::found(p, lane(k));
    }
    return found;
}

int main(int argc, char **argv) {
    if (argc < 3) {
        std::fprintf(stderr, "usage: embree_packets DIR RUNS\n");
        return 2;
    }
    std::string dir = argv[1];
    int runs = std::max(1, std::atoi(argv[2]));
    std::vector<float> v = load(dir, "vertices.f32");
    Rays r{load(dir, "origins.f32"), load(dir, "directions.f32"), load(dir, "shadow_directions.f32"),
           load(dir, "shadow_tmax.f32")};
    size_t tris = v.size() / 9, n = r.n();

    RTCDevice device = rtcNewDevice("threads=1");
    RTCScene scene = rtcNewScene(device);
    RTCGeometry geom = rtcNewGeometry(device, RTC_GEOMETRY_TYPE_TRIANGLE);
    auto *vb = (float *)rtcSetNewGeometryBuffer(geom, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT3, 12, tris * 3);
    std::memcpy(vb, v.data(), tris * 9 * sizeof(float));
    auto *ib = (unsigned *)rtcSetNewGeometryBuffer(geom, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3, 12, tris);
    for (size_t i = 0; i < tris * 3; i++) ib[i] = (unsigned)i;
    rtcCommitGeometry(geom);
    rtcAttachGeometry(scene, geom);
    rtcReleaseGeometry(geom);
    rtcCommitScene(scene);

    struct Query {
        const char *name;
        std::function<size_t()> run;
    };
    std::vector<Query> queries = {
        {"closest1", [&] { return singles<Closest, RTCRayHit>(scene, r, rtcIntersect1); }},
        {"closest8", [&] { return packets<Closest, 8, RTCRayHit8>(scene, r, rtcIntersect8); }},
        {"closest16", [&] { return packets<Closest, 16, RTCRayHit16>(scene, r, rtcIntersect16); }},
        {"occluded1", [&] { return singles<Occluded, RTCRay>(scene, r, rtcOccluded1); }},
        {"occluded8", [&] { return packets<Occluded, 8, RTCRay8>(scene, r, rtcOccluded8); }},
        {"occluded16", [&] { return packets<Occluded, 16, RTCRay16>(scene, r, rtcOccluded16); }},
    };
    for (auto &q : queries) {
        q.run();  // warm-up
        std::vector<double> rates;
        size_t hits = 0;
        for (int k = 0; k < runs; k++) {
            auto [rate, h] = timed(n, q.run);
            rates.push_back(rate);
            hits = h;
        }
        std::sort(rates.begin(), rates.end());
        std::printf("%s %.3f %zu\n", q.name, rates[rates.size() / 2], hits);
    }
    rtcReleaseScene(scene);
    rtcReleaseDevice(device);
    return 0;
}
