//! Issue 26, section 3: what a client written from the README and the proto alone got accepted that should
//! have been refused: intrinsics and poses far out of range, a JSON array where an object is expected, and a
//! compressed body read as an image. Each is a 400 (or 415) naming the field, and nothing is stored.

use base64::Engine;
use scone::offline::scene::Scene;
use scone::server::proto;
use tonic::Code;

use crate::common::{fixture, temp_dir};
use crate::service::{clients, image_frame, keyframe_requests, serve, settings};

fn b64(bytes: &[u8]) -> String {
    base64::engine::general_purpose::STANDARD.encode(bytes)
}

/// A keyframe request for frame 0 of the fixture, as JSON, with `edit` applied.
fn keyframe_json(scene: &Scene, edit: impl FnOnce(&mut serde_json::Value)) -> serde_json::Value {
    let f = &scene.frames[0];
    let p = f.pose.unwrap();
    let (q, t, c) = (p.rotation.quaternion(), p.translation.vector, scene.camera);
    let mut v = serde_json::json!({
        "keyframe_id": 0,
        "pose": {"tx": t.x, "ty": t.y, "tz": t.z, "qx": q.i, "qy": q.j, "qz": q.k, "qw": q.w},
        "intrinsics": {"fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy},
        "frame": {"image_base64": b64(&std::fs::read(&f.rgb).unwrap())},
    });
    edit(&mut v);
    v
}

/// The status AddKeyframes answers one request with (an error is expected).
async fn refusal(
    maps: &mut proto::maps_client::MapsClient<tonic::transport::Channel>,
    req: proto::AddKeyframeRequest,
) -> tonic::Status {
    match maps.add_keyframes(tokio_stream::iter([req])).await {
        Err(st) => st,
        Ok(acks) => acks.into_inner().message().await.expect_err("the keyframe was acknowledged"),
    }
}

async fn error_of(r: reqwest::Response) -> (u16, String) {
    let status = r.status().as_u16();
    let body: serde_json::Value = r.json().await.unwrap();
    (status, body["error"]["message"].as_str().unwrap_or_default().to_string())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn regression_out_of_range_intrinsics_and_poses_and_arrays_for_objects_are_refused() {
    let dir = temp_dir("bounds");
    let scene = Scene::load(&fixture("rendered")).unwrap();
    let server = serve(settings(&dir)).await;
    let http = reqwest::Client::new();
    let base = format!("http://{}", server.http_addr);

    // `["newid"]` is not a CreateMap request (serde would read the struct from the array by position).
    let r = http.post(format!("{base}/v1/maps")).json(&serde_json::json!(["newid"])).send().await.unwrap();
    let (status, msg) = error_of(r).await;
    assert_eq!(status, 400, "{msg}");
    assert!(msg.contains("must be a JSON object"), "{msg}");
    assert_eq!(http.get(format!("{base}/v1/maps/newid")).send().await.unwrap().status(), 404);

    let r = http.post(format!("{base}/v1/maps")).json(&serde_json::json!({"map_id": "m"})).send().await.unwrap();
    assert_eq!(r.status(), 201);
    let cases: Vec<(&str, serde_json::Value)> = vec![
        ("intrinsics.cx", keyframe_json(&scene, |v| v["intrinsics"]["cx"] = 1e300.into())),
        ("intrinsics.fx", keyframe_json(&scene, |v| v["intrinsics"]["fx"] = 1e300.into())),
        ("pose", keyframe_json(&scene, |v| v["pose"]["tx"] = 1e300.into())),
        ("pose", keyframe_json(&scene, |v| v["pose"] = serde_json::json!([0, 0, 0, 0, 0, 0, 1]))),
        ("intrinsics", keyframe_json(&scene, |v| v["intrinsics"] = serde_json::json!([500, 500, 320, 240]))),
    ];
    for (field, body) in cases {
        let r = http.post(format!("{base}/v1/maps/m/keyframes")).json(&body).send().await.unwrap();
        let (status, msg) = error_of(r).await;
        assert_eq!(status, 400, "{field}: {msg}");
        let named = field.split('.').all(|part| msg.contains(part));
        assert!(named, "{field}: the message does not name the field: {msg}");
    }
    let info: serde_json::Value = http.get(format!("{base}/v1/maps/m")).send().await.unwrap().json().await.unwrap();
    assert_eq!((info["keyframes"].as_u64(), info["version"].as_u64()), (Some(0), Some(0)), "{info}");
    // The same request in range is stored: the refusals were about the values.
    let r = http.post(format!("{base}/v1/maps/m/keyframes")).json(&keyframe_json(&scene, |_| {})).send().await;
    assert_eq!(r.unwrap().status(), 200);

    // gRPC: the same bounds.
    let (mut maps, mut matching) = clients(&server).await;
    let mut req = keyframe_requests("m", &scene, &[1]).remove(0);
    req.frame.as_mut().unwrap().intrinsics.as_mut().unwrap().cx = 1e300;
    let st = refusal(&mut maps, req).await;
    assert_eq!(st.code(), Code::InvalidArgument, "{st:?}");
    assert!(st.message().contains("cx"), "{}", st.message());
    let mut req = keyframe_requests("m", &scene, &[1]).remove(0);
    req.pose.as_mut().unwrap().tx = 1e300;
    let st = refusal(&mut maps, req).await;
    assert_eq!(st.code(), Code::InvalidArgument, "{st:?}");
    let mut frame = image_frame(&scene.frames[2].rgb, &scene.camera);
    frame.intrinsics.as_mut().unwrap().fy = 1e300;
    let st = matching.localize(proto::LocalizeRequest { map_id: "m".into(), frame: Some(frame), ..Default::default() });
    assert_eq!(st.await.unwrap_err().code(), Code::InvalidArgument);
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn regression_compressed_bodies_are_refused_not_read_as_images() {
    let dir = temp_dir("gzip");
    let scene = Scene::load(&fixture("rendered")).unwrap();
    let server = serve(settings(&dir)).await;
    let http = reqwest::Client::new();
    let base = format!("http://{}", server.http_addr);
    let c = scene.camera;
    for (url, ct, body) in [
        (format!("{base}/v1/describe"), "image/png", std::fs::read(&scene.frames[0].rgb).unwrap()),
        (format!("{base}/v1/maps"), "application/json", br#"{"map_id":"z"}"#.to_vec()),
        (
            format!("{base}/v1/maps/z/localize?fx={}&fy={}&cx={}&cy={}", c.fx, c.fy, c.cx, c.cy),
            "image/png",
            std::fs::read(&scene.frames[0].rgb).unwrap(),
        ),
    ] {
        let r = http
            .post(&url)
            .header("content-type", ct)
            .header("content-encoding", "gzip")
            .body(body)
            .send()
            .await
            .unwrap();
        // The body stays unread, so the connection is not offered for another request.
        assert_eq!(r.headers().get("connection").map(|v| v.as_bytes()), Some(&b"close"[..]), "{url}");
        let (status, msg) = error_of(r).await;
        assert_eq!(status, 415, "{url}: {msg}");
        assert!(msg.contains("content-encoding 'gzip'"), "{msg}");
    }
    assert_eq!(http.get(format!("{base}/v1/maps/z")).send().await.unwrap().status(), 404);
    server.shutdown().await.unwrap();
}
