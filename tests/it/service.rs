//! The real server on ephemeral loopback ports, driven with a tonic client and an HTTP client.

use std::path::Path;
use std::time::Duration;

use nalgebra::Isometry3;
use scone::camera::Camera;
use scone::offline::scene::Scene;
use scone::server::proto::{self, frame::Source, maps_client::MapsClient, matching_client::MatchingClient};
use scone::server::{start, Running};
use scone::settings::Settings;
use tonic::transport::Channel;
use tonic::{Code, Request};

use crate::common::{fixture, shared_data, temp_dir};

pub(crate) const WRITE_KEY: &str = "write-key-0123456789";
pub(crate) const READ_KEY: &str = "read-key-0123456789";

pub(crate) fn settings(data: &Path) -> Settings {
    let mut s = Settings::default();
    s.server.grpc_addr = "127.0.0.1:0".parse().unwrap();
    s.server.http_addr = "127.0.0.1:0".parse().unwrap();
    s.store.data_dir = data.to_path_buf();
    s
}

pub(crate) async fn serve(s: Settings) -> Running {
    let r = start(s).await.expect("server starts");
    r.wait_ready(Duration::from_secs(60)).await.expect("maps load");
    r
}

pub(crate) async fn clients(r: &Running) -> (MapsClient<Channel>, MatchingClient<Channel>) {
    let url = format!("http://{}", r.grpc_addr);
    (MapsClient::connect(url.clone()).await.unwrap(), MatchingClient::connect(url).await.unwrap())
}

pub(crate) fn keyed<T>(msg: T, key: &str) -> Request<T> {
    let mut r = Request::new(msg);
    r.metadata_mut().insert("x-api-key", key.parse().unwrap());
    r
}

pub(crate) fn intrinsics(c: &Camera) -> proto::Intrinsics {
    proto::Intrinsics { fx: c.fx, fy: c.fy, cx: c.cx, cy: c.cy, width: c.width, height: c.height, ..Default::default() }
}

fn pose_msg(p: &Isometry3<f64>) -> proto::Pose {
    let q = p.rotation.quaternion();
    let t = p.translation.vector;
    proto::Pose { tx: t.x, ty: t.y, tz: t.z, qx: q.i, qy: q.j, qz: q.k, qw: q.w }
}

pub(crate) fn image_frame(path: &Path, cam: &Camera) -> proto::Frame {
    proto::Frame {
        source: Some(Source::Image(proto::Image { data: std::fs::read(path).unwrap() })),
        intrinsics: Some(intrinsics(cam)),
    }
}

pub(crate) fn keyframe_requests(map: &str, scene: &Scene, frames: &[usize]) -> Vec<proto::AddKeyframeRequest> {
    frames
        .iter()
        .map(|&i| {
            let f = &scene.frames[i];
            proto::AddKeyframeRequest {
                map_id: map.to_string(),
                keyframe_id: i as u64,
                frame: Some(image_frame(&f.rgb, &scene.camera)),
                pose: Some(pose_msg(&f.pose.unwrap())),
                depth_png: f.depth.as_ref().map(|d| std::fs::read(d).unwrap()).unwrap_or_default(),
                depth_scale: 0.0,
                external_landmarks: Vec::new(),
                pose_convention: 0,
            }
        })
        .collect()
}

/// Translation (map units) and rotation (degrees) between an estimated and a true camera-to-world pose.
pub(crate) fn pose_error(p: &proto::Pose, truth: &Isometry3<f64>) -> (f64, f64) {
    let t = nalgebra::Vector3::new(p.tx, p.ty, p.tz);
    let q = nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(p.qw, p.qx, p.qy, p.qz));
    let dt = (t - truth.translation.vector).norm();
    let dr = q.angle_to(&truth.rotation).to_degrees();
    (dt, dr)
}

