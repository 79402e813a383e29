//! Mutation fuzzing of the glTF loader and the render behind it: the repository's scenes, each
//! changed in one place (a number set to an extreme, a value of the wrong type, a key or an array
//! entry removed, an enum swapped, bytes of a buffer overwritten), must load or fail with an
//! error, never panic; what loads must render a small image (both the scalar path and the
//! eight-lane kernel, animated scenes at a later frame too) to finite values, never panic.
//!
//! The mutations are a function of the case number, so a failure names the case that reproduces
//! it: `TESSERA_FUZZ_CASE=N cargo test --release -p tessera-renderer --test mutation_fuzz`.
//! `TESSERA_FUZZ_CASES` sets how many cases run (default 240: a few seconds). An abort (a failed
//! allocation, a panic on another thread) ends the process before any report: with
//! `TESSERA_FUZZ_TRACE=1` (and `--nocapture`) each case is printed before it runs, so the last one
//! printed is the culprit.

use base64::Engine;
use renderer::image_io::panic_message;
use serde_json::Value;
use std::path::{Path, PathBuf};

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// The scene files mutated: self-contained (data URIs or GLB), covering meshes, Draco (the two
/// Khronos boxes), textures, KHR material extensions from Blender, punctual lights, cameras, skins
/// and animation.
const CORPUS: &[&str] = &[
    "scenes/cornell/cornell.gltf",
    "scenes/cornell/cornell.glb",
    "scenes/glass_absorb/glass_absorb.gltf",
    "scenes/envlit/envlit.gltf",
    "scenes/animation/moving_light.gltf",
    "scenes/animation/rig.glb",
    "scenes/blender/lights.glb",
    "scenes/blender/materials.glb",
    "scenes/khronos/Box.glb",
    "scenes/khronos/BoxTextured.glb",
];

/// [`CORPUS`]' files as (name, bytes).
fn files() -> &'static [(String, Vec<u8>)] {
    static FILES: std::sync::OnceLock<Vec<(String, Vec<u8>)>> = std::sync::OnceLock::new();
    FILES.get_or_init(|| {
        CORPUS.iter().map(|f| (f.to_string(), std::fs::read(root().join(f)).expect("corpus file"))).collect()
    })
}

/// Scenes made here, a corpus of their own so that adding one does not change which file a case
/// of [`files`] mutates: a grid in EXT_meshopt_compression (meshoptimizer's C++ decoders on
/// mutated streams).
fn generated() -> &'static [(String, Vec<u8>)] {
    static MADE: std::sync::OnceLock<Vec<(String, Vec<u8>)>> = std::sync::OnceLock::new();
    MADE.get_or_init(|| vec![("meshopt_grid.gltf".into(), renderer::testing::meshopt_grid_gltf(true).into_bytes())])
}

/// SplitMix64 (Steele, Lea and Flood 2014): the case's random choices.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    fn below(&mut self, n: usize) -> usize {
        (self.next() % n.max(1) as u64) as usize
    }
}

/// A GLB split into its JSON and its binary chunk.
struct Glb {
    json: Value,
    bin: Option<Vec<u8>>,
}

fn parse_glb(bytes: &[u8]) -> Glb {
    let u32_at = |o: usize| u32::from_le_bytes([bytes[o], bytes[o + 1], bytes[o + 2], bytes[o + 3]]) as usize;
    assert_eq!(&bytes[..4], b"glTF", "the corpus's GLB files are GLB");
    let json_len = u32_at(12);
    let json = serde_json::from_slice(&bytes[20..20 + json_len]).expect("the corpus's JSON parses");
    let at = 20 + json_len;
    let bin = (at + 8 <= bytes.len()).then(|| bytes[at + 8..at + 8 + u32_at(at)].to_vec());
    Glb { json, bin }
}

