//! Issue 16, "Hostile clients": regression tests against the real server on loopback, one per defect.

use std::time::{Duration, Instant};

use scone::offline::scene::Scene;
use scone::server::proto::{self, frame::Source};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;
use tonic::Code;

use crate::common::{fixture, temp_dir};
use crate::raw::{body_bytes_read, http_answer, RawCodec};
use crate::service::{add_keyframes, clients, image_frame, keyframe_requests, multipart_keyframe, serve, settings};

/// The soft limit on open files of this process (client and server sockets both count).
fn open_file_limit() -> usize {
    let limits = std::fs::read_to_string("/proc/self/limits").unwrap_or_default();
    limits
        .lines()
        .find(|l| l.starts_with("Max open files"))
        .and_then(|l| l.split_whitespace().nth(3))
        .and_then(|n| n.parse().ok())
        .unwrap_or(1024)
}

/// Reads until the server closes the connection (EOF or reset); `None` if it is still open at `deadline`.
async fn closed_by(mut s: TcpStream, deadline: Instant) -> Option<Vec<u8>> {
    let mut got = Vec::new();
    let mut buf = [0u8; 4096];
    loop {
        let left = deadline.saturating_duration_since(Instant::now());
        match tokio::time::timeout(left, s.read(&mut buf)).await {
            Err(_) => return None,
            Ok(Ok(0)) | Ok(Err(_)) => return Some(got),
            Ok(Ok(n)) => got.extend_from_slice(&buf[..n]),
        }
    }
}

/// Issue 16, item 1: connections with nothing sent, a partial head or a partial body stayed open for more
/// than 130 s (2,000 half-open requests held 2,021 descriptors). With short test timeouts, 2,000 of them
/// (fewer if this process may not open enough files) are all closed within the timeouts, partial bodies
/// get 408, a keep-alive connection is closed once idle, silent gRPC connections (nothing, or only the
/// HTTP/2 preface) are closed too, and a normal request succeeds on both transports meanwhile.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn regression_slowloris_connections_are_closed() {
    let data = temp_dir("slowloris");
    let mut s = settings(&data);
    s.server.header_read_timeout_ms = 1_000;
    s.server.body_read_timeout_ms = 1_500;
    s.server.idle_timeout_ms = 2_000;
    s.server.max_connections = 4_096;
    let server = serve(s).await;
    // Each connection costs two descriptors here (client and server end); keep 300 for everything else.
    let n = 2_000.min(open_file_limit().saturating_sub(300) / 2);
    assert!(n >= 300, "the open-file limit {} leaves too few descriptors for this test", open_file_limit());
    let started = Instant::now();
    let mut slow = Vec::new();
    for i in 0..n {
        let mut c = TcpStream::connect(server.http_addr).await.unwrap();
        match i % 3 {
            0 => {}
            1 => c.write_all(b"POST /v1/describe HTTP/1.1\r\nhost: x\r\ncontent-type: ima").await.unwrap(),
            _ => c
                .write_all(b"POST /v1/describe HTTP/1.1\r\nhost: x\r\ncontent-type: image/png\r\ncontent-length: 1000\r\n\r\n\x89PNG")
                .await
                .unwrap(),
        }
        slow.push((i % 3, c));
    }
    let mut grpc_silent = Vec::new();
    for i in 0..50 {
        let mut c = TcpStream::connect(server.grpc_addr).await.unwrap();
        if i % 2 == 1 {
            // The HTTP/2 preface and no call: closed as idle.
            c.write_all(b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n").await.unwrap();
        }
        grpc_silent.push(c);
    }
    let mut keep_alive = TcpStream::connect(server.http_addr).await.unwrap();
    keep_alive.write_all(b"GET /healthz HTTP/1.1\r\nhost: x\r\n\r\n").await.unwrap();
    let mut first = [0u8; 64];
    let got = keep_alive.read(&mut first).await.unwrap();
    assert!(first[..got].starts_with(b"HTTP/1.1 200"), "{}", String::from_utf8_lossy(&first[..got]));

    // Meanwhile normal requests are served on both transports.
    let r = reqwest::get(format!("http://{}/healthz", server.http_addr)).await.unwrap();
    assert_eq!(r.status(), 200);
    let (mut maps, _) = clients(&server).await;
    maps.list_maps(proto::ListMapsRequest {}).await.unwrap();

    // Every slow connection is closed: by the header timeout (1 s), the body timeout (1.5 s, after a 408) or
    // the idle timeout (2 s); 8 s of slack for a loaded machine, far below the 130 s seen before.
    let deadline = started + Duration::from_secs(10);
    let waits: Vec<_> =
        slow.into_iter().map(|(kind, c)| tokio::spawn(async move { (kind, closed_by(c, deadline).await) })).collect();
    let mut still_open = 0;
    for w in waits {
        match w.await.unwrap() {
            (_, None) => still_open += 1,
            (2, Some(answer)) => {
                let text = String::from_utf8_lossy(&answer);
                assert!(text.starts_with("HTTP/1.1 408"), "a partial body got {text}");
                assert!(text.contains("\"DEADLINE_EXCEEDED\""), "{text}");
            }
            (_, Some(answer)) => assert!(answer.is_empty(), "{}", String::from_utf8_lossy(&answer)),
        }
    }
    assert_eq!(still_open, 0, "{still_open} of {n} slow HTTP connections still open after 10 s");
    for c in grpc_silent {
        assert!(closed_by(c, deadline).await.is_some(), "a silent gRPC connection is still open");
    }
    let rest = closed_by(keep_alive, deadline).await;
    assert!(rest.is_some(), "an idle keep-alive connection is still open");
    // Slots were given back: new connections are served.
    let r = reqwest::get(format!("http://{}/healthz", server.http_addr)).await.unwrap();
    assert_eq!(r.status(), 200);
    server.shutdown().await.unwrap();
}

