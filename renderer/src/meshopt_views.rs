//! EXT_meshopt_compression: buffer views stored compressed by meshoptimizer's codecs (how gltfpack
//! ships large models). Each compressed view is decoded once, at load, into its place in the
//! uncompressed ("fallback") buffer, so every accessor reader downstream sees plain glTF data.
//! Decoding is meshoptimizer's own C++ decoder through the `meshopt` crate, which is written to be
//! safe on untrusted input (it may produce garbage indices, which the loader's index checks refuse).

use crate::error::SceneError;
use std::path::Path;

/// The compressed layout of one buffer view (the extension's JSON object).
#[derive(serde::Deserialize)]
#[serde(rename_all = "camelCase")]
struct Compressed {
    buffer: usize,
    #[serde(default)]
    byte_offset: usize,
    byte_length: usize,
    byte_stride: usize,
    count: usize,
    mode: String,
    #[serde(default)]
    filter: Option<String>,
}

/// A vertex of `N` 32-bit words: meshoptimizer decodes whole vertices of `byteStride` bytes.
#[derive(Clone, Copy)]
struct Words<const N: usize>([u32; N]);

impl<const N: usize> Default for Words<N> {
    fn default() -> Self {
        Words([0; N])
    }
}

fn words_to_bytes<const N: usize>(v: Vec<Words<N>>) -> Vec<u8> {
    v.iter().flat_map(|w| w.0.iter().flat_map(|x| x.to_le_bytes())).collect()
}

/// Decodes an ATTRIBUTES stream of `count` vertices of `4·N` bytes, then applies its filter.
fn attributes<const N: usize>(src: &[u8], count: usize, filter: &str) -> Result<Vec<u8>, String> {
    let mut v: Vec<Words<N>> =
        meshopt::decode_vertex_buffer(src, count).map_err(|e| format!("vertex stream does not decode: {e:?}"))?;
    match filter {
        "NONE" => {}
        "EXPONENTIAL" => {
            let mut raw: Vec<[u32; N]> = v.iter().map(|w| w.0).collect();
            meshopt::decode_filter_exp(&mut raw);
            v = raw.into_iter().map(Words).collect();
        }
        "OCTAHEDRAL" | "QUATERNION" | "COLOR" => {
            let mut bytes = words_to_bytes(v);
            match (filter, N) {
                ("OCTAHEDRAL", 1) | ("COLOR", 1) => {
                    let mut c: Vec<[i8; 4]> =
                        bytes.chunks_exact(4).map(|b| [b[0] as i8, b[1] as i8, b[2] as i8, b[3] as i8]).collect();
                    if filter == "COLOR" {
                        meshopt::decode_filter_color(&mut c);
                    } else {
                        meshopt::decode_filter_oct(&mut c);
                    }
                    bytes = c.iter().flat_map(|x| x.map(|b| b as u8)).collect();
                }
                ("OCTAHEDRAL", 2) | ("QUATERNION", 2) | ("COLOR", 2) => {
                    let mut c: Vec<[i16; 4]> = bytes
                        .chunks_exact(8)
                        .map(|b| std::array::from_fn(|k| i16::from_le_bytes([b[2 * k], b[2 * k + 1]])))
                        .collect();
                    match filter {
                        "QUATERNION" => meshopt::decode_filter_quat(&mut c),
                        "COLOR" => meshopt::decode_filter_color(&mut c),
                        _ => meshopt::decode_filter_oct(&mut c),
                    }
                    bytes = c.iter().flat_map(|x| x.iter().flat_map(|s| s.to_le_bytes())).collect();
                }
                _ => return Err(format!("filter {filter} with byteStride {}", 4 * N)),
            }
            return Ok(bytes);
        }
        other => return Err(format!("unknown filter {other}")),
    }
    Ok(words_to_bytes(v))
}

/// Dispatches a runtime byteStride (a multiple of 4, at most 256) to `attributes::<stride / 4>`.
macro_rules! by_words {
    ($words:expr, $src:expr, $count:expr, $filter:expr, [$($n:literal)*]) => {
        match $words {
            $($n => attributes::<$n>($src, $count, $filter),)*
            _ => Err(format!("byteStride {} (a multiple of 4 up to 256 is allowed)", 4 * $words)),
        }
    };
}

