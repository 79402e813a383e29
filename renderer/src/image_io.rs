//! Writing results: OpenEXR (linear radiance, float32 R, G, B plus the per-pixel variance of the
//! mean luminance and the sample count) and a tone-mapped sRGB PNG preview. Also reading EXRs back
//! (tests, reference comparisons).

use crate::budget::{StopReason, TILE};
use crate::error::RenderError;
use crate::film::{PartialSums, Rect};
use crate::noise;
use exr::prelude::*;
use std::path::Path;

/// Name of the EXR channel holding the variance of each pixel's mean luminance.
pub const VARIANCE_CHANNEL: &str = "variance";
/// Name of the EXR channel holding each pixel's sample count.
pub const SPP_CHANNEL: &str = "spp";

/// The header attribute every Tessera EXR carries (the same for a local and a farm render, so the
/// files are byte-identical): `tessera`, the version, the settings that made the image, why it
/// stopped, and its noise: the estimated relative standard error of the image (`rel_error`, see
/// [`crate::noise`]) and of every tile (`tiles=x0,y0,spp,rel_error;...` over the [`TILE`] grid).
/// One attribute, because the EXR writer keeps custom attributes in a hash map whose order would
/// vary.
/// The EXR attributes of a result: `tessera` (settings, budget outcome, noise), and
/// `tessera_warnings` when the scene had any (what was rendered without, e.g. an optional
/// extension), so a file says how it differs from what its scene asked for.
pub fn standard_attributes(
    s: &crate::RenderSettings,
    image: &PartialSums,
    stop: StopReason,
    warnings: &[String],
) -> Vec<(&'static str, String)> {
    // The map by file name only: a local path and the farm's bundle path name the same file.
    let mut env = s.environment.clone();
    env.map = env.map.map(|m| m.rsplit(['/', '\\']).next().unwrap_or(&m).to_string());
    let whole = noise::estimate(image);
    let tiles: Vec<String> = Rect::tiles(s.width, s.height, TILE)
        .iter()
        .map(|t| {
            let e = noise::estimate_rect(image, *t);
            format!("{},{},{},{:.4e}", t.x0, t.y0, e.spp_max, e.rel_error)
        })
        .collect();
    let mut attrs = vec![(
        "tessera",
        format!(
            "version={} width={} height={} spp={} pass_spp={} integrator={:?} mis_heuristic={:?} sampler={:?} seed={} max_depth={} rr_depth={} camera={:?} filter={:?} environment={:?} light_sampler={:?} light_units={:?} noise_target={:?} min_spp={} time_budget={:?} stop={} spp_min={} spp_max={} rel_mse={:.4e} rel_error={:.4e} tiles={}",
            env!("CARGO_PKG_VERSION"),
            s.width,
            s.height,
            s.spp,
            s.pass_spp,
            s.integrator,
            s.mis_heuristic,
            s.sampler,
            s.seed,
            s.max_depth,
            s.rr_depth,
            s.camera,
            s.filter,
            env,
            s.light_sampler,
            s.light_units,
            s.noise_target,
            s.min_spp,
            s.time_budget,
            stop.as_str(),
            whole.spp_min,
            whole.spp_max,
            whole.rel_mse,
            whole.rel_error,
            tiles.join(";")
        ),
    )];
    // The frame of a sequence, and how frames map to time (fps, which animation plays).
    attrs.push(("tessera_frame", format!("frame={} fps={} animation={:?}", s.frame, s.fps, s.animation)));
    if !warnings.is_empty() {
        attrs.push(("tessera_warnings", warnings.join("; ")));
    }
    attrs
}

/// Reads one `key=value` field of the `tessera` attribute (values hold no spaces, except inside
/// the environment's debug form, which no caller asks for).
pub fn attribute_field<'a>(attribute: &'a str, key: &str) -> Option<&'a str> {
    attribute.split(' ').find_map(|kv| kv.strip_prefix(key)?.strip_prefix('='))
}

