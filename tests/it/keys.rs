//! Issue 42: a request's key is checked before its body is read, on every route that takes one, and a
//! request looks its map up once.

use std::time::{Duration, Instant};

use scone::offline::scene::Scene;
use scone::server::proto;
use tokio::io::AsyncWriteExt;
use tokio::net::TcpStream;
use tonic::Code;

use crate::common::{fixture, temp_dir};
use crate::raw::{body_bytes_read, http_answer, RawCodec};
use crate::service::{
    add_keyframes, add_keyframes_http, clients, image_frame, keyed, keyframe_requests, serve, settings, READ_KEY,
    WRITE_KEY,
};

/// Every HTTP route that takes a body, with a content type it accepts.
const BODY_ROUTES: &[(&str, &str)] = &[
    ("/v1/describe", "image/jpeg"),
    ("/v1/describe", "application/json"),
    ("/v1/match", "application/json"),
    ("/v1/match", "multipart/form-data; boundary=x"),
    ("/v1/maps/m/localize", "image/jpeg"),
    ("/v1/maps/m/localize", "application/json"),
    ("/v1/maps", "application/json"),
    ("/v1/maps/m/keyframes", "application/json"),
    ("/v1/maps/m/keyframes", "multipart/form-data; boundary=x"),
    ("/v1/maps/m/merge", "application/json"),
    ("/v1/maps/m/import", "application/octet-stream"),
];

/// Every `scone.v1` method, as a path.
const GRPC_METHODS: &[&str] = &[
    "/scone.v1.Maps/CreateMap",
    "/scone.v1.Maps/GetMap",
    "/scone.v1.Maps/ListMaps",
    "/scone.v1.Maps/DeleteMap",
    "/scone.v1.Maps/AddKeyframes",
    "/scone.v1.Maps/RemoveKeyframe",
    "/scone.v1.Maps/MergeMaps",
    "/scone.v1.Maps/ExportMap",
    "/scone.v1.Maps/ImportMap",
    "/scone.v1.Matching/Describe",
    "/scone.v1.Matching/MatchPair",
    "/scone.v1.Matching/Localize",
];

/// Sends a request head declaring `declared` body bytes (with `key` when given) and the first 64 KiB of the
/// body, and returns the answer, which must come without the rest of the body.
async fn refused_head(
    addr: std::net::SocketAddr,
    route: &str,
    content_type: &str,
    declared: usize,
    key: Option<&str>,
) -> String {
    let mut c = TcpStream::connect(addr).await.unwrap();
    let key = key.map(|k| format!("x-api-key: {k}\r\n")).unwrap_or_default();
    let head = format!(
        "POST {route} HTTP/1.1\r\nhost: x\r\ncontent-type: {content_type}\r\n{key}content-length: {declared}\r\n\r\n"
    );
    c.write_all(head.as_bytes()).await.unwrap();
    // The server may already have answered and closed: a broken pipe is fine.
    let _ = c.write_all(&vec![b'{'; 64 << 10]).await;
    let deadline = Instant::now() + Duration::from_secs(5);
    http_answer(&mut c, deadline).await.unwrap_or_else(|| panic!("{route} ({content_type}): no answer within 5 s"))
}

