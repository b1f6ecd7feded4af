//! Maps made by an external SfM: reading a COLMAP *text* model (`cameras.txt`, `images.txt`, `points3D.txt`)
//! and writing it into a map through the same store, planning and durable write path as the service.
//!
//! Conventions, converted on reading so that everything past this module is in scone's:
//!
//! * **Poses**: `images.txt` holds world-to-camera (`X_cam = R(q) * X_world + t`, quaternion as `QW QX QY QZ`);
//!   scone stores camera-to-world, so the pose becomes `(R^T, -R^T t)` (the camera centre is `-R^T t`).
//! * **Pixels**: COLMAP puts (0, 0) at the top-left *corner* of the image (the centre of the first pixel is
//!   (0.5, 0.5)); scone at the centre of the first pixel. 0.5 is subtracted from every `POINTS2D` x, y and
//!   from the principal point.
//! * **Cameras**: only `PINHOLE` (fx fy cx cy) and `SIMPLE_PINHOLE` (f cx cy); any other model is refused,
//!   naming the camera and its model (undistort first: `colmap image_undistorter` writes a PINHOLE model
//!   and undistorted images).
//!
//! Every parse error names the file and line. Each registered image becomes a keyframe whose id is its
//! `IMAGE_ID`, with its `POINTS2D` that have a 3D point as external landmarks ([`ExternalObservation`]);
//! the images themselves are read from `--images` by `NAME`, and described (FAST + FREAK + SConE) like any
//! other. An image whose keyframe the map already has is skipped, so an interrupted import can be re-run.

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};

use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion, Vector3};
use serde::Serialize;

use crate::camera::Camera;
use crate::describe::pipeline::Describer;
use crate::error::{ImportError, MapError, SceneError};
use crate::map::builder::{ExternalCounts, ExternalObservation, KeyframeInput};
use crate::map::store::{KeyframeAdded, MapStore, MapSummary};

/// COLMAP's pixel origin is the top-left corner, scone's the centre of the top-left pixel.
const PIXEL_SHIFT: f64 = 0.5;

/// One registered image of a COLMAP model.
#[derive(Debug, Clone, PartialEq)]
pub struct ColmapImage {
    pub id: u32,
    pub camera_id: u32,
    /// File name relative to the images directory.
    pub name: String,
    /// Camera-to-world (converted from COLMAP's world-to-camera).
    pub pose: Isometry3<f64>,
    /// `POINTS2D`: pixel (scone's convention) and the 3D point's id, if it has one.
    pub points: Vec<(f64, f64, Option<u64>)>,
    /// Lines of `images.txt` holding the image and its `POINTS2D`.
    pub line: usize,
    pub points_line: usize,
}

/// A COLMAP text model.
#[derive(Debug, Clone, PartialEq)]
pub struct ColmapModel {
    pub dir: PathBuf,
    /// Intrinsics in scone's pixel convention.
    pub cameras: BTreeMap<u32, Camera>,
    pub images: BTreeMap<u32, ColmapImage>,
    pub points: HashMap<u64, [f64; 3]>,
}

fn parse_err(path: &Path, line: usize, reason: impl Into<String>) -> SceneError {
    SceneError::Parse { path: path.to_path_buf(), line, reason: reason.into() }
}

fn number<T: std::str::FromStr>(path: &Path, line: usize, field: &str, s: &str) -> Result<T, SceneError> {
    s.parse::<T>().map_err(|_| parse_err(path, line, format!("{field} '{s}' is not a valid number")))
}

fn real(path: &Path, line: usize, field: &str, s: &str) -> Result<f64, SceneError> {
    let v: f64 = number(path, line, field, s)?;
    if v.is_finite() {
        Ok(v)
    } else {
        Err(parse_err(path, line, format!("{field} '{s}' is not finite")))
    }
}

fn read_text(path: &Path) -> Result<String, SceneError> {
    std::fs::read_to_string(path).map_err(|source| SceneError::Io { path: path.to_path_buf(), source })
}

/// `(line number, line)` of every line that is not a comment (`#`); empty lines are kept (an empty
/// `POINTS2D` line is meaningful).
fn content_lines(text: &str) -> impl Iterator<Item = (usize, &str)> {
    text.lines().enumerate().map(|(i, l)| (i + 1, l.trim())).filter(|(_, l)| !l.starts_with('#'))
}