/// A finished image, in the form written to disk.
pub struct FinalImage {
    pub width: u32,
    pub height: u32,
    pub rgb: Vec<[f32; 3]>,
    pub variance: Vec<f32>,
    pub spp: Vec<u32>,
}

impl FinalImage {
    pub fn from_sums(sums: &PartialSums) -> Self {
        let n = sums.rect.pixels();
        FinalImage {
            width: sums.rect.width,
            height: sums.rect.height,
            rgb: (0..n).map(|i| sums.mean(i)).collect(),
            variance: (0..n).map(|i| sums.variance_of_mean(i)).collect(),
            spp: sums.count.clone(),
        }
    }

    /// The EXR file's bytes (see `write_exr`).
    pub fn exr_bytes(&self, attributes: &[(&str, String)]) -> std::result::Result<Vec<u8>, String> {
        let mut buf = std::io::Cursor::new(Vec::new());
        self.exr_image(attributes).write().to_buffered(&mut buf).map_err(|e| e.to_string())?;
        let mut bytes = buf.into_inner();
        canonical_header(&mut bytes)?;
        Ok(bytes)
    }

    /// Writes the EXR (ZIP-compressed, lossless). `attributes` become string header attributes.
    pub fn write_exr(&self, path: &Path, attributes: &[(&str, String)]) -> std::result::Result<(), RenderError> {
        let bytes = self.exr_bytes(attributes).map_err(|message| RenderError::Write { path: path.into(), message })?;
        std::fs::write(path, bytes).map_err(|e| RenderError::Write { path: path.into(), message: e.to_string() })
    }

    fn exr_image(&self, attributes: &[(&str, String)]) -> Image<Layer<AnyChannels<FlatSamples>>> {
        let plane = |f: &dyn Fn(usize) -> f32| FlatSamples::F32((0..self.rgb.len()).map(f).collect());
        let channels = AnyChannels::sort(SmallVec::from_vec(vec![
            AnyChannel::new("R", plane(&|i| self.rgb[i][0])),
            AnyChannel::new("G", plane(&|i| self.rgb[i][1])),
            AnyChannel::new("B", plane(&|i| self.rgb[i][2])),
            AnyChannel::new(VARIANCE_CHANNEL, plane(&|i| self.variance[i])),
            AnyChannel::new(SPP_CHANNEL, FlatSamples::U32(self.spp.clone())),
        ]));
        let mut layer_attributes = LayerAttributes::named("tessera");
        for (k, v) in attributes {
            layer_attributes.other.insert(Text::from(*k), AttributeValue::Text(Text::from(v.as_str())));
        }
        let layer = Layer::new(
            (self.width as usize, self.height as usize),
            layer_attributes,
            Encoding::SMALL_LOSSLESS,
            channels,
        );
        Image::from_layer(layer)
    }

    /// Reads back an image this module wrote (R, G, B; variance and spp when present), from bytes
    /// (the farm keeps finished EXRs in its database). A file without R, G or B is an error.
    pub fn from_exr_bytes(bytes: &[u8]) -> std::result::Result<Self, String> {
        let exr = read_exr_bytes(bytes)?;
        let (Some(r), Some(g), Some(b)) = (exr.channel("R"), exr.channel("G"), exr.channel("B")) else {
            return Err("the EXR has no R, G and B channels".into());
        };
        let n = r.len();
        Ok(FinalImage {
            width: exr.width,
            height: exr.height,
            rgb: (0..n).map(|i| [r[i], g[i], b[i]]).collect(),
            variance: exr.channel(VARIANCE_CHANNEL).map_or_else(|| vec![0.0; n], <[f32]>::to_vec),
            spp: exr.channel(SPP_CHANNEL).map_or_else(|| vec![0; n], |v| v.iter().map(|&x| x as u32).collect()),
        })
    }