/// Issue 42: with keys configured and no key sent, a 30 MB body was read in full before the 401 on
/// `/v1/describe`, `/v1/match` and `/v1/maps/m/localize`, and `POST /v1/maps` read it and answered 400 for
/// the body. Now every route that takes a body answers 401 (or 403 for a read key on a write) from the
/// request head alone, whether the declared body is under the limit (30 MB) or over it (40 MiB), and no byte
/// of any of those bodies is read; over gRPC, every method answers UNAUTHENTICATED to a 4 MiB message that
/// is not even protobuf, without reading it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn regression_keys_are_checked_before_bodies_are_read() {
    let data = temp_dir("keys-before-bodies");
    let mut s = settings(&data);
    s.auth.write_keys = vec![WRITE_KEY.into()];
    s.auth.read_keys = vec![READ_KEY.into()];
    let server = serve(s).await;
    let (http_before, grpc_before) = (body_bytes_read(&server, "http").await, body_bytes_read(&server, "grpc").await);
    for &(route, content_type) in BODY_ROUTES {
        for declared in [30_000_000, 40 << 20] {
            let answer = refused_head(server.http_addr, route, content_type, declared, None).await;
            assert!(answer.starts_with("HTTP/1.1 401"), "{route} ({content_type}, {declared} bytes): {answer}");
            assert!(answer.contains("\"UNAUTHENTICATED\""), "{answer}");
            assert!(answer.to_ascii_lowercase().contains("\r\nconnection: close\r\n"), "{answer}");
        }
    }
    for route in ["/v1/maps", "/v1/maps/m/keyframes", "/v1/maps/m/merge", "/v1/maps/m/import"] {
        let content_type = if route.ends_with("import") { "application/octet-stream" } else { "application/json" };
        let answer = refused_head(server.http_addr, route, content_type, 30_000_000, Some(READ_KEY)).await;
        assert!(answer.starts_with("HTTP/1.1 403"), "{route}: {answer}");
        assert!(answer.contains("\"PERMISSION_DENIED\""), "{answer}");
    }
    assert_eq!(body_bytes_read(&server, "http").await, http_before, "HTTP body bytes were read before the key check");

    let channel = tonic::transport::Endpoint::from_shared(format!("http://{}", server.grpc_addr))
        .unwrap()
        .connect()
        .await
        .unwrap();
    for &method in GRPC_METHODS {
        let mut grpc = tonic::client::Grpc::new(channel.clone());
        grpc.ready().await.unwrap();
        let path = tonic::codegen::http::uri::PathAndQuery::from_static(method);
        let e = grpc.unary(tonic::Request::new(vec![0xff; 4 << 20]), path, RawCodec).await.unwrap_err();
        assert_eq!(e.code(), Code::Unauthenticated, "{method}: {e:?}");
    }
    assert_eq!(
        body_bytes_read(&server, "grpc").await,
        grpc_before,
        "gRPC message bytes were read before the key check"
    );

    // With the key, the same server reads bodies and answers.
    let (mut maps, _) = clients(&server).await;
    maps.create_map(keyed(proto::CreateMapRequest { map_id: "m".into() }, WRITE_KEY)).await.unwrap();
    let e = maps.create_map(keyed(proto::CreateMapRequest { map_id: "n".into() }, READ_KEY)).await.unwrap_err();
    assert_eq!(e.code(), Code::PermissionDenied, "{e:?}");
    assert!(body_bytes_read(&server, "grpc").await > grpc_before);
    server.shutdown().await.unwrap();
}

/// The map cache's lookups so far (hits and misses) and its freshness checks.
fn lookups(server: &scone::server::Running) -> (u64, u64) {
    let h = server.app.service.holdings();
    let count = |name: &str| h.cache_events.iter().find(|(n, _)| *n == name).map_or(0, |(_, c)| *c);
    (count("hit") + count("miss"), count("check"))
}

/// Issue 42: a request's map was looked up 2 to 4 times (the transport loaded it and dropped it, the service
/// looked it up again), so with maps loaded on demand and `freshness_ms = 0` a Localize made two freshness
/// checks. Now Localize, a keyframe write, GetMap and RemoveKeyframe each make one lookup and one check, over
/// both transports.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn regression_a_request_looks_its_map_up_once() {
    let data = temp_dir("one-lookup");
    let scene = Scene::load(&fixture("rendered")).unwrap();
    let mut s = settings(&data);
    s.store.cache.lazy = Some(true);
    s.store.cache.freshness_ms = 0;
    let server = serve(s).await;
    let (mut maps, mut matching) = clients(&server).await;
    maps.create_map(proto::CreateMapRequest { map_id: "m".into() }).await.unwrap();
    let once = |before: (u64, u64), after: (u64, u64), what: &str| {
        assert_eq!(after.0 - before.0, 1, "{what}: map lookups");
        assert_eq!(after.1 - before.1, 1, "{what}: freshness checks");
    };

    let before = lookups(&server);
    add_keyframes(&mut maps, keyframe_requests("m", &scene, &[0]), None).await;
    once(before, lookups(&server), "gRPC AddKeyframes (one keyframe)");
    let http = reqwest::Client::new();
    let base = format!("http://{}", server.http_addr);
    let before = lookups(&server);
    add_keyframes_http(&http, &base, "m", &scene, &[4]).await;
    once(before, lookups(&server), "HTTP keyframe");

    let query = proto::LocalizeRequest {
        map_id: "m".into(),
        frame: Some(image_frame(&scene.frames[2].rgb, &scene.camera)),
        ..Default::default()
    };
    let before = lookups(&server);
    let r = matching.localize(query).await.unwrap().into_inner();
    assert!(r.localized);
    once(before, lookups(&server), "gRPC Localize");
    let c = scene.camera;
    let before = lookups(&server);
    let r = http
        .post(format!("{base}/v1/maps/m/localize?fx={}&fy={}&cx={}&cy={}", c.fx, c.fy, c.cx, c.cy))
        .header("content-type", "image/png")
        .body(std::fs::read(&scene.frames[2].rgb).unwrap())
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200, "{}", r.text().await.unwrap());
    once(before, lookups(&server), "HTTP Localize");

    let before = lookups(&server);
    maps.get_map(proto::GetMapRequest { map_id: "m".into() }).await.unwrap();
    once(before, lookups(&server), "GetMap");
    let before = lookups(&server);
    maps.remove_keyframe(proto::RemoveKeyframeRequest { map_id: "m".into(), keyframe_id: 4 }).await.unwrap();
    once(before, lookups(&server), "RemoveKeyframe");
    server.shutdown().await.unwrap();
}