/// Issue 16, item 1: nothing capped open connections. With `max_connections = 8` and eight silent
/// connections holding every slot, a ninth client waits in the backlog until the header timeout frees a
/// slot, then is served.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn regression_connections_beyond_the_cap_wait_for_a_slot() {
    let data = temp_dir("conncap");
    let mut s = settings(&data);
    s.server.max_connections = 8;
    s.server.header_read_timeout_ms = 1_500;
    let server = serve(s).await;
    let mut silent = Vec::new();
    for _ in 0..8 {
        silent.push(TcpStream::connect(server.http_addr).await.unwrap());
    }
    tokio::time::sleep(Duration::from_millis(200)).await;
    let t = Instant::now();
    let r = reqwest::get(format!("http://{}/healthz", server.http_addr)).await.unwrap();
    let waited = t.elapsed();
    assert_eq!(r.status(), 200);
    assert!(waited >= Duration::from_millis(800), "served after {waited:?} although every slot was taken");
    assert!(waited < Duration::from_secs(8), "served only after {waited:?}");
    drop(silent);
    server.shutdown().await.unwrap();
}

async fn error_of(r: reqwest::Response) -> (u16, String, String) {
    let status = r.status().as_u16();
    let ct = r.headers().get("content-type").map(|v| v.to_str().unwrap().to_string()).unwrap_or_default();
    let text = r.text().await.unwrap();
    assert!(ct.starts_with("application/json"), "{status} with content-type '{ct}': {text}");
    let v: serde_json::Value = serde_json::from_str(&text).unwrap_or_else(|e| panic!("{e}: {text}"));
    let code = v["error"]["code"].as_str().unwrap_or_else(|| panic!("no error envelope: {text}")).to_string();
    let message = v["error"]["message"].as_str().unwrap().to_string();
    (status, code, message)
}