    /// The image shrunk by a whole factor so that it is at most `max_width` wide (box filter over
    /// the factor × factor block; edge blocks average what they cover). Previews are downloaded at
    /// the size they are shown: a 160 px thumbnail of a 4K frame is 0.3 % of its pixels.
    pub fn downscaled(&self, max_width: u32) -> FinalImage {
        let f = self.width.div_ceil(max_width.max(1)).max(1);
        if f == 1 {
            return FinalImage {
                width: self.width,
                height: self.height,
                rgb: self.rgb.clone(),
                variance: self.variance.clone(),
                spp: self.spp.clone(),
            };
        }
        let (w, h) = (self.width.div_ceil(f), self.height.div_ceil(f));
        let mut rgb = vec![[0.0f32; 3]; (w * h) as usize];
        let mut variance = vec![0.0f32; (w * h) as usize];
        let mut spp = vec![0u32; (w * h) as usize];
        for y in 0..h {
            for x in 0..w {
                let (mut acc, mut var, mut n, mut s) = ([0.0f32; 3], 0.0f32, 0u32, 0u32);
                for sy in y * f..((y + 1) * f).min(self.height) {
                    for sx in x * f..((x + 1) * f).min(self.width) {
                        let i = (sy * self.width + sx) as usize;
                        for (a, v) in acc.iter_mut().zip(self.rgb[i]) {
                            *a += v;
                        }
                        var += self.variance[i];
                        s = s.max(self.spp[i]);
                        n += 1;
                    }
                }
                let o = (y * w + x) as usize;
                let n = n.max(1) as f32;
                rgb[o] = [acc[0] / n, acc[1] / n, acc[2] / n];
                variance[o] = var / (n * n);
                spp[o] = s;
            }
        }
        FinalImage { width: w, height: h, rgb, variance, spp }
    }

    /// An 8-bit sRGB PNG: radiance × 2^exposure, clamped, sRGB-encoded.
    pub fn png_bytes(&self, exposure: f32) -> std::result::Result<Vec<u8>, String> {
        let scale = 2f32.powf(exposure);
        let encode = |v: f32| -> u8 {
            let v = if v.is_finite() { (v * scale).clamp(0.0, 1.0) } else { 0.0 };
            let s = if v <= 0.003_130_8 { 12.92 * v } else { 1.055 * v.powf(1.0 / 2.4) - 0.055 };
            (s * 255.0 + 0.5) as u8
        };
        let data: Vec<u8> = self.rgb.iter().flat_map(|p| [encode(p[0]), encode(p[1]), encode(p[2])]).collect();
        let mut out = Vec::new();
        let mut enc = png::Encoder::new(&mut out, self.width, self.height);
        enc.set_color(png::ColorType::Rgb);
        enc.set_depth(png::BitDepth::Eight);
        let mut w = enc.write_header().map_err(|e| e.to_string())?;
        w.write_image_data(&data).map_err(|e| e.to_string())?;
        w.finish().map_err(|e| e.to_string())?;
        Ok(out)
    }

    /// Writes the PNG preview (see `png_bytes`).
    pub fn write_png(&self, path: &Path, exposure: f32) -> std::result::Result<(), RenderError> {
        let err = |message: String| RenderError::Write { path: path.into(), message };
        let bytes = self.png_bytes(exposure).map_err(err)?;
        std::fs::write(path, bytes).map_err(|e| err(e.to_string()))
    }
}

/// An EXR read back: named float channels of the first layer.
pub struct ExrChannels {
    pub width: u32,
    pub height: u32,
    pub channels: Vec<(String, Vec<f32>)>,
    /// The `tessera` header attribute, when the file has one.
    pub tessera: Option<String>,
}

impl ExrChannels {
    pub fn channel(&self, name: &str) -> Option<&[f32]> {
        self.channels.iter().find(|(n, _)| n == name).map(|(_, v)| v.as_slice())
    }
}

/// Reads all channels of the first layer of an EXR as f32.
pub fn read_exr(path: &Path) -> std::result::Result<ExrChannels, RenderError> {
    let err = |message: String| RenderError::Read { path: path.into(), message };
    let bytes = std::fs::read(path).map_err(|e| err(e.to_string()))?;
    read_exr_bytes(&bytes).map_err(err)
}

