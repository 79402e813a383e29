//! Errors of the renderer library. Every message names the file (or setting) and what is wrong with
//! it, because these are shown to users and returned by the farm's API as they are.

use std::path::PathBuf;

#[derive(Debug, thiserror::Error)]
pub enum SceneError {
    #[error("{path}: cannot read: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("{path}: not a valid glTF 2.0 file: {message}")]
    Parse { path: PathBuf, message: String },
    #[error("{path}: unsupported glTF feature: {feature}")]
    Unsupported { path: PathBuf, feature: String },
    #[error("{path}: invalid scene data: {message}")]
    Invalid { path: PathBuf, message: String },
    #[error("{path}: URI '{uri}' is not allowed: {reason}")]
    ForbiddenUri { path: PathBuf, uri: String, reason: String },
    #[error("{path}: {what} is {size} bytes, over the limit of {limit} bytes")]
    TooLarge { path: PathBuf, what: String, size: u64, limit: u64 },
    #[error("{path}: scene has no camera numbered {index} (it has {count})")]
    NoSuchCamera { path: PathBuf, index: usize, count: usize },
}

#[derive(Debug, thiserror::Error)]
pub enum RenderError {
    #[error("invalid render settings: {0}")]
    Settings(String),
    #[error("{path}: cannot write image: {message}")]
    Write { path: PathBuf, message: String },
    #[error("{path}: cannot read image: {message}")]
    Read { path: PathBuf, message: String },
}