/// Issue 16, item 2: on loopback without keys, a page of any site could create maps (`POST /v1/maps` as
/// text/plain or a form, a multipart keyframe), since such requests need no CORS preflight; OPTIONS was 405.
/// Writes from foreign origins are now 403, the documented content types are required (415), and
/// preflights are answered by the same policy.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn regression_cross_site_writes_are_refused_without_auth() {
    let data = temp_dir("csrf");
    let scene = Scene::load(&fixture("rendered")).unwrap();
    let server = serve(settings(&data)).await;
    let http = reqwest::Client::new();
    let base = format!("http://{}", server.http_addr);
    let own = format!("http://127.0.0.1:{}", server.http_addr.port());
    let evil = "https://evil.example";
    for ct in ["text/plain", "application/x-www-form-urlencoded"] {
        let r = http
            .post(format!("{base}/v1/maps"))
            .header("origin", evil)
            .header("content-type", ct)
            .body(r#"{"map_id": "pwned"}"#)
            .send()
            .await
            .unwrap();
        assert!(r.headers().get("access-control-allow-origin").is_none());
        let (status, code, message) = error_of(r).await;
        assert_eq!((status, code.as_str()), (403, "PERMISSION_DENIED"), "{message}");
        assert!(message.contains(evil), "{message}");
    }
    let r = http.post(format!("{base}/v1/maps")).json(&serde_json::json!({"map_id": "m"})).send().await.unwrap();
    assert_eq!(r.status(), 201);
    let r = http
        .post(format!("{base}/v1/maps/m/keyframes"))
        .header("origin", evil)
        .multipart(multipart_keyframe(&scene, 0))
        .send()
        .await
        .unwrap();
    assert_eq!(error_of(r).await.0, 403);
    let r = http.delete(format!("{base}/v1/maps/m")).header("origin", "null").send().await.unwrap();
    assert_eq!(error_of(r).await.0, 403);
    let listed: serde_json::Value = http.get(format!("{base}/v1/maps")).send().await.unwrap().json().await.unwrap();
    assert_eq!(listed["maps"].as_array().unwrap().len(), 1, "{listed}");
    assert_eq!(listed["maps"][0]["keyframes"], 0, "{listed}");

    // Without an Origin the content type is still checked: text/plain is not JSON.
    let r = http
        .post(format!("{base}/v1/maps"))
        .header("content-type", "text/plain")
        .body(r#"{"map_id": "plain"}"#)
        .send()
        .await
        .unwrap();
    let (status, code, message) = error_of(r).await;
    assert_eq!((status, code.as_str()), (415, "UNSUPPORTED_MEDIA_TYPE"), "{message}");
    assert!(message.contains("application/json"), "{message}");
    let r = http
        .post(format!("{base}/v1/maps/m/import"))
        .header("content-type", "application/x-www-form-urlencoded")
        .body("a=b")
        .send()
        .await
        .unwrap();
    assert_eq!(error_of(r).await.0, 415);

    // Preflights: the listener's own origin gets the CORS headers, a foreign one 403 and none.
    let preflight = |origin: &str| {
        http.request(reqwest::Method::OPTIONS, format!("{base}/v1/maps"))
            .header("origin", origin)
            .header("access-control-request-method", "POST")
            .header("access-control-request-headers", "content-type")
            .send()
    };
    // Any 2xx lets the browser go on (tower-http's CorsLayer answers 200).
    let r = preflight(&own).await.unwrap();
    assert!(r.status().is_success(), "{}", r.status());
    assert_eq!(r.headers()["access-control-allow-origin"], own.as_str());
    assert!(r.headers()["access-control-allow-methods"].to_str().unwrap().contains("POST"));
    assert!(r.headers()["access-control-allow-headers"].to_str().unwrap().contains("content-type"));
    let r = preflight(&format!("http://localhost:{}", server.http_addr.port())).await.unwrap();
    assert!(r.status().is_success(), "{}", r.status());
    assert_eq!(r.headers()["access-control-allow-origin"], format!("http://localhost:{}", server.http_addr.port()));
    let r = preflight(evil).await.unwrap();
    assert!(r.headers().get("access-control-allow-origin").is_none());
    assert_eq!(error_of(r).await.0, 403);

    // The own origin may write and reads its answers; a foreign origin may read (no CORS header, so its
    // page cannot see the answer).
    let r = http
        .post(format!("{base}/v1/maps"))
        .header("origin", &own)
        .json(&serde_json::json!({"map_id": "mine"}))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 201);
    assert_eq!(r.headers()["access-control-allow-origin"], own.as_str());
    let r = http.get(format!("{base}/v1/maps")).header("origin", evil).send().await.unwrap();
    assert_eq!(r.status(), 200);
    assert!(r.headers().get("access-control-allow-origin").is_none());
    server.shutdown().await.unwrap();
}

/// Issue 16, item 2: `server.allowed_origins` replaces the default, and `*` allows every origin.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn regression_configured_origins_replace_the_listeners_own() {
    let data = temp_dir("origins");
    let mut s = settings(&data);
    s.server.allowed_origins = vec!["https://app.example.com".into()];
    let server = serve(s).await;
    let http = reqwest::Client::new();
    let base = format!("http://{}", server.http_addr);
    let create = |origin: String, id: &str| {
        http.post(format!("{base}/v1/maps")).header("origin", origin).json(&serde_json::json!({"map_id": id})).send()
    };
    assert_eq!(create("https://app.example.com".into(), "a").await.unwrap().status(), 201);
    let own = format!("http://127.0.0.1:{}", server.http_addr.port());
    assert_eq!(create(own, "b").await.unwrap().status(), 403);
    server.shutdown().await.unwrap();
}

