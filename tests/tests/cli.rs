//! The `tessera` command's local features end to end: budgets on `tessera render`,
//! `tessera bench convergence` and `tessera bench rays --scene`.

use std::process::Command;
use tessera_tests::*;

fn tessera(args: &[&str], dir: &std::path::Path) -> (bool, String, String) {
    let out = Command::new(tessera_bin()).args(args).current_dir(dir).output().expect("tessera runs");
    (out.status.success(), String::from_utf8_lossy(&out.stdout).into(), String::from_utf8_lossy(&out.stderr).into())
}

#[test]
fn render_reports_noise_and_honours_budgets() {
    let tmp = temp_dir("cli-render");
    let (ok, _, err) =
        tessera(&["render", "-o", "n.exr", "--width", "64", "--height", "64", "--noise-target", "0.05"], &tmp);
    assert!(ok, "{err}");
    assert!(err.contains("estimated noise: relative error"), "{err}");
    assert!(err.contains("stopped by noise_target"), "{err}");
    let exr = renderer::image_io::read_exr(&tmp.join("n.exr")).unwrap();
    let attr = exr.tessera.expect("tessera attribute");
    let rel: f64 = renderer::image_io::attribute_field(&attr, "rel_error").unwrap().parse().unwrap();
    assert!(rel > 0.0 && rel <= 0.05, "{attr}");
    assert_eq!(renderer::image_io::attribute_field(&attr, "stop"), Some("noise_target"));
    let tiles = renderer::image_io::attribute_field(&attr, "tiles").unwrap();
    assert_eq!(tiles.split(';').count(), 4, "2×2 tiles of 32 px: {tiles}");

    let (ok, _, err) =
        tessera(&["render", "-o", "t.exr", "--width", "64", "--height", "64", "--time-budget", "0.5"], &tmp);
    assert!(ok, "{err}");
    assert!(err.contains("stopped by time_budget"), "{err}");

    for bad in [["--noise-target", "0"], ["--time-budget", "-1"], ["--min-spp", "1"]] {
        let mut args = vec!["render", "-o", "x.exr", "--width", "8", "--height", "8"];
        args.extend_from_slice(&bad);
        let (ok, _, err) = tessera(&args, &tmp);
        assert!(!ok && err.contains("error:"), "{bad:?} was accepted: {err}");
    }
}

#[test]
fn bench_convergence_writes_csv_plots_and_summary() {
    let tmp = temp_dir("cli-convergence");
    let scenes = repo_root().join("scenes");
    let extra = scenes.join("khronos/DamagedHelmet/DamagedHelmet.gltf");
    let (ok, stdout, err) = tessera(
        &[
            "bench",
            "convergence",
            "--suite",
            "cornell",
            "--switches",
            "integrator,sampler",
            "--time-cap",
            "0.05",
            "--scenes-dir",
            scenes.to_str().unwrap(),
            "--reference-spp",
            "16",
            "--width",
            "32",
            "--height",
            "32",
            "-o",
            "out",
            extra.to_str().unwrap(),
        ],
        &tmp,
    );
    assert!(ok, "{err}");
    let csv = std::fs::read_to_string(tmp.join("out/convergence.csv")).unwrap();
    let rows: Vec<Vec<&str>> = csv.lines().skip(1).map(|l| l.split(',').collect()).collect();
    for (scene, value) in [("cornell", "bsdf"), ("cornell", "independent"), ("DamagedHelmet", "mis")] {
        let r: Vec<_> = rows.iter().filter(|r| r[0] == scene && r[2] == value).collect();
        assert!(!r.is_empty(), "no {scene} {value} rows:\n{csv}");
        // spp doubles from 1, errors and times are positive numbers.
        for (k, row) in r.iter().enumerate() {
            assert_eq!(row[3].parse::<u32>().unwrap(), 1 << k);
            assert!(row[4].parse::<f64>().unwrap() > 0.0 && row[9].parse::<f64>().unwrap() > 0.0, "{row:?}");
            // rel_mse = raw − the reference's own relMSE, resolved only clear of it.
            let (rel, raw, own) =
                (row[5].parse::<f64>().unwrap(), row[9].parse::<f64>().unwrap(), row[10].parse::<f64>().unwrap());
            assert!((rel - (raw - own)).abs() <= 1e-5 * raw, "{row:?}");
            assert_eq!(row[11] == "true", rel > 0.0 && rel >= 0.25 * own, "{row:?}");
        }
    }
    assert!(rows.iter().any(|r| r[8] == "Tessera mis 16 spp"), "the helmet has no committed reference");
    for png in ["cornell.png", "DamagedHelmet.png"] {
        let bytes = std::fs::read(tmp.join("out").join(png)).unwrap();
        assert_eq!(&bytes[1..4], b"PNG");
    }
    assert!(stdout.contains("| integrator | bsdf |"), "{stdout}");
    let (ok, _, err) = tessera(&["bench", "convergence", "--suite", "nowhere", "-o", "out2"], &tmp);
    assert!(!ok && err.contains("not in the suite"), "{err}");
}

