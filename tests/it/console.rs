//! The web console in a real browser: headless Chromium (Debian's `chromium`) driven through Debian's
//! `chromedriver` over WebDriver (thirtyfour), against the real server on a map built from a scene. The page
//! must load without errors, list the maps, draw the 3D view, and place a localisation uploaded through the
//! page where the API puts it, and a track of uploaded images with a poses file where the truth puts it; the
//! pair page and the API reference must render.
//!
//! The browser is installed by `scripts/setup`; without it the tests skip, except under `CI=true`.
//! `SCONE_CONSOLE_SCENE=<scene dir>` builds the map from another scene (e.g. a real one of ../shared/data), and
//! `SCONE_CONSOLE_SCREENSHOTS=<dir>` saves screenshots there (the README's come from
//! `docs/figures`; command in `docs/console.md`).

use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use futures_util::FutureExt;
use scone::offline::scene::Scene;
use scone::server::proto;
use serde_json::Value;
use thirtyfour::prelude::*;
use thirtyfour::ChromiumLikeCapabilities;

use crate::common::{fixture, temp_dir};
use crate::service::{add_keyframes, clients, keyframe_requests, serve, settings};

const CHROMIUM: &str = "/usr/bin/chromium";
const CHROMEDRIVER: &str = "/usr/bin/chromedriver";

/// The browser and its driver, or `None` (skip) when they are not installed outside CI.
fn browser_installed() -> bool {
    let present = Path::new(CHROMIUM).exists() && Path::new(CHROMEDRIVER).exists();
    if !present {
        if std::env::var("CI").as_deref() == Ok("true") {
            panic!("CI=true but {CHROMIUM} / {CHROMEDRIVER} are missing: scripts/setup installs them");
        }
        eprintln!("skipping: no {CHROMIUM} / {CHROMEDRIVER} (scripts/setup installs them)");
    }
    present
}

/// chromedriver on a free loopback port, killed when dropped.
struct Driver {
    child: Child,
    url: String,
}

