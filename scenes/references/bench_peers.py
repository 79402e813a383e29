#!/usr/bin/env python3
"""Tessera against its peers on the same scenes, in one command: paths/s, relMSE and efficiency.

    cargo build --release
    apt-get install libllvm19    # for Mitsuba's vectorised CPU backend (llvm_ad_rgb)
    python3 scenes/references/bench_peers.py [--spp 64] [--runs 3] [--variants scalar_rgb llvm_ad_rgb] [scenes...]
    python3 scenes/references/bench_peers.py --before /tmp/tessera-before ...   # before and after in one command
    python3 scenes/references/bench_peers.py --before target/release/tessera --before-args '--rr-depth 2' ...
        # one build against itself with another setting ('tessera before' is then the other setting)
    python3 scenes/references/bench_peers.py --threads 1 ...   # per core: one thread for every renderer
    python3 scenes/references/bench_peers.py --equal-strategy ...   # the same paths: light choice by power, no roulette

For each scene with a Mitsuba reference (make_references.py) it renders, at the reference's resolution
and `--spp`, with `tessera render` (default settings: mis, Sobol; the render time Tessera reports,
without process start and scene load) and with each Mitsuba variant (path integrator, independent
sampler, the scene translation of make_references.py; mi.render() timed on a loaded scene after one
warm-up render, so the LLVM backend's kernel compilation is not counted). The runs alternate between
Tessera and each peer, so a noisy machine's slow spells fall on all of them. Median over --runs runs
with different seeds; the errors also by their mean over the runs (a relMSE is heavy-tailed where
fireflies are, and the mean, not the median, estimates the expected error that equal error in equal
time is about), with a "by mean errors" efficiency ratio beside the median's ("mean relMSE" is net of
the reference's own share, as "relMSE" is; the range is of the raw figures). relMSE against the
reference: mean over pixels and channels of (x − ref)² / (ref² +
0.01). The reference is itself a noisy estimate, and its own error adds to every renderer's measured
relMSE alike (E[(x − ref)²] = Var x + Var ref), pulling every efficiency ratio towards 1; its expected
share is subtracted, as `tessera bench convergence` does, and the "raw" columns keep the measured figure.
The share is estimated from the reference's `variance` channel, the variance of its mean luminance, over
(luminance² + 0.01): the metric's per-channel terms, taken as equal to the luminance's (exact for grey
noise, close for the suite's white lights). A relMSE not at least 1.25 times that share is marked
"(unresolved)": the reference cannot tell it apart from its own noise, and its net figure is floored at
a tenth of the measured one. Efficiency = 1 / (relMSE · seconds): equal
efficiency means equal error in equal time; the ratio column is each renderer's efficiency over
Tessera's (above 1: better than Tessera). The summary also gives each paths/s ratio paired run by run
(the median over runs of the peer's time over Tessera's in that run, and their range), which a slow
spell of a shared machine moves less than the ratio of the medians, and the range of the efficiency
ratio run by run ("runs a–b": each run's own time and net relMSE on both sides), how far a single
run's answer can stray where fireflies make the relMSE heavy-tailed.
"""
import argparse
import collections
import os
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

LLVM = "/usr/lib/x86_64-linux-gnu/libLLVM-19.so"
if os.path.exists(LLVM):
    os.environ.setdefault("DRJIT_LIBLLVM_PATH", LLVM)

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import make_references as mr  # noqa: E402
from equal_time import TESSERA, rel_mse  # noqa: E402  (the same metric and binary as equal_time.py)
from bench_mitsuba_rays import set_vector_width  # noqa: E402


def reference_own_rel_mse(ref_rgb, variance):
    """The reference's own expected relMSE: its variance of the mean luminance over (luminance² + 0.01),
    averaged over pixels (`tessera bench convergence`'s `reference_of`)."""
    y = ref_rgb @ np.array([0.2126, 0.7152, 0.0722])
    own = variance / (y * y + 1e-2)
    return float(np.mean(np.where(np.isfinite(own), own, 0.0)))


Build = collections.namedtuple("Build", "label binary extra times errs")


