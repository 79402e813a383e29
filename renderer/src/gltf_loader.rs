//! glTF 2.0 loading (`.glb`, `.gltf` with data-URI or sibling-file buffers) into a [`Scene`].
//!
//! The file is untrusted input (the farm accepts uploads), so every size is bounded before it is
//! allocated, every accessor is checked against its buffer before it is read, URIs may not leave the
//! scene's folder, and anything the renderer does not model is refused with an error naming it
//! rather than rendered silently wrong.

use crate::camera::Camera;
use crate::error::SceneError;
use crate::material::Material;
use crate::math::{Mat4, Vec2, Vec3, Vec4};
use crate::mesh::{flags, Mesh, Triangle};
use crate::scene::Scene;
use crate::texture::{Texture, TextureRef, Wrap};
use base64::Engine;
use gltf::accessor::{DataType, Dimensions};
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// Largest scene file or external buffer/image file we read.
pub const MAX_FILE_BYTES: u64 = 2 << 30;
/// Largest texture side; larger images are refused before decoding.
pub const MAX_TEXTURE_SIDE: u32 = 16384;
/// Deepest node hierarchy we follow (also guards against cyclic node graphs).
const MAX_NODE_DEPTH: usize = 256;

/// Extensions this renderer implements. Another one in `extensionsRequired` is refused, naming it;
/// one only in `extensionsUsed` (the file says it renders without it) is ignored with a warning
/// naming it (`Scene::warnings`: CLI output, EXR header, REST job, web page): never a silent
/// difference, never a needless refusal.
const SUPPORTED_EXTENSIONS: &[&str] = &[
    "KHR_materials_emissive_strength",
    "KHR_materials_specular",
    "KHR_materials_ior",
    "KHR_lights_punctual",
    "KHR_materials_transmission",
    "KHR_texture_transform",
    "KHR_materials_clearcoat",
    "KHR_materials_sheen",
    "KHR_materials_volume",
    "KHR_materials_unlit",
    "KHR_mesh_quantization",
    "KHR_draco_mesh_compression",
    "EXT_mesh_gpu_instancing",
    "EXT_meshopt_compression",
];
/// Extensions that carry only metadata and cannot change the image.
const HARMLESS_EXTENSIONS: &[&str] = &["KHR_xmp_json_ld", "KHR_xmp"];

/// Most mesh placements (nodes with a mesh, plus EXT_mesh_gpu_instancing instances) in a scene.
const MAX_PLACEMENTS: usize = 1 << 24;
/// Most stored triangles (unique geometry: instances do not count).
const MAX_TRIANGLES: usize = 1 << 28;

/// Largest point (and face) count a Draco stream may decode to.
const MAX_DRACO_POINTS: u64 = 1 << 27;

/// A primitive's vertex attributes (POSITION's count each) and triangle-list indices, from
/// accessors or from a Draco stream.
struct VertexData {
    positions: Vec<[f32; 3]>,
    normals: Option<Vec<[f32; 3]>>,
    tangents: Option<Vec<[f32; 4]>>,
    uvs: Option<Vec<[f32; 2]>>,
    uvs1: Option<Vec<[f32; 2]>>,
    colors: Option<Vec<[f32; 4]>>,
    indices: Vec<u32>,
}

/// A texture's KHR_texture_transform, as read from the file.
#[derive(Clone, Copy, Debug)]
struct TexTransform {
    offset: [f32; 2],
    rotation: f32,
    scale: [f32; 2],
    tex_coord: Option<u32>,
}

impl From<gltf::texture::TextureTransform<'_>> for TexTransform {
    fn from(t: gltf::texture::TextureTransform<'_>) -> Self {
        TexTransform { offset: t.offset(), rotation: t.rotation(), scale: t.scale(), tex_coord: t.tex_coord() }
    }
}

/// Loads a scene from a `.glb` or `.gltf` file.
pub fn load(path: &Path) -> Result<Scene, SceneError> {
    let bytes = read_bounded(path, path, "scene file")?;
    load_from_bytes(path, &bytes)
}

/// Loads a scene from bytes; `path` names the file in errors and anchors relative URIs.
pub fn load_from_bytes(path: &Path, bytes: &[u8]) -> Result<Scene, SceneError> {
    let loader = Loader {
        path: path.to_path_buf(),
        dir: path.parent().map(Path::to_path_buf).unwrap_or_else(|| PathBuf::from(".")),
        decoded: Default::default(),
        asked: Default::default(),
    };
    // Extensions first, so that an unsupported one (e.g. Draco compression, whose accessors have no
    // bufferView) is reported by name rather than as the validation errors it causes.
    let warnings = loader.check_extensions(bytes)?;
    let parse_error = |e: gltf::Error| SceneError::Parse { path: path.into(), message: e.to_string() };
    let mut gltf = gltf::Gltf::from_slice_without_validation(bytes).map_err(parse_error)?;
    // The gltf crate's validation refuses every required extension it does not parse itself; the
    // ones this loader models from the raw JSON (clearcoat, sheen, volume, unlit, quantization)
    // were accepted by `check_extensions` above, so only the crate's own stay for it to check.
    let mut root = gltf.document.into_json();
    root.extensions_required.retain(|e| gltf::json::extensions::ENABLED_EXTENSIONS.contains(&e.as_str()));
    gltf.document = validate(root).map_err(parse_error)?;
    let t0 = std::time::Instant::now();
    let buffers = loader.load_buffers(&gltf.document, gltf.blob.as_deref())?;
    let t1 = std::time::Instant::now();
    let mut scene = loader.build(&gltf.document, &buffers)?;
    tracing::debug!(buffers_s = (t1 - t0).as_secs_f64(), build_s = t1.elapsed().as_secs_f64(), "glTF loaded");
    for w in &warnings {
        tracing::warn!(file = %path.display(), "{w}");
    }
    scene.warnings = warnings;
    scene.generator = gltf.document.as_json().asset.generator.clone();
    Ok(scene)
}

/// The gltf crate's validation, minus one finding the spec allows: an accessor of a
/// KHR_draco_mesh_compression primitive has no bufferView (its data is in the Draco stream).
fn validate(root: gltf::json::Root) -> Result<gltf::Document, gltf::Error> {
    let holes = validation_holes(&root);
    if !holes.is_empty() {
        return Err(gltf::Error::Validation(holes));
    }
    let draco_accessors: std::collections::HashSet<String> = root
        .meshes
        .iter()
        .flat_map(|m| &m.primitives)
        .filter(|p| p.extensions.as_ref().is_some_and(|e| e.others.contains_key("KHR_draco_mesh_compression")))
        .flat_map(|p| p.attributes.values().map(|a| a.value()).chain(p.indices.as_ref().map(|i| i.value())))
        .map(|i| format!("accessors[{i}].bufferView"))
        .collect();
    if draco_accessors.is_empty() {
        return gltf::Document::from_json(root);
    }
    match gltf::Document::from_json(root.clone()) {
        Ok(document) => Ok(document),
        Err(gltf::Error::Validation(errors)) => {
            let rest: Vec<_> = errors
                .into_iter()
                .filter(|(path, e)| {
                    !(matches!(e, gltf::json::validation::Error::Missing) && draco_accessors.contains(path.as_str()))
                })
                .collect();
            if rest.is_empty() {
                Ok(gltf::Document::from_json_without_validation(root))
            } else {
                Err(gltf::Error::Validation(rest))
            }
        }
        Err(e) => Err(e),
    }
}

/// What the gltf crate's validation (1.4) does not check, though its accessors rely on it and panic
/// otherwise: a primitive's accessor indices (its validation hook indexes the POSITION accessor
/// before anything checks the index) and an animation channel's target (node index and path, which
/// `Animation::validate` skips), and an image's source. Found by `tests/mutation_fuzz.rs`.
fn validation_holes(root: &gltf::json::Root) -> Vec<(gltf::json::Path, gltf::json::validation::Error)> {
    use gltf::json::validation::{Checked, Error};
    use gltf::json::Path;
    let mut holes = Vec::new();
    let accessors = root.accessors.len();
    for (m, mesh) in root.meshes.iter().enumerate() {
        for (p, prim) in mesh.primitives.iter().enumerate() {
            let at = || Path::new().field("meshes").index(m).field("primitives").index(p);
            for (semantic, index) in &prim.attributes {
                if index.value() >= accessors {
                    let name = match semantic {
                        Checked::Valid(s) => s.to_string(),
                        Checked::Invalid => "?".to_string(),
                    };
                    holes.push((at().field("attributes").key(&name), Error::IndexOutOfBounds));
                }
            }
            if prim.indices.as_ref().is_some_and(|i| i.value() >= accessors) {
                holes.push((at().field("indices"), Error::IndexOutOfBounds));
            }
            for (t, target) in prim.targets.iter().flatten().enumerate() {
                let fields =
                    [("POSITION", &target.positions), ("NORMAL", &target.normals), ("TANGENT", &target.tangents)];
                for (name, index) in fields {
                    if index.as_ref().is_some_and(|i| i.value() >= accessors) {
                        holes.push((at().field("targets").index(t).key(name), Error::IndexOutOfBounds));
                    }
                }
            }
        }
    }
    // An image is a URI or a buffer view with its MIME type (glTF 2.0 §5.18); the crate's
    // `Image::source` unwraps both without its validation having checked either.
    for (i, image) in root.images.iter().enumerate() {
        let at = || Path::new().field("images").index(i);
        match (&image.uri, &image.buffer_view, &image.mime_type) {
            (None, None, _) => holes.push((at().field("uri"), Error::Missing)),
            (_, Some(_), None) => holes.push((at().field("mimeType"), Error::Missing)),
            _ => {}
        }
    }
    for (a, animation) in root.animations.iter().enumerate() {
        for (c, channel) in animation.channels.iter().enumerate() {
            let at = || Path::new().field("animations").index(a).field("channels").index(c).field("target");
            if channel.target.node.value() >= root.nodes.len() {
                holes.push((at().field("node"), Error::IndexOutOfBounds));
            }
            if matches!(channel.target.path, Checked::Invalid) {
                holes.push((at().field("path"), Error::Invalid));
            }
        }
    }
    holes
}