impl Drop for Driver {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

async fn start_driver() -> Driver {
    let port = TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let mut child = Command::new(CHROMEDRIVER)
        .arg(format!("--port={port}"))
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("chromedriver starts");
    let url = format!("http://127.0.0.1:{port}");
    let status = format!("{url}/status");
    let t = Instant::now();
    while t.elapsed() < Duration::from_secs(20) {
        if let Ok(r) = reqwest::get(&status).await {
            if r.status().is_success() {
                return Driver { child, url };
            }
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let _ = child.kill();
    let _ = child.wait();
    panic!("chromedriver did not answer on {url}");
}

async fn browser(driver: &Driver, profile: &Path) -> WebDriver {
    let mut caps = DesiredCapabilities::chrome();
    caps.set_binary(CHROMIUM).unwrap();
    for arg in [
        "--headless=new",
        "--no-sandbox",
        "--disable-dev-shm-usage",
        // WebGL without a GPU: ANGLE on SwiftShader, Chromium's software renderer.
        "--use-angle=swiftshader",
        "--enable-unsafe-swiftshader",
        "--window-size=1500,950",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
    ] {
        caps.add_arg(arg).unwrap();
    }
    caps.add_arg(&format!("--user-data-dir={}", profile.display())).unwrap();
    WebDriver::new(&driver.url, caps).await.expect("a browser session")
}

/// Polls `script` (returning a value) until `done` accepts it, for at most `secs`.
async fn wait_for(d: &WebDriver, script: &str, secs: u64, done: impl Fn(&Value) -> bool) -> Value {
    let t = Instant::now();
    loop {
        let v = d.execute(script, Vec::new()).await.unwrap().json().clone();
        if done(&v) {
            return v;
        }
        if t.elapsed() > Duration::from_secs(secs) {
            let status = d.execute("return document.getElementById('status')?.textContent", Vec::new()).await;
            panic!("timed out on `{script}` (last {v}; status line {:?})", status.map(|s| s.json().clone()));
        }
        tokio::time::sleep(Duration::from_millis(150)).await;
    }
}

async fn no_page_errors(d: &WebDriver, page: &str) {
    let errors = d.execute("return window.sconeErrors || ['no error collector']", Vec::new()).await.unwrap();
    assert_eq!(errors.json(), &Value::Array(vec![]), "errors on {page}");
}

async fn screenshot(d: &WebDriver, name: &str) {
    if let Some(dir) = std::env::var_os("SCONE_CONSOLE_SCREENSHOTS") {
        let path = PathBuf::from(dir).join(format!("console-{name}.png"));
        std::fs::write(&path, d.screenshot_as_png().await.unwrap()).unwrap();
        eprintln!("wrote {}", path.display());
    }
}

async fn set_number(d: &WebDriver, id: &str, value: f64) {
    let e = d.find(By::Id(id)).await.unwrap();
    e.clear().await.unwrap();
    e.send_keys(value.to_string()).await.unwrap();
}

fn pose_distance(a: &Value, b: &Value) -> (f64, f64) {
    let f = |v: &Value, k: &str| v[k].as_f64().unwrap();
    let t = |v: &Value| nalgebra::Vector3::new(f(v, "tx"), f(v, "ty"), f(v, "tz"));
    let q = |v: &Value| {
        nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
            f(v, "qw"),
            f(v, "qx"),
            f(v, "qy"),
            f(v, "qz"),
        ))
    };
    ((t(a) - t(b)).norm(), q(a).angle_to(&q(b)).to_degrees())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_console_lists_maps_draws_one_in_3d_and_localises_an_upload_as_the_api_does() {
    if !browser_installed() {
        return;
    }
    let scene_dir = std::env::var_os("SCONE_CONSOLE_SCENE").map(PathBuf::from).unwrap_or_else(|| fixture("rendered"));
    let scene = Scene::load(&scene_dir).unwrap();
    let data = temp_dir("console");
    let server = serve(settings(&data)).await;
    let (mut maps, _) = clients(&server).await;
    let map = "console-map";
    maps.create_map(proto::CreateMapRequest { map_id: map.into() }).await.unwrap();
    let n = scene.frames.len();
    let stride = (n / 12).max(2);
    let mapped: Vec<usize> = (0..n).step_by(stride).filter(|&i| scene.frames[i].pose.is_some()).collect();
    add_keyframes(&mut maps, keyframe_requests(map, &scene, &mapped), None).await;
    // A held-out frame two thirds through the scene (away from the start, where sequences often linger).
    let held: Vec<usize> = (0..n).filter(|i| !mapped.contains(i) && scene.frames[*i].pose.is_some()).collect();
    let query = held[held.len() * 2 / 3];
    let query_path = std::fs::canonicalize(&scene.frames[query].rgb).unwrap();

    // The API's own answer for the image the page will upload.
    let base = format!("http://{}", server.http_addr);
    let cam = scene.camera;
    let intr = format!("fx={}&fy={}&cx={}&cy={}", cam.fx, cam.fy, cam.cx, cam.cy);
    let http = reqwest::Client::new();
    let api: Value = http
        .post(format!("{base}/v1/maps/{map}/localize?{intr}"))
        .header("content-type", "image/png")
        .body(std::fs::read(&query_path).unwrap())
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(api["localized"], true, "{api}");

    let driver = start_driver().await;
    let profile = temp_dir("console-profile");
    let d = browser(&driver, &profile).await;
    let checks = async {
        // The map list.
        d.goto(format!("{base}/ui")).await.unwrap();
        let rows = wait_for(&d, "return document.querySelectorAll('#maps-table tbody tr').length", 20, |v| {
            v.as_u64() == Some(1)
        })
        .await;
        assert_eq!(rows, 1);
        let listed = d.find(By::Css(format!("tr[data-map='{map}']"))).await.unwrap().text().await.unwrap();
        assert!(listed.contains(map), "{listed}");
        no_page_errors(&d, "/ui").await;
        screenshot(&d, "maps").await;

        // One map in 3D: frames rendered, and the canvas is not blank.
        d.goto(format!("{base}/ui#/map/{map}")).await.unwrap();
        d.refresh().await.unwrap();
        wait_for(&d, "return window.sconeView ? window.sconeView.frames : 0", 30, |v| v.as_u64().unwrap_or(0) >= 5)
            .await;
        let drawn = d
            .execute(
                r#"const c = document.getElementById('scene');
                   const t = document.createElement('canvas'); t.width = c.width; t.height = c.height;
                   const g = t.getContext('2d'); g.drawImage(c, 0, 0);
                   const px = g.getImageData(0, 0, t.width, t.height).data;
                   let lit = 0;
                   for (let i = 0; i < px.length; i += 4) {
                     if (Math.abs(px[i] - 11) + Math.abs(px[i + 1] - 13) + Math.abs(px[i + 2] - 16) > 40) lit++;
                   }
                   return {lit, total: px.length / 4, landmarks: window.sconeView.landmarks,
                           keyframes: window.sconeView.keyframes};"#,
                Vec::new(),
            )
            .await
            .unwrap()
            .json()
            .clone();
        let lit = drawn["lit"].as_f64().unwrap() / drawn["total"].as_f64().unwrap();
        assert!(lit > 0.002, "the 3D view is blank: {drawn}");
        assert_eq!(drawn["keyframes"].as_u64(), Some(mapped.len() as u64), "{drawn}");
        assert!(drawn["landmarks"].as_u64().unwrap() > 100, "{drawn}");

        // A localisation uploaded through the page agrees with the API's.
        d.find(By::Id("loc-image")).await.unwrap().send_keys(query_path.display().to_string()).await.unwrap();
        for (id, v) in [("loc-fx", cam.fx), ("loc-fy", cam.fy), ("loc-cx", cam.cx), ("loc-cy", cam.cy)] {
            set_number(&d, id, v).await;
        }
        d.find(By::Id("loc-go")).await.unwrap().click().await.unwrap();
        wait_for(&d, "return document.getElementById('loc-pose') !== null", 60, |v| v == &Value::Bool(true)).await;
        let shown: Value =
            serde_json::from_str(&d.find(By::Id("loc-pose")).await.unwrap().text().await.unwrap()).unwrap();
        assert_eq!(shown["localized"], true, "{shown}");
        let (dt, dr) = pose_distance(&shown["pose"], &api["pose"]);
        assert!(dt < 0.01 && dr < 0.5, "page {shown} vs API {api}: {dt} m, {dr} deg");
        wait_for(&d, "const i = document.getElementById('loc-picture'); return i ? i.naturalWidth : 0", 20, |v| {
            v.as_u64().unwrap_or(0) > 0
        })
        .await;
        wait_for(&d, "return window.sconeView.estimate !== null", 10, |v| v == &Value::Bool(true)).await;
        no_page_errors(&d, "the map page").await;
        screenshot(&d, "map").await;

        // A track of two held-out frames with their poses from a file (TUM lines; the ground truth in the
        // map's own frame, so every frame must come back where the truth puts it).
        let track: Vec<usize> = vec![query, held[(held.len() * 2 / 3 + 1).min(held.len() - 1)]];
        let poses_file = profile.join("track-poses.txt");
        let mut lines = String::from("# timestamp tx ty tz qx qy qz qw\n");
        for (n, &i) in track.iter().enumerate() {
            let p = scene.frames[i].pose.unwrap();
            let (t, q) = (p.translation.vector, p.rotation.quaternion());
            lines += &format!("{n} {} {} {} {} {} {} {}\n", t.x, t.y, t.z, q.i, q.j, q.k, q.w);
        }
        std::fs::write(&poses_file, lines).unwrap();
        let images: Vec<String> =
            track.iter().map(|&i| std::fs::canonicalize(&scene.frames[i].rgb).unwrap().display().to_string()).collect();
        d.find(By::Id("track-images")).await.unwrap().send_keys(images.join("\n")).await.unwrap();
        d.find(By::Id("track-poses")).await.unwrap().send_keys(poses_file.display().to_string()).await.unwrap();
        for (id, v) in [("track-fx", cam.fx), ("track-fy", cam.fy), ("track-cx", cam.cx), ("track-cy", cam.cy)] {
            set_number(&d, id, v).await;
        }
        d.find(By::Id("track-go")).await.unwrap().click().await.unwrap();
        wait_for(&d, "return document.getElementById('track-answer') !== null", 60, |v| v == &Value::Bool(true)).await;
        let shown: Value =
            serde_json::from_str(&d.find(By::Id("track-answer")).await.unwrap().text().await.unwrap()).unwrap();
        assert_eq!(shown["localized"], true, "{shown}");
        // The page sorts the images by name; the fixture's names follow its frame order.
        let mut sorted = track.clone();
        sorted.sort_by_key(|&i| scene.frames[i].rgb.file_name().unwrap().to_owned());
        for (f, &i) in shown["frames"].as_array().unwrap().iter().zip(&sorted) {
            let p = scene.frames[i].pose.unwrap();
            let (t, q) = (p.translation.vector, p.rotation.quaternion());
            let truth =
                serde_json::json!({"tx": t.x, "ty": t.y, "tz": t.z, "qx": q.i, "qy": q.j, "qz": q.k, "qw": q.w});
            let (dt, dr) = pose_distance(&f["pose"], &truth);
            assert!(dt < 0.05 && dr < 1.0, "track frame {i}: {dt} m, {dr} deg: {shown}");
        }
        assert_eq!(d.find_all(By::Css("#track-frames tbody tr")).await.unwrap().len(), 2);
        let drawn = d.execute("return window.sconeView.estimate.length", Vec::new()).await.unwrap();
        assert_eq!(drawn.json().as_u64(), Some(2));
        no_page_errors(&d, "the map page's track").await;
        screenshot(&d, "track").await;

        // The pair page: SConE and FREAK side by side.
        d.goto(format!("{base}/ui#/pair")).await.unwrap();
        let before = *mapped.iter().rev().find(|&&m| m < query).unwrap_or(&mapped[0]);
        let other = std::fs::canonicalize(&scene.frames[before].rgb).unwrap();
        d.find(By::Id("pair-a")).await.unwrap().send_keys(query_path.display().to_string()).await.unwrap();
        d.find(By::Id("pair-b")).await.unwrap().send_keys(other.display().to_string()).await.unwrap();
        for (id, v) in [("pair-fx", cam.fx), ("pair-fy", cam.fy), ("pair-cx", cam.cx), ("pair-cy", cam.cy)] {
            set_number(&d, id, v).await;
        }
        d.find(By::Id("pair-go")).await.unwrap().click().await.unwrap();
        let loaded =
            "return [...document.querySelectorAll('#pair-results img')].filter(i => i.naturalWidth > 0).length";
        wait_for(&d, loaded, 60, |v| v.as_u64() == Some(2)).await;
        let titles = d.find_all(By::Css("#pair-results h2")).await.unwrap();
        assert_eq!(titles.len(), 2);
        for t in titles {
            let text = t.text().await.unwrap();
            assert!(text.contains("inliers of") && !text.contains("null"), "{text}");
        }
        no_page_errors(&d, "the pair page").await;
        screenshot(&d, "pair").await;

        // The API reference renders every documented operation.
        d.goto(format!("{base}/ui/api.html")).await.unwrap();
        let documented: Value = http.get(format!("{base}/openapi.json")).send().await.unwrap().json().await.unwrap();
        let operations: usize =
            documented["paths"].as_object().unwrap().values().map(|p| p.as_object().unwrap().len()).sum();
        wait_for(&d, "return document.querySelectorAll('.opblock').length", 30, |v| {
            v.as_u64() == Some(operations as u64)
        })
        .await;
        screenshot(&d, "api").await;
    };
    // End the browser session whatever happened, so no Chromium outlives the test.
    let outcome = std::panic::AssertUnwindSafe(checks).catch_unwind().await;
    let _ = d.quit().await;
    drop(driver);
    server.shutdown().await.unwrap();
    if let Err(panic) = outcome {
        std::panic::resume_unwind(panic);
    }
}