def net_rel_mse(e, own):
    """A measured relMSE less the reference's own share `own`, floored at a tenth of the measured
    figure (a render as noisy as the reference cannot be resolved by it)."""
    return max(e - own, 0.1 * e)


def host_description():
    """The CPU this run measured on, as the ratios depend on it (Dr.Jit runs 16 lanes where the CPU
    has AVX-512, 8 on AVX2; our kernel runs 8 on both): model name, family and model, and the vector
    extension. "unknown host" where /proc/cpuinfo cannot be read."""
    try:
        with open("/proc/cpuinfo") as f:
            fields = {}
            for line in f:
                if not line.strip():
                    break  # the first processor's block is enough
                key, _, value = line.partition(":")
                fields[key.strip()] = value.strip()
    except OSError:
        return "unknown host"
    flags = fields.get("flags", "").split()
    isa = "AVX-512" if "avx512f" in flags else "AVX2" if "avx2" in flags else "no AVX2"
    return (f"{fields.get('model name', '?')}, family {fields.get('cpu family', '?')} "
            f"model {fields.get('model', '?')}, {isa}")


# Issue 15's two goals, per scene against Mitsuba's llvm_ad_rgb: Tessera's paths/s at least the
# peer's (the ratio paired run by run, which a slow spell moves least) and the peer's efficiency at
# most half of Tessera's (by mean errors, the estimate of the expected error; a median of a few
# heavy-tailed relMSEs underestimates it).
GOAL_PATHS = 1.0
GOAL_EFFICIENCY = 0.5


def goal_ratios(ours, peer, own):
    """The two goals' figures from per-run (time, relMSE) pairs of Tessera and the peer: the median
    over runs of the peer's time over ours (paired paths/s), and the peer's efficiency over ours by
    mean errors (median times, mean relMSE less the reference's own share)."""
    paired = statistics.median(pt / t for (t, _), (pt, _) in zip(ours, peer))
    t = statistics.median(t for t, _ in ours)
    pt = statistics.median(pt for pt, _ in peer)
    e = net_rel_mse(statistics.fmean(e for _, e in ours), own)
    pe = net_rel_mse(statistics.fmean(pe for _, pe in peer), own)
    return paired, (t * e) / (pt * pe)


def goal_interval(ours, peer, own, draws=2000, level=0.9):
    """A bootstrap interval (`level`, percentile) of each of `goal_ratios`, the runs resampled with
    replacement as pairs (a run's renders of both sides together): how far the figures could move
    with other seeds and another slow spell. With three to five runs it is coarse, but it tells a
    ratio at the goal's line from one clear of it. A fixed seed, so the same runs give the same
    interval."""
    rng = np.random.default_rng(15)
    n = len(ours)
    paths, efficiency = [], []
    for _ in range(draws):
        pick = rng.integers(0, n, n)
        a, b = goal_ratios([ours[i] for i in pick], [peer[i] for i in pick], own)
        paths.append(a)
        efficiency.append(b)
    lo, hi = (1 - level) / 2 * 100, (1 + level) / 2 * 100
    return (tuple(np.percentile(paths, [lo, hi])), tuple(np.percentile(efficiency, [lo, hi])))


def verdict(value, interval, goal, at_least):
    """'met' where the whole interval is on the goal's side, 'NOT met' where the figure is not, and
    'at the line' where the figure is but the interval crosses the goal."""
    ok = value >= goal if at_least else value <= goal
    sure = interval[0] >= goal if at_least else interval[1] <= goal
    return "met" if ok and sure else "at the line" if ok else "NOT met"


def goal_verdicts(rows):
    """Per scene (name, paired paths/s ratio and its interval, efficiency ratio by mean errors and
    its interval), the verdict lines, whether every scene met both goals (the figure on the goal's
    side, 'at the line' included) and whether every one of those was clear of the line."""
    lines, met_all, clear_all = [], True, True
    for name, paths, paths_ci, efficiency, efficiency_ci in rows:
        fast = verdict(paths, paths_ci, GOAL_PATHS, True)
        efficient = verdict(efficiency, efficiency_ci, GOAL_EFFICIENCY, False)
        met_all &= fast != "NOT met" and efficient != "NOT met"
        clear_all &= fast == "met" and efficient == "met"
        lines.append(f"{name:<14} paths/s {paths:.2f} (90 % {paths_ci[0]:.2f}–{paths_ci[1]:.2f}) {fast} "
                     f"(>= {GOAL_PATHS:.1f}),   peer efficiency {efficiency:.2f} (90 % {efficiency_ci[0]:.2f}–"
                     f"{efficiency_ci[1]:.2f}) {efficient} (<= {GOAL_EFFICIENCY:.1f})")
    return lines, met_all, clear_all