/// One component of a vertex attribute as f32 (glTF 2.0 §3.6.2.3, KHR_mesh_quantization):
/// normalized integers to [0, 1] or [−1, 1] (signed: max(c / MAX, −1)), others to their value.
fn decode_component(ty: DataType, norm: bool, b: &[u8]) -> f32 {
    match ty {
        DataType::F32 => f32::from_le_bytes([b[0], b[1], b[2], b[3]]),
        DataType::I8 => {
            let v = b[0] as i8 as f32;
            if norm {
                (v / 127.0).max(-1.0)
            } else {
                v
            }
        }
        DataType::U8 => {
            let v = b[0] as f32;
            if norm {
                v / 255.0
            } else {
                v
            }
        }
        DataType::I16 => {
            let v = i16::from_le_bytes([b[0], b[1]]) as f32;
            if norm {
                (v / 32767.0).max(-1.0)
            } else {
                v
            }
        }
        DataType::U16 => {
            let v = u16::from_le_bytes([b[0], b[1]]) as f32;
            if norm {
                v / 65535.0
            } else {
                v
            }
        }
        DataType::U32 => u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f32,
    }
}

/// Appends `n` values of a vertex attribute for the vertices from `base` on, to storage that stays
/// empty until some primitive has the attribute (then it is filled with `fill` up to `base` first).
fn append_lazy<T: Copy>(store: &mut Vec<T>, base: usize, n: usize, values: Option<impl Iterator<Item = T>>, fill: T) {
    match values {
        Some(v) => {
            store.resize(base, fill);
            store.extend(v);
        }
        None if !store.is_empty() => {
            store.resize(base, fill);
            store.extend(std::iter::repeat_n(fill, n));
        }
        None => {}
    }
}

fn read_bounded(path: &Path, scene: &Path, what: &str) -> Result<Vec<u8>, SceneError> {
    let meta = std::fs::metadata(path).map_err(|source| SceneError::Io { path: path.into(), source })?;
    if meta.len() > MAX_FILE_BYTES {
        return Err(SceneError::TooLarge {
            path: scene.into(),
            what: format!("{what} {}", path.display()),
            size: meta.len(),
            limit: MAX_FILE_BYTES,
        });
    }
    std::fs::read(path).map_err(|source| SceneError::Io { path: path.into(), source })
}

struct Loader {
    path: PathBuf,
    dir: PathBuf,
    /// The materials' images decoded ahead, in parallel (`Loader::decode_images`), by image
    /// index: taken by the first texture that refers to one (an image also read with the other
    /// colour space is decoded again then). An image that failed keeps its error until asked.
    decoded: std::sync::Mutex<HashMap<usize, Result<Decoded, SceneError>>>,
    /// While `decode_images` finds which images the materials read: the indices asked for (the
    /// texture references made meanwhile are thrown away).
    asked: std::sync::Mutex<Option<Vec<usize>>>,
}

/// An image decoded to 8-bit RGBA: width, height, texels.
type Decoded = (u32, u32, Vec<[u8; 4]>);

fn percent_decode(s: &str) -> Option<String> {
    let b = s.as_bytes();
    let mut out = Vec::with_capacity(b.len());
    let mut i = 0;
    while i < b.len() {
        if b[i] == b'%' {
            let hex = std::str::from_utf8(b.get(i + 1..i + 3)?).ok()?;
            out.push(u8::from_str_radix(hex, 16).ok()?);
            i += 3;
        } else {
            out.push(b[i]);
            i += 1;
        }
    }
    String::from_utf8(out).ok()
}

impl Loader {
    fn invalid(&self, message: impl Into<String>) -> SceneError {
        SceneError::Invalid { path: self.path.clone(), message: message.into() }
    }

    fn unsupported(&self, feature: impl Into<String>) -> SceneError {
        SceneError::Unsupported { path: self.path.clone(), feature: feature.into() }
    }

    /// Reads `extensionsUsed`/`extensionsRequired` straight from the JSON (the gltf crate's own
    /// parser already rejects unknown required extensions, with a less helpful message).
    fn check_extensions(&self, bytes: &[u8]) -> Result<Vec<String>, SceneError> {
        let json: &[u8] = if bytes.starts_with(b"glTF") {
            match gltf::binary::Glb::from_slice(bytes) {
                Ok(glb) => return self.check_extension_json(&glb.json),
                Err(e) => return Err(SceneError::Parse { path: self.path.clone(), message: e.to_string() }),
            }
        } else {
            bytes
        };
        self.check_extension_json(json)
    }

    fn check_extension_json(&self, json: &[u8]) -> Result<Vec<String>, SceneError> {
        #[derive(serde::Deserialize)]
        struct Extensions {
            #[serde(default, rename = "extensionsUsed")]
            used: Vec<String>,
            #[serde(default, rename = "extensionsRequired")]
            required: Vec<String>,
        }
        let ext: Extensions = serde_json::from_slice(json)
            .map_err(|e| SceneError::Parse { path: self.path.clone(), message: e.to_string() })?;
        let modelled = |e: &str| SUPPORTED_EXTENSIONS.contains(&e) || HARMLESS_EXTENSIONS.contains(&e);
        if let Some(e) = ext.required.iter().find(|e| !modelled(e)) {
            return Err(self.unsupported(format!("extension {e} (required by the file)")));
        }
        let mut warnings = Vec::new();
        for e in ext.used.iter().filter(|e| !modelled(e)) {
            let e: String = e.chars().take(128).collect();
            warnings.push(format!("extension {e} is not modelled: rendered without it (the file marks it optional)"));
        }
        warnings.truncate(64);
        Ok(warnings)
    }

    /// Resolves a URI to bytes: `data:` URIs (base64) or a relative path inside the scene's folder.
    fn fetch_uri(&self, uri: &str, what: &str) -> Result<Vec<u8>, SceneError> {
        let forbid = |reason: &str| SceneError::ForbiddenUri {
            path: self.path.clone(),
            uri: uri.chars().take(120).collect(),
            reason: reason.into(),
        };
        if let Some(rest) = uri.strip_prefix("data:") {
            let (header, data) = rest.split_once(',').ok_or_else(|| forbid("malformed data URI (no ',')"))?;
            if !header.ends_with(";base64") {
                return Err(forbid("data URIs must be base64-encoded"));
            }
            if data.len() as u64 > MAX_FILE_BYTES * 4 / 3 + 4 {
                return Err(SceneError::TooLarge {
                    path: self.path.clone(),
                    what: format!("{what} data URI"),
                    size: data.len() as u64,
                    limit: MAX_FILE_BYTES,
                });
            }
            return base64::engine::general_purpose::STANDARD
                .decode(data.trim())
                .map_err(|e| self.invalid(format!("{what}: bad base64 in data URI: {e}")));
        }
        if let Some(colon) = uri.find(':') {
            if !uri[..colon].contains('/') {
                return Err(forbid("only data URIs and relative paths inside the scene's folder are allowed"));
            }
        }
        let decoded = percent_decode(uri).ok_or_else(|| forbid("bad percent-encoding"))?;
        if decoded.starts_with('/') || decoded.contains('\\') || decoded.split('/').any(|c| c == "..") {
            return Err(forbid("path escapes the scene's folder"));
        }
        let full = self.dir.join(&decoded);
        let base = self.dir.canonicalize().map_err(|source| SceneError::Io { path: self.dir.clone(), source })?;
        let canon = full.canonicalize().map_err(|source| SceneError::Io { path: full.clone(), source })?;
        if !canon.starts_with(&base) {
            return Err(forbid("path escapes the scene's folder (through a link)"));
        }
        read_bounded(&canon, &self.path, what)
    }

    fn load_buffers(&self, doc: &gltf::Document, blob: Option<&[u8]>) -> Result<Vec<Vec<u8>>, SceneError> {
        let mut out = Vec::new();
        for buffer in doc.buffers() {
            if crate::meshopt_views::is_fallback(&buffer) {
                // Filled by the compressed views that decode into it (below); bounded like a file.
                if buffer.length() as u64 > MAX_FILE_BYTES {
                    return Err(SceneError::TooLarge {
                        path: self.path.clone(),
                        what: format!("EXT_meshopt_compression fallback buffer {}", buffer.index()),
                        size: buffer.length() as u64,
                        limit: MAX_FILE_BYTES,
                    });
                }
                out.push(vec![0u8; buffer.length()]);
                continue;
            }
            let data = match buffer.source() {
                gltf::buffer::Source::Bin => blob
                    .ok_or_else(|| {
                        self.invalid(format!(
                            "buffer {} refers to the GLB binary chunk, which is missing",
                            buffer.index()
                        ))
                    })?
                    .to_vec(),
                gltf::buffer::Source::Uri(uri) => self.fetch_uri(uri, &format!("buffer {}", buffer.index()))?,
            };
            if data.len() < buffer.length() {
                return Err(self.invalid(format!(
                    "buffer {} holds {} bytes but declares {}",
                    buffer.index(),
                    data.len(),
                    buffer.length()
                )));
            }
            out.push(data);
        }
        for view in doc.views() {
            let end = view.offset().checked_add(view.length());
            let len = out.get(view.buffer().index()).map(Vec::len).unwrap_or(0);
            if end.is_none_or(|e| e > len) {
                return Err(self.invalid(format!(
                    "bufferView {} (offset {}, length {}) runs past its buffer ({} bytes)",
                    view.index(),
                    view.offset(),
                    view.length(),
                    len
                )));
            }
        }
        crate::meshopt_views::decode_views(&self.path, doc, &mut out)?;
        Ok(out)
    }

    /// Checks an accessor's type and that all of its elements lie inside its buffer view.
    fn check_accessor(
        &self,
        acc: &gltf::Accessor,
        what: &str,
        types: &[DataType],
        dims: Dimensions,
    ) -> Result<usize, SceneError> {
        let name = format!("{what} (accessor {})", acc.index());
        if acc.sparse().is_some() {
            return Err(self.unsupported(format!("sparse accessor for {name}")));
        }
        self.check_dense(acc, what, types, dims)
    }

