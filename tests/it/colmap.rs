//! Maps from an external SfM: a COLMAP text model is synthesised from the committed rendered sequence (3D
//! points back-projected from depth at keypoints of some frames, observed in every frame where depth says
//! they are visible), written as cameras.txt / images.txt / points3D.txt, imported through the core function
//! and through `scone map import-colmap`, and checked by localising a held-out frame and by restarting.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::Path;
use std::process::Command;
use std::sync::Arc;

use nalgebra::{Isometry3, Point3};
use opencv::core::Mat;
use opencv::prelude::*;
use scone::camera::Camera;
use scone::describe::decode::{decode_depth_png, decode_grey, ImageLimitSettings};
use scone::describe::embedding::{Embedder, EmbedderSettings};
use scone::describe::features::{self, ExtractorSettings};
use scone::describe::pipeline::Describer;
use scone::map::builder::{ExternalObservation, KeyframeInput};
use scone::map::store::{MapStore, ModelInfo, StoreSettings};
use scone::offline::colmap::{self, ColmapModel};
use scone::offline::scene::Scene;
use scone::pose::rotation_error_deg;

use crate::common::{fixture, temp_dir};

/// A synthetic SfM reconstruction of a scene.
pub struct SyntheticSfm {
    /// Point `i` has id `i + 1`.
    pub points: Vec<[f64; 3]>,
    /// Per frame: where it sees which point, in scone's pixel convention.
    pub views: BTreeMap<usize, Vec<ExternalObservation>>,
}

fn depth_at(depth: &Mat, x: f64, y: f64) -> Option<f64> {
    let (xi, yi) = (x.round() as i32, y.round() as i32);
    if xi < 0 || yi < 0 || xi >= depth.cols() || yi >= depth.rows() {
        return None;
    }
    let raw = *depth.at_2d::<u16>(yi, xi).unwrap();
    (raw > 0).then(|| raw as f64 / 5000.0)
}

/// Pixel of a world point in a frame when it is in the image and its depth agrees (not occluded).
fn visible(pose: &Isometry3<f64>, cam: &Camera, depth: &Mat, p: &[f64; 3]) -> Option<(f64, f64)> {
    let c = pose.inverse_transform_point(&Point3::from(*p));
    if c.z <= 1e-6 {
        return None;
    }
    let (u, v) = (cam.fx * c.x / c.z + cam.cx, cam.fy * c.y / c.z + cam.cy);
    if u < 0.0 || v < 0.0 || u > (cam.width - 1) as f64 || v > (cam.height - 1) as f64 {
        return None;
    }
    let d = depth_at(depth, u, v)?;
    ((d - c.z).abs() <= 0.02 * c.z + 0.01).then_some((u, v))
}

/// Points from depth at the keypoints of `sources` (a keypoint an earlier point already explains, within
/// 2 px, makes none), and their views in every frame of `views` where they are visible.
pub fn synthetic_sfm(scene: &Scene, sources: &[usize], views: &[usize]) -> SyntheticSfm {
    let limits = ImageLimitSettings::default();
    let cam = scene.camera;
    let depth =
        |f: usize| decode_depth_png(&std::fs::read(scene.frames[f].depth.as_ref().unwrap()).unwrap(), &limits).unwrap();
    let pose = |f: usize| scene.frames[f].pose.unwrap();
    let mut points: Vec<[f64; 3]> = Vec::new();
    for &f in sources {
        let grey = decode_grey(&std::fs::read(&scene.frames[f].rgb).unwrap(), &limits).unwrap();
        let feats = features::extract(&grey, &ExtractorSettings::default()).unwrap();
        let d = depth(f);
        let explained: Vec<(f64, f64)> = points.iter().filter_map(|p| visible(&pose(f), &cam, &d, p)).collect();
        for k in &feats.keypoints {
            let (x, y) = (k.x as f64, k.y as f64);
            if explained.iter().any(|e| (e.0 - x).hypot(e.1 - y) <= 2.0) {
                continue;
            }
            let Some(z) = depth_at(&d, x, y) else { continue };
            let pw = pose(f) * Point3::new((x - cam.cx) / cam.fx * z, (y - cam.cy) / cam.fy * z, z);
            points.push([pw.x, pw.y, pw.z]);
        }
    }
    let mut out = BTreeMap::new();
    for &g in views {
        let d = depth(g);
        let seen = points
            .iter()
            .enumerate()
            .filter_map(|(i, p)| {
                visible(&pose(g), &cam, &d, p).map(|(x, y)| ExternalObservation {
                    x,
                    y,
                    landmark_id: i as u64 + 1,
                    point: *p,
                })
            })
            .collect();
        out.insert(g, seen);
    }
    SyntheticSfm { points, views: out }
}