/// Parses `cameras.txt`: `CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]`.
pub fn parse_cameras(text: &str, path: &Path) -> Result<BTreeMap<u32, Camera>, SceneError> {
    let mut cameras = BTreeMap::new();
    for (line, l) in content_lines(text).filter(|(_, l)| !l.is_empty()) {
        let f: Vec<&str> = l.split_whitespace().collect();
        if f.len() < 4 {
            return Err(parse_err(path, line, "expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]"));
        }
        let id: u32 = number(path, line, "CAMERA_ID", f[0])?;
        let width: u32 = number(path, line, "WIDTH", f[2])?;
        let height: u32 = number(path, line, "HEIGHT", f[3])?;
        let params: Vec<f64> =
            f[4..].iter().map(|s| real(path, line, "camera parameter", s)).collect::<Result<_, _>>()?;
        let (fx, fy, cx, cy) = match (f[1], params.as_slice()) {
            ("SIMPLE_PINHOLE", &[fl, cx, cy]) => (fl, fl, cx, cy),
            ("PINHOLE", &[fx, fy, cx, cy]) => (fx, fy, cx, cy),
            ("SIMPLE_PINHOLE" | "PINHOLE", p) => {
                let want = if f[1] == "PINHOLE" { "4 (fx fy cx cy)" } else { "3 (f cx cy)" };
                return Err(parse_err(
                    path,
                    line,
                    format!("camera {id} ({}) has {} parameters, expected {want}", f[1], p.len()),
                ));
            }
            (model, _) => {
                return Err(parse_err(
                    path,
                    line,
                    format!(
                        "camera {id} has model {model}: only PINHOLE and SIMPLE_PINHOLE are supported (undistort \
                         the images and the model first, e.g. with `colmap image_undistorter`, which writes PINHOLE)"
                    ),
                ))
            }
        };
        if !(fx > 0.0 && fy > 0.0 && width > 0 && height > 0) {
            return Err(parse_err(path, line, format!("camera {id}: focal lengths and size must be positive")));
        }
        let camera = Camera { fx, fy, cx: cx - PIXEL_SHIFT, cy: cy - PIXEL_SHIFT, width, height };
        if cameras.insert(id, camera).is_some() {
            return Err(parse_err(path, line, format!("camera {id} is defined twice")));
        }
    }
    Ok(cameras)
}

/// Parses `images.txt`: per image a line `IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME` (world-to-camera),
/// then a line of `X Y POINT3D_ID` triples (`-1`: no 3D point), which may be empty.
pub fn parse_images(text: &str, path: &Path) -> Result<BTreeMap<u32, ColmapImage>, SceneError> {
    let mut images = BTreeMap::new();
    let mut lines = content_lines(text).peekable();
    while let Some((line, l)) = lines.next() {
        if l.is_empty() {
            continue;
        }
        let f: Vec<&str> = l.split_whitespace().collect();
        if f.len() < 10 {
            return Err(parse_err(path, line, "expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME"));
        }
        let id: u32 = number(path, line, "IMAGE_ID", f[0])?;
        let v: Vec<f64> = ["QW", "QX", "QY", "QZ", "TX", "TY", "TZ"]
            .iter()
            .zip(&f[1..8])
            .map(|(name, s)| real(path, line, name, s))
            .collect::<Result<_, _>>()?;
        let camera_id: u32 = number(path, line, "CAMERA_ID", f[8])?;
        let name = after_fields(l, 9).to_string();
        let q = Quaternion::new(v[0], v[1], v[2], v[3]);
        if (q.norm() - 1.0).abs() > 1e-3 {
            return Err(parse_err(path, line, format!("image {id}: quaternion norm {:.6} is not 1", q.norm())));
        }
        let rotation_cw = UnitQuaternion::from_quaternion(q); // world -> camera
        let t = Vector3::new(v[4], v[5], v[6]);
        let centre = -(rotation_cw.inverse() * t);
        let pose = Isometry3::from_parts(Translation3::from(centre), rotation_cw.inverse());
        // The POINTS2D line follows, possibly empty; at the end of the file it may be missing.
        let (points_line, points) = match lines.next() {
            Some((pl, p)) => (pl, parse_points2d(p, path, pl)?),
            None => (line + 1, Vec::new()),
        };
        let image = ColmapImage { id, camera_id, name, pose, points, line, points_line };
        if images.insert(id, image).is_some() {
            return Err(parse_err(path, line, format!("image {id} is defined twice")));
        }
    }
    Ok(images)
}

/// The rest of `l` after its first `n` whitespace-separated fields (a NAME may hold spaces).
fn after_fields(l: &str, n: usize) -> &str {
    let mut s = l.trim_start();
    for _ in 0..n {
        let end = s.find(char::is_whitespace).unwrap_or(s.len());
        s = s[end..].trim_start();
    }
    s.trim_end()
}