    /// `check_accessor` without the refusal of sparse accessors (whose base is checked here).
    fn check_dense(
        &self,
        acc: &gltf::Accessor,
        what: &str,
        types: &[DataType],
        dims: Dimensions,
    ) -> Result<usize, SceneError> {
        let name = format!("{what} (accessor {})", acc.index());
        if !types.contains(&acc.data_type()) || acc.dimensions() != dims {
            return Err(self.unsupported(format!("{name} stored as {:?} {:?}", acc.data_type(), acc.dimensions())));
        }
        let view = acc.view().ok_or_else(|| self.invalid(format!("{name} has no bufferView")))?;
        let count = acc.count();
        if count == 0 {
            return Err(self.invalid(format!("{name} is empty")));
        }
        let elem = acc.size();
        let stride = view.stride().unwrap_or(elem);
        if stride < elem {
            return Err(self.invalid(format!("{name}: byteStride {stride} is smaller than an element ({elem} bytes)")));
        }
        let end =
            (count - 1).checked_mul(stride).and_then(|x| x.checked_add(elem)).and_then(|x| x.checked_add(acc.offset()));
        if end.is_none_or(|e| e > view.length()) {
            return Err(self.invalid(format!(
                "{name}: {count} elements run past bufferView {} ({} bytes)",
                view.index(),
                view.length()
            )));
        }
        Ok(count)
    }

    fn build(&self, doc: &gltf::Document, buffers: &[Vec<u8>]) -> Result<Scene, SceneError> {
        self.decode_images(doc, buffers)?;
        let mut textures = Vec::new();
        let mut texture_ids: HashMap<(usize, bool), u32> = HashMap::new();
        let mut materials = Vec::new();
        for m in doc.materials() {
            materials.push(self.material(doc, &m, buffers, &mut textures, &mut texture_ids)?);
        }
        let default_material = materials.len() as u32;
        materials.push(Material::default());

        let mut mesh = Mesh::default();
        let mut cameras = Vec::new();
        let mut punctual = Vec::new();
        let roots: Vec<gltf::Node> = match doc.default_scene().or_else(|| doc.scenes().next()) {
            Some(s) => s.nodes().collect(),
            None => {
                // No scene: render every root node (nodes that are nobody's child).
                let children: std::collections::HashSet<usize> =
                    doc.nodes().flat_map(|n| n.children().map(|c| c.index())).collect();
                doc.nodes().filter(|n| !children.contains(&n.index())).collect()
            }
        };
        let mut stack: Vec<(gltf::Node, Mat4, usize)> =
            roots.into_iter().rev().map(|n| (n, Mat4::IDENTITY, 0)).collect();
        let mut visits = 0usize;
        // (mesh, node, world transform, local transform under the node, from
        // EXT_mesh_gpu_instancing) in traversal order.
        let mut placements: Vec<(usize, usize, Mat4, Mat4, bool)> = Vec::new();
        // Animated mode: the file animates, skins or morphs. Then every mesh that neither deforms
        // nor emits is instanced (its BVH built once), and the rest is re-posed per frame.
        let animated = doc.animations().next().is_some()
            || doc.skins().next().is_some()
            || doc.meshes().any(|m| m.primitives().any(|p| p.morph_targets().next().is_some()));
        let mut anim = crate::animation::Animator::default();
        if animated {
            anim.graph = self.node_graph(doc)?;
        }
        while let Some((node, parent, depth)) = stack.pop() {
            visits += 1;
            if depth > MAX_NODE_DEPTH || visits > doc.nodes().len() * 64 + 1024 {
                return Err(self.invalid("node hierarchy is too deep or cyclic"));
            }
            let local = Mat4::from_cols_array_2d(&node.transform().matrix());
            let world = parent * local;
            if !world.is_finite() {
                return Err(self.invalid(format!("node {} has a non-finite transform", node.index())));
            }
            if animated {
                anim.graph.order.push(node.index());
            }
            if let Some(light) = node.light() {
                punctual.push(self.punctual_light(&light, world)?);
                if animated {
                    anim.lights.push((node.index(), self.punctual_light(&light, Mat4::IDENTITY)?));
                }
            }
            if let Some(cam) = node.camera() {
                match cam.projection() {
                    gltf::camera::Projection::Perspective(p) => {
                        let c = Camera::from_matrix(world, p.yfov(), p.aspect_ratio()).ok_or_else(|| {
                            self.invalid(format!(
                                "camera on node {} has a degenerate transform or yfov {}",
                                node.index(),
                                p.yfov()
                            ))
                        })?;
                        cameras.push(c);
                        if animated {
                            anim.cameras.push((node.index(), p.yfov(), p.aspect_ratio()));
                        }
                    }
                    gltf::camera::Projection::Orthographic(_) => {
                        tracing::warn!(node = node.index(), "orthographic camera skipped (not supported)");
                    }
                }
            }
            if let Some(m) = node.mesh() {
                match node.extensions().and_then(|e| e.get("EXT_mesh_gpu_instancing")) {
                    Some(ext) => {
                        for local in self.gpu_instances(doc, ext, buffers, node.index())? {
                            placements.push((m.index(), node.index(), world * local, local, true));
                        }
                    }
                    None => placements.push((m.index(), node.index(), world, Mat4::IDENTITY, false)),
                }
                if placements.len() > MAX_PLACEMENTS {
                    return Err(self.invalid(format!("more than {MAX_PLACEMENTS} mesh placements")));
                }
            }
            for child in node.children() {
                stack.push((child, world, depth + 1));
            }
        }
        // A mesh placed more than once (by several nodes, or by EXT_mesh_gpu_instancing) is stored
        // once in object space and instanced, unless it emits: emitters stay flattened, because
        // every emitting triangle is a light NEE samples in world space.
        let mut uses: HashMap<usize, usize> = HashMap::new();
        for &(m, _, _, _, gpu) in &placements {
            *uses.entry(m).or_default() += if gpu { 2 } else { 1 };
        }
        let emits = |m: &gltf::Mesh| {
            m.primitives().any(|p| {
                let i = p.material().index().map_or(default_material as usize, |i| i);
                materials.get(i).is_some_and(Material::is_emissive)
            })
        };
        let mut prototype_of: HashMap<usize, u32> = HashMap::new();
        for &(mi, node_index, world, local, _) in &placements {
            let Some(m) = doc.meshes().nth(mi) else { continue };
            let mesh_name = match m.name() {
                Some(n) => format!("mesh {} '{}'", m.index(), n.chars().take(64).collect::<String>()),
                None => format!("mesh {}", m.index()),
            };
            let node = doc.nodes().nth(node_index);
            let deforms = node.as_ref().is_some_and(|n| n.skin().is_some())
                || m.primitives().any(|p| p.morph_targets().next().is_some());
            if animated && (deforms || emits(&m)) {
                // Re-posed every frame: loaded at rest (object space), its rest data kept.
                for prim in m.primitives() {
                    let what = format!("{mesh_name} primitive {} (node {node_index})", prim.index());
                    let first = mesh.positions.len();
                    self.primitive(
                        doc,
                        &prim,
                        &what,
                        Mat4::IDENTITY,
                        buffers,
                        &mut mesh,
                        &materials,
                        default_material,
                    )?;
                    if mesh.positions.len() > first {
                        let skin = node.as_ref().and_then(|n| n.skin());
                        anim.posed.push(self.posed_primitive(
                            doc,
                            &prim,
                            &what,
                            node_index,
                            first,
                            &mesh,
                            skin.as_ref(),
                            &mut anim.skins,
                            buffers,
                        )?);
                    }
                }
                continue;
            }
            if (animated || uses.get(&mi).copied().unwrap_or(0) > 1) && !emits(&m) {
                let proto = match prototype_of.get(&mi) {
                    Some(&p) => p,
                    None => {
                        let first = mesh.triangles.len();
                        for prim in m.primitives() {
                            let what = format!("{mesh_name} primitive {} (instanced)", prim.index());
                            self.primitive(
                                doc,
                                &prim,
                                &what,
                                Mat4::IDENTITY,
                                buffers,
                                &mut mesh,
                                &materials,
                                default_material,
                            )?;
                        }
                        for t in &mut mesh.triangles[first..] {
                            t.flags |= flags::OBJECT_SPACE;
                        }
                        // Rigid placements keep a flat triangle's normals its own (not so a
                        // skinned or morphed one's, re-posed above with their normals).
                        mesh.drop_flat_normals(first..mesh.triangles.len());
                        mesh.prototypes.push(first as u32..mesh.triangles.len() as u32);
                        let p = mesh.prototypes.len() as u32 - 1;
                        prototype_of.insert(mi, p);
                        p
                    }
                };
                match crate::mesh::Instance::new(proto, world) {
                    Some(inst) => {
                        mesh.instances.push(inst);
                        if animated {
                            anim.instance_nodes.push((node_index, local));
                        }
                    }
                    None => tracing::warn!(node = node_index, "instance skipped: its transform is singular"),
                }
                continue;
            }
            let first = mesh.triangles.len();
            for prim in m.primitives() {
                let what = format!("{mesh_name} primitive {} (node {node_index})", prim.index());
                self.primitive(doc, &prim, &what, world, buffers, &mut mesh, &materials, default_material)?;
            }
            mesh.drop_flat_normals(first..mesh.triangles.len());
        }
        // As a world vertex past the usable range is refused above, so is an instance placed there.
        let proto_boxes = mesh.prototype_bounds();
        for inst in &mesh.instances {
            let Some(&bx) = proto_boxes.get(inst.prototype as usize) else { continue };
            if bx.0.cmple(bx.1).all() && Mesh::instance_box(inst, bx).is_none() {
                return Err(self.invalid(format!(
                    "an instance of mesh prototype {} reaches past ±{:e} (or is not finite) once placed by its node transforms",
                    inst.prototype,
                    crate::mesh::MAX_COORDINATE
                )));
            }
        }
        if mesh.triangles.len() > MAX_TRIANGLES {
            return Err(self.invalid(format!("{} triangles (the limit is {MAX_TRIANGLES})", mesh.triangles.len())));
        }
        if animated {
            anim.clips = self.clips(doc, buffers)?;
            anim.select(None).map_err(|e| self.invalid(e.0))?;
            // The rest pose is not a frame: pose frame 0 before anything is built from the geometry.
            punctual = anim.apply(0.0, &mut mesh, &mut cameras);
        }
        let mut scene = Scene::new(mesh, materials, textures, cameras);
        if !punctual.is_empty() {
            scene.replace_punctual(punctual);
        }
        if animated {
            scene.set_animator(anim);
        }
        Ok(scene)
    }

