//! A scene as one blob: the main `.gltf`/`.glb` file plus the files it refers to (buffers, textures),
//! so the farm can store, hash, deduplicate and ship a scene as a unit. The encoding is a small
//! length-prefixed format whose decoder bounds every size before it allocates.

use std::path::{Path, PathBuf};

const MAGIC: &[u8; 4] = b"TSB1";
/// Most files a bundle may hold.
pub const MAX_FILES: usize = 4096;

#[derive(Clone, Debug, PartialEq, Eq)]
pub struct SceneBundle {
    /// Name of the scene file inside `files`.
    pub main: String,
    /// (relative name, contents).
    pub files: Vec<(String, Vec<u8>)>,
}

/// A file name allowed in a bundle: relative, `/`-separated, no `..`, no empty or hidden components.
pub fn valid_name(name: &str) -> bool {
    !name.is_empty()
        && name.len() <= 512
        && !name.starts_with('/')
        && !name.contains('\\')
        && !name.contains('\0')
        && name.split('/').all(|c| !c.is_empty() && c != "." && c != ".." && !c.starts_with('.'))
}

impl SceneBundle {
    /// Checks names, uniqueness, and that `main` is present and is a glTF file.
    pub fn validate(&self) -> Result<(), String> {
        if self.files.len() > MAX_FILES {
            return Err(format!("{} files, over the limit of {MAX_FILES}", self.files.len()));
        }
        let mut seen = std::collections::HashSet::new();
        for (name, _) in &self.files {
            if !valid_name(name) {
                return Err(format!("file name '{name}' is not allowed (relative names without '..' only)"));
            }
            if !seen.insert(name.as_str()) {
                return Err(format!("file '{name}' appears twice"));
            }
        }
        if !seen.contains(self.main.as_str()) {
            return Err(format!("scene file '{}' is not in the bundle", self.main));
        }
        let lower = self.main.to_ascii_lowercase();
        if !lower.ends_with(".gltf") && !lower.ends_with(".glb") {
            return Err(format!("scene file '{}' is not a .gltf or .glb", self.main));
        }
        Ok(())
    }

    pub fn encode(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(self.files.iter().map(|(n, d)| n.len() + d.len() + 12).sum::<usize>() + 16);
        out.extend_from_slice(MAGIC);
        out.extend_from_slice(&(self.files.len() as u32).to_le_bytes());
        let main = self.files.iter().position(|(n, _)| *n == self.main).unwrap_or(0) as u32;
        out.extend_from_slice(&main.to_le_bytes());
        for (name, data) in &self.files {
            out.extend_from_slice(&(name.len() as u32).to_le_bytes());
            out.extend_from_slice(name.as_bytes());
            out.extend_from_slice(&(data.len() as u64).to_le_bytes());
            out.extend_from_slice(data);
        }
        out
    }

    pub fn decode(bytes: &[u8]) -> Result<Self, String> {
        let mut r = Reader { b: bytes, at: 0 };
        if r.take(4)? != MAGIC {
            return Err("not a scene bundle (bad magic)".into());
        }
        let count = r.u32()? as usize;
        if count == 0 || count > MAX_FILES {
            return Err(format!("bundle declares {count} files"));
        }
        let main = r.u32()? as usize;
        let mut files = Vec::with_capacity(count);
        for _ in 0..count {
            let nlen = r.u32()? as usize;
            let name =
                std::str::from_utf8(r.take(nlen)?).map_err(|_| "file name is not UTF-8".to_string())?.to_string();
            let dlen = r.u64()?;
            let data = r.take(usize::try_from(dlen).map_err(|_| "file too large".to_string())?)?.to_vec();
            files.push((name, data));
        }
        if r.at != bytes.len() {
            return Err(format!("{} trailing bytes after the last file", bytes.len() - r.at));
        }
        let main = files.get(main).map(|(n, _)| n.clone()).ok_or("main file index out of range")?;
        let b = SceneBundle { main, files };
        b.validate()?;
        Ok(b)
    }

    /// Writes the files under `dir` and returns the path of the scene file.
    pub fn unpack(&self, dir: &Path) -> std::io::Result<PathBuf> {
        self.validate().map_err(std::io::Error::other)?;
        for (name, data) in &self.files {
            let path = dir.join(name);
            if let Some(parent) = path.parent() {
                std::fs::create_dir_all(parent)?;
            }
            std::fs::write(&path, data)?;
        }
        Ok(dir.join(&self.main))
    }

    /// Total bytes of file contents.
    pub fn size(&self) -> usize {
        self.files.iter().map(|(_, d)| d.len()).sum()
    }
}

struct Reader<'a> {
    b: &'a [u8],
    at: usize,
}

impl Reader<'_> {
    fn take(&mut self, n: usize) -> Result<&[u8], String> {
        let end = self
            .at
            .checked_add(n)
            .filter(|&e| e <= self.b.len())
            .ok_or_else(|| format!("truncated bundle: {n} bytes wanted at offset {}", self.at))?;
        let s = &self.b[self.at..end];
        self.at = end;
        Ok(s)
    }
    fn u32(&mut self) -> Result<u32, String> {
        let mut a = [0u8; 4];
        a.copy_from_slice(self.take(4)?);
        Ok(u32::from_le_bytes(a))
    }
    fn u64(&mut self) -> Result<u64, String> {
        let mut a = [0u8; 8];
        a.copy_from_slice(self.take(8)?);
        Ok(u64::from_le_bytes(a))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_rejections() {
        let b = SceneBundle {
            main: "a.gltf".into(),
            files: vec![("a.gltf".into(), b"{}".to_vec()), ("tex/b.png".into(), vec![1, 2, 3])],
        };
        let e = b.encode();
        assert_eq!(SceneBundle::decode(&e).unwrap(), b);
        for cut in [0, 3, 8, 13, e.len() - 1] {
            assert!(SceneBundle::decode(&e[..cut]).is_err(), "cut at {cut}");
        }
        let mut huge = e.clone();
        huge[12..16].copy_from_slice(&u32::MAX.to_le_bytes());
        assert!(SceneBundle::decode(&huge).is_err());
        for bad in ["../x", "/etc/passwd", "a/../../b", ".hidden", "a\\b", ""] {
            assert!(!valid_name(bad), "{bad}");
        }
        let escaping =
            SceneBundle { main: "a.gltf".into(), files: vec![("a.gltf".into(), vec![]), ("../x".into(), vec![])] };
        assert!(escaping.validate().is_err());
    }
}
