//! Generated gRPC code for `proto/scone/v1/scone.proto`.
#![allow(clippy::all, missing_docs)]
// The .proto comments contain `<hex>`, which rustdoc would read as an unclosed HTML tag.
#![allow(rustdoc::invalid_html_tags)]
tonic::include_proto!("scone.v1");
/// Encoded descriptors of the API, for server reflection.
pub const FILE_DESCRIPTOR_SET: &[u8] = tonic::include_file_descriptor_set!("scone_descriptor");