/// The most channels [`read_exr_bytes`] reads (a Tessera EXR has five).
const MAX_EXR_CHANNELS: usize = 16;

/// [`read_exr`] of a file's bytes.
pub fn read_exr_bytes(bytes: &[u8]) -> std::result::Result<ExrChannels, String> {
    decoder_guard(|| read_exr_bytes_unguarded(bytes))
}

/// Runs a third-party decoder on untrusted bytes, turning a panic inside it into an error. The
/// `exr` crate's B44 decoder subtracts with overflow on a damaged block (a panic in a debug build,
/// garbage in a release one: `tests/mutation_fuzz.rs`), and that panic, on one of the crate's own
/// rayon threads, aborted the process; so its blocks are decoded on the calling thread
/// (`non_parallel`), where this guard sees any panic of the decoder's.
pub fn decoder_guard<T>(f: impl FnOnce() -> std::result::Result<T, String>) -> std::result::Result<T, String> {
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)).unwrap_or_else(|p| {
        let why = panic_message(p.as_ref());
        Err(format!("the EXR decoder failed on this file ({})", if why.is_empty() { "no message" } else { why }))
    })
}

/// A caught panic's message: its `String` or `&str` payload, empty for any other.
pub fn panic_message(payload: &(dyn std::any::Any + Send)) -> &str {
    payload
        .downcast_ref::<String>()
        .map(String::as_str)
        .or_else(|| payload.downcast_ref::<&str>().copied())
        .unwrap_or("")
}

/// Whether a part is DWA-compressed (DWAA or DWAB), whose blocks [`check_dwa_blocks`] bounds.
fn is_dwa(header: &exr::meta::header::Header) -> bool {
    matches!(header.compression, exr::compression::Compression::DWAA(_) | exr::compression::Compression::DWAB(_))
}

/// The bytes of a DWA block's leading counters: eleven u64s.
const DWA_COUNTERS_BYTES: usize = 11 * 8;

fn read_exr_bytes_unguarded(bytes: &[u8]) -> std::result::Result<ExrChannels, String> {
    // The header's sizes are the file's word: bound them before the reader allocates for them (a
    // flipped byte in a data window asked for 49 GB, and a failed allocation aborts the process:
    // `tests/mutation_fuzz.rs`).
    let meta =
        exr::meta::MetaData::read_from_buffered(std::io::Cursor::new(bytes), false).map_err(|e| e.to_string())?;
    let max_side = crate::settings::MAX_IMAGE_SIDE as usize;
    for header in &meta.headers {
        let (w, h) = (header.layer_size.width(), header.layer_size.height());
        if w > max_side || h > max_side {
            return Err(format!("a {w}x{h} EXR exceeds the limit of {max_side} per side"));
        }
        if header.channels.list.len() > MAX_EXR_CHANNELS {
            return Err(format!(
                "the EXR has {} channels (the limit is {MAX_EXR_CHANNELS})",
                header.channels.list.len()
            ));
        }
    }
    if meta.headers.iter().any(is_dwa) {
        check_dwa_blocks(bytes, &meta.headers)?;
    }
    let image = read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .first_valid_layer()
        .all_attributes()
        .non_parallel()
        .from_buffered(std::io::Cursor::new(bytes))
        .map_err(|e| e.to_string())?;
    let layer = image.layer_data;
    let tessera = match layer.attributes.other.get(&Text::from("tessera")) {
        Some(AttributeValue::Text(t)) => Some(t.to_string()),
        _ => None,
    };
    let (w, h) = (layer.size.width(), layer.size.height());
    let channels = layer
        .channel_data
        .list
        .iter()
        .map(|c| (c.name.to_string(), c.sample_data.values_as_f32().collect::<Vec<f32>>()))
        .collect::<Vec<_>>();
    // Every reader indexes the channels by pixel: a subsampled channel (fewer values) is refused.
    if let Some((name, v)) = channels.iter().find(|(_, v)| v.len() != w * h) {
        return Err(format!("the EXR's channel {name} holds {} values for {w}x{h} pixels (subsampled?)", v.len()));
    }
    Ok(ExrChannels { width: w as u32, height: h as u32, channels, tessera })
}