fn decode_view(c: &Compressed, src: &[u8]) -> Result<Vec<u8>, String> {
    match c.mode.as_str() {
        "ATTRIBUTES" => {
            if c.byte_stride == 0 || !c.byte_stride.is_multiple_of(4) {
                return Err(format!("ATTRIBUTES byteStride {} is not a positive multiple of 4", c.byte_stride));
            }
            let filter = c.filter.as_deref().unwrap_or("NONE");
            by_words!(c.byte_stride / 4, src, c.count, filter, [
                1 2 3 4 5 6 7 8 9 10 11 12 13 14 15 16 17 18 19 20 21 22 23 24 25 26 27 28 29 30 31 32
                33 34 35 36 37 38 39 40 41 42 43 44 45 46 47 48 49 50 51 52 53 54 55 56 57 58 59 60 61 62 63 64
            ])
        }
        "TRIANGLES" | "INDICES" => {
            let tri = c.mode == "TRIANGLES";
            match c.byte_stride {
                2 => {
                    let v: Vec<u16> = if tri {
                        meshopt::decode_index_buffer(src, c.count)
                    } else {
                        meshopt::decode_index_sequence(src, c.count)
                    }
                    .map_err(|e| format!("index stream does not decode: {e:?}"))?;
                    Ok(v.iter().flat_map(|x| x.to_le_bytes()).collect())
                }
                4 => {
                    let v: Vec<u32> = if tri {
                        meshopt::decode_index_buffer(src, c.count)
                    } else {
                        meshopt::decode_index_sequence(src, c.count)
                    }
                    .map_err(|e| format!("index stream does not decode: {e:?}"))?;
                    Ok(v.iter().flat_map(|x| x.to_le_bytes()).collect())
                }
                s => Err(format!("{} byteStride {s} (2 or 4)", c.mode)),
            }
        }
        m => Err(format!("unknown mode {m}")),
    }
}

/// The buffers a file without their data may leave empty: a buffer marked
/// `EXT_meshopt_compression: {fallback: true}` holds only what compressed views decode into.
pub fn is_fallback(buffer: &gltf::Buffer) -> bool {
    buffer
        .extensions()
        .and_then(|e| e.get("EXT_meshopt_compression"))
        .and_then(|x| x.get("fallback"))
        .and_then(|f| f.as_bool())
        .unwrap_or(false)
}

/// Decodes every compressed view of `doc` into `buffers` (already loaded; fallback buffers
/// zero-filled to their declared length).
pub fn decode_views(path: &Path, doc: &gltf::Document, buffers: &mut [Vec<u8>]) -> Result<(), SceneError> {
    for view in doc.views() {
        let Some(ext) = view.extensions().and_then(|e| e.get("EXT_meshopt_compression")) else { continue };
        let bad = |m: String| SceneError::Invalid {
            path: path.into(),
            message: format!("bufferView {} EXT_meshopt_compression: {m}", view.index()),
        };
        let c: Compressed = serde_json::from_value(ext.clone()).map_err(|e| bad(e.to_string()))?;
        let decoded_len =
            c.count.checked_mul(c.byte_stride).ok_or_else(|| bad("count × byteStride overflows".into()))?;
        if decoded_len != view.length() {
            return Err(bad(format!(
                "count {} × byteStride {} = {decoded_len} bytes, but the view is {} bytes",
                c.count,
                c.byte_stride,
                view.length()
            )));
        }
        let src = buffers
            .get(c.buffer)
            .and_then(|b| b.get(c.byte_offset..c.byte_offset.checked_add(c.byte_length)?))
            .ok_or_else(|| bad(format!("compressed bytes lie outside buffer {}", c.buffer)))?
            .to_vec();
        let out = decode_view(&c, &src).map_err(bad)?;
        let dst = buffers
            .get_mut(view.buffer().index())
            .and_then(|b| b.get_mut(view.offset()..view.offset() + view.length()))
            .ok_or_else(|| bad("the view lies outside its buffer".into()))?;
        if out.len() != dst.len() {
            return Err(bad(format!("decoded {} bytes for a {}-byte view", out.len(), dst.len())));
        }
        dst.copy_from_slice(&out);
    }
    Ok(())
}
