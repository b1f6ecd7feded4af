//! Golden parity: Rust extraction + tensor layout + ort inference against Python onnxruntime on the same
//! committed image and model (`training/scone_train/golden.py` made the fixtures): the embedded ring-context
//! model at the extraction it declares (`golden-ring/`), and the constellation model at revision 2 (`golden/`).
//! Then what a model declares, and the models that are refused.

use std::path::PathBuf;

use ndarray::{Array1, Array2, Array3};
use ndarray_npy::{NpzReader, ReadNpyExt};

use scone::constellation;
use scone::decode::{decode_grey, ImageLimitSettings};
use scone::embedding::{constellation_model_path, Embedder, EmbedderSettings};
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

/// The model's embeddings of `features` are the golden ones (Python onnxruntime) within 1e-4.
fn embeddings_match(embedder: &Embedder, features: &scone::features::Features, golden: &Array2<f32>) {
    let ours = embedder.embed(features).unwrap();
    assert_eq!(golden.shape(), &[features.len(), embedder.dim()]);
    let max_diff = ours.iter().zip(golden.iter()).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
    eprintln!("max |rust - python| = {max_diff:e} over {} values", ours.len());
    assert!(max_diff <= 1e-4, "embeddings differ from Python onnxruntime by {max_diff}");
}

#[test]
fn rust_features_and_embeddings_match_the_python_golden_fixture() {
    let dir = golden_dir();
    let image = decode_grey(&std::fs::read(fixture("astronaut.jpg")).unwrap(), &ImageLimitSettings::default()).unwrap();
    let features = extract(&image, &ExtractorSettings::revision_2()).unwrap();
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
    let golden = Array2::<f32>::read_npy(std::fs::File::open(dir.join("astronaut.embeddings.npy")).unwrap()).unwrap();
    embeddings_match(&embedder, &features, &golden);
}

#[test]
fn the_embedded_model_matches_its_python_golden_fixture_at_its_declared_extraction() {
    let dir = fixture("golden-ring");
    let info: serde_json::Value = serde_json::from_slice(&std::fs::read(dir.join("golden.json")).unwrap()).unwrap();
    let embedder = Embedder::load(&EmbedderSettings::default()).unwrap();
    assert_eq!(embedder.model_id(), format!("sha256:{}", info["model_sha256"].as_str().unwrap()));
    let declared: ExtractorSettings = serde_json::from_value(info["extraction"].clone()).unwrap();
    assert_eq!(embedder.declared_extraction(), Some(&declared));
    assert_eq!(declared, ExtractorSettings::default(), "the embedded model declares the default extraction");
    assert_eq!(embedder.declared_matcher(), Some("union"));

    let image = decode_grey(&std::fs::read(fixture("astronaut.jpg")).unwrap(), &ImageLimitSettings::default()).unwrap();
    let mut features = extract(&image, &embedder.extraction()).unwrap();
    features.sample_context(&image).unwrap();
    let mut npz = NpzReader::new(std::fs::File::open(dir.join("astronaut.ring.npz")).unwrap()).unwrap();
    let kp: Array2<f32> = npz.by_name("keypoints").unwrap();
    let desc: Array2<u8> = npz.by_name("descriptors").unwrap();
    let context: Array2<u8> = npz.by_name("context").unwrap();
    let golden: Array2<f32> = npz.by_name("embeddings").unwrap();
    assert_eq!(kp.nrows(), features.len(), "keypoint count differs from the golden extraction");
    for (i, k) in features.keypoints.iter().enumerate() {
        let ours = [k.x, k.y, k.size, k.angle, k.response, k.octave as f32];
        assert_eq!(&ours[..], kp.row(i).as_slice().unwrap(), "keypoint {i}");
        assert_eq!(&features.descriptors[i][..], desc.row(i).as_slice().unwrap(), "descriptor {i}");
        assert_eq!(&features.context[i][..], context.row(i).as_slice().unwrap(), "ring context {i}");
    }
    embeddings_match(&embedder, &features, &golden);
}

#[test]
fn a_model_that_declares_nothing_is_served_at_revision_2() {
    let e =
        Embedder::load(&EmbedderSettings { model: constellation_model_path(), ..EmbedderSettings::default() }).unwrap();
    assert_eq!((e.declared_extraction(), e.declared_matcher()), (None, None));
    assert_eq!(e.extraction(), ExtractorSettings::revision_2());
    assert_eq!((e.extraction().levels, e.extraction().max_keypoints), (6, 1500));
}

/// `bad-declaration.onnx` declares an extraction of 0 levels; `partial-declaration.onnx` only two of its five
/// fields (a default of this build would stand in for the rest); `bad-matcher.onnx` a matcher that does not
/// exist.
#[test]
fn a_declaration_that_cannot_be_served_is_refused_naming_it() {
    let cfg = EmbedderSettings { model: fixture("bad-declaration.onnx"), ..EmbedderSettings::default() };
    let err = Embedder::load(&cfg).unwrap_err().to_string();
    assert!(err.contains("scone.extraction") && err.contains("levels") && err.contains("bad-declaration"), "{err}");
    let cfg = EmbedderSettings { model: fixture("partial-declaration.onnx"), ..EmbedderSettings::default() };
    let err = Embedder::load(&cfg).unwrap_err().to_string();
    assert!(err.contains("scone.extraction") && err.contains("2 fields"), "{err}");

    let cfg = EmbedderSettings { model: fixture("bad-matcher.onnx"), ..EmbedderSettings::default() };
    let embedder = std::sync::Arc::new(Embedder::load(&cfg).unwrap());
    let describer = scone::pipeline::Describer {
        extractor: embedder.extraction(),
        limits: ImageLimitSettings::default(),
        embedder,
    };
    let err = scone::service::Service::new(describer, Default::default(), Default::default())
        .err()
        .expect("a matcher that does not exist")
        .to_string();
    assert!(err.contains("scone.matcher") && err.contains("fastest"), "{err}");
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