    #[allow(clippy::too_many_arguments)] // the primitive, its name, transform, and the scene being built
    fn primitive(
        &self,
        doc: &gltf::Document,
        prim: &gltf::Primitive,
        what: &str,
        world: Mat4,
        buffers: &[Vec<u8>],
        mesh: &mut Mesh,
        materials: &[Material],
        default_material: u32,
    ) -> Result<(), SceneError> {
        use gltf::mesh::Mode;
        let mode = prim.mode();
        if matches!(mode, Mode::Points | Mode::Lines | Mode::LineLoop | Mode::LineStrip) {
            tracing::warn!(?mode, "primitive skipped: points and lines have no area to render");
            return Ok(());
        }
        let draco = prim.extensions().and_then(|e| e.get("KHR_draco_mesh_compression"));
        let VertexData { positions, normals, tangents, uvs, uvs1, colors, indices } = match draco {
            Some(ext) => self.draco_vertex_data(doc, ext, buffers, what)?,
            None => self.accessor_vertex_data(prim, buffers, what)?,
        };
        let n = positions.len();
        if let Some(bad) = indices.iter().find(|&&i| i as usize >= n) {
            return Err(self.invalid(format!("index {bad} out of range for {n} vertices")));
        }
        let tris: Vec<[u32; 3]> = match mode {
            Mode::Triangles => indices.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect(),
            Mode::TriangleStrip => (0..indices.len().saturating_sub(2))
                .map(|i| {
                    if i % 2 == 0 {
                        [indices[i], indices[i + 1], indices[i + 2]]
                    } else {
                        [indices[i + 1], indices[i], indices[i + 2]]
                    }
                })
                .collect(),
            Mode::TriangleFan => {
                (1..indices.len().saturating_sub(1)).map(|i| [indices[i], indices[i + 1], indices[0]]).collect()
            }
            _ => Vec::new(),
        };

        let material = prim.material().index().map_or(default_material, |i| i as u32);
        let mat = &materials[material as usize];
        let needs_tangents = mat.normal_texture.is_some() || mat.clearcoat_normal_texture.is_some();
        if needs_tangents && uvs.is_none() {
            return Err(
                self.invalid(format!("material '{}' has a normal map but the primitive has no TEXCOORD_0", mat.name))
            );
        }

        // World transform: points by M, normals by the inverse transpose, tangents by M's linear part.
        let linear = glam::Mat3::from_mat4(world);
        let det = linear.determinant();
        if det == 0.0 || !det.is_finite() {
            tracing::warn!("primitive skipped: its node transform is singular");
            return Ok(());
        }
        let normal_m = linear.inverse().transpose();
        let base = mesh.positions.len() as u32;
        let first_world = mesh.positions.len();
        mesh.positions.extend(positions.iter().map(|p| world.transform_point3(Vec3::from(*p))));
        if let Some(i) = mesh.positions[first_world..].iter().position(|&p| !crate::mesh::is_usable_position(p)) {
            return Err(self.invalid(format!(
                "{what}: vertex {i} {:?} is at {}: not finite once placed by its node transforms, or past ±{:e}",
                positions[i],
                mesh.positions[first_world + i],
                crate::mesh::MAX_COORDINATE
            )));
        }
        // Vertex attributes other than POSITION are stored only once some primitive has them
        // (then parallel to `positions`, filled where a primitive has none): a scene of bare
        // triangles pays 12 bytes a vertex, not 12 + 12 + 16 + 8 + 8 + 16.
        append_lazy(
            &mut mesh.normals,
            base as usize,
            n,
            normals.as_ref().map(|ns| ns.iter().map(|v| (normal_m * Vec3::from(*v)).normalize_or_zero())),
            Vec3::ZERO,
        );
        append_lazy(
            &mut mesh.tangents,
            base as usize,
            n,
            tangents.as_ref().map(|ts| {
                ts.iter().map(|t| {
                    (linear * Vec3::new(t[0], t[1], t[2])).normalize_or_zero().extend(if t[3] < 0.0 {
                        -1.0
                    } else {
                        1.0
                    })
                })
            }),
            Vec4::ZERO,
        );
        append_lazy(
            &mut mesh.uvs,
            base as usize,
            n,
            uvs.as_ref().map(|us| us.iter().map(|u| Vec2::from(*u))),
            Vec2::ZERO,
        );
        append_lazy(
            &mut mesh.colors,
            base as usize,
            n,
            colors.as_ref().map(|cs| cs.iter().map(|c| Vec4::from(*c))),
            Vec4::ONE,
        );
        append_lazy(
            &mut mesh.uvs1,
            base as usize,
            n,
            uvs1.as_ref().map(|us| us.iter().map(|u| Vec2::from(*u))),
            Vec2::ZERO,
        );
        let mut f = 0u8;
        if normals.is_some() {
            f |= flags::NORMALS;
        }
        if tangents.is_some() {
            f |= flags::TANGENTS;
        }
        if uvs.is_some() {
            f |= flags::UVS;
        }
        if uvs1.is_some() {
            f |= flags::UVS1;
        }
        if colors.is_some() {
            f |= flags::COLORS;
        }
        let first = mesh.triangles.len();
        for t in tris {
            // A mirroring transform (negative determinant) flips the winding (glTF spec §3.7.4).
            let v = if det < 0.0 {
                [base + t[0], base + t[2], base + t[1]]
            } else {
                [base + t[0], base + t[1], base + t[2]]
            };
            mesh.triangles.push(Triangle { v, material, flags: f });
        }
        if needs_tangents && tangents.is_none() {
            mesh.generate_tangents(first..mesh.triangles.len());
        }
        Ok(())
    }

    /// A primitive's vertex attributes and indices read from its accessors.
    fn accessor_vertex_data(
        &self,
        prim: &gltf::Primitive,
        buffers: &[Vec<u8>],
        what: &str,
    ) -> Result<VertexData, SceneError> {
        let get = |b: gltf::Buffer| buffers.get(b.index()).map(Vec::as_slice);
        let reader = prim.reader(get);
        let pos_acc = prim.get(&gltf::Semantic::Positions).ok_or_else(|| self.invalid("primitive without POSITION"))?;
        // Float, or the integer types of KHR_mesh_quantization (dequantized here; the node
        // transform carries the scale and offset).
        const POSITION_TYPES: &[DataType] = &[DataType::F32, DataType::I8, DataType::U8, DataType::I16, DataType::U16];
        const UNIT_VECTOR_TYPES: &[DataType] = &[DataType::F32, DataType::I8, DataType::I16];
        let positions: Vec<[f32; 3]> = self.read_floats(&pos_acc, buffers, "POSITION", POSITION_TYPES, false)?;
        let n = positions.len();
        // A NaN or infinite vertex would poison the BVH bounds and every ray near it: refuse it,
        // naming where it is (issue 10; the glTF spec requires finite positions).
        if let Some((i, p)) =
            positions.iter().enumerate().find(|(_, p)| !crate::mesh::is_usable_position(Vec3::from(**p)))
        {
            return Err(self.invalid(format!(
                "{what}: POSITION accessor {} vertex {i} is {p:?}, not a finite position within ±{:e}",
                pos_acc.index(),
                crate::mesh::MAX_COORDINATE
            )));
        }
        let normals: Option<Vec<[f32; 3]>> = match prim.get(&gltf::Semantic::Normals) {
            Some(a) => {
                let v = self.read_floats(&a, buffers, "NORMAL", UNIT_VECTOR_TYPES, true)?;
                self.expect_count(v.len(), n, "NORMAL")?;
                Some(v)
            }
            None => None,
        };
        let tangents: Option<Vec<[f32; 4]>> = match prim.get(&gltf::Semantic::Tangents) {
            Some(a) => {
                let v = self.read_floats(&a, buffers, "TANGENT", UNIT_VECTOR_TYPES, true)?;
                self.expect_count(v.len(), n, "TANGENT")?;
                Some(v)
            }
            None => None,
        };
        let uvs = self.read_tex_coords(prim, 0, n, buffers)?;
        let uvs1 = self.read_tex_coords(prim, 1, n, buffers)?;
        // COLOR_0: RGB or RGBA, float or normalized 8/16-bit; multiplies the base color.
        let colors: Option<Vec<[f32; 4]>> = match prim.get(&gltf::Semantic::Colors(0)) {
            Some(a) => {
                const COLOR_TYPES: &[DataType] = &[DataType::F32, DataType::U8, DataType::U16];
                let v: Vec<[f32; 4]> = if a.dimensions() == Dimensions::Vec3 {
                    self.read_floats::<3>(&a, buffers, "COLOR_0", COLOR_TYPES, true)?
                        .into_iter()
                        .map(|c| [c[0], c[1], c[2], 1.0])
                        .collect()
                } else {
                    self.read_floats::<4>(&a, buffers, "COLOR_0", COLOR_TYPES, true)?
                };
                self.expect_count(v.len(), n, "COLOR_0")?;
                if v.iter().flatten().any(|c| !c.is_finite()) {
                    return Err(self.invalid(format!("{what}: COLOR_0 has a non-finite value")));
                }
                Some(v)
            }
            None => None,
        };
        let indices: Vec<u32> = match prim.indices() {
            Some(a) => {
                self.check_accessor(&a, "indices", &[DataType::U8, DataType::U16, DataType::U32], Dimensions::Scalar)?;
                reader.read_indices().ok_or_else(|| self.invalid("index data missing"))?.into_u32().collect()
            }
            None => (0..n as u32).collect(),
        };
        Ok(VertexData { positions, normals, tangents, uvs, uvs1, colors, indices })
    }

