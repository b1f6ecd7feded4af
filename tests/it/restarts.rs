//! Issue 26, sections 2 and 3: graceful restarts with writes in between answer Localize exactly as before
//! the restart (the index dump that is loaded is the one that was written) and as a map built in one run;
//! an exported and imported map answers exactly as the original (its graph travels in the export); a log
//! shortened at its end is reported in GetMap / ListMaps and the metrics.

use std::path::Path;

use scone::offline::scene::Scene;
use scone::settings::Settings;

use crate::common::{fixture, temp_dir};
use crate::service::{add_keyframes_http, serve, settings};

/// Settings whose index is HNSW from a few hundred observations on (the fixture's frames are small).
fn hnsw_settings(data: &Path) -> Settings {
    let mut s = settings(data);
    s.store.index.exact_below = 200;
    s
}

async fn create(http: &reqwest::Client, base: &str, map: &str) {
    let r = http.post(format!("{base}/v1/maps")).json(&serde_json::json!({"map_id": map})).send().await.unwrap();
    assert_eq!(r.status(), 201, "{}", r.text().await.unwrap());
}

/// Localize of frame `i` against `map`, as the HTTP answer's JSON.
async fn localize(http: &reqwest::Client, base: &str, map: &str, scene: &Scene, i: usize) -> serde_json::Value {
    let c = scene.camera;
    let r = http
        .post(format!("{base}/v1/maps/{map}/localize?fx={}&fy={}&cx={}&cy={}", c.fx, c.fy, c.cx, c.cy))
        .header("content-type", "image/png")
        .body(std::fs::read(&scene.frames[i].rgb).unwrap())
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    r.json().await.unwrap()
}

async fn info(http: &reqwest::Client, base: &str, map: &str) -> serde_json::Value {
    http.get(format!("{base}/v1/maps/{map}")).send().await.unwrap().json().await.unwrap()
}

/// The map directory holds one index dump, and it is the one `index.json` names (replaced dumps deleted).
fn one_dump_named_by_the_manifest(map_dir: &Path) {
    let graphs: Vec<String> = std::fs::read_dir(map_dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.ends_with(".hnsw.graph"))
        .collect();
    assert_eq!(graphs.len(), 1, "{graphs:?}");
    let manifest: serde_json::Value =
        serde_json::from_slice(&std::fs::read(map_dir.join("index.json")).unwrap()).unwrap();
    assert_eq!(format!("{}.hnsw.graph", manifest["base"].as_str().unwrap()), graphs[0]);
}