/// A sequence is frames × the still: each frame of `--frames 0-3` is byte-identical to the same
/// frame rendered alone with `--frame N`, and frames differ where the scene moves.
#[test]
fn render_frames_writes_a_sequence_identical_to_single_frames() {
    let tmp = temp_dir("cli-frames");
    let scene = repo_root().join("scenes/animation/moving_light.gltf");
    let scene = scene.to_string_lossy().into_owned();
    let common = ["--width", "32", "--height", "32", "--spp", "8", "--max-depth", "2"];
    let mut args = vec!["render", scene.as_str(), "--frames", "0-3", "-o", "seq/shot.####.exr"];
    args.extend_from_slice(&common);
    let (ok, _, err) = tessera(&args, &tmp);
    assert!(ok, "{err}");
    let mut previous: Option<Vec<u8>> = None;
    for f in 0..4 {
        let seq = std::fs::read(tmp.join(format!("seq/shot.{f:04}.exr"))).expect("frame written");
        let out = format!("single{f}.exr");
        let n = f.to_string();
        let mut args = vec!["render", scene.as_str(), "--frame", n.as_str(), "-o", out.as_str()];
        args.extend_from_slice(&common);
        let (ok, _, err) = tessera(&args, &tmp);
        assert!(ok, "{err}");
        assert!(seq == std::fs::read(tmp.join(&out)).expect("single frame"), "frame {f} differs from --frame {f}");
        assert!(previous.as_ref() != Some(&seq), "frame {f} equals the frame before it: nothing moved");
        previous = Some(seq);
    }
    let (ok, _, err) = tessera(&["render", scene.as_str(), "--frames", "5-1", "-o", "x.exr"], &tmp);
    assert!(!ok && err.contains("settings.frames"), "{err}");
}

/// `bench rays --scene`: a row per accelerator, obvhs' wide and compressed nodes finding the
/// same closest hits on a real scene (the own BVH2's row is only required to be there); a
/// missing scene is an error naming it, not a panic.
#[test]
fn bench_rays_on_a_scene_compares_the_accelerators() {
    let tmp = temp_dir("cli-bench-rays");
    let scene = repo_root().join("scenes/glass/glass.gltf");
    let (ok, stdout, err) =
        tessera(&["bench", "rays", "--scene", scene.to_str().unwrap(), "--rays", "2000", "--runs", "1"], &tmp);
    assert!(ok, "{err}");
    let hits: Vec<&str> = ["obvhs ", "obvhs-compressed ", "own "]
        .iter()
        .map(|k| {
            let row = stdout.lines().find(|l| l.starts_with(k)).unwrap_or_else(|| panic!("no {k} row: {stdout}"));
            row.rsplit('(').next().unwrap_or_default()
        })
        .collect();
    assert!(hits[0].contains("closest hits") && !hits[0].starts_with("0 "), "{stdout}");
    assert_eq!(hits[0], hits[1], "{stdout}");
    // The interleaved pairs and batches find what each ray finds alone (closest and occluded).
    let full = format!("  batch of {}", renderer::accel::MAX_BATCH);
    for row in ["  paired", "  batch of 4", &full] {
        assert!(stdout.lines().any(|l| l.starts_with(row) && l.ends_with("one at a time: true)")), "{row}: {stdout}");
    }
    // `--dump` writes what scenes/references/bench_embree.py --scene reads: 2000 rays' origins,
    // directions, closest-hit distances (as many finite as the obvhs row's hits) and occlusion rays.
    let dump = tmp.join("dump");
    let (ok, stdout, err) = tessera(
        &["bench", "rays", "--scene", scene.to_str().unwrap(), "--rays", "2000", "--runs", "1", "--dump", "dump"],
        &tmp,
    );
    assert!(ok, "{err}");
    let floats = |name: &str| -> Vec<f32> {
        let bytes = std::fs::read(dump.join(name)).unwrap_or_else(|e| panic!("{name}: {e}"));
        bytes.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect()
    };
    for (name, len) in
        [("origins.f32", 6000), ("directions.f32", 6000), ("shadow_directions.f32", 6000), ("shadow_tmax.f32", 2000)]
    {
        assert_eq!(floats(name).len(), len, "{name}");
    }
    assert_eq!(floats("vertices.f32").len() % 9, 0);
    let finite = floats("t_closest.f32").iter().filter(|t| t.is_finite()).count();
    let obvhs = stdout.lines().find(|l| l.starts_with("obvhs ")).unwrap_or_default();
    assert!(obvhs.ends_with(&format!("({finite} closest hits)")), "{finite} finite distances: {stdout}");
    let (ok, _, err) = tessera(&["bench", "rays", "--scene", "missing.gltf", "--rays", "10"], &tmp);
    assert!(!ok && err.contains("missing.gltf"), "{err}");
    // `--accel own --no-batches`: that accelerator's row alone, the same hits as obvhs found.
    let (ok, alone, err) = tessera(
        &[
            "bench",
            "rays",
            "--scene",
            scene.to_str().unwrap(),
            "--rays",
            "2000",
            "--runs",
            "1",
            "--accel",
            "own",
            "--no-batches",
        ],
        &tmp,
    );
    assert!(ok, "{err}");
    let rows: Vec<&str> = alone.lines().skip(2).collect();
    assert_eq!(rows.len(), 1, "{alone}");
    assert!(rows[0].starts_with("own ") && rows[0].ends_with(&format!("({finite} closest hits)")), "{alone}");
    let (ok, _, err) = tessera(&["bench", "rays", "--scene", scene.to_str().unwrap(), "--accel", "bvh9"], &tmp);
    assert!(!ok && err.contains("bvh9"), "{err}");
}