pub(crate) async fn add_keyframes(
    maps: &mut MapsClient<Channel>,
    reqs: Vec<proto::AddKeyframeRequest>,
    key: Option<&str>,
) -> Vec<proto::KeyframeAck> {
    let n = reqs.len();
    let stream = tokio_stream::iter(reqs);
    let req = match key {
        Some(k) => keyed(stream, k),
        None => Request::new(stream),
    };
    let mut acks = maps.add_keyframes(req).await.unwrap().into_inner();
    let mut out = Vec::new();
    while let Some(a) = acks.message().await.unwrap() {
        out.push(a);
    }
    assert_eq!(out.len(), n);
    out
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn grpc_builds_a_map_localises_a_held_out_frame_and_keeps_it_across_restart() {
    let data = temp_dir("grpc");
    let scene = Scene::load(&fixture("rendered")).unwrap();
    let server = serve(settings(&data)).await;
    let (mut maps, mut matching) = clients(&server).await;

    let info = maps.create_map(proto::CreateMapRequest { map_id: "scene".into() }).await.unwrap().into_inner();
    assert_eq!(info.keyframes, 0);
    let acks = add_keyframes(&mut maps, keyframe_requests("scene", &scene, &[0, 2, 4, 6, 8]), None).await;
    assert_eq!(acks.iter().map(|a| a.keyframe_id).collect::<Vec<_>>(), vec![0, 2, 4, 6, 8]);
    assert!(acks.iter().all(|a| a.observations > 0));

    let query = |i: usize| proto::LocalizeRequest {
        map_id: "scene".into(),
        frame: Some(image_frame(&scene.frames[i].rgb, &scene.camera)),
        prior: None,
        pose_convention: 0,
    };
    let r = matching.localize(query(5)).await.unwrap().into_inner();
    assert!(r.localized, "{r:?}");
    let (dt, dr) = pose_error(r.pose.as_ref().unwrap(), &scene.frames[5].pose.unwrap());
    // The fixture's scene spans about 2 m; 5 cm and 1 degree is well inside the (0.25 m, 2 deg) band.
    assert!(dt < 0.05 && dr < 1.0, "pose off by {dt} m, {dr} deg");
    assert!(r.inliers >= 15 && r.confidence > 0.5, "{r:?}");

    let exported: Vec<u8> = {
        let mut s = maps.export_map(proto::ExportMapRequest { map_id: "scene".into() }).await.unwrap().into_inner();
        let mut bytes = Vec::new();
        while let Some(c) = s.message().await.unwrap() {
            bytes.extend(c.data);
        }
        bytes
    };
    server.shutdown().await.unwrap();

    // Restart on the same directory: the map is there and answers the same query.
    let server = serve(settings(&data)).await;
    let (mut maps, mut matching) = clients(&server).await;
    let info = maps.get_map(proto::GetMapRequest { map_id: "scene".into() }).await.unwrap().into_inner();
    assert_eq!(info.keyframes, 5);
    let r = matching.localize(query(3)).await.unwrap().into_inner();
    let (dt, dr) = pose_error(r.pose.as_ref().expect("localised after restart"), &scene.frames[3].pose.unwrap());
    assert!(dt < 0.05 && dr < 1.0, "pose off by {dt} m, {dr} deg after restart");

    // Import the export under another id (first chunk names the map).
    let chunks: Vec<proto::MapChunk> = exported
        .chunks(100_000)
        .enumerate()
        .map(|(i, c)| proto::MapChunk { map_id: if i == 0 { "copy".into() } else { String::new() }, data: c.to_vec() })
        .collect();
    let copy = maps.import_map(tokio_stream::iter(chunks)).await.unwrap().into_inner();
    assert_eq!(
        (copy.keyframes, copy.landmarks, copy.observations),
        (info.keyframes, info.landmarks, info.observations)
    );
    let listed = maps.list_maps(proto::ListMapsRequest {}).await.unwrap().into_inner();
    assert_eq!(listed.maps.iter().map(|m| m.map_id.as_str()).collect::<Vec<_>>(), vec!["copy", "scene"]);

    let after = maps.remove_keyframe(proto::RemoveKeyframeRequest { map_id: "copy".into(), keyframe_id: 4 }).await;
    assert!(after.unwrap().into_inner().live_observations < copy.live_observations);
    maps.delete_map(proto::DeleteMapRequest { map_id: "copy".into() }).await.unwrap();
    let gone = maps.get_map(proto::GetMapRequest { map_id: "copy".into() }).await.unwrap_err();
    assert_eq!(gone.code(), Code::NotFound);
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn describe_of_an_image_equals_describe_of_its_keypoints() {
    let data = temp_dir("describe");
    let server = serve(settings(&data)).await;
    let (_, mut matching) = clients(&server).await;
    let image = std::fs::read(fixture("coffee-640x480.jpg")).unwrap();
    let frame = proto::Frame { source: Some(Source::Image(proto::Image { data: image })), intrinsics: None };
    let a = matching.describe(proto::DescribeRequest { frame: Some(frame) }).await.unwrap().into_inner();
    assert!(a.keypoints.len() > 500);
    assert_eq!(a.embeddings.len(), a.keypoints.len() * a.dim as usize);
    assert_eq!(a.descriptors.len(), a.keypoints.len() * 64);
    let set = proto::KeypointSet {
        keypoints: a.keypoints.clone(),
        descriptors: a.descriptors.clone(),
        width: 640,
        height: 480,
        model_id: a.model_id.clone(),
        context: a.context.clone(),
    };
    let frame = proto::Frame { source: Some(Source::Keypoints(set)), intrinsics: None };
    let b = matching.describe(proto::DescribeRequest { frame: Some(frame) }).await.unwrap().into_inner();
    assert_eq!(a.keypoints, b.keypoints);
    let max = a.embeddings.iter().zip(&b.embeddings).map(|(x, y)| (x - y).abs()).fold(0.0f32, f32::max);
    assert!(max <= 1e-6, "embeddings differ by {max}");

    // Same through HTTP/JSON: the keypoint path with base64 descriptors.
    let http = reqwest::Client::new();
    let url = format!("http://{}/v1/describe", server.http_addr);
    let raw: serde_json::Value = http
        .post(&url)
        .header("content-type", "image/jpeg")
        .body(std::fs::read(fixture("coffee-640x480.jpg")).unwrap())
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    let body = serde_json::json!({"frame": {"keypoints": {
        "width": raw["width"], "height": raw["height"], "keypoints": raw["keypoints"],
        "descriptors_base64": raw["descriptors_base64"], "context_base64": raw["context_base64"],
        "model_id": raw["model_id"]}}});
    let via_keypoints: serde_json::Value = http.post(&url).json(&body).send().await.unwrap().json().await.unwrap();
    assert_eq!(raw["embeddings"], via_keypoints["embeddings"]);
    assert_eq!(
        (raw["extraction"]["levels"].as_u64(), raw["extraction"]["max_keypoints"].as_u64()),
        (Some(8), Some(2000))
    );
    assert_eq!(raw["embeddings"].as_array().unwrap().len(), a.embeddings.len());
    server.shutdown().await.unwrap();
}

pub(crate) fn multipart_keyframe(scene: &Scene, i: usize) -> reqwest::multipart::Form {
    let f = &scene.frames[i];
    let p = f.pose.unwrap();
    let q = p.rotation.quaternion();
    let t = p.translation.vector;
    let c = scene.camera;
    let request = serde_json::json!({
        "keyframe_id": i,
        "pose": {"tx": t.x, "ty": t.y, "tz": t.z, "qx": q.i, "qy": q.j, "qz": q.k, "qw": q.w},
        "intrinsics": {"fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy},
    });
    let mut form = reqwest::multipart::Form::new()
        .text("request", request.to_string())
        .part("image", reqwest::multipart::Part::bytes(std::fs::read(&f.rgb).unwrap()).mime_str("image/png").unwrap());
    if let Some(d) = &f.depth {
        form = form
            .part("depth", reqwest::multipart::Part::bytes(std::fs::read(d).unwrap()).mime_str("image/png").unwrap());
    }
    form
}

/// Adds frames `frames` of `scene` to map `map` over HTTP (`base` is the server's or a proxy's URL), each
/// answered 200.
pub(crate) async fn add_keyframes_http(http: &reqwest::Client, base: &str, map: &str, scene: &Scene, frames: &[usize]) {
    for &i in frames {
        let r = http
            .post(format!("{base}/v1/maps/{map}/keyframes"))
            .multipart(multipart_keyframe(scene, i))
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), 200, "{}", r.text().await.unwrap());
    }
}

/// `POST {base}/v1/maps/{map}/localize` with frame `frame` of `scene` as a PNG and the scene's intrinsics.
pub(crate) async fn localize_http(
    http: &reqwest::Client,
    base: &str,
    map: &str,
    scene: &Scene,
    frame: usize,
) -> reqwest::Response {
    let c = scene.camera;
    http.post(format!("{base}/v1/maps/{map}/localize?fx={}&fy={}&cx={}&cy={}", c.fx, c.fy, c.cx, c.cy))
        .header("content-type", "image/png")
        .body(std::fs::read(&scene.frames[frame].rgb).unwrap())
        .send()
        .await
        .unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn http_mirror_builds_a_map_and_localises_a_raw_image() {
    let data = temp_dir("http");
    let scene = Scene::load(&fixture("rendered")).unwrap();
    let server = serve(settings(&data)).await;
    let http = reqwest::Client::new();
    let base = format!("http://{}", server.http_addr);
    let r = http.post(format!("{base}/v1/maps")).json(&serde_json::json!({"map_id": "h"})).send().await.unwrap();
    assert_eq!(r.status(), 201);
    add_keyframes_http(&http, &base, "h", &scene, &[1, 3, 5, 7, 9]).await;
    let r: serde_json::Value = localize_http(&http, &base, "h", &scene, 6).await.json().await.unwrap();
    assert_eq!(r["localized"], true, "{r}");
    let pose: proto::Pose = proto::Pose {
        tx: r["pose"]["tx"].as_f64().unwrap(),
        ty: r["pose"]["ty"].as_f64().unwrap(),
        tz: r["pose"]["tz"].as_f64().unwrap(),
        qx: r["pose"]["qx"].as_f64().unwrap(),
        qy: r["pose"]["qy"].as_f64().unwrap(),
        qz: r["pose"]["qz"].as_f64().unwrap(),
        qw: r["pose"]["qw"].as_f64().unwrap(),
    };
    let (dt, dr) = pose_error(&pose, &scene.frames[6].pose.unwrap());
    assert!(dt < 0.05 && dr < 1.0, "pose off by {dt} m, {dr} deg");

    // MatchPair over multipart: two neighbouring frames give a relative pose close to the true one.
    let c = scene.camera;
    let request = serde_json::json!({
        "frame1": {"intrinsics": {"fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy}},
        "frame2": {"intrinsics": {"fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy}},
    });
    let form = reqwest::multipart::Form::new()
        .text("request", request.to_string())
        .part("image1", reqwest::multipart::Part::bytes(std::fs::read(&scene.frames[0].rgb).unwrap()))
        .part("image2", reqwest::multipart::Part::bytes(std::fs::read(&scene.frames[1].rgb).unwrap()));
    let m: serde_json::Value =
        http.post(format!("{base}/v1/match")).multipart(form).send().await.unwrap().json().await.unwrap();
    assert!(m["inliers"].as_u64().unwrap() >= 30, "{}", m["inliers"]);
    let rel = scone::pose::relative_motion(&scene.frames[0].pose.unwrap(), &scene.frames[1].pose.unwrap());
    let q = nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
        m["pose"]["qw"].as_f64().unwrap(),
        m["pose"]["qx"].as_f64().unwrap(),
        m["pose"]["qy"].as_f64().unwrap(),
        m["pose"]["qz"].as_f64().unwrap(),
    ));
    let dr = q.angle_to(&rel.rotation).to_degrees();
    assert!(dr < 2.0, "relative rotation off by {dr} deg");

    let listed: serde_json::Value = http.get(format!("{base}/v1/maps")).send().await.unwrap().json().await.unwrap();
    assert_eq!(listed["maps"][0]["keyframes"], 5);
    let r = http.delete(format!("{base}/v1/maps/h/keyframes/3")).send().await.unwrap();
    assert_eq!(r.status(), 200);
    let r = http.delete(format!("{base}/v1/maps/h")).send().await.unwrap();
    assert_eq!(r.status(), 204);
    assert_eq!(http.get(format!("{base}/v1/maps/h")).send().await.unwrap().status(), 404);
    assert_eq!(http.get(format!("{base}/readyz")).send().await.unwrap().status(), 200);
    let metrics = http.get(format!("{base}/metrics")).send().await.unwrap().text().await.unwrap();
    assert!(
        metrics
            .contains("scone_requests_total{transport=\"http\",route=\"/v1/maps/{map_id}/localize\",status=\"200\"} 1"),
        "{metrics}"
    );
    assert!(metrics.contains("scone_stage_duration_seconds_count{stage=\"embed\"}"));
    server.shutdown().await.unwrap();
}

fn external_msg(o: &scone::map::builder::ExternalObservation) -> proto::ExternalObservation {
    proto::ExternalObservation {
        x: o.x,
        y: o.y,
        landmark_id: o.landmark_id,
        point: Some(proto::Point3 { x: o.point[0], y: o.point[1], z: o.point[2] }),
    }
}

/// Keyframes whose landmarks an external SfM gave (the synthetic one of `tests/it/colmap.rs`), over gRPC
/// and HTTP: views of one id become one landmark, the map localises a held-out frame, a view that does not
/// fit the pose is rejected and counted, and a NaN point is refused naming the field without a write.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn keyframes_with_external_landmarks_merge_by_id_localise_and_refuse_a_nan_point() {
    let data = temp_dir("external");
    let scene = Scene::load(&fixture("rendered")).unwrap();
    let mapped = [0, 2, 4, 6, 8];
    let sfm = crate::colmap::synthetic_sfm(&scene, &mapped, &[0, 2, 4, 6, 8, 9]);
    let server = serve(settings(&data)).await;
    let (mut maps, mut matching) = clients(&server).await;
    maps.create_map(proto::CreateMapRequest { map_id: "sfm".into() }).await.unwrap();
    let mut reqs = keyframe_requests("sfm", &scene, &mapped);
    for (r, f) in reqs.iter_mut().zip(mapped) {
        r.depth_png.clear();
        r.external_landmarks = sfm.views[&f].iter().map(external_msg).collect();
    }
    // A view 20 px away from where its point projects.
    let mut off = sfm.views[&0][0];
    off.x += 20.0;
    off.landmark_id = 1_000_000;
    reqs[0].external_landmarks.push(external_msg(&off));
    let acks = add_keyframes(&mut maps, reqs, None).await;
    assert_eq!(acks[0].external_rejected, 1, "{:?}", acks[0]);
    assert!(acks[1..].iter().all(|a| a.external_rejected == 0), "{acks:?}");
    let new: u64 = acks.iter().map(|a| a.new_landmarks).sum();
    let observations: u64 = acks.iter().map(|a| a.observations).sum();
    let info = maps.get_map(proto::GetMapRequest { map_id: "sfm".into() }).await.unwrap().into_inner();
    assert_eq!((info.landmarks, info.observations), (new, observations));
    assert!(info.landmarks < info.observations, "{info:?}");

    let r = matching
        .localize(proto::LocalizeRequest {
            map_id: "sfm".into(),
            frame: Some(image_frame(&scene.frames[5].rgb, &scene.camera)),
            prior: None,
            pose_convention: 0,
        })
        .await
        .unwrap()
        .into_inner();
    let (dt, dr) = pose_error(r.pose.as_ref().expect("localised"), &scene.frames[5].pose.unwrap());
    assert!(dt < 0.05 && dr < 1.0, "pose off by {dt} m, {dr} deg");

    // NaN in a point: INVALID_ARGUMENT naming the field, and the map does not move.
    let v0 = info.version;
    let mut nan = keyframe_requests("sfm", &scene, &[9]);
    nan[0].depth_png.clear();
    nan[0].external_landmarks = sfm.views[&9].iter().map(external_msg).collect();
    nan[0].external_landmarks[3].point.as_mut().unwrap().y = f64::NAN;
    let mut acks = maps.add_keyframes(tokio_stream::iter(nan)).await.unwrap().into_inner();
    let e = acks.message().await.unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument, "{e:?}");
    assert!(e.message().contains("external_landmarks[3].point") && e.message().contains("not finite"), "{e:?}");
    let info = maps.get_map(proto::GetMapRequest { map_id: "sfm".into() }).await.unwrap().into_inner();
    assert_eq!(info.version, v0, "a refused request changed the map");

    // The same frame over HTTP (multipart, JSON part): its views of known ids observe existing landmarks.
    let f = &scene.frames[9];
    let p = f.pose.unwrap();
    let (q, t, c) = (p.rotation.quaternion(), p.translation.vector, scene.camera);
    let external: Vec<serde_json::Value> = sfm.views[&9]
        .iter()
        .map(|o| {
            serde_json::json!({"x": o.x, "y": o.y, "landmark_id": o.landmark_id,
                               "point": {"x": o.point[0], "y": o.point[1], "z": o.point[2]}})
        })
        .collect();
    let request = serde_json::json!({
        "keyframe_id": 9,
        "pose": {"tx": t.x, "ty": t.y, "tz": t.z, "qx": q.i, "qy": q.j, "qz": q.k, "qw": q.w},
        "intrinsics": {"fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy},
        "external_landmarks": external,
    });
    let form = reqwest::multipart::Form::new()
        .text("request", request.to_string())
        .part("image", reqwest::multipart::Part::bytes(std::fs::read(&f.rgb).unwrap()).mime_str("image/png").unwrap());
    let r = reqwest::Client::new()
        .post(format!("http://{}/v1/maps/sfm/keyframes", server.http_addr))
        .multipart(form)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    let ack: serde_json::Value = r.json().await.unwrap();
    assert_eq!(ack["external_rejected"], 0, "{ack}");
    let (new, obs) = (ack["new_landmarks"].as_u64().unwrap(), ack["observations"].as_u64().unwrap());
    assert!(obs > 30 && new * 5 < obs, "{ack}");
    server.shutdown().await.unwrap();
}

async fn version(maps: &mut MapsClient<Channel>, id: &str) -> u64 {
    maps.get_map(keyed(proto::GetMapRequest { map_id: id.into() }, READ_KEY)).await.unwrap().into_inner().version
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_error_path_gets_its_code_and_a_useful_message_and_changes_nothing() {
    let data = temp_dir("errors");
    let scene = Scene::load(&fixture("rendered")).unwrap();
    let mut s = settings(&data);
    s.auth.write_keys = vec![WRITE_KEY.into()];
    s.auth.read_keys = vec![READ_KEY.into()];
    let server = serve(s).await;
    let (mut maps, mut matching) = clients(&server).await;
    maps.create_map(keyed(proto::CreateMapRequest { map_id: "m".into() }, WRITE_KEY)).await.unwrap();
    add_keyframes(&mut maps, keyframe_requests("m", &scene, &[0, 4]), Some(WRITE_KEY)).await;
    let v0 = version(&mut maps, "m").await;

    let expect = |r: tonic::Status, code: Code, words: &[&str]| {
        assert_eq!(r.code(), code, "{r:?}");
        for w in words {
            assert!(r.message().contains(w), "'{}' lacks '{w}'", r.message());
        }
    };
    // Auth: no key, unknown key, read-only key on a write.
    let e = maps.create_map(proto::CreateMapRequest { map_id: "x".into() }).await.unwrap_err();
    expect(e, Code::Unauthenticated, &["x-api-key"]);
    let e = maps
        .create_map(keyed(proto::CreateMapRequest { map_id: "x".into() }, "not-a-key-at-all-0000"))
        .await
        .unwrap_err();
    expect(e, Code::Unauthenticated, &[]);
    let e = maps.delete_map(keyed(proto::DeleteMapRequest { map_id: "m".into() }, READ_KEY)).await.unwrap_err();
    expect(e, Code::PermissionDenied, &["read-only", "DeleteMap"]);
    let stream = tokio_stream::iter(keyframe_requests("m", &scene, &[6]));
    let e = maps.add_keyframes(keyed(stream, READ_KEY)).await.unwrap_err();
    expect(e, Code::PermissionDenied, &["AddKeyframes"]);

    // Unknown map, corrupt image, wrong descriptor length, NaN pose, duplicate keyframe.
    let loc = |map: &str, data: Vec<u8>| {
        keyed(
            proto::LocalizeRequest {
                map_id: map.into(),
                frame: Some(proto::Frame {
                    source: Some(Source::Image(proto::Image { data })),
                    intrinsics: Some(intrinsics(&scene.camera)),
                }),
                prior: None,
                pose_convention: 0,
            },
            READ_KEY,
        )
    };
    let png = std::fs::read(&scene.frames[1].rgb).unwrap();
    let e = matching.localize(loc("nope", png.clone())).await.unwrap_err();
    expect(e, Code::NotFound, &["nope"]);
    let mut corrupt = png.clone();
    corrupt.truncate(corrupt.len() / 3);
    let e = matching.localize(loc("m", corrupt)).await.unwrap_err();
    expect(e, Code::InvalidArgument, &["image"]);
    let set = proto::KeypointSet {
        keypoints: vec![proto::Keypoint { x: 50.0, y: 50.0, size: 7.0, angle: 10.0, response: 1.0, octave: 0 }; 30],
        descriptors: vec![0u8; 30 * 64 - 1],
        width: 320,
        height: 240,
        model_id: String::new(),
        context: Vec::new(),
    };
    let e = matching
        .describe(keyed(
            proto::DescribeRequest {
                frame: Some(proto::Frame { source: Some(Source::Keypoints(set)), intrinsics: None }),
            },
            READ_KEY,
        ))
        .await
        .unwrap_err();
    expect(e, Code::InvalidArgument, &["descriptors", "1919"]);
    let mut nan = keyframe_requests("m", &scene, &[6]);
    nan[0].pose.as_mut().unwrap().qw = f64::NAN;
    let mut acks = maps.add_keyframes(keyed(tokio_stream::iter(nan), WRITE_KEY)).await.unwrap().into_inner();
    expect(acks.message().await.unwrap_err(), Code::InvalidArgument, &["pose", "non-finite"]);
    let dup = keyframe_requests("m", &scene, &[4]);
    let mut acks = maps.add_keyframes(keyed(tokio_stream::iter(dup), WRITE_KEY)).await.unwrap().into_inner();
    expect(acks.message().await.unwrap_err(), Code::AlreadyExists, &["keyframe 4"]);
    let e = maps.create_map(keyed(proto::CreateMapRequest { map_id: "bad/id".into() }, WRITE_KEY)).await.unwrap_err();
    expect(e, Code::InvalidArgument, &["map id"]);
    let e = maps.create_map(keyed(proto::CreateMapRequest { map_id: "m".into() }, WRITE_KEY)).await.unwrap_err();
    expect(e, Code::AlreadyExists, &["'m'"]);
    let wrong_model =
        proto::KeypointSet { model_id: "sha256:another".into(), width: 320, height: 240, ..Default::default() };
    let e = matching
        .describe(keyed(
            proto::DescribeRequest {
                frame: Some(proto::Frame { source: Some(Source::Keypoints(wrong_model)), intrinsics: None }),
            },
            READ_KEY,
        ))
        .await
        .unwrap_err();
    expect(e, Code::FailedPrecondition, &["sha256:another"]);
    // A message over the limit (32 MiB by default) is refused by the transport.
    let e = matching.localize(loc("m", vec![0u8; 33 << 20])).await.unwrap_err();
    assert!(matches!(e.code(), Code::OutOfRange | Code::ResourceExhausted), "{e:?}");
    assert_eq!(version(&mut maps, "m").await, v0, "a refused request changed the map");

    // The same over HTTP: JSON error bodies with the code.
    let http = reqwest::Client::new();
    let base = format!("http://{}", server.http_addr);
    let r = http.post(format!("{base}/v1/maps")).json(&serde_json::json!({"map_id": "y"})).send().await.unwrap();
    assert_eq!(r.status(), 401);
    let r = http
        .post(format!("{base}/v1/maps"))
        .header("x-api-key", READ_KEY)
        .json(&serde_json::json!({"map_id": "y"}))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 403);
    assert_eq!(r.json::<serde_json::Value>().await.unwrap()["error"]["code"], "PERMISSION_DENIED");
    let r = http
        .post(format!("{base}/v1/maps/m/localize?fx=250&cx=160&cy=120"))
        .header("authorization", format!("Bearer {READ_KEY}"))
        .header("content-type", "image/png")
        .body(b"\x89PNG\r\n\x1a\nnot really".to_vec())
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 400);
    let body: serde_json::Value = r.json().await.unwrap();
    assert_eq!(body["error"]["code"], "INVALID_ARGUMENT");
    let r = http
        .post(format!("{base}/v1/maps/zzz/localize?fx=250&cx=160&cy=120"))
        .header("x-api-key", READ_KEY)
        .header("content-type", "image/png")
        .body(png.clone())
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 404);
    // A body over the limit is refused from its declared length, before any of it is read: the request goes
    // out on a raw socket that sends the headers and never the body (a client writing the 33 MiB would race
    // the server's early answer and could see a broken pipe instead of the 413).
    let head = oversized_request_status(server.http_addr, "/v1/describe", READ_KEY, 33 << 20).await;
    assert!(head.starts_with("HTTP/1.1 413"), "{head}");
    let r = http
        .post(format!("{base}/v1/maps/m/keyframes"))
        .header("x-api-key", WRITE_KEY)
        .json(&serde_json::json!({"keyframe_id": 7, "pose": {"tx": 0, "ty": 0, "tz": 0, "qx": 0, "qy": 0, "qz": 0, "qw": 2},
                                  "frame": {"image_base64": "aGVsbG8="}, "intrinsics": {"fx": 250, "fy": 250, "cx": 160, "cy": 120}}))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 400);
    let msg = r.json::<serde_json::Value>().await.unwrap()["error"]["message"].as_str().unwrap().to_string();
    assert!(msg.contains("quaternion"), "{msg}");
    let r = http
        .post(format!("{base}/v1/describe"))
        .header("x-api-key", READ_KEY)
        .header("content-type", "text/plain")
        .body("hello")
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 415);
    assert_eq!(r.json::<serde_json::Value>().await.unwrap()["error"]["code"], "UNSUPPORTED_MEDIA_TYPE");
    assert_eq!(version(&mut maps, "m").await, v0, "a refused request changed the map");
    server.shutdown().await.unwrap();
}

