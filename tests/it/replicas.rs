//! Two `scone serve` replicas on one bucket (moto's server mode: an S3 *emulator*, not Amazon S3) behind a
//! real proxy, Debian's nginx, running `deploy/nginx/scone-replicas.conf.template`: consistent hashing of the
//! map id on both transports. What a deployment scaled over object storage must get right: maps made through
//! one replica are seen by the other, writes are seen within the freshness bound, a replica killed mid-stream
//! loses no acknowledged keyframe and its maps move to the other, a stale writer is refused cleanly, and maps
//! beyond the memory budget are evicted and loaded again.
//!
//! nginx is installed by `scripts/setup`; the test never skips (a missing nginx is a failure).

use std::io::{BufRead, BufReader};
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use scone::offline::scene::Scene;
use scone::server::proto::{self, maps_client::MapsClient, matching_client::MatchingClient};
use tonic::transport::Channel;

use crate::common::{fixture, temp_dir};
use crate::object_store::{Moto, KEY_ID, PREFIX, SECRET};
use crate::service::{add_keyframes_http, image_frame, keyframe_requests, localize_http, multipart_keyframe};

/// The freshness bound the replicas run with (`store.cache.freshness_ms`).
const FRESHNESS_MS: u64 = 2000;

fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

/// A `scone serve` process on object storage (credentials and region for moto).
pub(crate) struct Replica {
    name: &'static str,
    child: Child,
    http_port: u16,
    grpc_port: u16,
}

impl Replica {
    fn start(name: &'static str, moto: &Moto, bucket: &str, dir: &Path, freshness_ms: u64) -> Self {
        Self::start_on(name, &moto.endpoint, bucket, dir, freshness_ms)
    }

    /// A replica on `bucket` behind the S3 API at `endpoint` (moto, or a proxy in front of it).
    pub(crate) fn start_on(name: &'static str, endpoint: &str, bucket: &str, dir: &Path, freshness_ms: u64) -> Self {
        let (http_port, grpc_port) = (free_port(), free_port());
        let mut child = Command::new(env!("CARGO_BIN_EXE_scone"))
            .current_dir(env!("CARGO_MANIFEST_DIR"))
            .args(["serve", "--grpc-addr", &format!("127.0.0.1:{grpc_port}")])
            .args(["--http-addr", &format!("127.0.0.1:{http_port}")])
            .envs([
                ("SCONE_STORE__DATA_DIR", dir.join(name).display().to_string()),
                ("SCONE_STORE__BACKEND__KIND", "s3".into()),
                ("SCONE_STORE__BACKEND__BUCKET", bucket.into()),
                ("SCONE_STORE__BACKEND__PREFIX", PREFIX.into()),
                ("SCONE_STORE__BACKEND__ENDPOINT", endpoint.to_string()),
                ("SCONE_STORE__BACKEND__ALLOW_HTTP", "true".into()),
                ("SCONE_STORE__CACHE__FRESHNESS_MS", freshness_ms.to_string()),
                // About two of this test's maps fit: loading a third evicts one.
                ("SCONE_STORE__CACHE__MEMORY_BUDGET_MB", "1".into()),
                ("SCONE_WORKERS__THREADS", "1".into()),
                ("AWS_REGION", "us-east-1".into()),
                ("AWS_ACCESS_KEY_ID", KEY_ID.into()),
                ("AWS_SECRET_ACCESS_KEY", SECRET.into()),
            ])
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        let line = BufReader::new(child.stdout.take().unwrap()).lines().next().expect("no banner").unwrap();
        assert!(line.contains(&http_port.to_string()), "{line}");
        Self { name, child, http_port, grpc_port }
    }

    pub(crate) fn http(&self) -> String {
        format!("http://127.0.0.1:{}", self.http_port)
    }

    fn kill9(&mut self) {
        self.child.kill().unwrap();
        self.child.wait().unwrap();
    }
}

