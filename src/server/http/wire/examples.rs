//! The documented example requests (the OpenAPI test sends each of them and checks the answer against the
//! documented schema): small keypoint sets, so the examples carry no image.

use base64::Engine;
use serde_json::{json, Value};

/// Twelve keypoints of a 640x480 frame on a 4x3 grid, shifted by `dx` pixels, with made-up descriptors and ring
/// contexts (113 bytes each; the embedded model reads them, a constellation model ignores them).
pub fn keypoint_set(dx: f32) -> Value {
    let keypoints: Vec<Value> = (0..12)
        .map(|i| {
            let (col, row) = ((i % 4) as f32, (i / 4) as f32);
            json!({"x": 120.0 + 110.0 * col + dx, "y": 110.0 + 120.0 * row, "size": 7.0,
                   "angle": (i * 29 % 360) as f32, "response": 20.0, "octave": 0})
        })
        .collect();
    let descriptors: Vec<u8> = (0..12 * 64).map(|i: u32| (i.wrapping_mul(2_654_435_761) >> 24) as u8).collect();
    let context: Vec<u8> = (0..12 * 113).map(|i: u32| (i.wrapping_mul(2_246_822_519) >> 24) as u8).collect();
    let b64 = |bytes: Vec<u8>| base64::engine::general_purpose::STANDARD.encode(bytes);
    json!({"width": 640, "height": 480, "keypoints": keypoints,
           "descriptors_base64": b64(descriptors), "context_base64": b64(context)})
}

fn intrinsics() -> Value {
    json!({"fx": 525.0, "fy": 525.0, "cx": 319.5, "cy": 239.5})
}

pub fn describe() -> Value {
    json!({"frame": {"keypoints": keypoint_set(0.0)}})
}

pub fn match_pair() -> Value {
    json!({
        "frame1": {"keypoints": keypoint_set(0.0), "intrinsics": intrinsics()},
        "frame2": {"keypoints": keypoint_set(6.0), "intrinsics": intrinsics()},
        "ratio": 0.8,
        "matcher": "rerank"
    })
}

pub fn localize() -> Value {
    json!({"frame": {"keypoints": keypoint_set(0.0)}, "intrinsics": intrinsics()})
}

pub fn keyframe() -> Value {
    json!({
        "keyframe_id": 1,
        "pose": {"tx": 0.0, "ty": 0.0, "tz": 0.0, "qx": 0.0, "qy": 0.0, "qz": 0.0, "qw": 1.0},
        "frame": {"keypoints": keypoint_set(0.0)},
        "intrinsics": intrinsics()
    })
}

pub fn create_map() -> Value {
    json!({"map_id": "office"})
}

pub fn merge_maps() -> Value {
    json!({"source_map_id": "office-copy",
           "transform": {"tx": 0.0, "ty": 0.0, "tz": 0.0, "qx": 0.0, "qy": 0.0, "qz": 0.0, "qw": 1.0, "scale": 1.0}})
}

pub fn localize_track() -> Value {
    let frame = |dx: f32, tx: f64| {
        json!({"frame": {"keypoints": keypoint_set(dx), "intrinsics": intrinsics()},
               "pose": {"tx": tx, "ty": 0.0, "tz": 0.0, "qx": 0.0, "qy": 0.0, "qz": 0.0, "qw": 1.0}})
    };
    json!({"frames": [frame(0.0, 0.0), frame(6.0, 0.1), frame(12.0, 0.2)], "estimate_scale": false})
}