fn write_glb(glb: &Glb) -> Vec<u8> {
    let mut json = serde_json::to_vec(&glb.json).expect("JSON serialises");
    while !json.len().is_multiple_of(4) {
        json.push(b' ');
    }
    let mut out = Vec::new();
    out.extend_from_slice(b"glTF");
    out.extend_from_slice(&2u32.to_le_bytes());
    out.extend_from_slice(&0u32.to_le_bytes()); // total length, set below
    out.extend_from_slice(&(json.len() as u32).to_le_bytes());
    out.extend_from_slice(b"JSON");
    out.extend_from_slice(&json);
    if let Some(bin) = &glb.bin {
        let mut bin = bin.clone();
        while !bin.len().is_multiple_of(4) {
            bin.push(0);
        }
        out.extend_from_slice(&(bin.len() as u32).to_le_bytes());
        out.extend_from_slice(b"BIN\0");
        out.extend_from_slice(&bin);
    }
    let total = out.len() as u32;
    out[8..12].copy_from_slice(&total.to_le_bytes());
    out
}

/// Every path to a value in `v` (object keys and array indices), depth first.
fn paths(v: &Value, prefix: &mut Vec<PathStep>, out: &mut Vec<Vec<PathStep>>) {
    out.push(prefix.clone());
    match v {
        Value::Object(m) => {
            for (k, c) in m {
                prefix.push(PathStep::Key(k.clone()));
                paths(c, prefix, out);
                prefix.pop();
            }
        }
        Value::Array(a) => {
            for (i, c) in a.iter().enumerate() {
                prefix.push(PathStep::Index(i));
                paths(c, prefix, out);
                prefix.pop();
            }
        }
        _ => {}
    }
}

#[derive(Clone, Debug)]
enum PathStep {
    Key(String),
    Index(usize),
}

fn at_mut<'a>(v: &'a mut Value, path: &[PathStep]) -> &'a mut Value {
    path.iter().fold(v, |v, s| match s {
        PathStep::Key(k) => &mut v[k.as_str()],
        PathStep::Index(i) => &mut v[*i],
    })
}

const EXTREMES: &[f64] = &[
    0.0,
    -1.0,
    1.0,
    2.0,
    3.0,
    7.0,
    255.0,
    65535.0,
    65536.0,
    2147483647.0,
    4294967295.0,
    4294967296.0,
    1e12,
    -1e12,
    1e30,
    3.4e38,
    -3.4e38,
    1e-40,
    0.5,
    -0.5,
    1.5,
];

const WORDS: &[&str] = &[
    "SCALAR",
    "VEC2",
    "VEC3",
    "VEC4",
    "MAT2",
    "MAT4",
    "MASK",
    "BLEND",
    "OPAQUE",
    "STEP",
    "LINEAR",
    "CUBICSPLINE",
    "translation",
    "rotation",
    "scale",
    "weights",
    "spot",
    "point",
    "directional",
    "orthographic",
    "perspective",
    "",
];

/// One mutation of the JSON; returns what it did.
fn mutate_json(json: &mut Value, rng: &mut Rng) -> String {
    let mut all = Vec::new();
    paths(json, &mut Vec::new(), &mut all);
    // Skip the root and the data URIs' long strings (a changed base64 payload is a bytes mutation).
    let path = all[1 + rng.below(all.len() - 1)].clone();
    let target = at_mut(json, &path);
    let what = match rng.below(10) {
        0..=3 if target.is_number() || rng.below(3) == 0 => {
            let x = EXTREMES[rng.below(EXTREMES.len())];
            *target = serde_json::Number::from_f64(x).map_or(Value::Null, Value::Number);
            if x.fract() == 0.0 && x.abs() < 9e15 {
                *target = Value::from(x as i64);
            }
            format!("= {x}")
        }
        4 => {
            let (v, name) = match rng.below(5) {
                0 => (Value::Null, "null"),
                1 => (Value::from("x"), "\"x\""),
                2 => (Value::Array(vec![]), "[]"),
                3 => (Value::Object(Default::default()), "{}"),
                _ => (Value::from(true), "true"),
            };
            *target = v;
            format!("= {name}")
        }
        5 if target.is_string() => {
            let w = WORDS[rng.below(WORDS.len())];
            *target = Value::from(w);
            format!("= \"{w}\"")
        }
        6 | 5 => {
            // Remove this key or array entry from its parent.
            let Some((last, parent)) = path.split_last() else { return "nothing".into() };
            match (at_mut(json, parent), last) {
                (Value::Object(m), PathStep::Key(k)) => {
                    m.remove(k);
                }
                (Value::Array(a), PathStep::Index(i)) => {
                    a.remove(*i);
                }
                _ => {}
            }
            "removed".into()
        }
        7 => {
            // Duplicate an array entry (or the value into a one-entry array).
            match target {
                Value::Array(a) if !a.is_empty() => {
                    let i = rng.below(a.len());
                    let c = a[i].clone();
                    a.push(c);
                    "array entry duplicated".into()
                }
                _ => {
                    let c = target.clone();
                    *target = Value::Array(vec![c]);
                    "wrapped in an array".into()
                }
            }
        }
        _ => {
            // An integer nudged by a small amount (indices one past the end, counts off by one).
            match target.as_i64() {
                Some(n) => {
                    let d = [-1i64, 1, 2, -2, 1000][rng.below(5)];
                    *target = Value::from(n.saturating_add(d));
                    format!("{n} + {d}")
                }
                None => {
                    *target = Value::from(-1);
                    "= -1".into()
                }
            }
        }
    };
    format!("{} {what}", path_name(&path))
}

