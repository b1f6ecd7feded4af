//! Golden parity: Rust extraction + tensor layout + ort inference against Python onnxruntime on the same
//! committed image and model (`training/scone_train/golden.py` made the fixture).

use std::path::PathBuf;

use ndarray::{Array1, Array2, Array3};
use ndarray_npy::{NpzReader, ReadNpyExt};

use scone::constellation;
use scone::decode::{decode_grey, ImageLimitSettings};
use scone::embedding::{Embedder, EmbedderSettings};
use scone::features::{extract, ExtractorSettings};

use crate::common::fixture;

fn golden_dir() -> PathBuf {
    std::env::var_os("SCONE_GOLDEN_DIR").map(PathBuf::from).unwrap_or_else(|| fixture("golden"))
}

fn golden_model() -> PathBuf {
    let info: serde_json::Value =
        serde_json::from_slice(&std::fs::read(golden_dir().join("golden.json")).unwrap()).unwrap();
    let name = info["model"].as_str().unwrap();
    std::env::var_os("SCONE_GOLDEN_MODEL")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("models").join(name))
}

#[test]
fn rust_features_and_embeddings_match_the_python_golden_fixture() {
    let dir = golden_dir();
    let image = decode_grey(&std::fs::read(fixture("astronaut.jpg")).unwrap(), &ImageLimitSettings::default()).unwrap();
    let features = extract(&image, &ExtractorSettings::default()).unwrap();
    let c = constellation::build(&features.keypoints, 20);

    let mut npz = NpzReader::new(std::fs::File::open(dir.join("astronaut.features.npz")).unwrap()).unwrap();
    let kp: Array2<f32> = npz.by_name("f0000_keypoints").unwrap();
    let desc: Array2<u8> = npz.by_name("f0000_descriptors").unwrap();
    let nb: Array2<i32> = npz.by_name("f0000_neighbours").unwrap();
    let rel: Array3<f32> = npz.by_name("f0000_relative").unwrap();
    let _meta: Array1<u8> = npz.by_name("meta_json").unwrap();
    assert_eq!(kp.nrows(), features.len(), "keypoint count differs from the golden extraction");
    for (i, k) in features.keypoints.iter().enumerate() {
        let row = kp.row(i);
        let ours = [k.x, k.y, k.size, k.angle, k.response, k.octave as f32];
        for (a, b) in ours.iter().zip(row.iter()) {
            assert!((a - b).abs() <= 1e-4 * b.abs().max(1.0), "keypoint {i}: {ours:?} vs {row:?}");
        }
        assert_eq!(&features.descriptors[i][..], desc.row(i).as_slice().unwrap(), "descriptor {i}");
    }
    let nb_ours: Vec<i32> = c.neighbours.iter().map(|&j| j as i32).collect();
    assert_eq!(nb_ours, nb.iter().copied().collect::<Vec<_>>(), "neighbour indices");
    let rel_ours = c.relative.as_flattened();
    let max_rel = rel_ours.iter().zip(rel.iter()).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
    assert!(max_rel <= 1e-5, "relative geometry differs by {max_rel}");

    let embedder = Embedder::load(&EmbedderSettings { model: golden_model(), ..EmbedderSettings::default() }).unwrap();
    let ours = embedder.embed(&features).unwrap();
    let golden = Array2::<f32>::read_npy(std::fs::File::open(dir.join("astronaut.embeddings.npy")).unwrap()).unwrap();
    assert_eq!(golden.shape(), &[features.len(), embedder.dim()]);
    let max_diff = ours.iter().zip(golden.iter()).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
    eprintln!("max |rust - python| = {max_diff:e} over {} values", ours.len());
    assert!(max_diff <= 1e-4, "embeddings differ from Python onnxruntime by {max_diff}");
}

#[test]
fn a_file_that_is_not_a_model_is_refused_with_its_name() {
    let cfg = EmbedderSettings { model: fixture("astronaut.jpg"), ..EmbedderSettings::default() };
    let err = Embedder::load(&cfg).unwrap_err().to_string();
    assert!(err.contains("astronaut.jpg"), "{err}");
}

/// `bad-contract.onnx` is a valid ONNX graph whose `descriptors` input is float32 instead of uint8.
#[test]
fn a_model_with_the_wrong_contract_is_refused_naming_the_mismatch() {
    let cfg = EmbedderSettings { model: fixture("bad-contract.onnx"), ..EmbedderSettings::default() };
    let err = Embedder::load(&cfg).unwrap_err().to_string();
    assert!(err.contains("descriptors") && err.contains("Uint8") && err.contains("contract"), "{err}");
}