/// Writes `sfm` as a COLMAP text model (COLMAP's conventions: world-to-camera poses, pixel origin at the
/// image corner) with frame `f` as image `f + 1`, named by its path relative to the scene.
pub fn write_colmap(dir: &Path, scene: &Scene, sfm: &SyntheticSfm, images: &[usize]) {
    std::fs::create_dir_all(dir).unwrap();
    let c = scene.camera;
    let cameras = format!(
        "# Camera list with one line of data per camera:\n#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n\
         1 PINHOLE {} {} {} {} {} {}\n",
        c.width,
        c.height,
        c.fx,
        c.fy,
        c.cx + 0.5,
        c.cy + 0.5
    );
    std::fs::write(dir.join("cameras.txt"), cameras).unwrap();
    let mut tracks: BTreeMap<u64, Vec<(u32, usize)>> = BTreeMap::new();
    let mut text = String::from(
        "# Image list with two lines of data per image:\n#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n\
         #   POINTS2D[] as (X, Y, POINT3D_ID)\n",
    );
    for &f in images {
        let id = f as u32 + 1;
        let w2c = scene.frames[f].pose.unwrap().inverse();
        let q = w2c.rotation.quaternion();
        let t = w2c.translation.vector;
        let name = scene.frames[f].rgb.strip_prefix(&scene.root).unwrap().display().to_string();
        writeln!(text, "{id} {} {} {} {} {} {} {} 1 {name}", q.w, q.i, q.j, q.k, t.x, t.y, t.z).unwrap();
        // A feature without a 3D point first, as COLMAP lists them.
        let mut points2d = vec!["3.5 4.5 -1".to_string()];
        for o in &sfm.views[&f] {
            tracks.entry(o.landmark_id).or_default().push((id, points2d.len()));
            points2d.push(format!("{} {} {}", o.x + 0.5, o.y + 0.5, o.landmark_id));
        }
        writeln!(text, "{}", points2d.join(" ")).unwrap();
    }
    std::fs::write(dir.join("images.txt"), text).unwrap();
    let mut text = String::from("# 3D point list with one line of data per point:\n");
    for (id, track) in &tracks {
        let p = sfm.points[*id as usize - 1];
        let track: Vec<String> = track.iter().map(|(i, k)| format!("{i} {k}")).collect();
        writeln!(text, "{id} {} {} {} 128 128 128 0.3 {}", p[0], p[1], p[2], track.join(" ")).unwrap();
    }
    std::fs::write(dir.join("points3D.txt"), text).unwrap();
}

fn open(dir: &Path) -> (MapStore, Describer) {
    let embedder = Arc::new(Embedder::load(&EmbedderSettings::default()).unwrap());
    let info = ModelInfo { model_id: embedder.model_id().into(), k: embedder.k(), dim: embedder.dim() };
    let store =
        MapStore::open(StoreSettings { data_dir: dir.to_path_buf(), ..StoreSettings::default() }, info).unwrap();
    (store, Describer { extractor: embedder.extraction(), limits: ImageLimitSettings::default(), embedder })
}

/// The frames of the map (even) and a held-out one; frame 9 is seen by the model but written later.
const MAPPED: [usize; 5] = [0, 2, 4, 6, 8];