fn path_name(path: &[PathStep]) -> String {
    path.iter()
        .map(|s| match s {
            PathStep::Key(k) => format!("/{k}"),
            PathStep::Index(i) => format!("/{i}"),
        })
        .collect()
}

/// Overwrites a few 4-byte words of a buffer with values that break floats and indices.
fn mutate_bytes(bin: &mut [u8], rng: &mut Rng) -> String {
    if bin.len() < 4 {
        return "buffer too short".into();
    }
    let words: [u32; 8] = [
        f32::NAN.to_bits(),
        f32::INFINITY.to_bits(),
        f32::NEG_INFINITY.to_bits(),
        3.0e38f32.to_bits(),
        1.0e-42f32.to_bits(),
        0xFFFF_FFFF,
        0x0000_FFFF,
        0x8000_0000,
    ];
    let n = 1 + rng.below(8);
    let mut at = Vec::new();
    for _ in 0..n {
        let o = rng.below(bin.len() / 4) * 4;
        let w = words[rng.below(words.len())];
        bin[o..o + 4].copy_from_slice(&w.to_le_bytes());
        at.push(format!("{o}={w:#x}"));
    }
    format!("buffer words {}", at.join(","))
}

/// The `.gltf`'s first data-URI buffer, decoded.
fn data_uri_buffer(json: &Value) -> Option<(usize, Vec<u8>)> {
    let buffers = json.get("buffers")?.as_array()?;
    buffers.iter().enumerate().find_map(|(i, b)| {
        let uri = b.get("uri")?.as_str()?;
        let comma = uri.find(";base64,")? + 8;
        Some((i, base64::engine::general_purpose::STANDARD.decode(&uri[comma..]).ok()?))
    })
}

/// Case `n` of `corpus`: one of its scenes with one or two mutations, as (file name, bytes,
/// description).
fn case(n: u64, corpus: &[(String, Vec<u8>)]) -> (String, Vec<u8>, String) {
    let mut rng = Rng(n.wrapping_mul(0x2545_f491_4f6c_dd1d) ^ 0x5eed);
    let (file, bytes) = &corpus[rng.below(corpus.len())];
    let is_glb = file.ends_with(".glb");
    let mut glb = if is_glb {
        parse_glb(bytes)
    } else {
        Glb { json: serde_json::from_slice(bytes).expect("corpus JSON"), bin: None }
    };
    let mut did = Vec::new();
    for _ in 0..1 + rng.below(2) {
        if rng.below(4) == 0 {
            if is_glb {
                if let Some(bin) = glb.bin.as_mut() {
                    did.push(mutate_bytes(bin, &mut rng));
                }
            } else if let Some((i, mut bin)) = data_uri_buffer(&glb.json) {
                did.push(mutate_bytes(&mut bin, &mut rng));
                let uri = format!(
                    "data:application/octet-stream;base64,{}",
                    base64::engine::general_purpose::STANDARD.encode(&bin)
                );
                glb.json["buffers"][i]["uri"] = Value::from(uri);
            }
        } else {
            did.push(mutate_json(&mut glb.json, &mut rng));
        }
    }
    let out = if is_glb { write_glb(&glb) } else { serde_json::to_vec(&glb.json).expect("JSON serialises") };
    let name = Path::new(file).file_name().map(|f| f.to_string_lossy().into_owned()).unwrap_or_default();
    (name, out, format!("{file}: {}", did.join("; ")))
}

