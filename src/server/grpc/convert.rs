//! The wire and the service's domain, both ways: frames, keypoints, intrinsics and lenses, poses and their
//! convention, map summaries; and the one mapping from service errors to gRPC statuses.

use tonic::{Code, Status};

use crate::camera::Camera;
use crate::describe::features::Keypoint;
use crate::server::proto::{self, frame::Source};
use crate::service::{
    Distortion, DistortionModel, ErrorKind, ExternalObservation, FrameInput, FrameSource, KeypointsInput, MapSummary,
    PoseConvention, ServiceError, Similarity,
};

/// The one mapping from service errors to gRPC statuses.
pub fn to_status(e: &ServiceError) -> Status {
    let code = match e.kind() {
        ErrorKind::InvalidArgument => Code::InvalidArgument,
        ErrorKind::NotFound => Code::NotFound,
        ErrorKind::AlreadyExists => Code::AlreadyExists,
        ErrorKind::FailedPrecondition => Code::FailedPrecondition,
        ErrorKind::Unavailable => Code::Unavailable,
        ErrorKind::ResourceExhausted | ErrorKind::InsufficientStorage => Code::ResourceExhausted,
        ErrorKind::PayloadTooLarge => Code::OutOfRange,
        ErrorKind::DeadlineExceeded => Code::DeadlineExceeded,
        ErrorKind::Unauthenticated => Code::Unauthenticated,
        ErrorKind::PermissionDenied => Code::PermissionDenied,
        ErrorKind::Internal => Code::Internal,
    };
    let mut status = Status::new(code, e.client_message());
    if let Some(s) = e.retry_after_s() {
        if let Ok(v) = s.to_string().parse() {
            status.metadata_mut().insert("retry-after", v);
        }
    }
    status
}

/// A request's `pose_convention` (proto enum value), refused when unknown.
pub(super) fn convention(value: i32) -> Result<PoseConvention, ServiceError> {
    match proto::PoseConvention::try_from(value) {
        Ok(proto::PoseConvention::OpencvCameraToWorld) => Ok(PoseConvention::OpencvCameraToWorld),
        Ok(proto::PoseConvention::OpencvWorldToCamera) => Ok(PoseConvention::OpencvWorldToCamera),
        Ok(proto::PoseConvention::OpenglCameraToWorld) => Ok(PoseConvention::OpenglCameraToWorld),
        Err(_) => Err(ServiceError::invalid("pose_convention", format!("{value} is not a PoseConvention"))),
    }
}

pub(super) fn invalid(field: &str, reason: &str) -> ServiceError {
    ServiceError::invalid(field, reason)
}

pub(crate) fn camera(i: &proto::Intrinsics) -> Camera {
    Camera { fx: i.fx, fy: i.fy, cx: i.cx, cy: i.cy, width: i.width, height: i.height }
}

/// The lens model of wire intrinsics, checked.
fn distortion(i: &proto::Intrinsics, field: &str) -> Result<Distortion, ServiceError> {
    let model = match proto::DistortionModel::try_from(i.distortion_model) {
        Ok(proto::DistortionModel::None) => DistortionModel::None,
        Ok(proto::DistortionModel::RadialTangential) => DistortionModel::RadialTangential,
        Ok(proto::DistortionModel::Fisheye) => DistortionModel::Fisheye,
        Err(_) => {
            return Err(invalid(
                &format!("{field}.intrinsics.distortion_model"),
                &format!("{} is not a DistortionModel", i.distortion_model),
            ))
        }
    };
    Distortion::new(model, &i.distortion)
        .map_err(|e| invalid(&format!("{field}.intrinsics.distortion"), &e.to_string()))
}

fn keypoint(k: &proto::Keypoint) -> Keypoint {
    Keypoint { x: k.x, y: k.y, size: k.size, angle: k.angle, response: k.response, octave: k.octave }
}

fn keypoints_input(k: proto::KeypointSet) -> KeypointsInput {
    KeypointsInput {
        width: k.width,
        height: k.height,
        keypoints: k.keypoints.iter().map(keypoint).collect(),
        descriptors: k.descriptors,
        model_id: (!k.model_id.is_empty()).then_some(k.model_id),
        context: k.context,
    }
}

/// A wire frame as the service's input (public for the fuzz target).
pub fn frame_input(f: Option<proto::Frame>, field: &str) -> Result<FrameInput, ServiceError> {
    let f = f.ok_or_else(|| invalid(field, "is required"))?;
    let source = match f.source {
        Some(Source::Image(img)) => FrameSource::Image(img.data),
        Some(Source::Keypoints(k)) => FrameSource::Keypoints(keypoints_input(k)),
        None => return Err(invalid(field, "needs an image or keypoints")),
    };
    let distortion = match &f.intrinsics {
        Some(i) => distortion(i, field)?,
        None => Distortion::None,
    };
    Ok(FrameInput { source, camera: f.intrinsics.as_ref().map(camera), distortion })
}

/// External SfM observations as the service's input (a missing point is the client's error, named).
pub(super) fn external_landmarks(
    obs: Vec<proto::ExternalObservation>,
) -> Result<Vec<ExternalObservation>, ServiceError> {
    obs.into_iter()
        .enumerate()
        .map(|(i, o)| {
            let p = o.point.ok_or_else(|| invalid(&format!("external_landmarks[{i}].point"), "is required"))?;
            Ok(ExternalObservation { x: o.x, y: o.y, landmark_id: o.landmark_id, point: [p.x, p.y, p.z] })
        })
        .collect()
}

pub(super) fn map_info(s: MapSummary) -> proto::MapInfo {
    proto::MapInfo {
        map_id: s.id,
        model_id: s.model_id,
        keyframes: s.keyframes as u64,
        landmarks: s.landmarks as u64,
        observations: s.observations as u64,
        live_observations: s.live_observations as u64,
        version: s.version,
        approximate_index: s.approximate_index,
        loaded: s.loaded,
        load_note: s.load_note.unwrap_or_default(),
    }
}

pub(super) fn pose_out(p: &nalgebra::Isometry3<f64>) -> proto::Pose {
    let q = p.rotation.quaternion();
    let t = p.translation.vector;
    proto::Pose { tx: t.x, ty: t.y, tz: t.z, qx: q.i, qy: q.j, qz: q.k, qw: q.w }
}

pub(super) fn similarity_out(t: &Similarity) -> proto::Similarity {
    proto::Similarity {
        tx: t.translation[0],
        ty: t.translation[1],
        tz: t.translation[2],
        qx: t.rotation[0],
        qy: t.rotation[1],
        qz: t.rotation[2],
        qw: t.rotation[3],
        scale: t.scale,
    }
}

pub(super) fn keypoint_out(k: &Keypoint) -> proto::Keypoint {
    proto::Keypoint { x: k.x, y: k.y, size: k.size, angle: k.angle, response: k.response, octave: k.octave }
}