    /// A primitive compressed with KHR_draco_mesh_compression, decoded by `draco-core` (a pure-Rust
    /// Draco decoder) with its decode limits set from this loader's own bounds, so a hostile stream
    /// cannot make it allocate more than a file of MAX_FILE_BYTES could describe.
    fn draco_vertex_data(
        &self,
        doc: &gltf::Document,
        ext: &serde_json::Value,
        buffers: &[Vec<u8>],
        what: &str,
    ) -> Result<VertexData, SceneError> {
        use draco_core::geometry_indices::PointIndex;
        let bad = |m: String| self.invalid(format!("{what}: KHR_draco_mesh_compression: {m}"));
        let view = ext.get("bufferView").and_then(|v| v.as_u64()).ok_or_else(|| bad("no bufferView".into()))?;
        let v = usize::try_from(view)
            .ok()
            .and_then(|i| doc.views().nth(i))
            .ok_or_else(|| bad(format!("bufferView {view} does not exist")))?;
        let (buffer, offset, length) = (v.buffer().index(), v.offset(), v.length());
        let bytes = buffers
            .get(buffer)
            .and_then(|b| b.get(offset..offset.checked_add(length)?))
            .ok_or_else(|| bad(format!("bufferView {view} is outside its buffer")))?;
        let limits = draco_core::DecodeLimits::default()
            .with_max_points(MAX_DRACO_POINTS)
            .with_max_faces(MAX_DRACO_POINTS)
            .with_max_decoded_bytes(MAX_FILE_BYTES);
        let mut input = draco_core::DecoderBuffer::new(bytes).with_limits(limits);
        let mut decoded = draco_core::mesh::Mesh::new();
        draco_core::mesh_decoder::MeshDecoder::new()
            .decode(&mut input, &mut decoded)
            .map_err(|e| bad(format!("cannot decode: {e:?}")))?;
        let n = decoded.num_points();
        if n == 0 || decoded.num_faces() == 0 {
            return Err(bad("the stream holds no triangles".into()));
        }
        let attributes =
            ext.get("attributes").and_then(|a| a.as_object()).ok_or_else(|| bad("no attributes".into()))?;
        let read = |name: &str, components: usize| -> Result<Option<Vec<f32>>, SceneError> {
            let Some(id) = attributes.get(name) else { return Ok(None) };
            let id = id.as_u64().and_then(|i| u32::try_from(i).ok()).ok_or_else(|| bad(format!("{name} id {id}")))?;
            let att = decoded
                .attribute_by_unique_id(id)
                .ok_or_else(|| bad(format!("{name}: the stream has no attribute {id}")))?;
            if (att.num_components() as usize) < components {
                return Err(bad(format!("{name} has {} components, {components} needed", att.num_components())));
            }
            let v = att.read_f32s(n, components);
            if v.iter().any(|x| !x.is_finite()) {
                return Err(bad(format!("{name} has a non-finite value")));
            }
            Ok(Some(v))
        };
        fn chunks<const N: usize>(v: Option<Vec<f32>>) -> Option<Vec<[f32; N]>> {
            v.map(|v| v.chunks_exact(N).map(|c| std::array::from_fn(|i| c[i])).collect())
        }
        let positions = chunks::<3>(read("POSITION", 3)?).ok_or_else(|| bad("no POSITION".into()))?;
        let normals = chunks::<3>(read("NORMAL", 3)?);
        let tangents = chunks::<4>(read("TANGENT", 4)?);
        let uvs = chunks::<2>(read("TEXCOORD_0", 2)?);
        let uvs1 = chunks::<2>(read("TEXCOORD_1", 2)?);
        let colors = match attributes.get("COLOR_0") {
            None => None,
            Some(id) => {
                let id =
                    id.as_u64().and_then(|i| u32::try_from(i).ok()).ok_or_else(|| bad(format!("COLOR_0 id {id}")))?;
                let c = decoded.attribute_by_unique_id(id).map_or(4, |a| a.num_components() as usize).clamp(3, 4);
                let v = read("COLOR_0", c)?.unwrap_or_default();
                Some(v.chunks_exact(c).map(|x| [x[0], x[1], x[2], if c == 4 { x[3] } else { 1.0 }]).collect())
            }
        };
        let indices = decoded.faces().iter().flat_map(|f| f.iter().map(|p: &PointIndex| p.0)).collect();
        Ok(VertexData { positions, normals, tangents, uvs, uvs1, colors, indices })
    }

    /// The node hierarchy with rest transforms and default morph weights (animated scenes).
    fn node_graph(&self, doc: &gltf::Document) -> Result<crate::animation::NodeGraph, SceneError> {
        use crate::animation::{NodeGraph, RestTransform};
        let n = doc.nodes().len();
        let mut g = NodeGraph {
            parent: vec![None; n],
            rest: Vec::with_capacity(n),
            weights: Vec::with_capacity(n),
            order: Vec::new(),
        };
        for node in doc.nodes() {
            for c in node.children() {
                g.parent[c.index()] = Some(node.index());
            }
            g.rest.push(match node.transform() {
                gltf::scene::Transform::Matrix { matrix } => RestTransform::Matrix(Mat4::from_cols_array_2d(&matrix)),
                gltf::scene::Transform::Decomposed { translation, rotation, scale } => RestTransform::Trs {
                    translation: Vec3::from(translation),
                    rotation: glam::Quat::from_array(rotation).normalize(),
                    scale: Vec3::from(scale),
                },
            });
            let targets =
                node.mesh().map_or(0, |m| m.primitives().map(|p| p.morph_targets().count()).max().unwrap_or(0));
            let mut w: Vec<f32> = node.weights().or(node.mesh().and_then(|m| m.weights())).unwrap_or(&[]).to_vec();
            w.resize(targets, 0.0);
            if w.iter().any(|x| !x.is_finite()) {
                return Err(self.invalid(format!("node {}: morph weights are not finite", node.index())));
            }
            g.weights.push(w);
        }
        Ok(g)
    }

    /// A primitive loaded at rest that a pose rewrites: its rest attributes (copied back from the
    /// mesh storage it was just loaded into), morph targets and skin influences.
    #[allow(clippy::too_many_arguments)] // the primitive, where it is, and the skin table being filled
    fn posed_primitive(
        &self,
        doc: &gltf::Document,
        prim: &gltf::Primitive,
        what: &str,
        node: usize,
        first: usize,
        mesh: &Mesh,
        skin: Option<&gltf::Skin>,
        skins: &mut Vec<crate::animation::Skin>,
        buffers: &[Vec<u8>],
    ) -> Result<crate::animation::Posed, SceneError> {
        use crate::animation::{MorphTarget, Posed, Skin};
        let n = mesh.positions.len() - first;
        let slice = |v: &[Vec3]| if v.len() >= first + n { v[first..first + n].to_vec() } else { Vec::new() };
        let positions = mesh.positions[first..].to_vec();
        let normals = slice(&mesh.normals);
        let tangents =
            if mesh.tangents.len() >= first + n { mesh.tangents[first..first + n].to_vec() } else { Vec::new() };
        let mut targets = Vec::new();
        for (k, t) in prim.morph_targets().enumerate() {
            let read = |a: Option<gltf::Accessor>, name: &str| -> Result<Vec<Vec3>, SceneError> {
                match a {
                    None => Ok(Vec::new()),
                    Some(a) => {
                        let label = format!("{what} morph target {k} {name}");
                        let v: Vec<[f32; 3]> = self.read_floats(
                            &a,
                            buffers,
                            &label,
                            &[DataType::F32, DataType::I8, DataType::I16, DataType::U8, DataType::U16],
                            false,
                        )?;
                        self.expect_count(v.len(), n, &label)?;
                        if v.iter().flatten().any(|c| !c.is_finite()) {
                            return Err(self.invalid(format!("{label} is not finite")));
                        }
                        Ok(v.into_iter().map(Vec3::from).collect())
                    }
                }
            };
            targets.push(MorphTarget {
                positions: read(t.positions(), "POSITION")?,
                normals: if normals.is_empty() { Vec::new() } else { read(t.normals(), "NORMAL")? },
                tangents: if tangents.is_empty() { Vec::new() } else { read(t.tangents(), "TANGENT")? },
            });
        }
        let mut influences = Vec::new();
        let skin_index = match skin {
            None => None,
            Some(sk) => {
                let joints: Vec<usize> = sk.joints().map(|j| j.index()).collect();
                let inverse_bind: Vec<Mat4> = match sk.inverse_bind_matrices() {
                    Some(a) => {
                        let m: Vec<[f32; 16]> = self.read_floats(
                            &a,
                            buffers,
                            &format!("skin {} inverseBindMatrices", sk.index()),
                            &[DataType::F32],
                            false,
                        )?;
                        self.expect_count(m.len(), joints.len(), "inverseBindMatrices")?;
                        m.iter().map(Mat4::from_cols_array).collect()
                    }
                    None => vec![Mat4::IDENTITY; joints.len()],
                };
                if inverse_bind.iter().any(|m| !m.is_finite()) {
                    return Err(self.invalid(format!("skin {}: an inverse bind matrix is not finite", sk.index())));
                }
                influences = vec![[(0u16, 0.0f32); 8]; n];
                for set in 0..2u32 {
                    let (Some(ja), Some(wa)) =
                        (prim.get(&gltf::Semantic::Joints(set)), prim.get(&gltf::Semantic::Weights(set)))
                    else {
                        if set == 0 {
                            return Err(self.invalid(format!("{what}: skinned but without JOINTS_0/WEIGHTS_0")));
                        }
                        continue;
                    };
                    let j: Vec<[f32; 4]> = self.read_floats(
                        &ja,
                        buffers,
                        &format!("{what} JOINTS_{set}"),
                        &[DataType::U8, DataType::U16],
                        false,
                    )?;
                    let w: Vec<[f32; 4]> = self.read_floats(
                        &wa,
                        buffers,
                        &format!("{what} WEIGHTS_{set}"),
                        &[DataType::F32, DataType::U8, DataType::U16],
                        true,
                    )?;
                    self.expect_count(j.len(), n, "JOINTS")?;
                    self.expect_count(w.len(), n, "WEIGHTS")?;
                    for i in 0..n {
                        for c in 0..4 {
                            let joint = j[i][c] as usize;
                            if w[i][c] != 0.0 && joint >= joints.len() {
                                return Err(self.invalid(format!(
                                    "{what}: vertex {i} names joint {joint} of a {}-joint skin",
                                    joints.len()
                                )));
                            }
                            if !w[i][c].is_finite() || w[i][c] < 0.0 {
                                return Err(self.invalid(format!("{what}: vertex {i} has weight {}", w[i][c])));
                            }
                            influences[i][set as usize * 4 + c] = (joint as u16, w[i][c]);
                        }
                    }
                }
                // One Skin entry per glTF skin (looked up by its joints and matrices).
                skins.push(Skin { joints, inverse_bind });
                Some(skins.len() - 1)
            }
        };
        let _ = doc;
        Ok(Posed { node, first, positions, normals, tangents, targets, skin: skin_index, influences })
    }