/// Prints a case before it runs when `TESSERA_FUZZ_TRACE` is set (see the module's doc).
fn trace(case: u64, what: &str) {
    if std::env::var_os("TESSERA_FUZZ_TRACE").is_some() {
        eprintln!("case {case}: {what}");
    }
}

/// Loads and renders case `n`; Err with a description when it panicked or rendered non-finite
/// values.
fn run_case(n: u64, corpus: &[(String, Vec<u8>)]) -> Result<(), String> {
    let (name, bytes, what) = case(n, corpus);
    trace(n, &what);
    match std::panic::catch_unwind(|| renderer::testing::loads_and_renders_finitely(&name, &bytes)) {
        Ok(Ok(())) => Ok(()),
        Ok(Err(e)) => Err(format!("case {n} ({what}): {e}")),
        Err(p) => Err(format!("case {n} ({what}): panicked: {}", panic_message(p.as_ref()))),
    }
}

/// Cases that panicked before their fixes (2026-12-01, 40 000 cases), run every time: a vertex at
/// 3e38 (266), POSITION and indices accessors out of range (720, 1011), an animation target's
/// path invalid (860) or node out of range (2706), an empty instanced mesh (7310, 39850), an
/// image with no source (20885) or no MIME type (38903).
const FOUND: &[u64] = &[266, 720, 860, 1011, 2706, 7310, 20885, 38903, 39850];

#[test]
fn mutated_scenes_load_or_fail_cleanly_and_render_finite_images() {
    let n = std::env::var("TESSERA_FUZZ_CASES").ok().and_then(|s| s.parse().ok()).unwrap_or(240u64);
    let one: Option<u64> = std::env::var("TESSERA_FUZZ_CASE").ok().map(|c| c.parse().expect("a case number"));
    let mut failures = Vec::new();
    let mut count = 0;
    // The files, and a quarter as many cases of the generated scenes (one scene, not ten).
    for (corpus, cases, found, label) in [(files(), n, FOUND, "file"), (generated(), n / 4, &[][..], "generated")] {
        let list: Vec<u64> = match one {
            Some(c) => vec![c],
            None => (0..cases).chain(found.iter().copied()).collect(),
        };
        count += list.len();
        failures.extend(list.iter().filter_map(|&c| run_case(c, corpus).err()).map(|e| format!("{label} {e}")));
    }
    assert!(failures.is_empty(), "{} of {count} cases failed:\n{}", failures.len(), failures.join("\n"));
}

#[test]
fn the_mutations_change_the_scenes() {
    // A fuzzer whose mutations were no-ops would pass whatever the loader did.
    let mut changed = 0;
    for n in 0..40 {
        let (name, bytes, _) = case(n, files());
        let (_, original) = files().iter().find(|(f, _)| f.ends_with(&name)).expect("corpus file");
        let reparsed = if name.ends_with(".glb") {
            write_glb(&parse_glb(original))
        } else {
            serde_json::to_vec(&serde_json::from_slice::<Value>(original).expect("JSON")).expect("JSON")
        };
        changed += usize::from(bytes != reparsed);
    }
    assert!(changed >= 36, "only {changed} of 40 cases changed their scene");
}

