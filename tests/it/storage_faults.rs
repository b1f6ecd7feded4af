//! Issue 42: object storage that fails the way networks fail, through a fault-injecting proxy in front of moto
//! (an S3 *emulator*, not Amazon S3). A write whose answer the storage lost after applying it, the storage
//! down, and a bucket that does not exist: the client gets an answer it can act on (a write that stands, or
//! 503 UNAVAILABLE saying to retry, or a message naming the bucket), and nothing acknowledged is lost.

use std::collections::HashSet;
use std::convert::Infallible;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use http_body_util::{BodyExt, Full};
use hyper::body::{Bytes, Incoming};
use hyper_util::rt::TokioIo;
use scone::offline::scene::Scene;

use crate::common::{fixture, temp_dir};
use crate::object_store::Moto;
use crate::replicas::{wait_ready, Replica};
use crate::service::multipart_keyframe;

/// What the proxy does to the calls it passes on.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Fault {
    /// Every call passes.
    None,
    /// The first PUT of each log segment is applied by moto, and its answer replaced by a 503 (what a
    /// connection lost after the write looks like to the client, which retries the PUT).
    LoseSegmentAnswers,
    /// Every call is answered 503 without reaching moto.
    Down,
}

struct Proxy {
    url: String,
    fault: Arc<Mutex<Fault>>,
    /// Segment PUTs whose answer was lost.
    lost: Arc<Mutex<HashSet<String>>>,
    task: tokio::task::JoinHandle<()>,
}

impl Drop for Proxy {
    fn drop(&mut self) {
        self.task.abort();
    }
}

fn unavailable() -> hyper::Response<Full<Bytes>> {
    let mut r = hyper::Response::new(Full::new(Bytes::from_static(b"injected fault")));
    *r.status_mut() = hyper::StatusCode::SERVICE_UNAVAILABLE;
    r
}

/// One call through the proxy: passed to `upstream` (moto) as it came, its answer passed back unless `fault`
/// says otherwise.
async fn pass(
    req: hyper::Request<Incoming>,
    upstream: String,
    fault: Fault,
    lost: Arc<Mutex<HashSet<String>>>,
) -> hyper::Response<Full<Bytes>> {
    if fault == Fault::Down {
        return unavailable();
    }
    let (parts, body) = req.into_parts();
    let body = body.collect().await.map(|b| b.to_bytes()).unwrap_or_default();
    let path = parts.uri.path_and_query().map_or("/", |p| p.as_str()).to_string();
    let client = reqwest::Client::new();
    let mut call = client.request(parts.method.clone(), format!("{upstream}{path}")).body(body);
    for (name, value) in &parts.headers {
        if name != hyper::header::HOST {
            call = call.header(name, value);
        }
    }
    let Ok(answer) = call.send().await else { return unavailable() };
    let is_segment_put = parts.method == hyper::Method::PUT && path.contains("/segments/");
    if fault == Fault::LoseSegmentAnswers && is_segment_put && lost.lock().unwrap().insert(path) {
        return unavailable();
    }
    let mut r = hyper::Response::new(Full::new(Bytes::new()));
    *r.status_mut() = answer.status();
    *r.headers_mut() = answer.headers().clone();
    *r.body_mut() = Full::new(answer.bytes().await.unwrap_or_default());
    r
}

impl Proxy {
    async fn start(upstream: &str) -> Self {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let url = format!("http://{}", listener.local_addr().unwrap());
        let fault = Arc::new(Mutex::new(Fault::None));
        let lost = Arc::new(Mutex::new(HashSet::new()));
        let (f, l, upstream) = (Arc::clone(&fault), Arc::clone(&lost), upstream.to_string());
        let task = tokio::spawn(async move {
            loop {
                let Ok((stream, _)) = listener.accept().await else { return };
                let (f, l, upstream) = (Arc::clone(&f), Arc::clone(&l), upstream.clone());
                tokio::spawn(async move {
                    let service = hyper::service::service_fn(move |req| {
                        let (fault, l, upstream) = (*f.lock().unwrap(), Arc::clone(&l), upstream.clone());
                        async move { Ok::<_, Infallible>(pass(req, upstream, fault, l).await) }
                    });
                    let _ = hyper::server::conn::http1::Builder::new()
                        .serve_connection(TokioIo::new(stream), service)
                        .await;
                });
            }
        });
        Self { url, fault, lost, task }
    }