fn parse_points2d(l: &str, path: &Path, line: usize) -> Result<Vec<(f64, f64, Option<u64>)>, SceneError> {
    let f: Vec<&str> = l.split_whitespace().collect();
    if !f.len().is_multiple_of(3) {
        return Err(parse_err(path, line, format!("POINTS2D has {} values, not X Y POINT3D_ID triples", f.len())));
    }
    f.chunks(3)
        .map(|c| {
            let x = real(path, line, "POINTS2D X", c[0])?;
            let y = real(path, line, "POINTS2D Y", c[1])?;
            let id: i64 = number(path, line, "POINT3D_ID", c[2])?;
            let id = match id {
                -1 => None,
                i if i >= 0 => Some(i as u64),
                i => return Err(parse_err(path, line, format!("POINT3D_ID {i} is negative (only -1 means none)"))),
            };
            Ok((x - PIXEL_SHIFT, y - PIXEL_SHIFT, id))
        })
        .collect()
}

/// Parses `points3D.txt`: `POINT3D_ID X Y Z R G B ERROR TRACK[]` (TRACK: `IMAGE_ID POINT2D_IDX` pairs).
pub fn parse_points3d(text: &str, path: &Path) -> Result<HashMap<u64, [f64; 3]>, SceneError> {
    let mut points = HashMap::new();
    for (line, l) in content_lines(text).filter(|(_, l)| !l.is_empty()) {
        let f: Vec<&str> = l.split_whitespace().collect();
        if f.len() < 8 || !(f.len() - 8).is_multiple_of(2) {
            return Err(parse_err(path, line, "expected POINT3D_ID X Y Z R G B ERROR then IMAGE_ID POINT2D_IDX pairs"));
        }
        let id: u64 = number(path, line, "POINT3D_ID", f[0])?;
        let p = [real(path, line, "X", f[1])?, real(path, line, "Y", f[2])?, real(path, line, "Z", f[3])?];
        for (name, s) in ["R", "G", "B"].iter().zip(&f[4..7]) {
            number::<u8>(path, line, name, s)?;
        }
        real(path, line, "ERROR", f[7])?;
        for pair in f[8..].chunks(2) {
            number::<u32>(path, line, "TRACK IMAGE_ID", pair[0])?;
            number::<u32>(path, line, "TRACK POINT2D_IDX", pair[1])?;
        }
        if points.insert(id, p).is_some() {
            return Err(parse_err(path, line, format!("point {id} is defined twice")));
        }
    }
    Ok(points)
}

impl ColmapModel {
    /// Reads the three text files of `dir` and checks that every image names a known camera.
    pub fn read(dir: &Path) -> Result<Self, SceneError> {
        let cameras_path = dir.join("cameras.txt");
        let images_path = dir.join("images.txt");
        let points_path = dir.join("points3D.txt");
        let cameras = parse_cameras(&read_text(&cameras_path)?, &cameras_path)?;
        let images = parse_images(&read_text(&images_path)?, &images_path)?;
        let points = parse_points3d(&read_text(&points_path)?, &points_path)?;
        for image in images.values() {
            if !cameras.contains_key(&image.camera_id) {
                return Err(parse_err(
                    &images_path,
                    image.line,
                    format!("image {} names camera {}, which cameras.txt does not define", image.id, image.camera_id),
                ));
            }
        }
        Ok(Self { dir: dir.to_path_buf(), cameras, images, points })
    }

    /// The external landmarks of an image: its `POINTS2D` with a 3D point, and that point.
    pub fn external_observations(&self, image: &ColmapImage) -> Result<Vec<ExternalObservation>, SceneError> {
        image
            .points
            .iter()
            .filter_map(|&(x, y, id)| id.map(|id| (x, y, id)))
            .map(|(x, y, id)| {
                let point = self.points.get(&id).ok_or_else(|| {
                    parse_err(
                        &self.dir.join("images.txt"),
                        image.points_line,
                        format!("image {}: POINT3D_ID {id} is not in points3D.txt", image.id),
                    )
                })?;
                Ok(ExternalObservation { x, y, landmark_id: id, point: *point })
            })
            .collect()
    }
}

/// What one image of an import did.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ImageImported {
    pub image_id: u32,
    pub name: String,
    /// `None`: the map had this keyframe already (skipped).
    pub added: Option<KeyframeAdded>,
}

/// The outcome of an import.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ImportSummary {
    pub images: usize,
    pub skipped: usize,
    /// External observations over all written images.
    pub external: ExternalCounts,
    pub map: MapSummary,
}