/// Small EXRs in each compression `Environment::load` decodes (half floats, so B44 applies), scan
/// lines and tiles, plus the repository's DWAB map (refused by name unless a mutation makes its
/// header name another compression).
fn exr_corpus() -> Vec<(String, Vec<u8>)> {
    use exr::prelude::*;
    let mut out = Vec::new();
    let compressions = [
        Compression::Uncompressed,
        Compression::RLE,
        Compression::ZIP1,
        Compression::ZIP16,
        Compression::PIZ,
        Compression::PXR24,
        Compression::B44,
        Compression::B44A,
    ];
    for (k, compression) in compressions.into_iter().enumerate() {
        let (w, h) = (24usize, 10usize);
        let plane = |c: usize| {
            FlatSamples::F16((0..w * h).map(|i| f16::from_f32(((i * 7 + c * 13) % 17) as f32 * 0.25)).collect())
        };
        let channels = AnyChannels::sort(SmallVec::from_vec(vec![
            AnyChannel::new("R", plane(0)),
            AnyChannel::new("G", plane(1)),
            AnyChannel::new("B", plane(2)),
        ]));
        let blocks = if k % 2 == 0 { Blocks::ScanLines } else { Blocks::Tiles(Vec2(8, 4)) };
        let encoding = Encoding { compression, blocks, line_order: LineOrder::Increasing };
        let layer = Layer::new((w, h), LayerAttributes::named("fuzz"), encoding, channels);
        let mut bytes = Vec::new();
        Image::from_layer(layer)
            .write()
            .to_buffered(std::io::Cursor::new(&mut bytes))
            .expect("the corpus EXR is written");
        out.push((format!("{compression:?}-{blocks:?}"), bytes));
    }
    let dwab = std::fs::read(root().join("scenes/env/sunset-dwab-compressed.exr")).expect("the DWAB map");
    out.push(("sunset-dwab-compressed.exr".into(), dwab));
    out
}

/// Case `n` of a corpus of binary files (the EXRs, the .hdr map): a few bytes overwritten, mostly
/// in the first 600 (an EXR's header: sizes, channel lists, compression, the offset table),
/// sometimes cut short, as (bytes, description).
fn byte_case(n: u64, corpus: &[(String, Vec<u8>)]) -> (Vec<u8>, String) {
    let mut rng = Rng(n.wrapping_mul(0x9e37_79b9_7f4a_7c15) ^ 0xe8);
    let (name, bytes) = &corpus[rng.below(corpus.len())];
    let mut bytes = bytes.clone();
    let mut did = Vec::new();
    for _ in 0..1 + rng.below(4) {
        let span = if rng.below(4) == 0 { bytes.len() } else { bytes.len().min(600) };
        let at = rng.below(span);
        let value: u8 = match rng.below(4) {
            0 => 0,
            1 => 0xff,
            2 => bytes[at] ^ (1 << rng.below(8)),
            _ => rng.next() as u8,
        };
        bytes[at] = value;
        did.push(format!("{at}={value:#x}"));
    }
    if rng.below(8) == 0 {
        let cut = rng.below(bytes.len());
        bytes.truncate(cut);
        did.push(format!("cut at {cut}"));
    }
    (bytes, format!("{name}: {}", did.join(",")))
}

