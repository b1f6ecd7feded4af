//! Scenes on disk in the TUM RGB-D layout: `rgb.txt`, `groundtruth.txt` (camera-to-world poses as
//! `stamp tx ty tz qx qy qz qw`), `camera.txt` (`fx fy cx cy width height`), optional `depth.txt`.
//!
//! Colour frames are the reference list. Poses and depth images are associated to each colour frame by the
//! nearest timestamp within `max_gap` seconds (0.02 s by default, the default of TUM's `associate.py`); a frame
//! with no pose or depth within the gap gets `None`. Real TUM sequences therefore load as they are once a
//! `camera.txt` is added.

use std::path::{Path, PathBuf};

use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};

use crate::camera::Camera;
use crate::error::SceneError;

/// Default association gap between colour, depth and pose timestamps, seconds.
pub const DEFAULT_MAX_GAP: f64 = 0.02;

/// One colour frame with what was associated to it.
#[derive(Debug, Clone)]
pub struct SceneFrame {
    /// The timestamp as written in `rgb.txt`.
    pub stamp: String,
    pub time: f64,
    pub rgb: PathBuf,
    pub depth: Option<PathBuf>,
    /// Camera-to-world pose.
    pub pose: Option<Isometry3<f64>>,
}

/// A scene: camera and frames in `rgb.txt` order.
#[derive(Debug, Clone)]
pub struct Scene {
    pub root: PathBuf,
    pub name: String,
    pub camera: Camera,
    pub frames: Vec<SceneFrame>,
}

/// Meaningful lines of a TUM list file: `(line number, whitespace-separated fields)`, comments skipped.
fn read_list(path: &Path) -> Result<Vec<(usize, Vec<String>)>, SceneError> {
    let text = std::fs::read_to_string(path).map_err(|source| SceneError::Io { path: path.into(), source })?;
    Ok(text
        .lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty() && !l.trim_start().starts_with('#'))
        .map(|(i, l)| (i + 1, l.split_whitespace().map(str::to_string).collect()))
        .collect())
}

fn parse_f64(path: &Path, line: usize, field: &str, s: &str) -> Result<f64, SceneError> {
    s.parse::<f64>().ok().filter(|v| v.is_finite()).ok_or_else(|| SceneError::Parse {
        path: path.into(),
        line,
        reason: format!("{field} '{s}' is not a number"),
    })
}

/// Reads `camera.txt`.
pub fn read_camera(path: &Path) -> Result<Camera, SceneError> {
    let lines = read_list(path)?;
    let (line, f) =
        lines.first().ok_or_else(|| SceneError::Invalid { path: path.into(), reason: "no intrinsics line".into() })?;
    if f.len() < 6 {
        return Err(SceneError::Parse {
            path: path.into(),
            line: *line,
            reason: "expected fx fy cx cy width height".into(),
        });
    }
    let v: Vec<f64> = ["fx", "fy", "cx", "cy", "width", "height"]
        .iter()
        .zip(f)
        .map(|(name, s)| parse_f64(path, *line, name, s))
        .collect::<Result<_, _>>()?;
    if v[0] <= 0.0 || v[1] <= 0.0 || v[4] < 1.0 || v[5] < 1.0 {
        return Err(SceneError::Parse {
            path: path.into(),
            line: *line,
            reason: "focal lengths and size must be positive".into(),
        });
    }
    Ok(Camera { fx: v[0], fy: v[1], cx: v[2], cy: v[3], width: v[4] as u32, height: v[5] as u32 })
}

/// Reads a stamped file list (`rgb.txt`, `depth.txt`).
fn read_file_list(path: &Path, root: &Path) -> Result<Vec<(String, f64, PathBuf)>, SceneError> {
    read_list(path)?
        .into_iter()
        .map(|(line, f)| {
            if f.len() < 2 {
                return Err(SceneError::Parse { path: path.into(), line, reason: "expected 'stamp file'".into() });
            }
            let t = parse_f64(path, line, "stamp", &f[0])?;
            Ok((f[0].clone(), t, root.join(&f[1])))
        })
        .collect()
}

/// Reads `groundtruth.txt` into stamped camera-to-world poses.
pub fn read_groundtruth(path: &Path) -> Result<Vec<(f64, Isometry3<f64>)>, SceneError> {
    read_list(path)?
        .into_iter()
        .map(|(line, f)| {
            if f.len() < 8 {
                return Err(SceneError::Parse {
                    path: path.into(),
                    line,
                    reason: "expected 'stamp tx ty tz qx qy qz qw'".into(),
                });
            }
            let v: Vec<f64> =
                f[..8].iter().map(|s| parse_f64(path, line, "pose value", s)).collect::<Result<_, _>>()?;
            let q = Quaternion::new(v[7], v[4], v[5], v[6]);
            if (q.norm() - 1.0).abs() > 1e-3 {
                return Err(SceneError::Parse {
                    path: path.into(),
                    line,
                    reason: format!("quaternion norm {} is not 1", q.norm()),
                });
            }
            let pose = Isometry3::from_parts(Translation3::new(v[1], v[2], v[3]), UnitQuaternion::from_quaternion(q));
            Ok((v[0], pose))
        })
        .collect()
}

