//! gRPC transport (tonic): `scone.v1.Maps`, `scone.v1.Matching`, `grpc.health.v1` and server reflection.
//!
//! Every `scone.v1` method runs on the CPU pool. Before a call's message is read or decoded ([`GateLayer`]) it
//! is answered RESOURCE_EXHAUSTED when the pool has no free slot, so a storm of clients that do not back off
//! costs a request head each (HTTP/2 resets the stream, which stops the client sending the rest of the
//! message), and UNAUTHENTICATED or PERMISSION_DENIED when its key does not allow it, so a client without a
//! key cannot make the server read a large message.

use std::future::Future;
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::{Duration, Instant};

use tokio_stream::wrappers::ReceiverStream;
use tokio_stream::Stream;
use tonic::{Code, Request, Response, Status, Streaming};

use super::connections::{CountRequestsLayer, Listener};
use super::metrics::CountedBody;
use crate::camera::{quaternion_xyzw, Camera, Pose};
use crate::features::Keypoint;
use crate::matching::{SconeMatcher, DEFAULT_RATIO};
use crate::server::app::{App, MapId, NoMap, Subject};
use crate::server::auth::{self, Authorized};
use crate::server::operation::Operation;
use crate::server::proto::{self, frame::Source};
use crate::service::{
    Distortion, DistortionModel, ErrorKind, ExternalObservation, FrameInput, FrameSource, KeyframeRequest,
    KeypointsInput, MapSummary, PairOptions, PoseConvention, Prior, ServiceError, Similarity,
};

/// Export chunks, bytes.
const CHUNK: usize = 1 << 20;

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
fn convention(value: i32) -> Result<PoseConvention, ServiceError> {
    match proto::PoseConvention::try_from(value) {
        Ok(proto::PoseConvention::OpencvCameraToWorld) => Ok(PoseConvention::OpencvCameraToWorld),
        Ok(proto::PoseConvention::OpencvWorldToCamera) => Ok(PoseConvention::OpencvWorldToCamera),
        Ok(proto::PoseConvention::OpenglCameraToWorld) => Ok(PoseConvention::OpenglCameraToWorld),
        Err(_) => Err(ServiceError::invalid("pose_convention", format!("{value} is not a PoseConvention"))),
    }
}