    fn set(&self, fault: Fault) {
        *self.fault.lock().unwrap() = fault;
    }
}

/// The keyframe ids of map `m` as the replica holds them.
async fn keyframes(http: &reqwest::Client, base: &str) -> Vec<u64> {
    let r = http.get(format!("{base}/v1/maps/m/contents")).send().await.unwrap();
    assert_eq!(r.status(), 200);
    let body: serde_json::Value = r.json().await.unwrap();
    let mut ids: Vec<u64> =
        body["keyframes"].as_array().unwrap().iter().map(|k| k["keyframe_id"].as_u64().unwrap()).collect();
    ids.sort();
    ids
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn regression_storage_faults_answer_what_a_retry_fixes() {
    let moto = tokio::task::spawn_blocking(Moto::start).await.unwrap();
    let http = reqwest::Client::new();
    let r = http.put(format!("{}/faults", moto.endpoint)).send().await.unwrap();
    assert!(r.status().is_success());
    let proxy = Proxy::start(&moto.endpoint).await;
    let dir = temp_dir("storage-faults");
    let scene = Scene::load(&fixture("rendered")).unwrap();
    let replica = Replica::start_on("a", &proxy.url, "faults", &dir, 0);
    let base = replica.http();
    wait_ready(&http, &base).await;
    let r = http.post(format!("{base}/v1/maps")).json(&serde_json::json!({"map_id": "m"})).send().await.unwrap();
    assert_eq!(r.status(), 201, "{}", r.text().await.unwrap());
    let post_keyframe =
        |i: usize| http.post(format!("{base}/v1/maps/m/keyframes")).multipart(multipart_keyframe(&scene, i)).send();

    // 1. The storage applied the segment but its answer was lost, and the object store's own retry of the PUT
    // found the segment there (If-None-Match): before, the write answered 500 INTERNAL. The segment is this
    // write's own (its name carries a nonce), so the write stands.
    proxy.set(Fault::LoseSegmentAnswers);
    for i in [0, 2] {
        let r = post_keyframe(i).await.unwrap();
        assert_eq!(r.status(), 200, "{}", r.text().await.unwrap());
    }
    assert_eq!(proxy.lost.lock().unwrap().len(), 2, "both segment answers were lost");
    proxy.set(Fault::None);
    assert_eq!(keyframes(&http, &base).await, [0, 2]);

    // 2. The storage is down: the write is 503 UNAVAILABLE, retryable, saying so, within the request deadline.
    proxy.set(Fault::Down);
    let started = std::time::Instant::now();
    let r = post_keyframe(4).await.unwrap();
    assert_eq!(r.status(), 503);
    assert_eq!(r.headers().get("retry-after").and_then(|v| v.to_str().ok()), Some("1"));
    let body: serde_json::Value = r.json().await.unwrap();
    assert_eq!(body["error"]["code"], "UNAVAILABLE");
    let message = body["error"]["message"].as_str().unwrap();
    assert!(message.contains("retry"), "{message}");
    assert!(!message.contains("s3://") && !message.contains("segments/"), "no storage internals: {message}");
    assert!(started.elapsed() < Duration::from_secs(10), "answered after {:?}", started.elapsed());
    // The client retries once the storage is back: the write is made once, nothing acknowledged is lost.
    proxy.set(Fault::None);
    let r = post_keyframe(4).await.unwrap();
    assert_eq!(r.status(), 200, "{}", r.text().await.unwrap());
    assert_eq!(keyframes(&http, &base).await, [0, 2, 4]);

    // 3. A bucket that does not exist is named, not an internal error.
    let nowhere = Replica::start_on("b", &proxy.url, "nowhere", &dir, 0);
    wait_ready(&http, &nowhere.http()).await;
    let r = http.post(format!("{}/v1/maps", nowhere.http())).json(&serde_json::json!({"map_id": "m"})).send().await;
    let r = r.unwrap();
    assert_eq!(r.status(), 503);
    let body: serde_json::Value = r.json().await.unwrap();
    let message = body["error"]["message"].as_str().unwrap();
    assert!(message.contains("bucket 'nowhere' does not exist"), "{message}");
}
