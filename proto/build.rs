//! Compiles tessera.proto with `protox` (a protobuf compiler in pure Rust), so no system `protoc` is
//! needed, then generates the tonic client and server.
fn main() -> Result<(), Box<dyn std::error::Error>> {
    println!("cargo:rerun-if-changed=tessera.proto");
    let fds = protox::compile(["tessera.proto"], ["."])?;
    tonic_prost_build::configure().compile_fds(fds)?;
    Ok(())
}