/// Issue 16, item 4: bytes that are no image, sent raw to HTTP Localize or as a multipart keyframe image,
/// were reported as an intrinsics error (`Camera { ..., width: 0, ... } needs finite, positive focal
/// lengths`) while Describe said "unsupported image format". The image error comes first everywhere.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn regression_undecodable_images_are_reported_as_images_not_intrinsics() {
    let data = temp_dir("undecodable");
    let scene = Scene::load(&fixture("rendered")).unwrap();
    let server = serve(settings(&data)).await;
    let http = reqwest::Client::new();
    let base = format!("http://{}", server.http_addr);
    http.post(format!("{base}/v1/maps")).json(&serde_json::json!({"map_id": "m"})).send().await.unwrap();
    let junk = b"this is not an image at all".to_vec();
    let expect_image_error = |(status, code, message): (u16, String, String)| {
        assert_eq!((status, code.as_str()), (400, "INVALID_ARGUMENT"), "{message}");
        assert!(message.contains("unsupported image format"), "{message}");
        assert!(!message.contains("intrinsics") && !message.contains("Camera"), "{message}");
    };
    let r = http.post(format!("{base}/v1/describe")).header("content-type", "image/png").body(junk.clone());
    expect_image_error(error_of(r.send().await.unwrap()).await);
    let r = http
        .post(format!("{base}/v1/maps/m/localize?fx=250&fy=250&cx=159.5&cy=119.5"))
        .header("content-type", "image/png")
        .body(junk.clone());
    expect_image_error(error_of(r.send().await.unwrap()).await);
    let c = scene.camera;
    let request = serde_json::json!({
        "keyframe_id": 1,
        "pose": {"tx": 0, "ty": 0, "tz": 0, "qx": 0, "qy": 0, "qz": 0, "qw": 1},
        "intrinsics": {"fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy},
    });
    let form = reqwest::multipart::Form::new()
        .text("request", request.to_string())
        .part("image", reqwest::multipart::Part::bytes(junk.clone()).mime_str("image/png").unwrap());
    let r = http.post(format!("{base}/v1/maps/m/keyframes")).multipart(form);
    expect_image_error(error_of(r.send().await.unwrap()).await);
    // gRPC, with intrinsics that lack a size: the image is still the first thing wrong.
    let (_, mut matching) = clients(&server).await;
    let e = matching
        .localize(proto::LocalizeRequest {
            map_id: "m".into(),
            frame: Some(proto::Frame {
                source: Some(Source::Image(proto::Image { data: junk })),
                intrinsics: Some(proto::Intrinsics {
                    fx: 250.0,
                    fy: 250.0,
                    cx: 160.0,
                    cy: 120.0,
                    width: 0,
                    height: 0,
                    ..Default::default()
                }),
            }),
            prior: None,
            pose_convention: 0,
        })
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument);
    assert!(e.message().contains("unsupported image format"), "{e:?}");
    server.shutdown().await.unwrap();
}

/// Issue 16, item 5: two `request` parts or two `image` parts were accepted and the last won.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn regression_repeated_multipart_parts_are_refused() {
    let data = temp_dir("parts");
    let scene = Scene::load(&fixture("rendered")).unwrap();
    let server = serve(settings(&data)).await;
    let http = reqwest::Client::new();
    let base = format!("http://{}", server.http_addr);
    http.post(format!("{base}/v1/maps")).json(&serde_json::json!({"map_id": "m"})).send().await.unwrap();
    let png = || reqwest::multipart::Part::bytes(std::fs::read(&scene.frames[0].rgb).unwrap()).mime_str("image/png");
    let form = reqwest::multipart::Form::new().part("image", png().unwrap()).part("image", png().unwrap());
    let (status, _, message) =
        error_of(http.post(format!("{base}/v1/describe")).multipart(form).send().await.unwrap()).await;
    assert_eq!(status, 400, "{message}");
    assert!(message.contains("'image'") && message.contains("more than once"), "{message}");
    let form = multipart_keyframe(&scene, 0).text("request", r#"{"keyframe_id": 99}"#);
    let (status, _, message) =
        error_of(http.post(format!("{base}/v1/maps/m/keyframes")).multipart(form).send().await.unwrap()).await;
    assert_eq!(status, 400, "{message}");
    assert!(message.contains("'request'") && message.contains("more than once"), "{message}");
    let info: serde_json::Value = http.get(format!("{base}/v1/maps/m")).send().await.unwrap().json().await.unwrap();
    assert_eq!(info["keyframes"], 0, "{info}");
    server.shutdown().await.unwrap();
}