/// Holds each DWA block's leading counters to what its pixels can need, before the `exr` crate
/// sizes its buffers from them. A DWA block (DWAA, DWAB) starts with eleven little-endian u64
/// counters (OpenEXR's `DataSizesSingle`, `internal_dwa_compressor.h`): version; the unknown
/// section's inflated size; four compressed sizes; the RLE section's inflated and raw sizes; the
/// AC and DC coefficient counts; the AC coder. The crate checks the compressed sizes against the
/// block's bytes but allocates the inflated sizes and counts as read: one flipped byte asked for
/// 358 TB, and a failed allocation aborts the process (`tests/mutation_fuzz.rs`). Bounds, for a
/// block of `w × h` pixels, `c` channels and `b` bytes uncompressed: the unknown and the raw RLE
/// data are channel bytes (≤ b), RLE tokens add a count byte to at most 127 literal bytes
/// (≤ 2b + 64), and a lossy channel has one DC and at most 63 AC values (64 with the end-of-block
/// mark) per 8 × 8 block (≤ c·⌈w/8⌉·⌈h/8⌉ and 64 times that).
fn check_dwa_blocks(bytes: &[u8], headers: &[exr::meta::header::Header]) -> std::result::Result<(), String> {
    use exr::block::chunk::CompressedBlock;
    let chunks = exr::block::read(std::io::Cursor::new(bytes), false)
        .and_then(|r| r.all_chunks(false))
        .map_err(|e| e.to_string())?;
    for chunk in chunks {
        let chunk = chunk.map_err(|e| e.to_string())?;
        let Some(header) = headers.get(chunk.layer_index) else {
            return Err(format!("an EXR block names layer {}, which the file does not have", chunk.layer_index));
        };
        if !is_dwa(header) {
            continue;
        }
        let data = match &chunk.compressed_block {
            CompressedBlock::ScanLine(b) => &b.compressed_pixels_le,
            CompressedBlock::Tile(b) => &b.compressed_pixels_le,
            // Deep data: the reader refuses it by name.
            _ => continue,
        };
        let rect = header
            .get_block_data_indices(&chunk.compressed_block)
            .and_then(|t| header.get_absolute_block_pixel_coordinates(t))
            .map_err(|e| e.to_string())?;
        let (w, h) = (rect.size.width() as u64, rect.size.height() as u64);
        let raw = w * h * header.channels.bytes_per_pixel as u64;
        // Empty, or stored raw (compression did not help), or too short for the counters (the
        // crate's own "truncated DWA header"): nothing is sized from counters.
        if data.is_empty() || data.len() as u64 == raw || data.len() < DWA_COUNTERS_BYTES {
            continue;
        }
        let mut counter = [0u64; 11];
        for (c, b) in counter.iter_mut().zip(data.chunks_exact(8)) {
            *c = u64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]);
        }
        let blocks = header.channels.list.len() as u64 * w.div_ceil(8) * h.div_ceil(8);
        let limits = [
            ("unknown section's size", counter[1], raw),
            ("RLE section's size", counter[6], 2 * raw + 64),
            ("RLE section's raw size", counter[7], raw),
            ("AC coefficient count", counter[8], 64 * blocks),
            ("DC coefficient count", counter[9], blocks),
        ];
        for (what, value, limit) in limits {
            if value > limit {
                return Err(format!(
                    "a DWA block of {w}x{h} pixels claims a {what} of {value} (at most {limit} for its pixels)"
                ));
            }
        }
    }
    Ok(())
}

