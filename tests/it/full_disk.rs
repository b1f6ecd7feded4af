//! Issue 26, section 1: the real server binary on a real full volume (a small tmpfs, mounted when the tests
//! run as root, as CI does; skipped with a message otherwise). Writes on the full volume are refused with
//! 507 / RESOURCE_EXHAUSTED and leave nothing behind, reads go on, writes resume once space is freed, and
//! every acknowledged keyframe survives kill -9 and a SIGTERM on the full volume (which exits 0 and leaves
//! no temporary file).

use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use scone::offline::scene::Scene;

use crate::common::{fixture, temp_dir};
use crate::test_dir::TestDir;

/// A tmpfs of `mib` MiB mounted on a fresh directory, unmounted on drop.
struct Tmpfs {
    dir: TestDir,
}

impl Tmpfs {
    /// `None` (with a message) where mounting is not possible: not root, or no permission in this sandbox.
    fn mount(mib: u32) -> Option<Self> {
        let dir = temp_dir("tmpfs");
        let out = Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size={mib}m"), "tmpfs"])
            .arg(&*dir)
            .output()
            .ok()?;
        if !out.status.success() {
            let msg = String::from_utf8_lossy(&out.stderr);
            if std::env::var("CI").as_deref() == Ok("true") {
                panic!("CI=true runs as root and must mount a tmpfs for the full-volume test: {msg}");
            }
            eprintln!("skipping the full-volume test: cannot mount a tmpfs ({msg}); run the tests as root");
            return None;
        }
        Some(Self { dir })
    }

    /// Fills the volume with a file until a write fails with "no space left".
    fn fill(&self) -> PathBuf {
        let path = self.dir.join("filler");
        let mut f = std::fs::File::create(&path).unwrap();
        let chunk = vec![0xa5u8; 64 << 10];
        loop {
            if let Err(e) = f.write_all(&chunk) {
                assert_eq!(e.kind(), std::io::ErrorKind::StorageFull, "{e}");
                break;
            }
        }
        // What is left is less than a chunk: fill it byte-wise with smaller writes.
        for size in [4096, 512, 1] {
            while f.write_all(&chunk[..size]).is_ok() {}
        }
        path
    }
}

impl Drop for Tmpfs {
    fn drop(&mut self) {
        let _ = Command::new("umount").arg("-l").arg(&*self.dir).status();
    }
}

/// `scone serve` as a child process on ephemeral ports.
pub(crate) struct Server {
    child: Child,
    pub(crate) base: String,
}

impl Server {
    pub(crate) fn start(data: &Path) -> Self {
        let mut child = Command::new(env!("CARGO_BIN_EXE_scone"))
            .args(["serve", "--grpc-addr", "127.0.0.1:0", "--http-addr", "127.0.0.1:0"])
            .arg("--data-dir")
            .arg(data)
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        let mut lines = BufReader::new(child.stdout.take().unwrap()).lines();
        let line = loop {
            let line = lines.next().expect("the server printed where it listens").unwrap();
            if line.starts_with("scone listening") {
                break line;
            }
        };
        let base = line.split_whitespace().last().unwrap().to_string();
        let server = Self { child, base };
        let t = Instant::now();
        while reqwest::blocking::get(format!("{}/readyz", server.base)).map(|r| r.status().as_u16()).ok() != Some(200) {
            assert!(t.elapsed() < Duration::from_secs(120), "not ready");
            std::thread::sleep(Duration::from_millis(50));
        }
        server
    }

    pub(crate) fn kill9(mut self) {
        self.child.kill().unwrap();
        self.child.wait().unwrap();
    }

    /// SIGTERM, and the exit code.
    fn term(mut self) -> i32 {
        let pid = self.child.id().to_string();
        assert!(Command::new("kill").args(["-TERM", &pid]).status().unwrap().success());
        let status = self.child.wait().unwrap();
        status.code().expect("exited, not killed")
    }
}

/// Status and body of adding frame `i` of `scene` as keyframe `i`.
pub(crate) fn add(http: &reqwest::blocking::Client, base: &str, scene: &Scene, i: usize) -> (u16, serde_json::Value) {
    let r = http.post(format!("{base}/v1/maps/m/keyframes")).multipart(blocking_form(scene, i)).send().unwrap();
    (r.status().as_u16(), r.json().unwrap_or(serde_json::Value::Null))
}

