//! Sequences in the HPatches layout: image files `1..N` and the homographies `H_1_k` that send image 1 onto
//! image k, found under the folders given and read with their errors named.

use std::path::{Path, PathBuf};

use nalgebra::Matrix3;

use crate::describe::decode::{decode_grey, GreyImage, ImageLimitSettings};

type BoxError = Box<dyn std::error::Error + Send + Sync>;

/// A sequence in the HPatches layout.
#[derive(Debug, Clone)]
pub struct Sequence {
    pub name: String,
    /// Image files 1..=N.
    pub images: Vec<PathBuf>,
    /// `H_1_k` for k = 2..=N (index k - 2).
    pub homographies: Vec<Matrix3<f64>>,
}

/// Reads a 3x3 homography written as 9 whitespace-separated numbers.
pub fn read_homography(path: &Path) -> Result<Matrix3<f64>, BoxError> {
    let text = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let v: Vec<f64> = text
        .split_whitespace()
        .map(|s| s.parse::<f64>().map_err(|e| format!("{}: {s:?}: {e}", path.display())))
        .collect::<Result<_, _>>()?;
    if v.len() != 9 || v.iter().any(|x| !x.is_finite()) {
        return Err(format!("{}: expected 9 finite numbers, found {}", path.display(), v.len()).into());
    }
    let h = Matrix3::from_row_slice(&v);
    if h.determinant().abs() < 1e-12 {
        return Err(format!("{}: the homography is singular", path.display()).into());
    }
    Ok(h)
}

fn image_file(dir: &Path, i: usize) -> Option<PathBuf> {
    ["png", "ppm", "jpg", "jpeg"].iter().map(|ext| dir.join(format!("{i}.{ext}"))).find(|p| p.is_file())
}

impl Sequence {
    /// Loads a sequence folder: images 1, 2, ... for as long as both the image and `H_1_k` exist.
    pub fn load(dir: &Path) -> Result<Sequence, BoxError> {
        let first = image_file(dir, 1).ok_or_else(|| format!("{}: no image 1.png / 1.ppm / 1.jpg", dir.display()))?;
        let mut images = vec![first];
        let mut homographies = Vec::new();
        for k in 2.. {
            let h = dir.join(format!("H_1_{k}"));
            match (image_file(dir, k), h.is_file()) {
                (Some(img), true) => {
                    homographies.push(read_homography(&h)?);
                    images.push(img);
                }
                (None, false) => break,
                (Some(_), false) => return Err(format!("{}: image {k} has no H_1_{k}", dir.display()).into()),
                (None, true) => return Err(format!("{}: H_1_{k} has no image {k}", dir.display()).into()),
            }
        }
        if homographies.is_empty() {
            return Err(format!("{}: no pair (image 2 and H_1_2)", dir.display()).into());
        }
        let name =
            dir.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| dir.display().to_string());
        Ok(Sequence { name, images, homographies })
    }
}

/// The sequences under `roots`: a root holding `H_1_2` is a sequence, otherwise each of its sub-folders that
/// holds one is (sorted by name).
pub fn find_sequences(roots: &[PathBuf]) -> Result<Vec<PathBuf>, BoxError> {
    let mut out = Vec::new();
    for root in roots {
        if root.join("H_1_2").is_file() {
            out.push(root.clone());
            continue;
        }
        let mut subs: Vec<PathBuf> = std::fs::read_dir(root)
            .map_err(|e| format!("{}: {e}", root.display()))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.join("H_1_2").is_file())
            .collect();
        if subs.is_empty() {
            return Err(format!("{}: neither a sequence (H_1_2) nor a folder of sequences", root.display()).into());
        }
        subs.sort();
        out.extend(subs);
    }
    Ok(out)
}

pub(super) fn load_image(path: &Path) -> Result<GreyImage, BoxError> {
    let bytes = std::fs::read(path).map_err(|e| format!("{}: {e}", path.display()))?;
    Ok(decode_grey(&bytes, &ImageLimitSettings::default()).map_err(|e| format!("{}: {e}", path.display()))?)
}