/// Issue 16, item 6: some 400s were text/plain from axum's extractors (`?fx=abc`: "Failed to deserialize
/// query string", `DELETE /v1/maps/m/keyframes/abc`: "Invalid URL"). Every error is the JSON envelope,
/// unknown routes and methods included.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn regression_every_http_error_is_a_json_envelope() {
    let data = temp_dir("envelope");
    let server = serve(settings(&data)).await;
    let http = reqwest::Client::new();
    let base = format!("http://{}", server.http_addr);
    http.post(format!("{base}/v1/maps")).json(&serde_json::json!({"map_id": "m"})).send().await.unwrap();
    let png = std::fs::read(fixture("rendered/rgb/000000.png")).unwrap();
    let r =
        http.post(format!("{base}/v1/maps/m/localize?fx=abc&cx=1&cy=1")).header("content-type", "image/png").body(png);
    let (status, code, message) = error_of(r.send().await.unwrap()).await;
    assert_eq!((status, code.as_str()), (400, "INVALID_ARGUMENT"));
    assert!(message.contains("fx") && message.contains("'abc' is not a number"), "{message}");
    let (status, code, message) =
        error_of(http.delete(format!("{base}/v1/maps/m/keyframes/abc")).send().await.unwrap()).await;
    assert_eq!((status, code.as_str()), (400, "INVALID_ARGUMENT"));
    assert!(message.contains("keyframe_id") && message.contains("'abc'"), "{message}");
    let (status, code, _) = error_of(http.get(format!("{base}/v1/nothing-here")).send().await.unwrap()).await;
    assert_eq!((status, code.as_str()), (404, "NOT_FOUND"));
    let (status, code, _) = error_of(http.put(format!("{base}/v1/maps")).send().await.unwrap()).await;
    assert_eq!((status, code.as_str()), (405, "METHOD_NOT_ALLOWED"));
    // Issue 42: the console's address typed with a trailing slash was a JSON 404; it is the console.
    let no_follow = reqwest::Client::builder().redirect(reqwest::redirect::Policy::none()).build().unwrap();
    let r = no_follow.get(format!("{base}/ui/?map=m")).send().await.unwrap();
    assert_eq!(r.status(), 308);
    assert_eq!(r.headers()["location"], "/ui?map=m");
    let page = http.get(format!("{base}/ui/")).send().await.unwrap();
    assert_eq!(page.status(), 200);
    assert!(page.headers()["content-type"].to_str().unwrap().starts_with("text/html"));
    server.shutdown().await.unwrap();
}

/// Issue 16, item 7: messages showed Rust debug output (`Camera { fx: 0.0, ... }`). Clients get the API's
/// words. (The server paths in a held-back map's reason: `durability::regression_held_back_reason_...`.)
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn regression_error_messages_carry_no_rust_debug_output() {
    let data = temp_dir("words");
    let scene = Scene::load(&fixture("rendered")).unwrap();
    let server = serve(settings(&data)).await;
    let http = reqwest::Client::new();
    let base = format!("http://{}", server.http_addr);
    http.post(format!("{base}/v1/maps")).json(&serde_json::json!({"map_id": "m"})).send().await.unwrap();
    let png = std::fs::read(&scene.frames[0].rgb).unwrap();
    let r = http
        .post(format!("{base}/v1/maps/m/localize?fx=-5&cx=160&cy=120"))
        .header("content-type", "image/png")
        .body(png);
    let (status, _, message) = error_of(r.send().await.unwrap()).await;
    assert_eq!(status, 400);
    assert_eq!(message, "invalid frame.intrinsics: fx must be finite and positive (got -5)");
    let (_, mut matching) = clients(&server).await;
    let mut frame = image_frame(&scene.frames[0].rgb, &scene.camera);
    frame.intrinsics.as_mut().unwrap().fy = f64::NAN;
    let e = matching
        .localize(proto::LocalizeRequest { map_id: "m".into(), frame: Some(frame), prior: None, pose_convention: 0 })
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument);
    assert_eq!(e.message(), "invalid frame.intrinsics: fy must be finite and positive (got NaN)");
    server.shutdown().await.unwrap();
}

/// Issue 16, item 8: a KeypointSet of 100000 x 100000 was accepted by Describe and Localize; the image
/// limits (width, height, pixels) now hold for keypoint input too, on both transports.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn regression_keypoint_sets_are_held_to_the_image_limits() {
    let data = temp_dir("kpsize");
    let server = serve(settings(&data)).await;
    let (mut maps, mut matching) = clients(&server).await;
    maps.create_map(proto::CreateMapRequest { map_id: "m".into() }).await.unwrap();
    let huge = proto::KeypointSet {
        keypoints: vec![proto::Keypoint { x: 50_000.0, y: 50_000.0, size: 7.0, angle: 0.0, response: 1.0, octave: 0 }],
        descriptors: vec![0u8; 64],
        width: 100_000,
        height: 100_000,
        model_id: String::new(),
        context: Vec::new(),
    };
    let frame = |intrinsics| proto::Frame { source: Some(Source::Keypoints(huge.clone())), intrinsics };
    let e = matching.describe(proto::DescribeRequest { frame: Some(frame(None)) }).await.unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument);
    assert!(e.message().contains("too large") && e.message().contains("width is 100000"), "{e:?}");
    let cam = proto::Intrinsics {
        fx: 500.0,
        fy: 500.0,
        cx: 50_000.0,
        cy: 50_000.0,
        width: 100_000,
        height: 100_000,
        ..Default::default()
    };
    let e = matching
        .localize(proto::LocalizeRequest {
            map_id: "m".into(),
            frame: Some(frame(Some(cam))),
            prior: None,
            pose_convention: 0,
        })
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument);
    assert!(e.message().contains("too large"), "{e:?}");
    // A narrow strip within the width and height limits but over the pixel limit.
    let http = reqwest::Client::new();
    let body = serde_json::json!({"frame": {"keypoints": {"width": 4096, "height": 4000,
        "keypoints": [{"x": 10.0, "y": 10.0, "size": 7.0, "angle": 0.0}], "descriptors_base64": base64_zeros(64)}}});
    let r = http.post(format!("http://{}/v1/describe", server.http_addr)).json(&body).send().await.unwrap();
    let (status, _, message) = error_of(r).await;
    assert_eq!(status, 400);
    assert!(message.contains("pixels is 16384000"), "{message}");
    server.shutdown().await.unwrap();
}