    /// The file's animations as clips (channels whose target node has no TRS, or whose path we do
    /// not know, are skipped with a warning).
    fn clips(&self, doc: &gltf::Document, buffers: &[Vec<u8>]) -> Result<Vec<crate::animation::Clip>, SceneError> {
        use crate::animation::{Channel, Clip, Interpolation, Property};
        use gltf::animation::{Interpolation as I, Property as P};
        let mut clips = Vec::new();
        for a in doc.animations() {
            let mut channels = Vec::new();
            for ch in a.channels() {
                let what = format!("animation {} channel {}", a.index(), ch.index());
                let sampler = ch.sampler();
                let times: Vec<[f32; 1]> =
                    self.read_floats(&sampler.input(), buffers, &format!("{what} input"), &[DataType::F32], false)?;
                let times: Vec<f32> = times.into_iter().map(|t| t[0]).collect();
                if times.iter().any(|t| !t.is_finite()) || times.windows(2).any(|w| w[1] <= w[0]) {
                    return Err(self.invalid(format!("{what}: key times must be finite and increasing")));
                }
                let interpolation = match sampler.interpolation() {
                    I::Linear => Interpolation::Linear,
                    I::Step => Interpolation::Step,
                    I::CubicSpline => Interpolation::CubicSpline,
                };
                let per_key = if interpolation == Interpolation::CubicSpline { 3 } else { 1 };
                let out = sampler.output();
                const INTS: &[DataType] = &[DataType::F32, DataType::I8, DataType::U8, DataType::I16, DataType::U16];
                let (property, values, width): (Property, Vec<f32>, usize) = match ch.target().property() {
                    P::Translation => (
                        Property::Translation,
                        self.read_floats::<3>(&out, buffers, &what, &[DataType::F32], false)?.concat(),
                        3,
                    ),
                    P::Scale => (
                        Property::Scale,
                        self.read_floats::<3>(&out, buffers, &what, &[DataType::F32], false)?.concat(),
                        3,
                    ),
                    P::Rotation => {
                        (Property::Rotation, self.read_floats::<4>(&out, buffers, &what, INTS, true)?.concat(), 4)
                    }
                    P::MorphTargetWeights => {
                        let v: Vec<f32> = self.read_floats::<1>(&out, buffers, &what, INTS, true)?.concat();
                        let keys = times.len() * per_key;
                        if keys == 0 || !v.len().is_multiple_of(keys) {
                            return Err(self.invalid(format!("{what}: {} weights for {} keys", v.len(), times.len())));
                        }
                        let width = v.len() / keys;
                        (Property::Weights, v, width)
                    }
                };
                if values.len() != times.len() * per_key * width || values.iter().any(|v| !v.is_finite()) {
                    return Err(self.invalid(format!(
                        "{what}: {} output values for {} keys of {width}",
                        values.len(),
                        times.len()
                    )));
                }
                let node = ch.target().node().index();
                channels.push(Channel { node, property, interpolation, times, values, width });
            }
            clips.push(Clip { name: a.name().map(str::to_owned), channels });
        }
        Ok(clips)
    }

    /// EXT_mesh_gpu_instancing: one local transform T·R·S per instance, from the TRANSLATION,
    /// ROTATION (unit quaternion, float or normalized integers) and SCALE accessors.
    fn gpu_instances(
        &self,
        doc: &gltf::Document,
        ext: &serde_json::Value,
        buffers: &[Vec<u8>],
        node: usize,
    ) -> Result<Vec<Mat4>, SceneError> {
        let what = format!("node {node} EXT_mesh_gpu_instancing");
        let attrs = ext
            .get("attributes")
            .and_then(|a| a.as_object())
            .ok_or_else(|| self.invalid(format!("{what}: no attributes")))?;
        let accessor = |name: &str| -> Result<Option<gltf::Accessor>, SceneError> {
            match attrs.get(name) {
                None => Ok(None),
                Some(v) => {
                    let i = v.as_u64().ok_or_else(|| self.invalid(format!("{what}: {name} {v}")))?;
                    let a = usize::try_from(i).ok().and_then(|i| doc.accessors().nth(i));
                    a.map(Some).ok_or_else(|| self.invalid(format!("{what}: accessor {i} does not exist")))
                }
            }
        };
        let name = |n: &str| format!("{what} {n}");
        let t: Option<Vec<[f32; 3]>> = match accessor("TRANSLATION")? {
            Some(a) => Some(self.read_floats(&a, buffers, &name("TRANSLATION"), &[DataType::F32], false)?),
            None => None,
        };
        let r: Option<Vec<[f32; 4]>> = match accessor("ROTATION")? {
            Some(a) => Some(self.read_floats(
                &a,
                buffers,
                &name("ROTATION"),
                &[DataType::F32, DataType::I8, DataType::I16],
                true,
            )?),
            None => None,
        };
        let sc: Option<Vec<[f32; 3]>> = match accessor("SCALE")? {
            Some(a) => Some(self.read_floats(&a, buffers, &name("SCALE"), &[DataType::F32], false)?),
            None => None,
        };
        let counts: Vec<usize> = [t.as_ref().map(Vec::len), r.as_ref().map(Vec::len), sc.as_ref().map(Vec::len)]
            .into_iter()
            .flatten()
            .collect();
        let Some(&n) = counts.first() else { return Err(self.invalid(format!("{what}: no attributes"))) };
        if counts.iter().any(|&c| c != n) {
            return Err(self.invalid(format!("{what}: attribute counts differ ({counts:?})")));
        }
        let mut out = Vec::with_capacity(n);
        for i in 0..n {
            let tr = t.as_ref().map_or(Vec3::ZERO, |v| Vec3::from(v[i]));
            let q = r.as_ref().map_or(glam::Quat::IDENTITY, |v| glam::Quat::from_array(v[i]).normalize());
            let s = sc.as_ref().map_or(Vec3::ONE, |v| Vec3::from(v[i]));
            let m = Mat4::from_scale_rotation_translation(s, q, tr);
            if !m.is_finite() {
                return Err(self.invalid(format!("{what}: instance {i} has a non-finite transform")));
            }
            out.push(m);
        }
        Ok(out)
    }

    fn punctual_light(
        &self,
        light: &gltf::khr_lights_punctual::Light,
        world: Mat4,
    ) -> Result<crate::punctual::PunctualLight, SceneError> {
        use crate::punctual::{PunctualKind, PunctualLight};
        use gltf::khr_lights_punctual::Kind;
        let name = light.name().map(str::to_owned).unwrap_or_else(|| format!("light {}", light.index()));
        let intensity = Vec3::from(light.color()) * light.intensity();
        if !intensity.is_finite() || intensity.min_element() < 0.0 {
            return Err(self.invalid(format!("{name}: color × intensity must be finite and non-negative")));
        }
        let kind = match light.kind() {
            Kind::Point => PunctualKind::Point,
            Kind::Directional => PunctualKind::Directional,
            Kind::Spot { inner_cone_angle, outer_cone_angle } => {
                if !(inner_cone_angle >= 0.0
                    && inner_cone_angle < outer_cone_angle
                    && outer_cone_angle <= std::f32::consts::FRAC_PI_2)
                {
                    return Err(self.invalid(format!("{name}: spot cone angles must satisfy 0 <= inner < outer <= π/2 (got {inner_cone_angle}, {outer_cone_angle})")));
                }
                PunctualKind::Spot { cos_inner: inner_cone_angle.cos(), cos_outer: outer_cone_angle.cos() }
            }
        };
        let direction = world.transform_vector3(-Vec3::Z).normalize_or_zero();
        if direction == Vec3::ZERO && kind != PunctualKind::Point {
            return Err(self.invalid(format!("{name}: its node transform has no direction")));
        }
        Ok(PunctualLight { kind, intensity, position: world.transform_point3(Vec3::ZERO), direction })
    }

    fn expect_count(&self, got: usize, want: usize, what: &str) -> Result<(), SceneError> {
        if got != want {
            return Err(self.invalid(format!("{what} has {got} elements but POSITION has {want}")));
        }
        Ok(())
    }