/// Translation (map units) between two answers' poses.
fn moved(a: &serde_json::Value, b: &serde_json::Value) -> f64 {
    let t = |v: &serde_json::Value| ["tx", "ty", "tz"].map(|k| v["pose"][k].as_f64().unwrap());
    let (a, b) = (t(a), t(b));
    a.iter().zip(b).map(|(x, y)| (x - y).powi(2)).sum::<f64>().sqrt()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn graceful_restarts_with_writes_between_answer_as_before_and_as_a_map_built_at_once() {
    let scene = Scene::load(&fixture("rendered")).unwrap();
    let (first, second, query) = ([0, 1, 2], [7, 8, 9], 6);
    let http = reqwest::Client::new();
    let dir = temp_dir("restarts");

    let server = serve(hnsw_settings(&dir)).await;
    let base = format!("http://{}", server.http_addr);
    create(&http, &base, "m").await;
    add_keyframes_http(&http, &base, "m", &scene, &first).await;
    assert_eq!(info(&http, &base, "m").await["approximate_index"], true, "the test needs an HNSW index");
    server.shutdown().await.unwrap();

    // Second run: loads the first run's dump, writes more, answers; its stop dumps the reloaded graph.
    let server = serve(hnsw_settings(&dir)).await;
    let base = format!("http://{}", server.http_addr);
    add_keyframes_http(&http, &base, "m", &scene, &second).await;
    let before = localize(&http, &base, "m", &scene, query).await;
    assert_eq!(before["localized"], true, "{before}");
    server.shutdown().await.unwrap();
    one_dump_named_by_the_manifest(&dir.join("maps/m"));

    // Third and fourth runs: the same answer, exactly (the graph loaded is the graph that was dumped).
    for run in 3..=4 {
        let server = serve(hnsw_settings(&dir)).await;
        let base = format!("http://{}", server.http_addr);
        let after = localize(&http, &base, "m", &scene, query).await;
        assert_eq!(after, before, "run {run} answers otherwise than before the restart");
        server.shutdown().await.unwrap();
        one_dump_named_by_the_manifest(&dir.join("maps/m"));
    }

    // A map built in one run from the same keyframes answers alike (its graph is another build: the same
    // pose within a millimetre, and about as many matches).
    let scratch = temp_dir("restarts-scratch");
    let server = serve(hnsw_settings(&scratch)).await;
    let base = format!("http://{}", server.http_addr);
    create(&http, &base, "m").await;
    add_keyframes_http(&http, &base, "m", &scene, &[first, second].concat()).await;
    let fresh = localize(&http, &base, "m", &scene, query).await;
    assert_eq!(fresh["localized"], true, "{fresh}");
    assert!(moved(&fresh, &before) < 1e-3, "{fresh} against {before}");
    let (m1, m2) = (fresh["matches"].as_f64().unwrap(), before["matches"].as_f64().unwrap());
    assert!((m1 - m2).abs() <= 0.1 * m1, "{m2} matches after restarts, {m1} in a map built at once");
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_imported_map_answers_exactly_as_the_exported_one() {
    let scene = Scene::load(&fixture("rendered")).unwrap();
    let http = reqwest::Client::new();
    let dir = temp_dir("export-exact");
    let server = serve(hnsw_settings(&dir)).await;
    let base = format!("http://{}", server.http_addr);
    create(&http, &base, "m").await;
    add_keyframes_http(&http, &base, "m", &scene, &[0, 2, 4, 7, 9]).await;
    assert_eq!(info(&http, &base, "m").await["approximate_index"], true);
    let export = http.get(format!("{base}/v1/maps/m/export")).send().await.unwrap().bytes().await.unwrap();
    for copy in ["copy1", "copy2"] {
        let r = http
            .post(format!("{base}/v1/maps/{copy}/import"))
            .header("content-type", "application/octet-stream")
            .body(export.clone())
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), 201, "{}", r.text().await.unwrap());
    }
    for query in [1, 3, 5, 6, 8] {
        let original = localize(&http, &base, "m", &scene, query).await;
        for copy in ["copy1", "copy2"] {
            assert_eq!(localize(&http, &base, copy, &scene, query).await, original, "frame {query} on {copy}");
        }
    }
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_log_cut_at_its_end_is_reported_in_get_map_list_maps_and_the_metrics() {
    let scene = Scene::load(&fixture("rendered")).unwrap();
    let dir = temp_dir("cut-log");
    // Three keyframes acknowledged by the server binary, then kill -9 (no snapshot: all three are in the log),
    // then 1,000 bytes are lost off the end of the log.
    let written = {
        let (scene, dir) = (scene.clone(), dir.to_path_buf());
        tokio::task::spawn_blocking(move || {
            let server = crate::full_disk::Server::start(&dir);
            let http = reqwest::blocking::Client::new();
            let r = http.post(format!("{}/v1/maps", server.base)).json(&serde_json::json!({"map_id": "m"})).send();
            assert_eq!(r.unwrap().status(), 201);
            for i in [0, 3, 6] {
                assert_eq!(crate::full_disk::add(&http, &server.base, &scene, i).0, 200);
            }
            server.kill9();
        })
    };
    written.await.unwrap();
    let log = dir.join("maps/m/log.bin");
    let len = std::fs::metadata(&log).unwrap().len();
    std::fs::OpenOptions::new().write(true).open(&log).unwrap().set_len(len - 1000).unwrap();

    let server = serve(settings(&dir)).await;
    let http = reqwest::Client::new();
    let base = format!("http://{}", server.http_addr);
    let got = info(&http, &base, "m").await;
    assert_eq!(got["keyframes"], 2, "{got}");
    let note = got["load_note"].as_str().expect("GetMap notes the cut log");
    assert!(note.contains("bytes were cut off") && note.contains("acknowledged"), "{note}");
    let list: serde_json::Value = http.get(format!("{base}/v1/maps")).send().await.unwrap().json().await.unwrap();
    assert_eq!(list["maps"][0]["load_note"].as_str(), Some(note), "{list}");
    let metrics = http.get(format!("{base}/metrics")).send().await.unwrap().text().await.unwrap();
    assert!(metrics.contains("scone_map_cache_events_total{event=\"log_cut\"} 1"), "{metrics}");
    let (mut maps, _) = crate::service::clients(&server).await;
    let m = maps.get_map(scone::server::proto::GetMapRequest { map_id: "m".into() }).await.unwrap().into_inner();
    assert_eq!(m.load_note, note);
    // A map loaded whole carries no note.
    create(&http, &base, "whole").await;
    assert!(info(&http, &base, "whole").await.get("load_note").is_none());
    server.shutdown().await.unwrap();
}