fn base64_zeros(n: usize) -> String {
    // Base64 of n zero bytes, n a multiple of 3 or padded.
    let full = "A".repeat(n / 3 * 4);
    match n % 3 {
        0 => full,
        1 => full + "AA==",
        _ => full + "AAA=",
    }
}

/// Issue 16, item 9: HTTP Localize took intrinsics inside `frame` and at the top level and silently used
/// the top level when they differed. A conflict is 400 naming both; identical values are accepted.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn regression_conflicting_intrinsics_are_refused() {
    let data = temp_dir("conflict");
    let server = serve(settings(&data)).await;
    let http = reqwest::Client::new();
    let base = format!("http://{}", server.http_addr);
    http.post(format!("{base}/v1/maps")).json(&serde_json::json!({"map_id": "m"})).send().await.unwrap();
    let png = std::fs::read(fixture("rendered/rgb/000000.png")).unwrap();
    let localize = |inner: serde_json::Value, outer: serde_json::Value| {
        let request = serde_json::json!({"frame": {"intrinsics": inner}, "intrinsics": outer});
        let form = reqwest::multipart::Form::new()
            .text("request", request.to_string())
            .part("image", reqwest::multipart::Part::bytes(png.clone()).mime_str("image/png").unwrap());
        http.post(format!("{base}/v1/maps/m/localize")).multipart(form).send()
    };
    let a = serde_json::json!({"fx": 250.0, "fy": 250.0, "cx": 159.5, "cy": 119.5});
    let b = serde_json::json!({"fx": 300.0, "fy": 300.0, "cx": 159.5, "cy": 119.5});
    let (status, _, message) = error_of(localize(a.clone(), b).await.unwrap()).await;
    assert_eq!(status, 400, "{message}");
    assert!(message.contains("frame.intrinsics and intrinsics"), "{message}");
    let r = localize(a.clone(), a).await.unwrap();
    assert_eq!(r.status(), 200, "{}", r.text().await.unwrap());
    // The query string is a third place; it must agree too.
    let r = http
        .post(format!("{base}/v1/maps/m/localize?fx=260&cx=159.5&cy=119.5"))
        .json(&serde_json::json!({"frame": {"image_base64": base64_of(&png),
                                            "intrinsics": {"fx": 250.0, "fy": 250.0, "cx": 159.5, "cy": 119.5}}}))
        .send()
        .await
        .unwrap();
    let (status, _, message) = error_of(r).await;
    assert_eq!(status, 400, "{message}");
    assert!(message.contains("frame.intrinsics") && message.contains("query string"), "{message}");
    server.shutdown().await.unwrap();
}

fn base64_of(bytes: &[u8]) -> String {
    use base64::Engine;
    base64::engine::general_purpose::STANDARD.encode(bytes)
}