#[test]
fn a_colmap_model_imports_localises_and_keeps_its_merged_landmarks_across_restart() {
    let root = temp_dir("import");
    let scene = Scene::load(&fixture("rendered")).unwrap();
    let sfm = synthetic_sfm(&scene, &MAPPED, &[0, 2, 4, 6, 8, 9]);
    let model_dir = root.join("sparse");
    write_colmap(&model_dir, &scene, &sfm, &MAPPED);
    let model = ColmapModel::read(&model_dir).unwrap();
    assert_eq!(model.images.len(), 5);
    let data_dir = root.join("data");

    let (store, describer) = open(&data_dir);
    let mut acked = Vec::new();
    let summary =
        colmap::import(&store, &describer, "sfm", &model, &scene.root, &mut |i| acked.push(i.image_id)).unwrap();
    assert_eq!(acked, vec![1, 3, 5, 7, 9]);
    let given: usize = MAPPED.iter().map(|f| sfm.views[f].len()).sum();
    eprintln!("{summary:?}; {} points, {given} views", sfm.points.len());
    assert_eq!(summary.external.given, given);
    assert_eq!(summary.external.rejected, 0, "every synthetic view reprojects exactly");
    assert_eq!(summary.external.associated, summary.map.observations);
    // Views of one point in several images are one landmark.
    assert!(summary.map.landmarks < summary.map.observations, "{:?}", summary.map);
    assert!(summary.map.observations as f64 > 1.3 * summary.map.landmarks as f64, "{:?}", summary.map);

    let localise = |store: &MapStore, f: usize| {
        let d = describer.describe_image(&std::fs::read(&scene.frames[f].rgb).unwrap()).unwrap();
        let loc = store.localize(&store.get("sfm").unwrap(), &d.features, &d.embeddings, &scene.camera, None).unwrap();
        let pose = loc.pose.unwrap_or_else(|| panic!("frame {f} not localised"));
        let gt = scene.frames[f].pose.unwrap();
        let dt = (pose.camera_to_world.translation.vector - gt.translation.vector).norm();
        let dr =
            rotation_error_deg(&pose.camera_to_world.rotation.to_rotation_matrix(), &gt.rotation.to_rotation_matrix());
        assert!(dt < 0.05 && dr < 1.0, "frame {f}: pose off by {dt} m, {dr} deg");
    };
    localise(&store, 5);
    drop(store);

    // Restart: the same map, its external ids still linked, so frame 9's views of known ids observe the
    // existing landmarks instead of creating new ones.
    let (store, describer2) = open(&data_dir);
    let after = store.summary("sfm").unwrap();
    assert_eq!((after.landmarks, after.observations), (summary.map.landmarks, summary.map.observations));
    let linked = store.get("sfm").unwrap().read(|d, _| d.external_ids.clone());
    assert_eq!(linked.len(), after.landmarks);
    localise(&store, 3);
    let d = describer2.describe_image(&std::fs::read(&scene.frames[9].rgb).unwrap()).unwrap();
    let views = &sfm.views[&9];
    let input = KeyframeInput {
        id: 100,
        pose: scene.frames[9].pose.unwrap(),
        camera: scene.camera,
        features: &d.features,
        embeddings: &d.embeddings,
        depth: None,
        external: Some(views),
    };
    let added = store.add_keyframe(&store.get("sfm").unwrap(), &input).unwrap();
    assert!(added.observations > 30, "{added:?}");
    let known = views.iter().filter(|o| linked.contains_key(&o.landmark_id)).count();
    assert!(known * 10 > views.len() * 9, "{known} of {} views of frame 9 are of imported points", views.len());
    assert!(added.new_landmarks * 5 < added.observations, "{added:?}");
    let merged = store.summary("sfm").unwrap();
    assert_eq!(merged.landmarks, after.landmarks + added.new_landmarks);

    // Export / import keeps the links.
    let bytes = store.export(&store.get("sfm").unwrap()).unwrap();
    store.import("copy", &bytes).unwrap();
    let copied = store.get("copy").unwrap().read(|d, _| d.external_ids.clone());
    assert_eq!(copied, store.get("sfm").unwrap().read(|d, _| d.external_ids.clone()));
    drop(store);

    // The command line writes the same map through the same core, and a re-run skips what is there.
    let cli_dir = root.join("cli");
    let run = || {
        Command::new(env!("CARGO_BIN_EXE_scone"))
            .args(["map", "import-colmap", "--map", "cli", "--radius-px", "2"])
            .arg("--data-dir")
            .arg(&cli_dir)
            .arg("--model-dir")
            .arg(&model_dir)
            .arg("--images")
            .arg(&scene.root)
            .stderr(std::process::Stdio::null())
            .output()
            .unwrap()
    };
    let out = run();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stdout));
    let stdout = String::from_utf8(out.stdout).unwrap();
    assert_eq!(stdout.lines().filter(|l| l.starts_with("ack ")).count(), 5, "{stdout}");
    let out = run();
    let stdout = String::from_utf8(out.stdout).unwrap();
    assert!(out.status.success());
    assert_eq!(stdout.lines().filter(|l| l.starts_with("skip ")).count(), 5, "{stdout}");
    let (store, _) = open(&cli_dir);
    let cli = store.summary("cli").unwrap();
    assert_eq!((cli.keyframes, cli.landmarks, cli.observations), (5, summary.map.landmarks, summary.map.observations));
}

#[test]
fn a_model_with_a_distorted_camera_is_refused_by_the_command_naming_it() {
    let root = temp_dir("distorted");
    std::fs::write(root.join("cameras.txt"), "1 SIMPLE_RADIAL 320 240 250 160 120 0.01\n").unwrap();
    std::fs::write(root.join("images.txt"), "").unwrap();
    std::fs::write(root.join("points3D.txt"), "").unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_scone"))
        .args(["map", "import-colmap", "--map", "x"])
        .arg("--data-dir")
        .arg(root.join("data"))
        .arg("--model-dir")
        .arg(&root)
        .arg("--images")
        .arg(&root)
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("cameras.txt:1") && err.contains("camera 1") && err.contains("SIMPLE_RADIAL"), "{err}");
    assert!(!root.join("data/maps/x").exists(), "a refused model created the map");
}