def main():
    import mitsuba as mi
    ap = argparse.ArgumentParser()
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--variants", nargs="+", default=["scalar_rgb", "llvm_ad_rgb"],
                    help='Mitsuba variants to run beside Tessera; "none" for Tessera alone')
    ap.add_argument("--tessera-args", default="", help="extra flags for tessera render (quoted)")
    ap.add_argument("--before", metavar="BIN",
                    help="another tessera build (e.g. the commit before a change), run in the same "
                         "alternation with the same seeds: a 'tessera before' row and before/after ratios, "
                         "so a noisy machine's slow spells fall on both builds alike")
    ap.add_argument("--before-args", default="", metavar="FLAGS",
                    help="extra flags for the --before build alone (quoted), after --tessera-args: one build "
                         "against itself with other settings in one command, e.g. --before target/release/tessera "
                         "--before-args '--rr-depth 2' (the 'tessera before' row is then the other setting)")
    ap.add_argument("--vector-width", type=int, choices=[4, 8, 16],
                    help="Dr.Jit's LLVM vector width for the llvm variants (default: the host's widest)")
    ap.add_argument("--threads", type=int, metavar="N",
                    help="threads for every renderer: Tessera's --threads and Dr.Jit's thread pool "
                         "(dr.set_thread_count, which Mitsuba's scalar and llvm variants both render on); "
                         "1 compares per-core speed, the issue's measure, without the two cores' interplay "
                         "(default: all cores for both)")
    ap.add_argument("--rr-depth", type=int, metavar="N",
                    help="the bounce from which Russian roulette may end paths, for every renderer (Tessera's "
                         "--rr-depth, Mitsuba's rr_depth; default 5 for both). The two play it differently past "
                         "that bounce (Tessera only below a throughput of 1/4, Mitsuba below 0.95), so their "
                         "paths differ in length; 65 or more turns it off for both, and paths/s then compares "
                         "paths ended by the same rule (escape, absorption, the depth limit)")
    ap.add_argument("--max-depth", type=int, metavar="N",
                    help="the bounce limit for every renderer (Tessera's --max-depth: 0 emission only, 1 direct "
                         "light; Mitsuba's max_depth N + 1; default 64): paths/s of the paths' first N bounces, "
                         "where a short path's fixed costs show. The references are of full depth, so the relMSE "
                         "and efficiency columns then measure the missing light, not noise")
    ap.add_argument("--equal-strategy", action="store_true",
                    help="every renderer traces the same paths by the same rules, so paths/s compares the "
                         "cost of a path alone: Tessera picks NEE's light in proportion to power, as Mitsuba "
                         "does (--light-sampler power; its default, auto, may pick the light tree), and "
                         "Russian roulette is off for both (--rr-depth 65 unless --rr-depth is given), so "
                         "paths end where they escape, are absorbed or reach the depth limit. Tessera's "
                         "defaults trade paths/s for efficiency (longer paths, the tree); this measures "
                         "the per-path speed those choices spend")
    ap.add_argument("scenes", nargs="*", default=list(mr.SCENES))
    a = ap.parse_args()
    # Whether the user asked for other Tessera settings (the flags below are added to these).
    own_tessera_args = a.tessera_args.strip() != ""
    if a.equal_strategy:
        if any(arg.split("=")[0] == "--light-sampler" for arg in a.tessera_args.split()):
            ap.error("--equal-strategy sets Tessera's --light-sampler itself")
        a.tessera_args = f"{a.tessera_args} --light-sampler power"
        if a.rr_depth is None:
            a.rr_depth = 65
    if a.rr_depth is not None:
        if a.rr_depth < 0:
            ap.error("--rr-depth must be at least 0")
        a.tessera_args = f"{a.tessera_args} --rr-depth {a.rr_depth}"
    if a.max_depth is not None:
        if a.max_depth < 0:
            ap.error("--max-depth must be at least 0")
        a.tessera_args = f"{a.tessera_args} --max-depth {a.max_depth}"
    if a.threads is not None:
        if a.threads < 1:
            ap.error("--threads must be at least 1")
        a.tessera_args = f"{a.tessera_args} --threads {a.threads}"

    def peer_render(scene, seed):
        """mi.render, evaluated, and its seconds, on `--threads` of Dr.Jit's pool. The pool is set
        to N only around the render, outside the timing: with one thread set beforehand,
        Mitsuba's own EXR loading (mi.Bitmap, which this script reads every image with) hangs
        (Mitsuba 3.9.1, Dr.Jit's pool of one)."""
        import drjit as dr
        default = dr.thread_count()
        if a.threads is not None:
            dr.set_thread_count(a.threads)
        try:
            t0 = time.perf_counter()
            img = np.array(mi.render(scene, seed=seed, spp=a.spp), dtype=np.float64)
            return img, time.perf_counter() - t0
        finally:
            dr.set_thread_count(default)
    # `--variants llvm_ad_rgb cornell` would otherwise take the scene for a variant (nargs="+" is
    # greedy) and run every scene: scene names given there are scenes.
    moved = [v for v in a.variants if v in mr.SCENES]
    if moved:
        a.variants = [v for v in a.variants if v not in mr.SCENES] or ["none"]
        a.scenes = ([s for s in a.scenes if s not in moved] if a.scenes != list(mr.SCENES) else []) + moved
    unknown = [v for v in a.variants if v != "none" and v not in mi.variants()]
    if unknown:
        ap.error(f"unknown Mitsuba variant(s) {unknown} (this Mitsuba has {mi.variants()}); "
                 f"scenes are {sorted(mr.SCENES)}")
    host = host_description()
    print(f"host: {host}", file=sys.stderr)
    summary = []
    # Per scene: the reference's own relMSE share, and each renderer's (time, relMSE) run by run.
    runs = {}
    for name in a.scenes:
        rel, w, h = mr.SCENES[name]
        mi.set_variant("scalar_rgb")
        full = np.array(mi.Bitmap(os.path.join(mr.HERE, f"{name}.exr")), dtype=np.float64)
        ref = full[:, :, :3]
        own = reference_own_rel_mse(ref, full[:, :, 3]) if full.shape[2] > 3 else 0.0
        env = mr.ENVIRONMENTS.get(name)
        env_args = mr.tessera_env_args(name)
        with tempfile.TemporaryDirectory() as tmp:
            # Every peer's scene is loaded and warmed up first; then the runs alternate, one
            # Tessera render and one of each peer in turn, so a shared, noisy machine slows all
            # renderers alike rather than whichever happened to run during a slow spell.
            peers = []
            for variant in (v for v in a.variants if v != "none"):
                try:
                    mi.set_variant(variant)
                    if variant.startswith("llvm"):
                        import drjit as dr
                        width = set_vector_width(dr, a.vector_width)
                        print(f"{name}: {variant} with Dr.Jit vector width {width}", file=sys.stderr)
                    scene = mi.load_dict(mr.build_scene(os.path.join(mr.ROOT, rel), w, h, 1, tmp, env,
                                                         5 if a.rr_depth is None else a.rr_depth,
                                                         mr.TESSERA_MAX_DEPTH if a.max_depth is None else a.max_depth))
                    peer_render(scene, 999)  # warm-up (JIT compilation for llvm)
                    peers.append((variant, scene, [], []))
                except Exception as e:  # a missing libLLVM says so and the others still run
                    print(f"{name}: {variant} unavailable: {e}", file=sys.stderr)
            # Each Tessera build's row label, binary, extra flags, and its times and errors run by run.
            builds = [Build("tessera", TESSERA, [], [], [])]
            if a.before:
                builds.append(Build("tessera before", a.before, a.before_args.split(), [], []))
            for r in range(a.runs):
                out = os.path.join(tmp, "t.exr")
                # The two builds swap places every run: whichever follows a peer's render (whose
                # threads may still be winding down) is not always the same one.
                for b in (builds if r % 2 == 0 else builds[::-1]):
                    p = subprocess.run([b.binary, "render", os.path.join(mr.ROOT, rel), "-o", out, "--spp", str(a.spp),
                                        "--width", str(w), "--height", str(h), "--seed", str(r), *env_args,
                                        *a.tessera_args.split(), *b.extra], check=True, stderr=subprocess.PIPE, text=True)
                    b.times.append(float(p.stderr.split(" in ")[1].split("s ")[0]))
                    b.errs.append(rel_mse(np.array(mi.Bitmap(out), dtype=np.float64)[:, :, :3], ref))
                for variant, scene, ptimes, perrs in peers:
                    mi.set_variant(variant)
                    img, seconds = peer_render(scene, 1000 + r)
                    ptimes.append(seconds)
                    perrs.append(rel_mse(img[:, :, :3], ref))
            # Times by their median (a slow spell is an outlier to drop); errors by both their
            # median and their mean: a relMSE is one draw of a heavy-tailed quantity (a firefly
            # or two can double it), and what equal error in equal time asks about is its
            # expectation, which the mean estimates without bias and a median of few runs
            # underestimates wherever the tail is long.
            rows = [(b.label, statistics.median(b.times), statistics.median(b.errs), statistics.fmean(b.errs),
                     min(b.errs), max(b.errs)) for b in builds]
            rows += [(f"mitsuba {v}", statistics.median(t), statistics.median(e), statistics.fmean(e), min(e), max(e))
                     for v, _, t, e in peers]
            # Each renderer's (time, relMSE) in every run, for the figures paired run by run: a
            # run's renders follow one another within seconds, so a slow spell of a shared machine
            # falls on both sides of a pair, where it can fall on one side only of the ratio of
            # medians.
            by_label = {b.label: list(zip(b.times, b.errs)) for b in builds}
            by_label.update({f"mitsuba {v}": list(zip(t, e)) for v, _, t, e in peers})
            runs[name] = (own, by_label)
            del peers
        # Efficiency from the relMSE less the reference's own (`net_rel_mse`) and, raw, as measured.
        def net(e):
            return net_rel_mse(e, own)
        base = 1.0 / (rows[0][1] * net(rows[0][2]))
        base_raw = 1.0 / (rows[0][1] * rows[0][2])
        base_mean = 1.0 / (rows[0][1] * net(rows[0][3]))
        threads = f", {a.threads} thread{'s' if a.threads > 1 else ''}" if a.threads else ""
        threads += f", roulette from bounce {a.rr_depth}" if a.rr_depth is not None else ""
        threads += ", equal strategy (Tessera: --light-sampler power)" if a.equal_strategy else ""
        threads += f", at most {a.max_depth} bounces (relMSE: the light left out)" if a.max_depth is not None else ""
        print(f"\n{name} ({w}x{h}, {a.spp} spp{threads}, median of {a.runs} runs; the reference's own relMSE "
              f"{own:.2e}, subtracted)")
        print(f"{'renderer':<22} {'seconds':>8} {'Mpaths/s':>9} {'raw relMSE':>10} {'relMSE':>10} {'efficiency':>11} "
              f"{'vs tessera':>10} {'raw vs':>7}   {'mean relMSE':>11} {'vs tessera':>10}   raw relMSE range")
        for label, t, e, mean_e, lo_e, hi_e in rows:
            eff = 1.0 / (t * net(e))
            raw = 1.0 / (t * e) / base_raw
            eff_mean = 1.0 / (t * net(mean_e)) / base_mean
            flag = "" if e - own >= 0.25 * own else "  (unresolved)"
            print(f"{label:<22} {t:>8.3f} {w * h * a.spp / t / 1e6:>9.3f} {e:>10.3e} {net(e):>10.3e} {eff:>11.1f} "
                  f"{eff / base:>10.2f} {raw:>7.2f}   {net(mean_e):>11.3e} {eff_mean:>10.2f}   "
                  f"{lo_e:.3e}–{hi_e:.3e}{flag}")
            summary.append((name, label, t, w * h * a.spp / t / 1e6, e, eff / base, raw, eff_mean))
    print("\nsummary: Tessera's paths/s over each peer's, and each peer's efficiency over Tessera's "
          "(the reference's own noise subtracted; raw: as measured; by mean errors: each renderer's "
          "relMSE averaged over the runs, the estimate of its expected error, instead of their median); "
          "paired: the median over runs of the peer's time over Tessera's in the same run, with the "
          "runs' range; runs: the range of the efficiency ratio run by run (each run's own time and "
          "error on both sides), how far one run's answer can stray")

    print(f"host: {host}")

    def paired(name, label):
        # The same spp and size on both sides, so a time ratio is the paths/s ratio.
        _, by_label = runs[name]
        ratios = [pt / t for (t, _), (pt, _) in zip(by_label["tessera"], by_label[label])]
        return statistics.median(ratios), min(ratios), max(ratios)

    def efficiency_by_run(name, label):
        # The peer's efficiency over Tessera's run by run, from each run's own time and net error
        # on both sides: a heavy-tailed relMSE spreads these wide where fireflies are.
        own, by_label = runs[name]
        return [(t * net_rel_mse(e, own)) / (pt * net_rel_mse(pe, own))
                for (t, e), (pt, pe) in zip(by_label["tessera"], by_label[label])]
    goals = []
    for name in a.scenes:
        mine = [s for s in summary if s[0] == name and s[1] == "tessera"]
        before = [s for s in summary if s[0] == name and s[1] == "tessera before"]
        for s in summary:
            if s[0] == name and not s[1].startswith("tessera") and mine:
                then = ""
                if before:
                    # The peer's efficiency over the earlier build's: both are over the current one.
                    then = (f"   (before: paths/s ratio {before[0][3] / s[3]:.2f}, peer efficiency ratio "
                            f"{s[5] / before[0][5]:.2f}, by mean errors {s[7] / before[0][7]:.2f})")
                pm, lo, hi = paired(name, s[1])
                by_run = efficiency_by_run(name, s[1])
                elo, ehi = min(by_run), max(by_run)
                if before:
                    bm, blo, bhi = paired(name, "tessera before")
                    then += f"   (this build over the one before, paired: {bm:.2f}, {blo:.2f}–{bhi:.2f})"
                print(f"{name:<14} vs {s[1]:<22} paths/s ratio {mine[0][3] / s[3]:>6.2f} (paired {pm:.2f}, "
                      f"{lo:.2f}–{hi:.2f})   peer efficiency ratio {s[5]:>6.2f} (runs {elo:.2f}–{ehi:.2f})   "
                      f"raw {s[6]:>6.2f}   "
                      f"by mean errors {s[7]:>6.2f}{then}")
                if s[1] == "mitsuba llvm_ad_rgb":
                    # The figures (the summary line's paired and by-mean-errors ones) and their
                    # intervals from one function.
                    own_share, by_label = runs[name]
                    ours, peer = by_label["tessera"], by_label[s[1]]
                    paths, efficiency = goal_ratios(ours, peer, own_share)
                    paths_ci, efficiency_ci = goal_interval(ours, peer, own_share)
                    goals.append((name, paths, paths_ci, efficiency, efficiency_ci))
    if goals:
        lines, met_all, clear_all = goal_verdicts(goals)
        changed = [f for f, on in (("--equal-strategy", a.equal_strategy), ("--rr-depth", a.rr_depth is not None),
                                   ("--max-depth", a.max_depth is not None),
                                   ("--vector-width", a.vector_width is not None),
                                   ("--tessera-args", own_tessera_args)) if on]
        print("\ngoals (issue 15: paths/s paired >= 1, Mitsuba llvm_ad_rgb's efficiency by mean errors <= 0.5; "
              "90 %: bootstrap interval over the runs; 'at the line': the figure meets the goal, the interval "
              "crosses it)"
              + (f"; NOT at default settings ({', '.join(changed)}), where the goals are stated" if changed else ""))
        for line in lines:
            print(line)
        print(f"every scene met both goals: {'yes' if met_all else 'no'}"
              f"{', some at the line' if met_all and not clear_all else ''} ({len(goals)} scenes, {a.runs} runs, "
              f"{a.spp} spp; host: {host})")


if __name__ == "__main__":
    main()
