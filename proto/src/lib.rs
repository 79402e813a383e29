//! Generated gRPC types for the worker protocol (see `tessera.proto`).

#![allow(clippy::all)]

pub mod v1 {
    tonic::include_proto!("tessera.v1");
}

/// Bumped whenever the protocol or the meaning of a work unit changes; workers with another value
/// are refused at registration.
/// 2: `WorkUnit.settings_json` is sent once per job and registration (empty afterwards).
pub const PROTOCOL_VERSION: u32 = 2;