#[test]
fn mutated_exr_files_load_or_fail_cleanly() {
    let corpus = exr_corpus();
    let n: u64 = std::env::var("TESSERA_FUZZ_CASES").ok().and_then(|s| s.parse().ok()).unwrap_or(240);
    let dir = std::env::temp_dir().join(format!("tessera-exr-fuzz-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp dir");
    let path = dir.join("map.exr");
    let mut failures = Vec::new();
    let mut loaded = 0;
    let cases: Vec<u64> = match std::env::var("TESSERA_FUZZ_CASE") {
        Ok(c) => vec![c.parse().expect("TESSERA_FUZZ_CASE is a number")],
        Err(_) => (0..n).chain(FOUND_EXR.iter().copied()).collect(),
    };
    for &case in &cases {
        let (bytes, what) = byte_case(case, &corpus);
        trace(case, &what);
        std::fs::write(&path, &bytes).expect("temp file");
        let outcome = std::panic::catch_unwind(|| {
            let env = renderer::environment::Environment::load(&path, 1.0, 0.0, true, true);
            let back = renderer::image_io::read_exr_bytes(&bytes).is_ok();
            (env.is_ok(), back)
        });
        match outcome {
            Ok((env, _)) => loaded += usize::from(env),
            Err(p) => failures.push(format!("case {case} ({what}): panicked: {}", panic_message(p.as_ref()))),
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
    assert!(failures.is_empty(), "{} of {} cases failed:\n{}", failures.len(), cases.len(), failures.join("\n"));
    // Most mutations leave a loadable map (a texel changed): the loader was exercised, not just
    // refusing everything at the magic number.
    assert!(cases.len() < 20 || loaded * 10 > cases.len(), "only {loaded} of {} mutated maps loaded", cases.len());
}

/// EXR cases that failed before their fixes: a data window made larger by one byte (252, of
/// 20 000 cases on 2026-12-01; the reader's 49 GB allocation aborted the process); a DWAB block's
/// counter (109742, of 200 000 on 2026-12-02; the crate asked for 358 TB, and the process
/// aborted).
const FOUND_EXR: &[u64] = &[252, 109_742];

/// The EXR finding as a plain test: a header whose data window claims 200 000 × 10 pixels is
/// refused by name before anything is allocated for it (it aborted the process).
#[test]
fn an_exr_claiming_a_huge_data_window_is_refused_before_allocating() {
    let (_, mut bytes) = exr_corpus().swap_remove(0);
    let key = b"dataWindow\0box2i\0";
    let at = bytes.windows(key.len()).position(|w| w == key).expect("a data window") + key.len() + 4;
    // box2i: x_min, y_min, x_max, y_max.
    bytes[at + 8..at + 12].copy_from_slice(&199_999i32.to_le_bytes());
    let e = renderer::image_io::read_exr_bytes(&bytes).err().expect("refused");
    assert!(e.contains("200000x10") && e.contains("exceeds the limit"), "{e}");
}

/// Where the first block of a single-part EXR starts: past the magic number and version, the
/// header's attributes (name\0 type\0 size:i32 value, ending in \0) and the offset table, whose
/// first entry is the block's position (OpenEXR's file layout).
fn first_block_offset(bytes: &[u8]) -> usize {
    let mut at = 8;
    while bytes[at] != 0 {
        for _ in 0..2 {
            at += bytes[at..].iter().position(|&b| b == 0).expect("a name ends") + 1;
        }
        let size = i32::from_le_bytes(bytes[at..at + 4].try_into().expect("4 bytes")) as usize;
        at += 4 + size;
    }
    u64::from_le_bytes(bytes[at + 1..at + 9].try_into().expect("8 bytes")) as usize
}

/// The DWA finding as a plain test: a DWAB block whose DC coefficient count claims 2^45 values
/// (the crate sized a buffer from it, and the failed allocation aborted the process) is refused
/// by name; a DWAA and a DWAB file as the crate writes them, and the repository's DWAB map, read.
#[test]
fn a_dwa_block_claiming_a_huge_count_is_refused_before_allocating() {
    use exr::prelude::*;
    let write = |compression: Compression| {
        let (w, h) = (40usize, 20usize);
        let plane = |c: usize| {
            FlatSamples::F16((0..w * h).map(|i| f16::from_f32(((i * 7 + c * 13) % 17) as f32 * 0.25 + 0.1)).collect())
        };
        let channels = AnyChannels::sort(SmallVec::from_vec(vec![
            AnyChannel::new("R", plane(0)),
            AnyChannel::new("G", plane(1)),
            AnyChannel::new("B", plane(2)),
        ]));
        let encoding = Encoding { compression, blocks: Blocks::ScanLines, line_order: LineOrder::Increasing };
        let mut bytes = Vec::new();
        Image::from_layer(Layer::new((w, h), LayerAttributes::named("dwa"), encoding, channels))
            .write()
            .to_buffered(std::io::Cursor::new(&mut bytes))
            .expect("written");
        bytes
    };
    let map = std::fs::read(root().join("scenes/env/sunset-dwab-compressed.exr")).expect("the DWAB map");
    for (what, bytes) in
        [("DWAA", write(Compression::DWAA(None))), ("DWAB", write(Compression::DWAB(None))), ("map", map)]
    {
        renderer::image_io::read_exr_bytes(&bytes).unwrap_or_else(|e| panic!("{what}: {e}"));
    }
    let mut bytes = write(Compression::DWAB(None));
    // The block: y (i32), its size (i32), then the eleven counters; the DC count is the tenth.
    let dc = first_block_offset(&bytes) + 8 + 9 * 8;
    let count = u64::from_le_bytes(bytes[dc..dc + 8].try_into().expect("8 bytes"));
    assert!(count > 0 && count <= 3 * 5 * 3, "the block's DC count {count} is where it should be");
    bytes[dc..dc + 8].copy_from_slice(&(1u64 << 45).to_le_bytes());
    let e = renderer::image_io::read_exr_bytes(&bytes).err().expect("refused");
    assert!(e.contains("DC coefficient count of 35184372088832"), "{e}");
}

/// A 24 × 12 Radiance .hdr map (the environment loader's other format) as the image crate writes
/// it: every texel `rgb`, or a pattern when `rgb` is None.
fn hdr_map(rgb: Option<[f32; 3]>) -> Vec<u8> {
    let (w, h) = (24usize, 12usize);
    let texel = |i: usize| rgb.unwrap_or([(i % 7) as f32 * 0.5, (i % 5) as f32 * 0.25, 1.0 + (i % 3) as f32]);
    let pixels: Vec<image::Rgb<f32>> = (0..w * h).map(|i| image::Rgb(texel(i))).collect();
    let mut out = Vec::new();
    image::codecs::hdr::HdrEncoder::new(&mut out).encode(&pixels, w, h).expect("the .hdr is written");
    out
}

/// A .hdr map lights the scene with its texels (times the strength): a constant map evaluates to
/// its colour in every direction, within RGBE's 8-bit mantissas; a cut file is an error.
#[test]
fn a_radiance_hdr_map_loads_its_texels() {
    let dir = std::env::temp_dir().join(format!("tessera-hdr-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp dir");
    let path = dir.join("map.hdr");
    std::fs::write(&path, hdr_map(Some([0.5, 1.0, 2.0]))).expect("temp file");
    let env = renderer::environment::Environment::load(&path, 3.0, 0.0, true, true).expect("the .hdr loads");
    for d in [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.3, -0.8, 0.5], [-0.2, 0.1, -0.97]] {
        let d = renderer::math::Vec3::from(d).normalize();
        let c = env.eval(d);
        let want = renderer::math::Vec3::new(1.5, 3.0, 6.0);
        assert!(((c - want) / want).abs().max_element() < 0.01, "{d:?}: {c:?}");
    }
    let whole = hdr_map(None);
    std::fs::write(&path, &whole[..whole.len() / 2]).expect("temp file");
    let e =
        renderer::environment::Environment::load(&path, 1.0, 0.0, true, true).err().expect("a cut .hdr is an error");
    assert!(e.to_string().contains("map.hdr"), "{e}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// Mutated .hdr maps (the EXR cases' mutations, on a map of its own so the EXR case numbers keep
/// their meaning) load or fail with an error, never panic or abort; a quarter as many cases as
/// `TESSERA_FUZZ_CASES`.
#[test]
fn mutated_hdr_maps_load_or_fail_cleanly() {
    let corpus = vec![("map.hdr".to_string(), hdr_map(None))];
    let n: u64 = std::env::var("TESSERA_FUZZ_CASES").ok().and_then(|s| s.parse().ok()).unwrap_or(240) / 4;
    let dir = std::env::temp_dir().join(format!("tessera-hdr-fuzz-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp dir");
    let path = dir.join("map.hdr");
    let (mut failures, mut loaded) = (Vec::new(), 0);
    for case in 0..n {
        let (bytes, what) = byte_case(case, &corpus);
        trace(case, &what);
        std::fs::write(&path, &bytes).expect("temp file");
        match std::panic::catch_unwind(|| renderer::environment::Environment::load(&path, 1.0, 0.0, true, true).is_ok())
        {
            Ok(ok) => loaded += usize::from(ok),
            Err(p) => failures.push(format!("case {case} ({what}): panicked: {}", panic_message(p.as_ref()))),
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
    assert!(failures.is_empty(), "{} of {n} cases failed:\n{}", failures.len(), failures.join("\n"));
    assert!(n < 20 || loaded * 10 > n as usize, "only {loaded} of {n} mutated maps loaded");
}
