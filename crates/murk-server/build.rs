//! Compiles the workspace's `proto/` (the API, shared with the clients in other languages) with
//! protox (pure Rust: no system `protoc`) and generates tonic code.

use std::path::PathBuf;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let files = [
        "../../proto/murk/v1/common.proto",
        "../../proto/murk/v1/tof.proto",
        "../../proto/murk/v1/mvs.proto",
        "../../proto/murk/v1/params.proto",
        "../../proto/murk/v1/ps.proto",
        "../../proto/murk/v1/stereo.proto",
        "../../proto/murk/v1/jobs.proto",
        "../../proto/murk/v1/sessions.proto",
    ];
    for f in &files {
        println!("cargo:rerun-if-changed={f}");
    }
    let fds = protox::compile(files, ["../../proto"])?;
    let out = PathBuf::from(std::env::var("OUT_DIR")?);
    std::fs::write(
        out.join("murk_descriptor.bin"),
        prost::Message::encode_to_vec(&fds),
    )?;
    tonic_prost_build::configure()
        // Undecodable requests are the caller's fault: INVALID_ARGUMENT, not prost's INTERNAL.
        .codec_path("crate::service::codec::ProtoCodec")
        .build_server(true)
        .build_client(true)
        .compile_fds(fds)?;
    Ok(())
}