    fn material(
        &self,
        doc: &gltf::Document,
        m: &gltf::Material,
        buffers: &[Vec<u8>],
        textures: &mut Vec<Texture>,
        ids: &mut HashMap<(usize, bool), u32>,
    ) -> Result<Material, SceneError> {
        let name = m.name().map(str::to_owned).unwrap_or_else(|| format!("material {}", m.index().unwrap_or(0)));
        let alpha_mode = match m.alpha_mode() {
            gltf::material::AlphaMode::Opaque => crate::material::AlphaMode::Opaque,
            gltf::material::AlphaMode::Mask => crate::material::AlphaMode::Mask(m.alpha_cutoff().unwrap_or(0.5)),
            gltf::material::AlphaMode::Blend => crate::material::AlphaMode::Blend,
        };
        let pbr = m.pbr_metallic_roughness();
        let mut tex = |info: Option<gltf::texture::Info>, srgb: bool| -> Result<Option<TextureRef>, SceneError> {
            match info {
                Some(i) => {
                    let xf = i.texture_transform().map(TexTransform::from);
                    Ok(Some(self.texture_ref(&i.texture(), i.tex_coord(), xf, srgb, buffers, textures, ids)?))
                }
                None => Ok(None),
            }
        };
        let base_color_texture = tex(pbr.base_color_texture(), true)?;
        let metallic_roughness_texture = tex(pbr.metallic_roughness_texture(), false)?;
        let emissive_texture = tex(m.emissive_texture(), true)?;
        let (specular, specular_texture, specular_color, specular_color_texture) = match m.specular() {
            Some(s) => (
                s.specular_factor(),
                tex(s.specular_texture(), false)?,
                Vec3::from(s.specular_color_factor()),
                tex(s.specular_color_texture(), true)?,
            ),
            None => (1.0, None, Vec3::ONE, None),
        };
        let (normal_texture, normal_scale) = match m.normal_texture() {
            Some(n) => {
                let xf = self.raw_transform(n.extensions())?;
                (Some(self.texture_ref(&n.texture(), n.tex_coord(), xf, false, buffers, textures, ids)?), n.scale())
            }
            None => (None, 1.0),
        };
        let emissive = Vec3::from(m.emissive_factor()) * m.emissive_strength().unwrap_or(1.0);
        let checked = |v: f32, what: &str| -> Result<f32, SceneError> {
            if v.is_finite() {
                Ok(v)
            } else {
                Err(self.invalid(format!("material '{name}': {what} is not finite")))
            }
        };
        for (v, what) in [(emissive.x, "emissive"), (emissive.y, "emissive"), (emissive.z, "emissive")] {
            if checked(v, what)? < 0.0 {
                return Err(self.invalid(format!("material '{name}': negative emission")));
            }
        }
        let raw = m.extensions();
        let ext = |name: &str| raw.and_then(|r| r.get(name));
        let mut raw_tex = |x: Option<&serde_json::Value>, key: &str, srgb: bool| {
            self.raw_texture(doc, x.and_then(|x| x.get(key)), key, srgb, buffers, textures, ids)
        };
        let number = |x: Option<&serde_json::Value>, key: &str, default: f32| -> Result<f32, SceneError> {
            match x.and_then(|x| x.get(key)) {
                None => Ok(default),
                Some(v) => v
                    .as_f64()
                    .map(|v| v as f32)
                    .filter(|v| v.is_finite())
                    .ok_or_else(|| self.invalid(format!("material '{name}': {key} {v} is not a finite number"))),
            }
        };
        let rgb = |x: Option<&serde_json::Value>, key: &str, default: Vec3| -> Result<Vec3, SceneError> {
            match x.and_then(|x| x.get(key)) {
                None => Ok(default),
                Some(v) => match v.as_array().map(|a| a.iter().filter_map(|c| c.as_f64()).collect::<Vec<_>>()) {
                    Some(a) if a.len() == 3 && a.iter().all(|c| c.is_finite() && *c >= 0.0) => {
                        Ok(Vec3::new(a[0] as f32, a[1] as f32, a[2] as f32))
                    }
                    _ => Err(self.invalid(format!("material '{name}': {key} {v} is not three non-negative numbers"))),
                },
            }
        };
        // KHR_materials_clearcoat.
        let cc = ext("KHR_materials_clearcoat");
        let clearcoat = number(cc, "clearcoatFactor", 0.0)?;
        let clearcoat_roughness = number(cc, "clearcoatRoughnessFactor", 0.0)?;
        let clearcoat_texture = raw_tex(cc, "clearcoatTexture", false)?;
        let clearcoat_roughness_texture = raw_tex(cc, "clearcoatRoughnessTexture", false)?;
        let clearcoat_normal_texture = raw_tex(cc, "clearcoatNormalTexture", false)?;
        let clearcoat_normal_scale = number(cc.and_then(|c| c.get("clearcoatNormalTexture")), "scale", 1.0)?;
        // KHR_materials_sheen.
        let sh = ext("KHR_materials_sheen");
        let sheen_color = rgb(sh, "sheenColorFactor", Vec3::ZERO)?;
        let sheen_roughness = number(sh, "sheenRoughnessFactor", 0.0)?;
        let sheen_color_texture = raw_tex(sh, "sheenColorTexture", true)?;
        let sheen_roughness_texture = raw_tex(sh, "sheenRoughnessTexture", false)?;
        // KHR_materials_volume: only the absorption matters to a path tracer (the thickness's
        // value is a hint for rasterisers that cannot trace the real path), but a thickness of 0,
        // its default, says the surface is thin-walled, with no volume behind it: no absorption
        // (the extension's specification, "Thickness").
        let vol = ext("KHR_materials_volume");
        let thickness = number(vol, "thicknessFactor", 0.0)?;
        if !(thickness >= 0.0 && thickness.is_finite()) {
            return Err(
                self.invalid(format!("material '{name}': thicknessFactor {thickness} must be finite and at least 0"))
            );
        }
        let attenuation_color = rgb(vol, "attenuationColor", Vec3::ONE)?;
        // Absent: infinite (no absorption); JSON has no infinity, so a present value is finite.
        let attenuation_distance = number(vol, "attenuationDistance", f32::INFINITY)?;
        if !(attenuation_distance > 0.0) {
            return Err(
                self.invalid(format!("material '{name}': attenuationDistance {attenuation_distance} must be positive"))
            );
        }
        let absorption = if attenuation_distance.is_finite() && thickness > 0.0 {
            let c = attenuation_color.clamp(Vec3::splat(1e-30), Vec3::ONE);
            Vec3::new(-c.x.ln(), -c.y.ln(), -c.z.ln()) / attenuation_distance
        } else {
            Vec3::ZERO
        };
        let unlit = ext("KHR_materials_unlit").is_some();
        Ok(Material {
            clearcoat,
            clearcoat_texture,
            clearcoat_roughness,
            clearcoat_roughness_texture,
            clearcoat_normal_texture,
            clearcoat_normal_scale,
            sheen_color,
            sheen_color_texture,
            sheen_roughness,
            sheen_roughness_texture,
            absorption,
            unlit,
            base_color: Vec4::from(pbr.base_color_factor()),
            base_color_texture,
            metallic: checked(pbr.metallic_factor(), "metallicFactor")?,
            roughness: checked(pbr.roughness_factor(), "roughnessFactor")?,
            metallic_roughness_texture,
            normal_texture,
            normal_scale: checked(normal_scale, "normalTexture.scale")?,
            emissive,
            emissive_texture,
            specular: checked(specular, "specularFactor")?,
            specular_texture,
            specular_color,
            specular_color_texture,
            ior: checked(m.ior().unwrap_or(1.5), "ior")?,
            transmission: checked(m.transmission().map_or(0.0, |t| t.transmission_factor()), "transmissionFactor")?,
            transmission_texture: match m.transmission().and_then(|t| t.transmission_texture()) {
                Some(info) => {
                    let xf = info.texture_transform().map(TexTransform::from);
                    Some(self.texture_ref(&info.texture(), info.tex_coord(), xf, false, buffers, textures, ids)?)
                }
                None => None,
            },
            double_sided: m.double_sided(),
            alpha_mode,
            name,
        })
    }

    /// A texture reference written as raw JSON (`{"index", "texCoord", "extensions"}`) inside an
    /// extension the gltf crate does not parse (clearcoat, sheen).
    #[allow(clippy::too_many_arguments)] // the texture info, where it is, and the tables being filled
    fn raw_texture(
        &self,
        doc: &gltf::Document,
        info: Option<&serde_json::Value>,
        what: &str,
        srgb: bool,
        buffers: &[Vec<u8>],
        textures: &mut Vec<Texture>,
        ids: &mut HashMap<(usize, bool), u32>,
    ) -> Result<Option<TextureRef>, SceneError> {
        let Some(info) = info else { return Ok(None) };
        let index = info
            .get("index")
            .and_then(|i| i.as_u64())
            .ok_or_else(|| self.invalid(format!("{what}: no texture index")))?;
        let texture = usize::try_from(index)
            .ok()
            .and_then(|i| doc.textures().nth(i))
            .ok_or_else(|| self.invalid(format!("{what}: texture {index} does not exist")))?;
        let tex_coord = match info.get("texCoord") {
            None => 0,
            Some(t) => {
                t.as_u64().ok_or_else(|| self.invalid(format!("{what}: texCoord {t}")))?.min(u32::MAX as u64) as u32
            }
        };
        let xf = self.raw_transform(info.get("extensions").and_then(|e| e.as_object()))?;
        Ok(Some(self.texture_ref(&texture, tex_coord, xf, srgb, buffers, textures, ids)?))
    }

    /// TEXCOORD_`set` if the primitive has it: float, or 8/16-bit integers (normalized, or not
    /// under KHR_mesh_quantization), its count that of POSITION.
    fn read_tex_coords(
        &self,
        prim: &gltf::Primitive,
        set: u32,
        n: usize,
        buffers: &[Vec<u8>],
    ) -> Result<Option<Vec<[f32; 2]>>, SceneError> {
        let Some(a) = prim.get(&gltf::Semantic::TexCoords(set)) else { return Ok(None) };
        let name = format!("TEXCOORD_{set}");
        const TYPES: &[DataType] = &[DataType::F32, DataType::I8, DataType::U8, DataType::I16, DataType::U16];
        let v = self.read_floats::<2>(&a, buffers, &name, TYPES, false)?;
        self.expect_count(v.len(), n, &name)?;
        if v.iter().flatten().any(|c| !c.is_finite()) {
            return Err(self.invalid(format!("{name} has a non-finite value")));
        }
        Ok(Some(v))
    }

    /// Reads a vertex attribute of `N` components as f32, after `check_accessor` has bounded it.
    /// Integer components (glTF core for colors and UVs, KHR_mesh_quantization for the rest) are
    /// converted as the spec says: normalized ones to [0, 1] or [−1, 1] (signed: max(c / MAX, −1)),
    /// others to their integer value. `normalized_only` refuses non-normalized integers (normals,
    /// tangents, colors must be normalized).
    fn read_floats<const N: usize>(
        &self,
        acc: &gltf::Accessor,
        buffers: &[Vec<u8>],
        what: &str,
        types: &[DataType],
        normalized_only: bool,
    ) -> Result<Vec<[f32; N]>, SceneError> {
        let dims = match N {
            2 => Dimensions::Vec2,
            3 => Dimensions::Vec3,
            4 => Dimensions::Vec4,
            16 => Dimensions::Mat4,
            _ => Dimensions::Scalar,
        };
        let ty = acc.data_type();
        if ty != DataType::F32 && normalized_only && !acc.normalized() {
            return Err(self.unsupported(format!("non-normalized integer {what} (accessor {})", acc.index())));
        }
        if let Some(sparse) = acc.sparse() {
            return self.read_sparse(acc, &sparse, buffers, what, types, dims);
        }
        let count = self.check_accessor(acc, what, types, dims)?;
        self.read_dense(acc, buffers, what, count)
    }