/// Writes every image of `model` into map `map` (created if missing) as a keyframe with its external
/// landmarks, in `IMAGE_ID` order, one durable write each; `on_image` hears of each once it is durable.
/// Images are read from `images_dir` by name. Association radius and thresholds are the store's
/// [`crate::map::builder::BuildSettings`].
pub fn import(
    store: &MapStore,
    describer: &Describer,
    map: &str,
    model: &ColmapModel,
    images_dir: &Path,
    on_image: &mut dyn FnMut(&ImageImported),
) -> Result<ImportSummary, ImportError> {
    if matches!(store.get(map), Err(MapError::UnknownMap { .. })) {
        store.create(map)?;
    }
    let held = store.get(map)?;
    let mut summary = ImportSummary { images: 0, skipped: 0, external: ExternalCounts::default(), map: held.summary() };
    for image in model.images.values() {
        let id = u64::from(image.id);
        let exists = held.read(|data, _| data.keyframes.contains_key(&id));
        if exists {
            summary.skipped += 1;
            on_image(&ImageImported { image_id: image.id, name: image.name.clone(), added: None });
            continue;
        }
        let camera = model.cameras[&image.camera_id];
        let external = model.external_observations(image)?;
        let path = images_dir.join(&image.name);
        let image_err = |reason: String| ImportError::Image { image: image.id, path: path.clone(), reason };
        let bytes = std::fs::read(&path).map_err(|e| image_err(e.to_string()))?;
        let d = describer.describe_image(&bytes).map_err(|e| image_err(e.to_string()))?;
        if d.features.width != camera.width || d.features.height != camera.height {
            return Err(image_err(format!(
                "is {}x{}, its camera {} is {}x{}",
                d.features.width, d.features.height, image.camera_id, camera.width, camera.height
            )));
        }
        let input = KeyframeInput {
            id,
            pose: image.pose,
            camera,
            features: &d.features,
            embeddings: &d.embeddings,
            depth: None,
            external: Some(&external),
        };
        let added = store.add_keyframe(&held, &input)?;
        summary.images += 1;
        let (s, a) = (&mut summary.external, &added.external);
        s.given += a.given;
        s.associated += a.associated;
        s.rejected += a.rejected;
        s.unassociated += a.unassociated;
        on_image(&ImageImported { image_id: image.id, name: image.name.clone(), added: Some(added) });
    }
    summary.map = held.summary();
    Ok(summary)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn path(name: &str) -> PathBuf {
        PathBuf::from("model").join(name)
    }

    /// A camera rotated 90 degrees about y (world-to-camera R = [[0,0,1],[0,1,0],[-1,0,0]]) with its centre
    /// at (1, 2, 3): t = -R C = (-3, -2, 1). The camera looks along world -x.
    const IMAGES: &str = "# Image list with two lines of data per image:\n\
        #   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n\
        1 0.7071067811865476 0 0.7071067811865476 0 -3 -2 1 1 a.png\n\
        10.5 20.5 7 30.5 40.5 -1\n\
        2 1 0 0 0 0 0 0 1 sub dir/b.png\n\
        \n";

    #[test]
    fn poses_come_out_camera_to_world_with_the_known_centre() {
        let images = parse_images(IMAGES, &path("images.txt")).unwrap();
        let a = &images[&1];
        let c = a.pose.translation.vector;
        assert!((c - Vector3::new(1.0, 2.0, 3.0)).norm() < 1e-12, "centre {c}");
        let forward = a.pose.rotation * Vector3::z();
        assert!((forward - Vector3::new(-1.0, 0.0, 0.0)).norm() < 1e-12, "viewing direction {forward}");
        // A world point 2 m in front of the camera is at depth 2 on the optical axis.
        let p = a.pose.inverse_transform_point(&nalgebra::Point3::new(-1.0, 2.0, 3.0));
        assert!((p.coords - Vector3::new(0.0, 0.0, 2.0)).norm() < 1e-12, "{p}");
        // Pixels move to scone's convention; -1 means no 3D point.
        assert_eq!(a.points, vec![(10.0, 20.0, Some(7)), (30.0, 40.0, None)]);
        assert_eq!(a.points_line, 4);
        // Names may hold spaces; an empty POINTS2D line is an image without points.
        let b = &images[&2];
        assert_eq!(b.name, "sub dir/b.png");
        assert!(b.points.is_empty());
        assert!(b.pose.translation.vector.norm() < 1e-12);
    }

    #[test]
    fn cameras_convert_the_principal_point_and_refuse_distortion() {
        let cams = parse_cameras(
            "# Camera list\n1 PINHOLE 320 240 250 251 160 120\n2 SIMPLE_PINHOLE 640 480 500 320 240\n",
            &path("cameras.txt"),
        )
        .unwrap();
        assert_eq!(cams[&1], Camera { fx: 250.0, fy: 251.0, cx: 159.5, cy: 119.5, width: 320, height: 240 });
        assert_eq!(cams[&2], Camera { fx: 500.0, fy: 500.0, cx: 319.5, cy: 239.5, width: 640, height: 480 });
        let e = parse_cameras(
            "1 PINHOLE 320 240 250 250 160 120\n7 OPENCV 640 480 500 500 320 240 0.1 0 0 0\n",
            &path("cameras.txt"),
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("cameras.txt:2") && e.contains("camera 7") && e.contains("OPENCV"), "{e}");
        let e = parse_cameras("3 PINHOLE 320 240 250 160 120\n", &path("cameras.txt")).unwrap_err().to_string();
        assert!(e.contains("cameras.txt:1") && e.contains("camera 3") && e.contains("3 parameters"), "{e}");
    }

    #[test]
    fn malformed_lines_are_named() {
        let images = |t: &str| parse_images(t, &path("images.txt")).unwrap_err().to_string();
        let e = images("# c\n1 0.7 0 0.7 x -3 -2 1 1 a.png\n\n");
        assert!(e.contains("images.txt:2") && e.contains("QZ 'x'"), "{e}");
        let e = images("1 1 0 0 0 0 0 0 1\n\n");
        assert!(e.contains("images.txt:1") && e.contains("IMAGE_ID"), "{e}");
        let e = images("1 1 0 0 0 0 0 0 1 a.png\n1 2 3 4.5 6\n");
        assert!(e.contains("images.txt:2") && e.contains("5 values"), "{e}");
        let e = images("1 1 0 0 0 0 0 0 1 a.png\n1 2 -7\n");
        assert!(e.contains("images.txt:2") && e.contains("-7"), "{e}");
        let e = images("1 2 0 0 0 0 0 0 1 a.png\n\n");
        assert!(e.contains("images.txt:1") && e.contains("norm"), "{e}");
        let e = images("1 1 0 0 0 0 0 0 1 a.png\n\n1 1 0 0 0 0 0 0 1 b.png\n\n");
        assert!(e.contains("images.txt:3") && e.contains("twice"), "{e}");
        let points = |t: &str| parse_points3d(t, &path("points3D.txt")).unwrap_err().to_string();
        let e = points("# 3D point list\n1 0 0 1 255 0 0 0.5 1 0\n2 0 nan 1 255 0 0 0.5\n");
        assert!(e.contains("points3D.txt:3") && e.contains("Y 'nan'"), "{e}");
        let e = points("1 0 0 1 255 0 0 0.5 1\n");
        assert!(e.contains("points3D.txt:1") && e.contains("pairs"), "{e}");
        let e = points("1 0 0 1 256 0 0 0.5\n");
        assert!(e.contains("points3D.txt:1") && e.contains("R '256'"), "{e}");
    }

    #[test]
    fn a_model_on_disk_reads_and_its_references_are_checked() {
        let dir = crate::test_dir::temp_dir("colmap");
        std::fs::write(dir.join("cameras.txt"), "1 PINHOLE 320 240 250 250 160 120\n").unwrap();
        std::fs::write(dir.join("images.txt"), IMAGES).unwrap();
        std::fs::write(dir.join("points3D.txt"), "7 -1 2 3 10 20 30 0.4 1 0\n").unwrap();
        let model = ColmapModel::read(&dir).unwrap();
        let obs = model.external_observations(&model.images[&1]).unwrap();
        assert_eq!(obs, vec![ExternalObservation { x: 10.0, y: 20.0, landmark_id: 7, point: [-1.0, 2.0, 3.0] }]);
        // A POINT3D_ID that points3D.txt lacks is named with its line.
        std::fs::write(dir.join("points3D.txt"), "8 -1 2 3 10 20 30 0.4\n").unwrap();
        let model = ColmapModel::read(&dir).unwrap();
        let e = model.external_observations(&model.images[&1]).unwrap_err().to_string();
        assert!(e.contains("images.txt:4") && e.contains("POINT3D_ID 7"), "{e}");
        // An image naming an unknown camera.
        std::fs::write(dir.join("cameras.txt"), "2 PINHOLE 320 240 250 250 160 120\n").unwrap();
        let e = ColmapModel::read(&dir).unwrap_err().to_string();
        assert!(e.contains("images.txt:3") && e.contains("camera 1"), "{e}");
    }
}