/// A keyframe as a multipart body (request JSON, image, depth), as `service::multipart_keyframe` builds it for
/// the async client.
fn blocking_form(scene: &Scene, i: usize) -> reqwest::blocking::multipart::Form {
    let f = &scene.frames[i];
    let p = f.pose.unwrap();
    let (q, t, c) = (p.rotation.quaternion(), p.translation.vector, scene.camera);
    let request = serde_json::json!({
        "keyframe_id": i,
        "pose": {"tx": t.x, "ty": t.y, "tz": t.z, "qx": q.i, "qy": q.j, "qz": q.k, "qw": q.w},
        "intrinsics": {"fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy},
    });
    use reqwest::blocking::multipart::{Form, Part};
    let mut form = Form::new()
        .text("request", request.to_string())
        .part("image", Part::bytes(std::fs::read(&f.rgb).unwrap()).mime_str("image/png").unwrap());
    if let Some(d) = &f.depth {
        form = form.part("depth", Part::bytes(std::fs::read(d).unwrap()).mime_str("image/png").unwrap());
    }
    form
}

fn keyframes(http: &reqwest::blocking::Client, base: &str) -> u64 {
    let r = http.get(format!("{base}/v1/maps/m")).send().unwrap();
    assert_eq!(r.status(), 200);
    r.json::<serde_json::Value>().unwrap()["keyframes"].as_u64().unwrap()
}

/// Files under `dir` whose names say they are temporary or a dump the manifest does not name.
fn leftovers(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            let name = p.file_name().unwrap().to_string_lossy().into_owned();
            if p.is_dir() {
                if name.starts_with('.') {
                    out.push(p.clone());
                }
                stack.push(p);
            } else if name.ends_with(".tmp") {
                out.push(p);
            } else if let Some(base) = name.strip_suffix(".hnsw.graph").or_else(|| name.strip_suffix(".hnsw.data")) {
                let manifest = std::fs::read_to_string(d.join("index.json")).unwrap_or_default();
                if !manifest.contains(&format!("\"base\":\"{base}\"")) {
                    out.push(p);
                }
            }
        }
    }
    out
}

#[test]
fn a_full_volume_refuses_writes_keeps_reads_and_loses_no_acknowledged_keyframe() {
    let Some(volume) = Tmpfs::mount(8) else { return };
    let data = volume.dir.join("data");
    let scene = Scene::load(&fixture("rendered")).unwrap();
    let http = reqwest::blocking::Client::builder().timeout(Duration::from_secs(120)).build().unwrap();

    let server = Server::start(&data);
    let base = server.base.clone();
    let r = http.post(format!("{base}/v1/maps")).json(&serde_json::json!({"map_id": "m"})).send().unwrap();
    assert_eq!(r.status(), 201);
    for i in [0, 1] {
        assert_eq!(add(&http, &base, &scene, i).0, 200);
    }

    // The volume fills up: writes are refused as insufficient storage, and leave nothing behind.
    let filler = volume.fill();
    let (status, body) = add(&http, &base, &scene, 2);
    assert_eq!(status, 507, "{body}");
    assert_eq!(body["error"]["code"], "RESOURCE_EXHAUSTED", "{body}");
    let msg = body["error"]["message"].as_str().unwrap();
    assert!(msg.contains("data volume") && msg.contains("store.data_dir"), "{msg}");
    let r = http.post(format!("{base}/v1/maps")).json(&serde_json::json!({"map_id": "n"})).send().unwrap();
    assert_eq!(r.status(), 507);
    assert!(!data.join("maps/n").exists());
    assert_eq!(std::fs::read_dir(data.join("maps")).unwrap().count(), 1, "a failed create left a directory");
    // Reads go on.
    assert_eq!(keyframes(&http, &base), 2);
    let c = scene.camera;
    let r = http
        .post(format!("{base}/v1/maps/m/localize?fx={}&fy={}&cx={}&cy={}", c.fx, c.fy, c.cx, c.cy))
        .header("content-type", "image/png")
        .body(std::fs::read(&scene.frames[1].rgb).unwrap())
        .send()
        .unwrap();
    assert_eq!(r.status(), 200);

    // Space is back: writes resume, and are acknowledged after good data.
    std::fs::remove_file(&filler).unwrap();
    for i in [3, 4] {
        assert_eq!(add(&http, &base, &scene, i).0, 200);
    }
    server.kill9();

    // kill -9, then a start: every acknowledged keyframe is there, nothing held back; the id of the failed
    // create is free.
    let server = Server::start(&data);
    let base = server.base.clone();
    assert_eq!(keyframes(&http, &base), 4);
    let list: serde_json::Value = http.get(format!("{base}/v1/maps")).send().unwrap().json().unwrap();
    assert!(list["held_back"].as_array().unwrap().is_empty(), "{list}");
    let r = http.post(format!("{base}/v1/maps")).json(&serde_json::json!({"map_id": "n"})).send().unwrap();
    assert_eq!(r.status(), 201);

    // SIGTERM on a full volume: a clean exit (0) that snapshots what it can, and no temporary file left.
    let filler = volume.fill();
    assert_eq!(add(&http, &base, &scene, 5).0, 507);
    assert_eq!(server.term(), 0, "SIGTERM on a full volume did not exit cleanly");
    assert_eq!(leftovers(&data), Vec::<PathBuf>::new());
    std::fs::remove_file(&filler).unwrap();
    let server = Server::start(&data);
    assert_eq!(keyframes(&http, &server.base), 4);
    assert_eq!(add(&http, &server.base, &scene, 5).0, 200);
    assert_eq!(server.term(), 0);
    assert_eq!(leftovers(&data), Vec::<PathBuf>::new());
}