fn invalid(field: &str, reason: &str) -> ServiceError {
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
fn external_landmarks(obs: Vec<proto::ExternalObservation>) -> Result<Vec<ExternalObservation>, ServiceError> {
    obs.into_iter()
        .enumerate()
        .map(|(i, o)| {
            let p = o.point.ok_or_else(|| invalid(&format!("external_landmarks[{i}].point"), "is required"))?;
            Ok(ExternalObservation { x: o.x, y: o.y, landmark_id: o.landmark_id, point: [p.x, p.y, p.z] })
        })
        .collect()
}

fn map_info(s: MapSummary) -> proto::MapInfo {
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

fn pose_out(p: &nalgebra::Isometry3<f64>) -> proto::Pose {
    let q = p.rotation.quaternion();
    let t = p.translation.vector;
    proto::Pose { tx: t.x, ty: t.y, tz: t.z, qx: q.i, qy: q.j, qz: q.k, qw: q.w }
}

fn keypoint_out(k: &Keypoint) -> proto::Keypoint {
    proto::Keypoint { x: k.x, y: k.y, size: k.size, angle: k.angle, response: k.response, octave: k.octave }
}

/// Both gRPC services over one [`App`].
#[derive(Clone)]
pub struct GrpcApi {
    app: Arc<App>,
}

impl GrpcApi {
    /// The one way a method reaches the service: with the key its [`GateLayer`] checked (before the message
    /// was read), finds what the request works on (its map, once) and runs `f` on the CPU pool
    /// ([`App::call`]); the outcome is counted, logged and mapped to a status.
    async fn call<S, R, F>(&self, authorized: Authorized, subject: S, f: F) -> Result<R, Status>
    where
        S: Subject,
        R: Send + 'static,
        F: FnOnce(&App, S::Held) -> Result<R, ServiceError> + Send + 'static,
    {
        let t = Instant::now();
        let r = self.app.call(authorized, subject, f).await;
        let route = authorized.operation().name();
        let code = match &r {
            Ok(_) => Code::Ok,
            Err(e) => to_status(e).code(),
        };
        self.app.metrics.request("grpc", route, &format!("{code:?}"), t.elapsed().as_secs_f64());
        r.map_err(|e| {
            self.app.log_error(route, &e);
            to_status(&e)
        })
    }
}

/// The proof that [`GateLayer`] checked the call's key (a request extension).
fn authorized<T>(req: &Request<T>) -> Result<Authorized, Status> {
    req.extensions().get::<Authorized>().copied().ok_or_else(|| {
        to_status(&ServiceError::Internal("a scone.v1 call reached its method without a key check".into()))
    })
}

impl GrpcApi {
    /// The next message of a client stream, or DEADLINE_EXCEEDED when none came within
    /// `server.idle_timeout_ms` (a stream left open without messages would hold its connection).
    async fn next_message<T>(&self, inbound: &mut Streaming<T>) -> Result<Option<T>, Status> {
        let ms = self.app.settings.server.idle_timeout_ms;
        match tokio::time::timeout(Duration::from_millis(ms), inbound.message()).await {
            Ok(r) => r,
            Err(_) => Err(to_status(&ServiceError::DeadlineExceeded { ms })),
        }
    }
}

type BoxStream<T> = Pin<Box<dyn Stream<Item = Result<T, Status>> + Send + 'static>>;

#[tonic::async_trait]
impl proto::maps_server::Maps for GrpcApi {
    async fn create_map(&self, req: Request<proto::CreateMapRequest>) -> Result<Response<proto::MapInfo>, Status> {
        let authorized = authorized(&req)?;
        let id = req.into_inner().map_id;
        let s = self.call(authorized, NoMap, move |a, ()| a.service.create_map(&id)).await?;
        Ok(Response::new(map_info(s)))
    }

    async fn get_map(&self, req: Request<proto::GetMapRequest>) -> Result<Response<proto::MapInfo>, Status> {
        let authorized = authorized(&req)?;
        let id = req.into_inner().map_id;
        let s = self.call(authorized, MapId(id), |_, map| Ok(map.summary())).await?;
        Ok(Response::new(map_info(s)))
    }

    async fn list_maps(
        &self,
        req: Request<proto::ListMapsRequest>,
    ) -> Result<Response<proto::ListMapsResponse>, Status> {
        let listing = self.call(authorized(&req)?, NoMap, |a, ()| a.service.list_maps()).await?;
        Ok(Response::new(proto::ListMapsResponse {
            maps: listing.maps.into_iter().map(map_info).collect(),
            held_back: listing
                .held_back
                .into_iter()
                .map(|(map_id, reason)| proto::HeldBackMap { map_id, reason })
                .collect(),
        }))
    }

    async fn delete_map(
        &self,
        req: Request<proto::DeleteMapRequest>,
    ) -> Result<Response<proto::DeleteMapResponse>, Status> {
        let authorized = authorized(&req)?;
        let id = req.into_inner().map_id;
        self.call(authorized, NoMap, move |a, ()| a.service.delete_map(&id)).await?;
        Ok(Response::new(proto::DeleteMapResponse {}))
    }

    type AddKeyframesStream = ReceiverStream<Result<proto::KeyframeAck, Status>>;

    async fn add_keyframes(
        &self,
        req: Request<Streaming<proto::AddKeyframeRequest>>,
    ) -> Result<Response<Self::AddKeyframesStream>, Status> {
        let authorized = authorized(&req)?;
        let mut inbound = req.into_inner();
        let (tx, rx) = tokio::sync::mpsc::channel(4);
        let api = self.clone();
        tokio::spawn(async move {
            loop {
                let msg = match api.next_message(&mut inbound).await {
                    Ok(Some(m)) => m,
                    Ok(None) => break,
                    Err(s) => {
                        let _ = tx.send(Err(s)).await;
                        break;
                    }
                };
                let map = MapId(msg.map_id.clone());
                let r = api
                    .call(authorized, map, move |a, map| {
                        let p = msg.pose.ok_or_else(|| invalid("pose", "is required"))?;
                        let request = KeyframeRequest {
                            id: msg.keyframe_id,
                            frame: frame_input(msg.frame, "frame")?,
                            pose: Pose { translation: [p.tx, p.ty, p.tz], rotation: [p.qx, p.qy, p.qz, p.qw] },
                            convention: convention(msg.pose_convention)?,
                            depth_png: (!msg.depth_png.is_empty()).then_some(msg.depth_png),
                            depth_scale: (msg.depth_scale != 0.0).then_some(msg.depth_scale),
                            external_landmarks: external_landmarks(msg.external_landmarks)?,
                        };
                        let (added, times) = a.service.add_keyframe(&map, request)?;
                        a.metrics.stages(&times);
                        Ok(proto::KeyframeAck {
                            keyframe_id: added.keyframe,
                            new_landmarks: added.new_landmarks as u64,
                            observations: added.observations as u64,
                            map_version: added.version,
                            external_rejected: added.external.rejected as u64,
                            external_unassociated: added.external.unassociated as u64,
                        })
                    })
                    .await;
                let failed = r.is_err();
                if tx.send(r).await.is_err() || failed {
                    break;
                }
            }
        });
        Ok(Response::new(ReceiverStream::new(rx)))
    }

    async fn remove_keyframe(
        &self,
        req: Request<proto::RemoveKeyframeRequest>,
    ) -> Result<Response<proto::MapInfo>, Status> {
        let authorized = authorized(&req)?;
        let r = req.into_inner();
        let keyframe = r.keyframe_id;
        let s = self.call(authorized, MapId(r.map_id), move |a, map| a.service.remove_keyframe(&map, keyframe)).await?;
        Ok(Response::new(map_info(s)))
    }

    async fn merge_maps(
        &self,
        req: Request<proto::MergeMapsRequest>,
    ) -> Result<Response<proto::MergeMapsResponse>, Status> {
        let authorized = authorized(&req)?;
        let r = req.into_inner();
        let target = MapId(r.target_map_id.clone());
        let o = self
            .call(authorized, target, move |a, map| {
                let transform = r.transform.map(|t| Similarity {
                    translation: [t.tx, t.ty, t.tz],
                    rotation: [t.qx, t.qy, t.qz, t.qw],
                    scale: t.scale,
                });
                a.service.merge_maps(&map, &r.source_map_id, transform)
            })
            .await?;
        let t = o.transform;
        Ok(Response::new(proto::MergeMapsResponse {
            target: Some(map_info(o.target)),
            transform: Some(proto::Similarity {
                tx: t.translation[0],
                ty: t.translation[1],
                tz: t.translation[2],
                qx: t.rotation[0],
                qy: t.rotation[1],
                qz: t.rotation[2],
                qw: t.rotation[3],
                scale: t.scale,
            }),
            transform_estimated: o.estimated,
            source_keyframes: o.source_keyframes as u32,
            keyframes_localised: o.localised as u32,
            transform_inliers: o.inliers as u32,
            keyframe_id_offset: o.keyframe_id_offset,
            landmarks_fused: o.landmarks_fused as u64,
            landmarks_added: o.landmarks_added as u64,
        }))
    }

    type ExportMapStream = BoxStream<proto::MapChunk>;

    async fn export_map(
        &self,
        req: Request<proto::ExportMapRequest>,
    ) -> Result<Response<Self::ExportMapStream>, Status> {
        let authorized = authorized(&req)?;
        let id = req.into_inner().map_id;
        let bytes = self.call(authorized, MapId(id), |a, map| a.service.export_map(&map)).await?;
        let chunks: Vec<Result<proto::MapChunk, Status>> =
            bytes.chunks(CHUNK).map(|c| Ok(proto::MapChunk { map_id: String::new(), data: c.to_vec() })).collect();
        Ok(Response::new(Box::pin(tokio_stream::iter(chunks))))
    }

    async fn import_map(&self, req: Request<Streaming<proto::MapChunk>>) -> Result<Response<proto::MapInfo>, Status> {
        let authorized = authorized(&req)?;
        let max = self.app.settings.server.max_map_bytes;
        let mut inbound = req.into_inner();
        let mut id = String::new();
        let mut bytes = Vec::new();
        while let Some(chunk) = self.next_message(&mut inbound).await? {
            if id.is_empty() {
                id = chunk.map_id;
            }
            if bytes.len() + chunk.data.len() > max {
                return Err(to_status(&ServiceError::TooLarge { what: "the map file".into(), limit: max }));
            }
            bytes.extend_from_slice(&chunk.data);
        }
        let s = self
            .call(authorized, NoMap, move |a, ()| {
                if id.is_empty() {
                    return Err(invalid("map_id", "the first chunk must name the map"));
                }
                a.service.import_map(&id, &bytes)
            })
            .await?;
        Ok(Response::new(map_info(s)))
    }
}

#[tonic::async_trait]
impl proto::matching_server::Matching for GrpcApi {
    async fn describe(
        &self,
        req: Request<proto::DescribeRequest>,
    ) -> Result<Response<proto::DescribeResponse>, Status> {
        let authorized = authorized(&req)?;
        let r = req.into_inner();
        let out = self
            .call(authorized, NoMap, move |a, ()| {
                let f = frame_input(r.frame, "frame")?;
                let d = a.service.describe(f.source)?;
                a.metrics.stages(&d.times);
                Ok(proto::DescribeResponse {
                    keypoints: d.features.keypoints.iter().map(keypoint_out).collect(),
                    descriptors: d.features.descriptors.concat(),
                    embeddings: d.embeddings,
                    dim: d.dim as u32,
                    model_id: d.model_id,
                    context: d.features.context.concat(),
                })
            })
            .await?;
        Ok(Response::new(out))
    }

    async fn match_pair(
        &self,
        req: Request<proto::MatchPairRequest>,
    ) -> Result<Response<proto::MatchPairResponse>, Status> {
        let authorized = authorized(&req)?;
        let r = req.into_inner();
        let out = self
            .call(authorized, NoMap, move |a, ()| {
                let matcher = match proto::PairMatcher::try_from(r.matcher) {
                    Ok(proto::PairMatcher::Default) => SconeMatcher::default(),
                    Ok(proto::PairMatcher::Plain) => SconeMatcher::Plain,
                    Ok(proto::PairMatcher::Union) => SconeMatcher::Union,
                    Ok(proto::PairMatcher::Rerank) => SconeMatcher::Rerank,
                    Ok(proto::PairMatcher::Freak) => SconeMatcher::Freak,
                    Ok(proto::PairMatcher::ScaleAware) => SconeMatcher::ScaleAware,
                    Err(_) => return Err(invalid("matcher", &format!("{} is not a PairMatcher", r.matcher))),
                };
                let conv = convention(r.pose_convention)?;
                let options = PairOptions {
                    ratio: if r.ratio == 0.0 { DEFAULT_RATIO } else { r.ratio },
                    mutual: r.mutual,
                    matcher,
                };
                let o = a.service.match_pair(
                    frame_input(r.frame1, "frame1")?,
                    frame_input(r.frame2, "frame2")?,
                    options,
                )?;
                a.metrics.stages(&o.times);
                Ok(proto::MatchPairResponse {
                    matches: o
                        .matches
                        .iter()
                        .zip(o.inlier_flags())
                        .map(|(m, inlier)| proto::Match {
                            index1: m.query as u32,
                            index2: m.train as u32,
                            distance: m.distance,
                            inlier,
                        })
                        .collect(),
                    inliers: o.inlier_count() as u32,
                    pose: o.pose.as_ref().map(|p| {
                        let (r, t) = conv.relative_from_opencv(&p.rotation, &p.translation);
                        let [qx, qy, qz, qw] = quaternion_xyzw(&r);
                        proto::RelativePose { qx, qy, qz, qw, tx: t.x, ty: t.y, tz: t.z }
                    }),
                })
            })
            .await?;
        Ok(Response::new(out))
    }

    async fn localize(
        &self,
        req: Request<proto::LocalizeRequest>,
    ) -> Result<Response<proto::LocalizeResponse>, Status> {
        let authorized = authorized(&req)?;
        let r = req.into_inner();
        let out = self
            .call(authorized, MapId(r.map_id.clone()), move |a, map| {
                let conv = convention(r.pose_convention)?;
                let prior = r.prior.map(|p| Prior { position: [p.x, p.y, p.z], radius: p.radius });
                let o = a.service.localize(&map, frame_input(r.frame, "frame")?, prior)?;
                a.metrics.stages(&o.times);
                Ok(proto::LocalizeResponse {
                    localized: o.pose.is_some(),
                    pose: o.pose.as_ref().map(|p| pose_out(&conv.from_opencv_camera_to_world(&p.camera_to_world))),
                    matches: o.matches.len() as u32,
                    inliers: o.pose.as_ref().map_or(0, |p| p.inliers.len() as u32),
                    reprojection_error: o.pose.as_ref().map_or(0.0, |p| p.reprojection_error),
                    confidence: o.confidence,
                    focal_length: o.pose.as_ref().map_or(0.0, |p| p.focal),
                    focal_estimated: o.focal_estimated,
                    covariance: o.covariance(conv),
                })
            })
            .await?;
        Ok(Response::new(out))
    }
}

/// The gate of the `scone.v1` services, before a call's message is read or decoded: a call is refused with
/// RESOURCE_EXHAUSTED (and `retry-after`, after [`App::hold_refusal`]) when the CPU pool has no free slot, then
/// with UNAUTHENTICATED or PERMISSION_DENIED when its key does not allow its operation ([`Operation`]); a call
/// that passes carries the proof ([`Authorized`]) to its method. Counts the bytes of the messages it lets
/// through.
#[derive(Clone)]
pub struct GateLayer {
    app: Arc<App>,
    body_bytes: prometheus_client::metrics::counter::Counter,
}

impl GateLayer {
    pub fn new(app: Arc<App>) -> Self {
        let body_bytes = app.metrics.body_bytes("grpc");
        Self { app, body_bytes }
    }
}

impl<S> tower::Layer<S> for GateLayer {
    type Service = Gate<S>;

    fn layer(&self, inner: S) -> Gate<S> {
        Gate { inner, layer: self.clone() }
    }
}

/// See [`GateLayer`].
#[derive(Clone)]
pub struct Gate<S> {
    inner: S,
    layer: GateLayer,
}

const POOL_SERVICES: &str = "/scone.v1.";

impl<S> tower::Service<axum::http::Request<tonic::body::Body>> for Gate<S>
where
    S: tower::Service<axum::http::Request<tonic::body::Body>, Response = axum::http::Response<tonic::body::Body>>,
    S::Future: Send + 'static,
    S::Error: Send + 'static,
{
    type Response = axum::http::Response<tonic::body::Body>;
    type Error = S::Error;
    type Future = Pin<Box<dyn Future<Output = Result<Self::Response, S::Error>> + Send + 'static>>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), S::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, mut req: axum::http::Request<tonic::body::Body>) -> Self::Future {
        let path = req.uri().path();
        if path.starts_with(POOL_SERVICES) {
            let (app, t) = (Arc::clone(&self.layer.app), Instant::now());
            let method = path.rsplit('/').next().unwrap_or(path).to_string();
            let refusal = match app.check_room() {
                Err(e) => Some((e, true)),
                // An unknown method passes: tonic answers UNIMPLEMENTED.
                Ok(()) => Operation::from_grpc_path(path).and_then(|operation| {
                    match app.authorize(auth::request_key(req.headers()).as_deref(), operation) {
                        Ok(authorized) => {
                            req.extensions_mut().insert(authorized);
                            None
                        }
                        Err(e) => Some((e, false)),
                    }
                }),
            };
            if let Some((e, overloaded)) = refusal {
                app.log_error(&method, &e);
                // The request, and with it the unread message, is dropped here.
                drop(req);
                return Box::pin(async move {
                    if overloaded {
                        app.hold_refusal().await;
                    }
                    let status = to_status(&e);
                    let code = format!("{:?}", status.code());
                    app.metrics.request("grpc", &method, &code, t.elapsed().as_secs_f64());
                    Ok(status.into_http())
                });
            }
        }
        let bytes = self.layer.body_bytes.clone();
        let req = req.map(|b| tonic::body::Body::new(CountedBody::new(b, bytes)));
        Box::pin(self.inner.call(req))
    }
}

/// Serves gRPC on `listener` until `shutdown` resolves, then lets in-flight calls finish. Connections are
/// held to the limits of [`super::connections`]; HTTP/2 pings find dead peers, streams per connection are
/// capped, and a call must be answered within `body_read_timeout_ms + request_timeout_ms`.
pub async fn serve<H>(
    app: Arc<App>,
    listener: Listener,
    health: tonic_health::pb::health_server::HealthServer<H>,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> anyhow::Result<()>
where
    H: tonic_health::pb::health_server::Health,
{
    let reflection = || {
        tonic_reflection::server::Builder::configure()
            .register_encoded_file_descriptor_set(proto::FILE_DESCRIPTOR_SET)
            .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
    };
    // v1 and v1alpha: grpcurl and older tools still ask for v1alpha.
    let reflection_v1 = reflection().build_v1()?;
    let reflection_v1alpha = reflection().build_v1alpha()?;
    let server = &app.settings.server;
    let max = server.max_request_bytes;
    let call_timeout = Duration::from_millis(server.body_read_timeout_ms + server.request_timeout_ms);
    let keepalive =
        (server.grpc_keepalive_interval_ms > 0).then(|| Duration::from_millis(server.grpc_keepalive_interval_ms));
    let keepalive_timeout = Duration::from_millis(server.grpc_keepalive_timeout_ms);
    let max_streams = server.max_concurrent_streams;
    let api = GrpcApi { app: Arc::clone(&app) };
    let incoming = futures_util::stream::unfold(listener, |listener| async move {
        let (conn, _peer) = listener.accept().await;
        Some((Ok::<_, std::io::Error>(conn), listener))
    });
    tonic::transport::Server::builder()
        .timeout(call_timeout)
        .http2_keepalive_interval(keepalive)
        .http2_keepalive_timeout(Some(keepalive_timeout))
        .max_concurrent_streams(max_streams)
        .layer(CountRequestsLayer)
        .layer(GateLayer::new(Arc::clone(&app)))
        .add_service(health)
        .add_service(reflection_v1)
        .add_service(reflection_v1alpha)
        .add_service(
            proto::maps_server::MapsServer::new(api.clone())
                .max_decoding_message_size(max)
                .max_encoding_message_size(max),
        )
        .add_service(
            proto::matching_server::MatchingServer::new(api)
                .max_decoding_message_size(max)
                .max_encoding_message_size(max),
        )
        // TCP_NODELAY is set by the listener.
        .serve_with_incoming_shutdown(incoming, shutdown)
        .await?;
    Ok(())
}
