//! Generated protobuf/tonic code for `proto/murk/v1`.

#![allow(missing_docs, clippy::all, clippy::pedantic)]

/// `murk.v1`: messages, the `Jobs` and `Reconstruction` services, clients and servers.
pub mod v1 {
    tonic::include_proto!("murk.v1");
}

/// Encoded `FileDescriptorSet` of murk's protos, served by gRPC reflection.
pub const FILE_DESCRIPTOR_SET: &[u8] = tonic::include_file_descriptor_set!("murk_descriptor");