/// Index of the entry of `times` (sorted) nearest to `t`, if within `max_gap`.
fn nearest(times: &[f64], t: f64, max_gap: f64) -> Option<usize> {
    let i = times.partition_point(|&x| x < t);
    [i.checked_sub(1), (i < times.len()).then_some(i)]
        .into_iter()
        .flatten()
        .min_by(|&a, &b| (times[a] - t).abs().total_cmp(&(times[b] - t).abs()))
        .filter(|&j| (times[j] - t).abs() <= max_gap)
}

impl Scene {
    /// Loads a scene directory with the default association gap.
    pub fn load(dir: &Path) -> Result<Self, SceneError> {
        Self::load_with_gap(dir, DEFAULT_MAX_GAP)
    }

    /// Loads a scene directory, associating poses and depth within `max_gap` seconds.
    pub fn load_with_gap(dir: &Path, max_gap: f64) -> Result<Self, SceneError> {
        let camera = read_camera(&dir.join("camera.txt"))?;
        let rgb = read_file_list(&dir.join("rgb.txt"), dir)?;
        if rgb.is_empty() {
            return Err(SceneError::Invalid { path: dir.join("rgb.txt"), reason: "no frames".into() });
        }
        let gt_path = dir.join("groundtruth.txt");
        let mut gt = if gt_path.exists() { read_groundtruth(&gt_path)? } else { Vec::new() };
        gt.sort_by(|a, b| a.0.total_cmp(&b.0));
        let gt_times: Vec<f64> = gt.iter().map(|g| g.0).collect();
        let depth_path = dir.join("depth.txt");
        let mut depth = if depth_path.exists() { read_file_list(&depth_path, dir)? } else { Vec::new() };
        depth.sort_by(|a, b| a.1.total_cmp(&b.1));
        let depth_times: Vec<f64> = depth.iter().map(|d| d.1).collect();
        let frames = rgb
            .into_iter()
            .map(|(stamp, time, rgb)| SceneFrame {
                pose: nearest(&gt_times, time, max_gap).map(|i| gt[i].1),
                depth: nearest(&depth_times, time, max_gap).map(|i| depth[i].2.clone()),
                stamp,
                time,
                rgb,
            })
            .collect();
        let name = dir.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        Ok(Self { root: dir.to_path_buf(), name, camera, frames })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nearest_respects_gap() {
        let t = [0.0, 1.0, 2.0];
        assert_eq!(nearest(&t, 1.01, 0.02), Some(1));
        assert_eq!(nearest(&t, 1.5, 0.02), None);
        assert_eq!(nearest(&t, -0.01, 0.02), Some(0));
        assert_eq!(nearest(&t, 2.019, 0.02), Some(2));
        assert_eq!(nearest(&[], 1.0, 0.02), None);
    }

    #[test]
    fn loads_a_tum_layout_with_offset_stamps() {
        let dir = crate::test_dir::temp_dir("scene");
        std::fs::write(dir.join("camera.txt"), "# fx fy cx cy w h\n500 500 320 240 640 480\n").unwrap();
        std::fs::write(dir.join("rgb.txt"), "# c\n1305031102.175304 rgb/a.png\n1305031102.211214 rgb/b.png\n").unwrap();
        std::fs::write(dir.join("depth.txt"), "1305031102.160407 depth/a.png\n").unwrap();
        std::fs::write(
            dir.join("groundtruth.txt"),
            "1305031102.1758 1.0 2.0 3.0 0 0 0 1\n1305031102.2112 1.0 2.0 3.5 0 0 0.7071068 0.7071068\n",
        )
        .unwrap();
        let s = Scene::load(&dir).unwrap();
        assert_eq!(s.frames.len(), 2);
        assert_eq!(s.camera.width, 640);
        assert!(s.frames[0].depth.is_some() && s.frames[1].depth.is_none());
        let p = s.frames[1].pose.unwrap();
        assert!((p.translation.vector.z - 3.5).abs() < 1e-12);
        assert!((p.rotation.angle() - std::f64::consts::FRAC_PI_2).abs() < 1e-6);
        std::fs::write(dir.join("groundtruth.txt"), "1 0 0 0 0 0 0 2\n").unwrap();
        assert!(matches!(Scene::load(&dir), Err(SceneError::Parse { line: 1, .. })));
    }
}