/// Sends only the headers of a POST declaring `length` bytes and returns the response's status line.
async fn oversized_request_status(addr: std::net::SocketAddr, path: &str, key: &str, length: usize) -> String {
    use tokio::io::{AsyncBufReadExt, AsyncWriteExt, BufReader};
    let mut socket = tokio::net::TcpStream::connect(addr).await.unwrap();
    let head = format!(
        "POST {path} HTTP/1.1\r\nhost: {addr}\r\nx-api-key: {key}\r\ncontent-type: image/jpeg\r\ncontent-length: {length}\r\n\r\n"
    );
    socket.write_all(head.as_bytes()).await.unwrap();
    let mut line = String::new();
    tokio::time::timeout(Duration::from_secs(10), BufReader::new(socket).read_line(&mut line))
        .await
        .expect("no answer to an oversized request within 10 s")
        .unwrap();
    line
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_saturated_server_refuses_quickly_with_resource_exhausted_and_keeps_serving() {
    let data = temp_dir("saturate");
    let mut s = settings(&data);
    s.workers.threads = 1;
    s.workers.queue = 1;
    let server = serve(s).await;
    let (_, matching) = clients(&server).await;
    let image = std::fs::read(fixture("coffee-640x480.jpg")).unwrap();
    let mut tasks = Vec::new();
    for _ in 0..12 {
        let mut m = matching.clone();
        let frame =
            proto::Frame { source: Some(Source::Image(proto::Image { data: image.clone() })), intrinsics: None };
        tasks.push(tokio::spawn(async move { m.describe(proto::DescribeRequest { frame: Some(frame) }).await }));
    }
    let (mut ok, mut refused) = (0, 0);
    for t in tasks {
        match t.await.unwrap() {
            Ok(_) => ok += 1,
            Err(e) => {
                assert_eq!(e.code(), Code::ResourceExhausted, "{e:?}");
                assert!(e.metadata().get("retry-after").is_some());
                refused += 1;
            }
        }
    }
    assert!(ok >= 1 && refused >= 1, "ok {ok}, refused {refused}");
    let http = reqwest::Client::new();
    let base = format!("http://{}", server.http_addr);
    let mut tasks = Vec::new();
    for _ in 0..12 {
        let (h, url, body) = (http.clone(), format!("{base}/v1/describe"), image.clone());
        tasks.push(tokio::spawn(async move {
            h.post(url).header("content-type", "image/jpeg").body(body).send().await.unwrap()
        }));
    }
    let mut statuses = Vec::new();
    for t in tasks {
        let r = t.await.unwrap();
        if r.status() == 429 {
            assert_eq!(r.headers()["retry-after"], "1");
        }
        statuses.push(r.status().as_u16());
    }
    assert!(statuses.contains(&429) && statuses.contains(&200), "{statuses:?}");
    // Still serving once the burst is over.
    let mut m = matching.clone();
    let frame = proto::Frame { source: Some(Source::Image(proto::Image { data: image })), intrinsics: None };
    m.describe(proto::DescribeRequest { frame: Some(frame) }).await.unwrap();
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn health_and_reflection_answer_standard_clients() {
    use tonic_health::pb::health_client::HealthClient;
    use tonic_health::pb::HealthCheckRequest;
    use tonic_reflection::pb::v1::server_reflection_client::ServerReflectionClient;
    use tonic_reflection::pb::v1::server_reflection_request::MessageRequest;
    use tonic_reflection::pb::v1::server_reflection_response::MessageResponse;
    use tonic_reflection::pb::v1::ServerReflectionRequest;

    let data = temp_dir("health");
    let server = serve(settings(&data)).await;
    let url = format!("http://{}", server.grpc_addr);
    let channel = Channel::from_shared(url).unwrap().connect().await.unwrap();
    let mut health = HealthClient::new(channel.clone());
    for service in ["", "scone.v1.Maps", "scone.v1.Matching"] {
        let r = health.check(HealthCheckRequest { service: service.into() }).await.unwrap().into_inner();
        assert_eq!(r.status, tonic_health::pb::health_check_response::ServingStatus::Serving as i32);
    }
    let mut reflection = ServerReflectionClient::new(channel);
    let req = ServerReflectionRequest {
        host: String::new(),
        message_request: Some(MessageRequest::ListServices(String::new())),
    };
    let mut stream = reflection.server_reflection_info(tokio_stream::iter(vec![req])).await.unwrap().into_inner();
    let resp = stream.message().await.unwrap().unwrap();
    let Some(MessageResponse::ListServicesResponse(list)) = resp.message_response else { panic!("{resp:?}") };
    let names: Vec<String> = list.service.into_iter().map(|s| s.name).collect();
    for want in ["scone.v1.Maps", "scone.v1.Matching", "grpc.health.v1.Health"] {
        assert!(names.iter().any(|n| n == want), "{want} missing from {names:?}");
    }
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rgbd_slambook_map_localises_held_out_frames_and_no_frame_of_another_scene() {
    let Some(dir) = shared_data() else { return };
    let scene = Scene::load(&dir.join("scenes/rgbd-slambook-5")).unwrap();
    let data = temp_dir("slambook");
    let server = serve(settings(&data)).await;
    let (mut maps, mut matching) = clients(&server).await;
    maps.create_map(proto::CreateMapRequest { map_id: "slam".into() }).await.unwrap();
    let n = scene.frames.len();
    let mapped: Vec<usize> = (0..n).step_by(2).collect();
    add_keyframes(&mut maps, keyframe_requests("slam", &scene, &mapped), None).await;
    for i in (1..n).step_by(2) {
        let r = matching
            .localize(proto::LocalizeRequest {
                map_id: "slam".into(),
                frame: Some(image_frame(&scene.frames[i].rgb, &scene.camera)),
                prior: None,
                pose_convention: 0,
            })
            .await
            .unwrap()
            .into_inner();
        let (dt, dr) = pose_error(r.pose.as_ref().expect("localised"), &scene.frames[i].pose.unwrap());
        assert!(dt < 0.25 && dr < 2.0, "frame {i}: off by {dt} m, {dr} deg");
    }
    // No false poses: frames of other scenes get none, with every stage of the default pipeline at work.
    for other in ["tum-fr3-long-office", "strecha-fountain-P11"] {
        let other = Scene::load(&dir.join("scenes").join(other)).unwrap();
        for f in other.frames.iter().step_by(4) {
            let r = matching
                .localize(proto::LocalizeRequest {
                    map_id: "slam".into(),
                    frame: Some(image_frame(&f.rgb, &other.camera)),
                    prior: None,
                    pose_convention: 0,
                })
                .await
                .unwrap()
                .into_inner();
            assert!(r.pose.is_none(), "{}: a pose against another scene's map", f.rgb.display());
        }
    }
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shutdown_finishes_in_flight_requests_then_flushes() {
    let data = temp_dir("shutdown");
    let scene = Scene::load(&fixture("rendered")).unwrap();
    let server = serve(settings(&data)).await;
    let (mut maps, matching) = clients(&server).await;
    maps.create_map(proto::CreateMapRequest { map_id: "s".into() }).await.unwrap();
    add_keyframes(&mut maps, keyframe_requests("s", &scene, &[0, 5]), None).await;
    // A few describes in flight when the shutdown starts: every one is answered, none is cut off.
    let image = std::fs::read(fixture("coffee-640x480.jpg")).unwrap();
    let mut inflight = Vec::new();
    for _ in 0..3 {
        let mut m = matching.clone();
        let frame =
            proto::Frame { source: Some(Source::Image(proto::Image { data: image.clone() })), intrinsics: None };
        inflight.push(tokio::spawn(async move { m.describe(proto::DescribeRequest { frame: Some(frame) }).await }));
    }
    // Wait until the server holds all three (running or queued), so none is still on its way in.
    let stats = server.app.pool.stats();
    let held = || {
        stats.running.load(std::sync::atomic::Ordering::Relaxed)
            + stats.queued.load(std::sync::atomic::Ordering::Relaxed)
    };
    while held() < 3 {
        tokio::time::sleep(Duration::from_millis(1)).await;
    }
    let addr = server.http_addr;
    server.request_shutdown();
    assert!(!server.app.is_ready(), "readiness must drop as soon as the shutdown starts");
    for t in inflight {
        let r = t.await.unwrap().expect("an in-flight request is answered during shutdown");
        assert!(!r.into_inner().keypoints.is_empty());
    }
    server.wait().await.unwrap();
    // New connections are refused once stopped; the flush left a snapshot the next start loads.
    assert!(reqwest::get(format!("http://{addr}/healthz")).await.is_err(), "still accepting after shutdown");
    assert!(data.join("maps/s/snapshot.bin").is_file());
    let server = serve(settings(&data)).await;
    assert_eq!(server.app.service.map("s").unwrap().summary().keyframes, 2);
    server.shutdown().await.unwrap();
}

/// MatchPair's matcher is selectable on both transports (the plain SConE embedding stays available), every
/// choice recovers the fixture pair's rotation, and an unknown one is the client's error.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn match_pair_matchers_are_selectable_and_unknown_ones_refused() {
    let data = temp_dir("matchers");
    let scene = Scene::load(&fixture("rendered")).unwrap();
    let server = serve(settings(&data)).await;
    let (_, mut matching) = clients(&server).await;
    let c = scene.camera;
    let rel = scone::pose::relative_motion(&scene.frames[0].pose.unwrap(), &scene.frames[1].pose.unwrap());
    let rotation_error = |p: &proto::RelativePose| {
        let q = nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(p.qw, p.qx, p.qy, p.qz));
        q.angle_to(&rel.rotation).to_degrees()
    };
    let request = |matcher: i32| proto::MatchPairRequest {
        frame1: Some(image_frame(&scene.frames[0].rgb, &c)),
        frame2: Some(image_frame(&scene.frames[1].rgb, &c)),
        ratio: 0.0,
        mutual: false,
        matcher,
        pose_convention: 0,
    };
    let mut counts = Vec::new();
    for m in [
        proto::PairMatcher::Default,
        proto::PairMatcher::Plain,
        proto::PairMatcher::Union,
        proto::PairMatcher::Rerank,
        proto::PairMatcher::ScaleAware,
        proto::PairMatcher::Joint,
        proto::PairMatcher::Both,
    ] {
        let r = matching.match_pair(request(m as i32)).await.unwrap().into_inner();
        let ran = if m == proto::PairMatcher::Default { proto::PairMatcher::Union } else { m };
        assert_eq!(r.matcher, ran as i32, "the answer names the matcher that ran");
        let dr = rotation_error(r.pose.as_ref().expect("a pose"));
        assert!(dr < 2.0, "{m:?}: relative rotation off by {dr} deg");
        counts.push(r.matches.len());
    }
    // The default is the embedded model's declared matcher, union.
    assert_eq!(counts[0], counts[2]);
    // Scale-aware re-ranks between these two frames of one scale: the same matches as rerank.
    assert_eq!(counts[4], counts[3]);
    // Both keeps every match union keeps, and FREAK's answers where SConE answered otherwise.
    assert!(counts[6] >= counts[2], "both {} < union {}", counts[6], counts[2]);
    let err = matching.match_pair(request(99)).await.unwrap_err();
    assert_eq!(err.code(), Code::InvalidArgument);
    assert!(err.message().contains("matcher"), "{}", err.message());

    let http = reqwest::Client::new();
    let base = format!("http://{}", server.http_addr);
    let post = |matcher: &str| {
        let request = serde_json::json!({
            "frame1": {"intrinsics": {"fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy}},
            "frame2": {"intrinsics": {"fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy}},
            "matcher": matcher,
        });
        let form = reqwest::multipart::Form::new()
            .text("request", request.to_string())
            .part("image1", reqwest::multipart::Part::bytes(std::fs::read(&scene.frames[0].rgb).unwrap()))
            .part("image2", reqwest::multipart::Part::bytes(std::fs::read(&scene.frames[1].rgb).unwrap()));
        http.post(format!("{base}/v1/match")).multipart(form).send()
    };
    let plain: serde_json::Value = post("plain").await.unwrap().json().await.unwrap();
    assert_eq!(plain["matches"].as_array().unwrap().len(), counts[1]);
    assert_eq!(plain["matcher"], "plain");
    let scale_aware: serde_json::Value = post("scale-aware").await.unwrap().json().await.unwrap();
    assert_eq!(scale_aware["matches"].as_array().unwrap().len(), counts[4]);
    let joint: serde_json::Value = post("joint").await.unwrap().json().await.unwrap();
    assert_eq!(
        (joint["matches"].as_array().unwrap().len(), &joint["matcher"]),
        (counts[5], &serde_json::json!("joint"))
    );
    let both: serde_json::Value = post("both").await.unwrap().json().await.unwrap();
    assert_eq!((both["matches"].as_array().unwrap().len(), &both["matcher"]), (counts[6], &serde_json::json!("both")));
    let r = post("nearest").await.unwrap();
    assert_eq!(r.status(), 400);
    server.shutdown().await.unwrap();
}