/// Issue 16, item 10: a kill -9 after all bytes of an ImportMap arrived left the map complete while the
/// client got UNAVAILABLE, and the retry got ALREADY_EXISTS. Importing identical content again succeeds and
/// returns the map, over gRPC and HTTP; other content under the id stays ALREADY_EXISTS / 409.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn regression_import_is_idempotent_for_identical_content() {
    let data = temp_dir("reimport");
    let scene = Scene::load(&fixture("rendered")).unwrap();
    let server = serve(settings(&data)).await;
    let (mut maps, _) = clients(&server).await;
    maps.create_map(proto::CreateMapRequest { map_id: "src".into() }).await.unwrap();
    add_keyframes(&mut maps, keyframe_requests("src", &scene, &[0, 4]), None).await;
    let export = |maps: &mut scone::server::proto::maps_client::MapsClient<tonic::transport::Channel>, id: &str| {
        let mut maps = maps.clone();
        let id = id.to_string();
        async move {
            let mut s = maps.export_map(proto::ExportMapRequest { map_id: id }).await.unwrap().into_inner();
            let mut bytes = Vec::new();
            while let Some(c) = s.message().await.unwrap() {
                bytes.extend(c.data);
            }
            bytes
        }
    };
    let file = export(&mut maps, "src").await;
    let chunks = |id: &str, bytes: &[u8]| {
        let chunks: Vec<proto::MapChunk> = bytes
            .chunks(50_000)
            .enumerate()
            .map(|(i, c)| proto::MapChunk { map_id: if i == 0 { id.into() } else { String::new() }, data: c.to_vec() })
            .collect();
        tokio_stream::iter(chunks)
    };
    let first = maps.import_map(chunks("copy", &file)).await.unwrap().into_inner();
    let again = maps.import_map(chunks("copy", &file)).await.unwrap().into_inner();
    assert_eq!(first, again);
    // Also after a restart (the map then comes from disk, as after the crash of the issue).
    server.shutdown().await.unwrap();
    let server = serve(settings(&data)).await;
    let (mut maps, _) = clients(&server).await;
    let after_restart = maps.import_map(chunks("copy", &file)).await.unwrap().into_inner();
    assert_eq!(first, after_restart);
    let http = reqwest::Client::new();
    let base = format!("http://{}", server.http_addr);
    let import_http = |id: &str, bytes: Vec<u8>| {
        http.post(format!("{base}/v1/maps/{id}/import"))
            .header("content-type", "application/octet-stream")
            .body(bytes)
            .send()
    };
    for _ in 0..2 {
        let r = import_http("copy", file.clone()).await.unwrap();
        assert_eq!(r.status(), 201);
        let info: serde_json::Value = r.json().await.unwrap();
        assert_eq!(info["version"], first.version, "{info}");
    }
    // Different content under a taken id: ALREADY_EXISTS, and the map is left as it was.
    add_keyframes(&mut maps, keyframe_requests("src", &scene, &[8]), None).await;
    let changed = export(&mut maps, "src").await;
    let e = maps.import_map(chunks("copy", &changed)).await.unwrap_err();
    assert_eq!(e.code(), Code::AlreadyExists, "{e:?}");
    let (status, code, _) = error_of(import_http("copy", changed).await.unwrap()).await;
    assert_eq!((status, code.as_str()), (409, "ALREADY_EXISTS"));
    let info = maps.get_map(proto::GetMapRequest { map_id: "copy".into() }).await.unwrap().into_inner();
    assert_eq!(info, first);
    server.shutdown().await.unwrap();
}

