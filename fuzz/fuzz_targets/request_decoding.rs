//! Arbitrary bytes as a gRPC Describe / Localize request: protobuf decoding, the wire-to-domain conversion and
//! the validation of client keypoints (the path a phone's precomputed keypoints take) must never panic, and
//! whatever they refuse must be the client's error.
#![no_main]

use libfuzzer_sys::fuzz_target;
use prost::Message;
use scone::describe::features::{from_precomputed, KeypointLimitSettings};
use scone::server::grpc::frame_input;
use scone::server::proto::{DescribeRequest, LocalizeRequest};
use scone::service::{ErrorKind, FrameSource, ServiceError};

fn check(f: Option<scone::server::proto::Frame>) {
    match frame_input(f, "frame") {
        Ok(input) => {
            if let FrameSource::Keypoints(k) = input.source {
                if let Err(e) =
                    from_precomputed(k.width, k.height, k.keypoints, &k.descriptors, &KeypointLimitSettings::default())
                {
                    assert_eq!(ServiceError::from(e).kind(), ErrorKind::InvalidArgument);
                }
            }
        }
        Err(e) => assert_eq!(e.kind(), ErrorKind::InvalidArgument),
    }
}

fuzz_target!(|data: &[u8]| {
    if let Ok(r) = DescribeRequest::decode(data) {
        check(r.frame);
    }
    if let Ok(r) = LocalizeRequest::decode(data) {
        check(r.frame);
    }
});