impl Drop for Replica {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

struct Nginx {
    child: Child,
    http: String,
    grpc: String,
}

impl Drop for Nginx {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn nginx_binary() -> PathBuf {
    ["/usr/sbin/nginx", "/usr/local/sbin/nginx", "/usr/bin/nginx"]
        .iter()
        .map(PathBuf::from)
        .find(|p| p.exists())
        .expect("nginx is not installed: scripts/setup installs it (apt-get install nginx)")
}

/// Renders the shipped template for these replicas and runs nginx on it in the foreground.
fn start_nginx(dir: &Path, replicas: &[&Replica]) -> Nginx {
    let runtime = dir.join("nginx");
    std::fs::create_dir_all(&runtime).unwrap();
    let template = std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("deploy/nginx/scone-replicas.conf.template"),
    )
    .unwrap();
    let servers = |port: fn(&Replica) -> u16| {
        replicas
            .iter()
            .map(|r| format!("        server 127.0.0.1:{} max_fails=1 fail_timeout=10s;", port(r)))
            .collect::<Vec<_>>()
            .join("\n")
    };
    let (http_port, grpc_port) = (free_port(), free_port());
    let root = Command::new("id").arg("-u").output().map(|o| o.stdout == b"0\n").unwrap_or(false);
    let conf = template
        .replace("@RUNTIME_DIR@", &runtime.display().to_string())
        .replace("@HTTP_LISTEN@", &format!("127.0.0.1:{http_port}"))
        .replace("@GRPC_LISTEN@", &format!("127.0.0.1:{grpc_port}"))
        .replace("@HTTP_SERVERS@", &servers(|r| r.http_port))
        .replace("@GRPC_SERVERS@", &servers(|r| r.grpc_port))
        .replace("@USER@", if root { "user root;" } else { "" });
    assert!(!conf.contains('@'), "a placeholder is left");
    let path = runtime.join("nginx.conf");
    std::fs::write(&path, conf).unwrap();
    let bin = nginx_binary();
    let check = Command::new(&bin).arg("-t").arg("-p").arg(&runtime).arg("-c").arg(&path).output().unwrap();
    assert!(check.status.success(), "nginx -t: {}", String::from_utf8_lossy(&check.stderr));
    let child = Command::new(&bin)
        .arg("-p")
        .arg(&runtime)
        .arg("-c")
        .arg(&path)
        .args(["-g", "daemon off;"])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    Nginx { child, http: format!("http://127.0.0.1:{http_port}"), grpc: format!("http://127.0.0.1:{grpc_port}") }
}

pub(crate) async fn wait_ready(http: &reqwest::Client, base: &str) {
    let t = Instant::now();
    while http.get(format!("{base}/readyz")).send().await.map(|r| r.status() != 200).unwrap_or(true) {
        assert!(t.elapsed() < Duration::from_secs(90), "{base} not ready");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

fn with_map<T>(msg: T, map: &str) -> tonic::Request<T> {
    let mut r = tonic::Request::new(msg);
    r.metadata_mut().insert("x-scone-map-id", map.parse().unwrap());
    r
}

async fn map_json(http: &reqwest::Client, base: &str, map: &str) -> (u16, serde_json::Value) {
    let r = http.get(format!("{base}/v1/maps/{map}")).send().await.unwrap();
    let status = r.status().as_u16();
    (status, r.json().await.unwrap_or_default())
}

/// A counter of a replica's `/metrics`, summed over the series whose labels contain `labels`.
async fn metric(http: &reqwest::Client, base: &str, name: &str, labels: &str) -> f64 {
    let text = http.get(format!("{base}/metrics")).send().await.unwrap().text().await.unwrap();
    text.lines()
        .filter(|l| l.starts_with(name) && l.contains(labels))
        .filter_map(|l| l.rsplit(' ').next()?.parse::<f64>().ok())
        .sum()
}

async fn keyframe_ids(http: &reqwest::Client, base: &str, map: &str) -> Vec<u64> {
    let r = http.get(format!("{base}/v1/maps/{map}/contents")).header("x-scone-map-id", map).send().await.unwrap();
    assert_eq!(r.status(), 200);
    let body: serde_json::Value = r.json().await.unwrap();
    let mut ids: Vec<u64> =
        body["keyframes"].as_array().unwrap().iter().map(|k| k["keyframe_id"].as_u64().unwrap()).collect();
    ids.sort();
    ids
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn replicas_behind_nginx_share_maps_see_writes_survive_a_kill_and_evict() {
    // Moto's helpers block on their own runtime: not on this test's.
    let moto = tokio::task::spawn_blocking(Moto::start).await.unwrap();
    let bucket = "replicas".to_string();
    let r = reqwest::Client::new().put(format!("{}/{bucket}", moto.endpoint)).send().await.unwrap();
    assert!(r.status().is_success());
    let dir = temp_dir("replicas");
    let scene = Scene::load(&fixture("rendered")).unwrap();
    let mut a = Replica::start("a", &moto, &bucket, &dir, FRESHNESS_MS);
    let mut b = Replica::start("b", &moto, &bucket, &dir, FRESHNESS_MS);
    // Not behind the proxy: a replica that checks its copies only every 10 minutes, to be stale on purpose.
    let stale = Replica::start("c", &moto, &bucket, &dir, 600_000);
    let proxy = start_nginx(&dir, &[&a, &b]);
    let http = reqwest::Client::new();
    let started = Instant::now();
    let step = |what: &str| eprintln!("{:>6} ms  {what}", started.elapsed().as_millis());
    for base in [a.http(), b.http(), stale.http(), proxy.http.clone()] {
        wait_ready(&http, &base).await;
    }
    step("replicas and proxy ready");

    // 1. Through the proxy: create (the header is required), fill over HTTP, localise over both transports.
    let create = |base: &str, id: &str, header: bool| {
        let mut r = http.post(format!("{base}/v1/maps")).json(&serde_json::json!({ "map_id": id }));
        if header {
            r = r.header("x-scone-map-id", id);
        }
        r.send()
    };
    assert_eq!(create(&proxy.http, "m", false).await.unwrap().status(), 400, "the proxy needs the header");
    assert_eq!(create(&proxy.http, "m", true).await.unwrap().status(), 201);
    add_keyframes_http(&http, &proxy.http, "m", &scene, &[0, 2, 4]).await;
    let r = localize_http(&http, &proxy.http, "m", &scene, 3).await;
    assert_eq!(r.status(), 200);
    assert_eq!(r.json::<serde_json::Value>().await.unwrap()["localized"], true);
    let channel = Channel::from_shared(proxy.grpc.clone()).unwrap().connect().await.unwrap();
    let mut matching = MatchingClient::new(channel.clone());
    let query = proto::LocalizeRequest {
        map_id: "m".into(),
        frame: Some(image_frame(&scene.frames[3].rgb, &scene.camera)),
        prior: None,
        pose_convention: 0,
    };
    let out = matching.localize(with_map(query.clone(), "m")).await.unwrap().into_inner();
    assert!(out.localized, "gRPC Localize through the proxy");
    assert!(matching.localize(tonic::Request::new(query)).await.is_err(), "the proxy needs the metadata");

    step("made, filled and localised through the proxy");

    // 2. A map created on A is known to B at its next request, and listed by it.
    assert_eq!(create(&a.http(), "direct", false).await.unwrap().status(), 201);
    let (status, info) = map_json(&http, &b.http(), "direct").await;
    assert_eq!((status, info["version"].as_u64()), (200, Some(0)));
    let listed: serde_json::Value =
        http.get(format!("{}/v1/maps", b.http())).send().await.unwrap().json().await.unwrap();
    let ids: Vec<&str> = listed["maps"].as_array().unwrap().iter().map(|m| m["map_id"].as_str().unwrap()).collect();
    assert_eq!(ids, vec!["direct", "m"]);

    step("a map made on A seen on B");

    // 3. A write on A is seen by B within the freshness bound.
    let add = |base: String, map: &'static str, i: usize| {
        http.post(format!("{base}/v1/maps/{map}/keyframes")).multipart(multipart_keyframe(&scene, i)).send()
    };
    assert_eq!(add(a.http(), "direct", 0).await.unwrap().status(), 200);
    let t = Instant::now();
    while map_json(&http, &b.http(), "direct").await.1["version"].as_u64() != Some(1) {
        assert!(t.elapsed() < Duration::from_millis(FRESHNESS_MS + 3000), "B did not see A's write");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    eprintln!("B saw A's write after {} ms (bound {FRESHNESS_MS} ms)", t.elapsed().as_millis());

    step("A's write seen on B");

    // 4. A stale writer is refused cleanly: C loads the map, A writes, C writes on its copy (C's bound is 10
    // minutes, so it does not check): C's conditional write fails, nothing of it is stored, C reloads, and the
    // retry works.
    assert_eq!(map_json(&http, &stale.http(), "direct").await.1["version"], 1);
    assert_eq!(add(a.http(), "direct", 2).await.unwrap().status(), 200);
    let refused = add(stale.http(), "direct", 4).await.unwrap();
    assert_eq!(refused.status(), 503, "a stale replica's write");
    let body: serde_json::Value = refused.json().await.unwrap();
    assert!(body["error"]["message"].as_str().unwrap().contains("writer"), "{body}");
    assert_eq!(keyframe_ids(&http, &a.http(), "direct").await, vec![0, 2], "the refused write stored nothing");
    assert_eq!(add(stale.http(), "direct", 4).await.unwrap().status(), 200, "the retry, on the reloaded copy");
    assert_eq!(keyframe_ids(&http, &stale.http(), "direct").await, vec![0, 2, 4]);
    step("stale writer refused");

    // 5. The replica that owns "m" is killed mid-stream; the stream finishes through the proxy on the other.
    // The rings of the two transports differ (nginx hashes each upstream's addresses, and their ports
    // differ), so the gRPC owner of "m" is found by asking through the proxy and counting on each replica.
    let mut maps = MapsClient::new(channel.clone());
    let get_map = "transport=\"grpc\",route=\"GetMap\"";
    let before = metric(&http, &a.http(), "scone_requests_total", get_map).await;
    maps.get_map(with_map(proto::GetMapRequest { map_id: "m".into() }, "m")).await.unwrap();
    let owner_is_a = metric(&http, &a.http(), "scone_requests_total", get_map).await > before;
    let (owner, survivor) = if owner_is_a { (&mut a, &mut b) } else { (&mut b, &mut a) };
    eprintln!("map m is owned by replica {} on gRPC", owner.name);
    let mut reqs = keyframe_requests("m", &scene, &[1, 5, 6, 7, 8, 9]);
    for r in &mut reqs {
        r.keyframe_id += 100;
    }
    let wanted: Vec<u64> = reqs.iter().map(|r| r.keyframe_id).collect();
    let (tx, rx) = tokio::sync::mpsc::channel(1);
    let mut acks =
        maps.add_keyframes(with_map(tokio_stream::wrappers::ReceiverStream::new(rx), "m")).await.unwrap().into_inner();
    let mut acked = Vec::new();
    for r in reqs.iter().take(2) {
        tx.send(r.clone()).await.unwrap();
        acked.push(acks.message().await.unwrap().expect("an ack").keyframe_id);
    }
    tx.send(reqs[2].clone()).await.unwrap();
    owner.kill9();
    while let Ok(Some(ack)) = acks.message().await {
        acked.push(ack.keyframe_id);
    }
    drop(tx);
    step("stream broken by the kill");
    let present = keyframe_ids(&http, &proxy.http, "m").await;
    step("contents read through the proxy");
    for id in &acked {
        assert!(present.contains(id), "acknowledged keyframe {id} lost: {present:?}");
    }
    let rest: Vec<proto::AddKeyframeRequest> =
        reqs.iter().filter(|r| !present.contains(&r.keyframe_id)).cloned().collect();
    let n = rest.len();
    let mut acks = maps.add_keyframes(with_map(tokio_stream::iter(rest), "m")).await.unwrap().into_inner();
    let mut resumed = 0;
    while let Some(_ack) = acks.message().await.unwrap() {
        resumed += 1;
    }
    assert_eq!(resumed, n);
    let present = keyframe_ids(&http, &proxy.http, "m").await;
    for id in wanted.iter().chain(&[0, 2, 4]) {
        assert!(present.contains(id), "keyframe {id} missing after the failover: {present:?}");
    }
    eprintln!("acknowledged before the kill: {acked:?}; resumed {n} on replica {}", survivor.name);

    step("stream finished after the kill");

    // 6. The survivor holds both maps within a 1 MiB budget only by evicting: each request reloads.
    let base = survivor.http();
    let evictions = metric(&http, &base, "scone_map_cache_events_total", "event=\"eviction\"").await;
    for map in ["direct", "m", "direct", "m"] {
        assert_eq!(map_json(&http, &base, map).await.0, 200);
    }
    let after = metric(&http, &base, "scone_map_cache_events_total", "event=\"eviction\"").await;
    assert!(after >= evictions + 3.0, "evictions {evictions} -> {after}");
    assert!(metric(&http, &base, "scone_object_storage_requests_total", "operation=\"get\"").await > 0.0);
    let r = localize_http(&http, &base, "direct", &scene, 3).await;
    assert_eq!(r.status(), 200, "a reloaded map localises");
    step("evicted and reloaded");
    drop(proxy);
}