/// Issue 16, item 3: with 24-32 clients that do not back off, answered Localize throughput fell to 45-60 %
/// of the 2-client figure: every refusal cost the server a body read (HTTP) or a message read and decode
/// (gRPC). With one worker, no waiting slot and a slow job holding the pool, a flood is now refused before
/// any body is read: HTTP requests that declare 8 MiB and send only the first 64 KiB get their 429 (with
/// Retry-After, in the JSON envelope) although the rest never comes, gRPC calls whose 4 MiB message is not
/// even protobuf get RESOURCE_EXHAUSTED (decoding them would have been INTERNAL), and no byte of the flood
/// is counted as read; a refused request with a small body keeps its keep-alive connection. Once the slow
/// job is done it has its answer, and requests are served again.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn regression_storm_is_refused_before_bodies_are_read() {
    let data = temp_dir("storm");
    let mut s = settings(&data);
    s.workers.threads = 1;
    s.workers.queue = 0;
    let server = serve(s).await;
    let (release, gate) = std::sync::mpsc::channel::<()>();
    let app = std::sync::Arc::clone(&server.app);
    let slow = tokio::spawn(async move {
        app.pool.run(Instant::now() + Duration::from_secs(60), move || gate.recv_timeout(Duration::from_secs(50))).await
    });
    while server.app.pool.stats().running.load(std::sync::atomic::Ordering::Relaxed) == 0 {
        tokio::time::sleep(Duration::from_millis(1)).await;
    }
    let (http_before, grpc_before) = (body_bytes_read(&server, "http").await, body_bytes_read(&server, "grpc").await);

    // Before, the server waited for each 8 MiB body (body_read_timeout_ms, 60 s) before refusing it.
    const DECLARED: usize = 8 << 20;
    const SENT: usize = 64 << 10;
    let started = Instant::now();
    let deadline = started + Duration::from_secs(10);
    let flood: Vec<_> = (0..16)
        .map(|_| {
            let addr = server.http_addr;
            tokio::spawn(async move {
                let mut c = TcpStream::connect(addr).await.unwrap();
                let head = format!(
                    "POST /v1/describe HTTP/1.1\r\nhost: x\r\ncontent-type: image/jpeg\r\ncontent-length: {DECLARED}\r\n\r\n"
                );
                c.write_all(head.as_bytes()).await.unwrap();
                // The server may already have answered and closed: a broken pipe is fine.
                let _ = c.write_all(&vec![0xd8; SENT]).await;
                http_answer(&mut c, deadline).await
            })
        })
        .collect();
    for f in flood {
        let answer = f.await.unwrap().expect("no answer within 10 s: the server waited for the body");
        let lower = answer.to_ascii_lowercase();
        assert!(answer.starts_with("HTTP/1.1 429"), "{answer}");
        assert!(lower.contains("\r\nretry-after: 1\r\n"), "{answer}");
        assert!(lower.contains("\r\nconnection: close\r\n"), "the unread body must end the connection: {answer}");
        assert!(lower.contains("content-type: application/json"), "{answer}");
        assert!(answer.contains("\"RESOURCE_EXHAUSTED\""), "{answer}");
    }

    let channel = tonic::transport::Endpoint::from_shared(format!("http://{}", server.grpc_addr))
        .unwrap()
        .connect()
        .await
        .unwrap();
    let calls: Vec<_> = (0..8)
        .map(|_| {
            let mut grpc = tonic::client::Grpc::new(channel.clone());
            tokio::spawn(async move {
                grpc.ready().await.unwrap();
                let path = tonic::codegen::http::uri::PathAndQuery::from_static("/scone.v1.Matching/Describe");
                grpc.unary(tonic::Request::new(vec![0xff; 4 << 20]), path, RawCodec).await
            })
        })
        .collect();
    for c in calls {
        let e = c.await.unwrap().expect_err("refused");
        assert_eq!(e.code(), Code::ResourceExhausted, "{e:?}");
        assert_eq!(e.metadata().get("retry-after").and_then(|v| v.to_str().ok()), Some("1"));
    }
    // A well-formed call is refused the same way.
    let (_, mut matching) = clients(&server).await;
    let big = proto::Frame { source: Some(Source::Image(proto::Image { data: vec![0; 4 << 20] })), intrinsics: None };
    let e = matching.describe(proto::DescribeRequest { frame: Some(big) }).await.unwrap_err();
    assert_eq!(e.code(), Code::ResourceExhausted, "{e:?}");
    let refused_in = started.elapsed();
    assert!(refused_in < Duration::from_secs(8), "the flood took {refused_in:?} to refuse");
    assert_eq!(body_bytes_read(&server, "http").await, http_before, "HTTP body bytes were read during the flood");
    assert_eq!(body_bytes_read(&server, "grpc").await, grpc_before, "gRPC message bytes were read during the flood");
    assert!(server.app.pool.stats().rejected.load(std::sync::atomic::Ordering::Relaxed) >= 25);
    let metrics = reqwest::get(format!("http://{}/metrics", server.http_addr)).await.unwrap().text().await.unwrap();
    assert!(metrics.contains("# TYPE scone_pool_rejected counter\n"), "{metrics}");
    let rejected = metrics.lines().find_map(|l| l.strip_prefix("scone_pool_rejected_total "));
    assert!(rejected.is_some_and(|v| v.trim().parse::<u64>().unwrap() >= 25), "{metrics}");

    // A refused HTTP/1.1 request with a small body keeps its connection: the body is discarded after the
    // answer and the next request on the same connection is served.
    let mut c = TcpStream::connect(server.http_addr).await.unwrap();
    let small = 100 << 10;
    let head =
        format!("POST /v1/describe HTTP/1.1\r\nhost: x\r\ncontent-type: image/jpeg\r\ncontent-length: {small}\r\n\r\n");
    c.write_all(head.as_bytes()).await.unwrap();
    c.write_all(&vec![0xd8; small]).await.unwrap();
    let deadline = Instant::now() + Duration::from_secs(10);
    let answer = http_answer(&mut c, deadline).await.expect("an answer");
    assert!(answer.starts_with("HTTP/1.1 429"), "{answer}");
    assert!(!answer.to_ascii_lowercase().contains("connection: close"), "{answer}");
    c.write_all(b"GET /healthz HTTP/1.1\r\nhost: x\r\n\r\n").await.unwrap();
    let answer = http_answer(&mut c, deadline).await.expect("the connection was kept");
    assert!(answer.starts_with("HTTP/1.1 200"), "{answer}");

    // The slow job gets its answer; then the pool takes requests again, on both transports.
    release.send(()).unwrap();
    assert_eq!(slow.await.unwrap(), Ok(Ok(())));
    let image = std::fs::read(fixture("coffee-640x480.jpg")).unwrap();
    let r = reqwest::Client::new()
        .post(format!("http://{}/v1/describe", server.http_addr))
        .header("content-type", "image/jpeg")
        .body(image.clone())
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    assert!(body_bytes_read(&server, "http").await >= http_before + image.len() as u64);
    let frame = proto::Frame { source: Some(Source::Image(proto::Image { data: image })), intrinsics: None };
    matching.describe(proto::DescribeRequest { frame: Some(frame) }).await.unwrap();
    assert!(body_bytes_read(&server, "grpc").await > grpc_before);
    server.shutdown().await.unwrap();
}