    /// A sparse accessor (Blender writes morph targets so): its base (a buffer view, or zeros),
    /// then `count` replaced elements, their indices and values bounds-checked first.
    fn read_sparse<const N: usize>(
        &self,
        acc: &gltf::Accessor,
        sparse: &gltf::accessor::sparse::Sparse,
        buffers: &[Vec<u8>],
        what: &str,
        types: &[DataType],
        dims: Dimensions,
    ) -> Result<Vec<[f32; N]>, SceneError> {
        let name = format!("{what} (sparse accessor {})", acc.index());
        if !types.contains(&acc.data_type()) || acc.dimensions() != dims {
            return Err(self.unsupported(format!("{name} stored as {:?} {:?}", acc.data_type(), acc.dimensions())));
        }
        let count = acc.count();
        if count == 0 || (count as u64).saturating_mul(N as u64 * 4) > MAX_FILE_BYTES {
            return Err(self.invalid(format!("{name}: {count} elements")));
        }
        let mut out: Vec<[f32; N]> = match acc.view() {
            Some(_) => {
                let c = self.check_dense(acc, what, types, dims)?;
                self.read_dense(acc, buffers, what, c)?
            }
            None => vec![[0.0; N]; count],
        };
        let n = sparse.count();
        if n > count {
            return Err(self.invalid(format!("{name}: {n} sparse elements for {count}")));
        }
        let slice = |view: gltf::buffer::View, offset: usize, len: usize| -> Result<&[u8], SceneError> {
            let start = view.offset().checked_add(offset);
            let end = start.and_then(|st| st.checked_add(len));
            match (start, end) {
                (Some(st), Some(e)) if offset.saturating_add(len) <= view.length() => buffers
                    .get(view.buffer().index())
                    .and_then(|b| b.get(st..e))
                    .ok_or_else(|| self.invalid(format!("{name}: sparse data outside its buffer"))),
                _ => Err(self.invalid(format!("{name}: sparse data runs past its buffer view"))),
            }
        };
        let idx = sparse.indices();
        let isize = match idx.index_type() {
            gltf::accessor::sparse::IndexType::U8 => 1,
            gltf::accessor::sparse::IndexType::U16 => 2,
            gltf::accessor::sparse::IndexType::U32 => 4,
        };
        let ibytes = slice(idx.view(), idx.offset(), n * isize)?;
        let esize = acc.size();
        let vals = sparse.values();
        let vbytes = slice(vals.view(), vals.offset(), n * esize)?;
        let (ty, norm, csize) = (acc.data_type(), acc.normalized(), acc.data_type().size());
        for k in 0..n {
            let b = &ibytes[k * isize..(k + 1) * isize];
            let i = match isize {
                1 => b[0] as usize,
                2 => u16::from_le_bytes([b[0], b[1]]) as usize,
                _ => u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize,
            };
            let slot = out.get_mut(i).ok_or_else(|| self.invalid(format!("{name}: sparse index {i} of {count}")))?;
            for (c, x) in slot.iter_mut().enumerate() {
                let o = k * esize + c * csize;
                *x = decode_component(ty, norm, &vbytes[o..o + csize]);
            }
        }
        Ok(out)
    }

    /// Reads a dense accessor already bounded by `check_accessor`.
    fn read_dense<const N: usize>(
        &self,
        acc: &gltf::Accessor,
        buffers: &[Vec<u8>],
        what: &str,
        count: usize,
    ) -> Result<Vec<[f32; N]>, SceneError> {
        let ty = acc.data_type();
        let view = acc.view().ok_or_else(|| self.invalid(format!("{what} has no bufferView")))?;
        let buf = buffers
            .get(view.buffer().index())
            .ok_or_else(|| self.invalid(format!("{what}: buffer {} missing", view.buffer().index())))?;
        let stride = view.stride().unwrap_or(acc.size());
        let start = view.offset() + acc.offset();
        let size = ty.size();
        let norm = acc.normalized();
        let decode = |b: &[u8]| decode_component(ty, norm, b);
        // `check_accessor` proved start + (count − 1)·stride + N·size ≤ the view's end, and the
        // views were checked against their buffers in `load_buffers`.
        let mut out = Vec::with_capacity(count);
        for i in 0..count {
            let at = start + i * stride;
            let mut v = [0.0f32; N];
            for (c, x) in v.iter_mut().enumerate() {
                let o = at + c * size;
                *x = decode(&buf[o..o + size]);
            }
            out.push(v);
        }
        Ok(out)
    }

    /// KHR_texture_transform from a texture info's raw extensions (normal and occlusion textures,
    /// which the gltf crate does not parse it for).
    fn raw_transform(
        &self,
        ext: Option<&serde_json::Map<String, serde_json::Value>>,
    ) -> Result<Option<TexTransform>, SceneError> {
        let Some(x) = ext.and_then(|e| e.get("KHR_texture_transform")) else { return Ok(None) };
        let pair = |k: &str, d: [f32; 2]| -> Result<[f32; 2], SceneError> {
            match x.get(k) {
                None => Ok(d),
                // Finiteness (after the cast to f32) is checked once, in `texture_ref`.
                Some(v) => match v.as_array().map(|a| a.iter().filter_map(|c| c.as_f64()).collect::<Vec<_>>()) {
                    Some(a) if a.len() == 2 => Ok([a[0] as f32, a[1] as f32]),
                    _ => Err(self.invalid(format!("KHR_texture_transform {k} {v} is not two numbers"))),
                },
            }
        };
        let rotation = match x.get("rotation") {
            None => 0.0,
            Some(v) => {
                v.as_f64().ok_or_else(|| self.invalid(format!("KHR_texture_transform rotation {v} is not a number")))?
                    as f32
            }
        };
        let tex_coord = match x.get("texCoord") {
            None => None,
            Some(tc) => Some(
                tc.as_u64()
                    .ok_or_else(|| self.invalid(format!("KHR_texture_transform texCoord {tc}")))?
                    .min(u32::MAX as u64) as u32,
            ),
        };
        Ok(Some(TexTransform {
            offset: pair("offset", [0.0, 0.0])?,
            rotation,
            scale: pair("scale", [1.0, 1.0])?,
            tex_coord,
        }))
    }

    #[allow(clippy::too_many_arguments)] // the texture, how it is addressed, and the tables being filled
    fn texture_ref(
        &self,
        t: &gltf::Texture,
        tex_coord: u32,
        xf: Option<TexTransform>,
        srgb: bool,
        buffers: &[Vec<u8>],
        textures: &mut Vec<Texture>,
        ids: &mut HashMap<(usize, bool), u32>,
    ) -> Result<TextureRef, SceneError> {
        // KHR_texture_transform (on any texture slot): offset, rotation, scale, and a texCoord that
        // overrides the slot's own.
        let (mut set, mut transform) = (tex_coord, None);
        if let Some(x) = xf {
            if !(x.offset.iter().chain(&x.scale).all(|v| v.is_finite()) && x.rotation.is_finite()) {
                return Err(self.invalid(format!(
                    "KHR_texture_transform offset {:?} rotation {} scale {:?} is not finite",
                    x.offset, x.rotation, x.scale
                )));
            }
            transform = Some(crate::texture::texture_transform(x.offset, x.rotation, x.scale));
            set = x.tex_coord.unwrap_or(set);
        }
        if set > 1 {
            return Err(self.unsupported(format!("texCoord {set} (TEXCOORD_0 and TEXCOORD_1 are supported)")));
        }
        let image = t.source();
        if let Some(asked) = self.asked.lock().ok().as_mut().and_then(|a| a.as_mut()) {
            asked.push(image.index());
            return Ok(TextureRef {
                texture: 0,
                wrap_s: Wrap::Repeat,
                wrap_t: Wrap::Repeat,
                set: set as u8,
                transform,
            });
        }
        let key = (image.index(), srgb);
        let id = match ids.get(&key) {
            Some(&id) => id,
            None => {
                let ahead = self.decoded.lock().ok().and_then(|mut d| d.remove(&image.index()));
                let tex = match ahead {
                    Some(decoded) => {
                        let (width, height, texels) = decoded?;
                        Texture { width, height, texels, srgb }
                    }
                    None => self.decode_image(&image, srgb, buffers)?,
                };
                textures.push(tex);
                let id = textures.len() as u32 - 1;
                ids.insert(key, id);
                id
            }
        };
        let wrap = |w: gltf::texture::WrappingMode| match w {
            gltf::texture::WrappingMode::ClampToEdge => Wrap::ClampToEdge,
            gltf::texture::WrappingMode::MirroredRepeat => Wrap::MirroredRepeat,
            gltf::texture::WrappingMode::Repeat => Wrap::Repeat,
        };
        let s = t.sampler();
        Ok(TextureRef { texture: id, wrap_s: wrap(s.wrap_s()), wrap_t: wrap(s.wrap_t()), set: set as u8, transform })
    }

    /// Decodes every image the materials read, in parallel, into `self.decoded` (a textured
    /// asset's load was mostly its images' decoding, one after another: the Khronos
    /// DamagedHelmet's 2048² JPEGs).
    ///
    /// Which images those are, the materials say: they are read once without decoding anything
    /// (`asked`: `texture_ref` notes each image and returns a stand-in), so an image only an
    /// occlusion texture uses (ignored on purpose) is not decoded. A material that fails here
    /// fails the same way when it is read again.
    fn decode_images(&self, doc: &gltf::Document, buffers: &[Vec<u8>]) -> Result<(), SceneError> {
        use rayon::prelude::*;
        if let Ok(mut a) = self.asked.lock() {
            *a = Some(Vec::new());
        }
        let (mut textures, mut ids) = (Vec::new(), HashMap::new());
        let read =
            doc.materials().try_for_each(|m| self.material(doc, &m, buffers, &mut textures, &mut ids).map(|_| ()));
        let mut images = self.asked.lock().ok().and_then(|mut a| a.take()).unwrap_or_default();
        read?;
        images.sort_unstable();
        images.dedup();
        let all: Vec<gltf::Image> = doc.images().collect();
        let decoded: HashMap<usize, Result<Decoded, SceneError>> =
            images.par_iter().filter_map(|&i| all.get(i).map(|image| (i, self.decode_rgba(image, buffers)))).collect();
        if let Ok(mut d) = self.decoded.lock() {
            *d = decoded;
        }
        Ok(())
    }

    fn decode_image(&self, image: &gltf::Image, srgb: bool, buffers: &[Vec<u8>]) -> Result<Texture, SceneError> {
        let (width, height, texels) = self.decode_rgba(image, buffers)?;
        Ok(Texture { width, height, texels, srgb })
    }

    fn decode_rgba(&self, image: &gltf::Image, buffers: &[Vec<u8>]) -> Result<Decoded, SceneError> {
        let what = format!("image {}", image.index());
        let bytes: Vec<u8> = match image.source() {
            gltf::image::Source::View { view, .. } => {
                let b = &buffers[view.buffer().index()];
                b[view.offset()..view.offset() + view.length()].to_vec()
            }
            gltf::image::Source::Uri { uri, .. } => self.fetch_uri(uri, &what)?,
        };
        let mut reader = image::ImageReader::new(std::io::Cursor::new(bytes))
            .with_guessed_format()
            .map_err(|e| self.invalid(format!("{what}: {e}")))?;
        let mut limits = image::Limits::default();
        limits.max_image_width = Some(MAX_TEXTURE_SIDE);
        limits.max_image_height = Some(MAX_TEXTURE_SIDE);
        limits.max_alloc = Some(2 << 30);
        reader.limits(limits);
        let img = reader.decode().map_err(|e| self.invalid(format!("{what}: cannot decode: {e}")))?;
        let rgba = img.to_rgba8();
        let (width, height) = rgba.dimensions();
        let texels = rgba.pixels().map(|p| p.0).collect();
        Ok((width, height, texels))
    }
}