/// Sorts the header attributes of a single-part EXR by name, in place. The `exr` crate keeps
/// custom attributes in a `HashMap` and writes them in its per-process random order, so two
/// processes writing the same image would write different bytes; the determinism rule promises
/// byte-identical files (a local frame and the farm's). The header keeps its length, so the offset
/// table after it stays valid. (OpenEXR 2, "Header": name\0 type\0 size:i32 value, ending in \0.)
fn canonical_header(bytes: &mut [u8]) -> std::result::Result<(), String> {
    const MULTIPART_OR_DEEP: u32 = 0x1000 | 0x800;
    if bytes.len() < 8 || bytes[0..4] != [0x76, 0x2f, 0x31, 0x01] {
        return Err("not an EXR".into());
    }
    let flags = u32::from_le_bytes([bytes[4], bytes[5], bytes[6], bytes[7]]);
    if flags & MULTIPART_OR_DEEP != 0 {
        return Ok(());
    }
    let mut attrs: Vec<(Vec<u8>, Vec<u8>)> = Vec::new();
    let mut at = 8;
    loop {
        let name_end = bytes[at..].iter().position(|&b| b == 0).ok_or("unterminated header")? + at;
        if name_end == at {
            break;
        }
        let type_end = bytes[name_end + 1..].iter().position(|&b| b == 0).ok_or("bad attribute")? + name_end + 1;
        let size_at = type_end + 1;
        let size = bytes.get(size_at..size_at + 4).ok_or("bad attribute size")?;
        let size = i32::from_le_bytes([size[0], size[1], size[2], size[3]]);
        let end = size_at + 4 + usize::try_from(size).map_err(|_| "negative attribute size")?;
        if end > bytes.len() {
            return Err("attribute runs past the file".into());
        }
        attrs.push((bytes[at..name_end].to_vec(), bytes[at..end].to_vec()));
        at = end;
    }
    attrs.sort();
    let mut out = 8;
    for (_, raw) in &attrs {
        bytes[out..out + raw.len()].copy_from_slice(raw);
        out += raw.len();
    }
    debug_assert_eq!(out, at);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::FinalImage;

    fn image(w: u32, h: u32) -> FinalImage {
        let n = (w * h) as usize;
        FinalImage {
            width: w,
            height: h,
            rgb: (0..n).map(|i| [i as f32, 2.0 * i as f32, 0.5]).collect(),
            variance: vec![1.0; n],
            spp: (0..n as u32).collect(),
        }
    }

    #[test]
    fn downscaling_averages_blocks_and_keeps_partial_edges() {
        let img = image(5, 3);
        let d = img.downscaled(2);
        // factor 3: 2×1 blocks; the right block covers columns 3..5 only.
        assert_eq!((d.width, d.height), (2, 1));
        let left: f32 = [0, 1, 2, 5, 6, 7, 10, 11, 12].iter().map(|&i| i as f32).sum::<f32>() / 9.0;
        let right: f32 = [3, 4, 8, 9, 13, 14].iter().map(|&i| i as f32).sum::<f32>() / 6.0;
        assert!((d.rgb[0][0] - left).abs() < 1e-5 && (d.rgb[1][0] - right).abs() < 1e-5, "{:?}", d.rgb);
        assert!((d.variance[0] - 1.0 / 9.0).abs() < 1e-6, "variance of a mean of 9");
        assert_eq!(d.spp, vec![12, 14]);
        assert_eq!(img.downscaled(0).width, 1, "a zero width is treated as 1");
        assert_eq!(img.downscaled(100).rgb, img.rgb, "no upscaling");
    }

    #[test]
    fn an_exr_reads_back_from_bytes() {
        let img = image(7, 4);
        let bytes = img.exr_bytes(&[("tessera", "x".into())]).expect("encodes");
        let back = FinalImage::from_exr_bytes(&bytes).expect("decodes");
        assert_eq!((back.width, back.height), (7, 4));
        assert_eq!(back.rgb, img.rgb);
        assert_eq!(back.spp, img.spp);
        let err = FinalImage::from_exr_bytes(&bytes[..bytes.len() / 2]).err().expect("a cut file is an error");
        assert!(!err.is_empty());
        assert!(FinalImage::from_exr_bytes(b"not an exr").is_err());
    }
}
