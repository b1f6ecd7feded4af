//! Golden parity: Rust extraction + tensor layout + ort inference against Python onnxruntime on the same
//! committed image and model (`training/scone_train/model/golden.py` made the fixtures): the embedded ring-context
//! model at the extraction it declares (`golden-ring/`), and the constellation model at revision 2 (`golden/`).
//! Then what a model declares, and the models that are refused.

use std::path::PathBuf;

use ndarray::{Array1, Array2, Array3};
use ndarray_npy::{NpzReader, ReadNpyExt};

use scone::describe::constellation;
use scone::describe::decode::{decode_grey, ImageLimitSettings};
use scone::describe::embedding::{constellation_model_path, default_model_path, Embedder, EmbedderSettings};
use scone::describe::features::{extract, ExtractorSettings};

use crate::common::{fixture, temp_dir};

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
fn embeddings_match(embedder: &Embedder, features: &scone::describe::features::Features, golden: &Array2<f32>) {
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
    let describer = scone::describe::pipeline::Describer {
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

/// The embedded graph reads the FREAK bits unpacked (`models/scone-ring-e1-real-bits.onnx`, written from
/// `models/scone-ring-e1-real.onnx` by `scone_train.model.bits_input`): on two images at the declared extraction
/// it gives its source graph's embeddings bit for bit, and declares the source's id, which a map built with
/// either records.
#[test]
fn the_bits_input_graph_gives_its_source_graphs_embeddings_bit_for_bit() {
    let source = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("models/scone-ring-e1-real.onnx");
    let bits = Embedder::load(&EmbedderSettings { sessions: 1, ..EmbedderSettings::default() }).unwrap();
    let source =
        Embedder::load(&EmbedderSettings { model: source, sessions: 1, ..EmbedderSettings::default() }).unwrap();
    assert_eq!(bits.model_id(), source.model_id());
    assert!(bits.model_id().starts_with("sha256:8cace533"), "{}", bits.model_id());
    for name in ["astronaut.jpg", "coffee-640x480.jpg"] {
        let image = decode_grey(&std::fs::read(fixture(name)).unwrap(), &ImageLimitSettings::default()).unwrap();
        let mut features = extract(&image, &bits.extraction()).unwrap();
        features.sample_context(&image).unwrap();
        let (a, b) = (bits.embed(&features).unwrap(), source.embed(&features).unwrap());
        let differ = a.iter().zip(&b).filter(|(x, y)| x.to_bits() != y.to_bits()).count();
        assert!(a.len() == b.len() && a.len() == 48 * features.len() && differ == 0, "{name}: {differ} values differ");
    }
}

/// A graph whose `scone.embeds_as` is not a model id is refused, naming it: the embedded graph with the hex digits
/// of its declaration upper-cased (the same length, so the file stays a valid model).
#[test]
fn a_declared_embedding_id_that_is_not_a_model_id_is_refused_naming_it() {
    let bytes = std::fs::read(default_model_path()).unwrap();
    let needle = b"sha256:8cace533";
    let at = bytes.windows(needle.len()).position(|w| w == needle).expect("the declaration");
    let mut bad = bytes.clone();
    bad[at + 7..at + 15].copy_from_slice(b"8CACE533");
    let dir = temp_dir("embeds-as");
    let path = dir.join("bad-embeds-as.onnx");
    std::fs::write(&path, bad).unwrap();
    let err = Embedder::load(&EmbedderSettings { model: path, ..EmbedderSettings::default() }).unwrap_err().to_string();
    assert!(err.contains("scone.embeds_as") && err.contains("8CACE533") && err.contains("bad-embeds-as"), "{err}");
}

/// `bad-contract.onnx` is a valid ONNX graph whose `descriptors` input is float32 instead of uint8.
#[test]
fn a_model_with_the_wrong_contract_is_refused_naming_the_mismatch() {
    let cfg = EmbedderSettings { model: fixture("bad-contract.onnx"), ..EmbedderSettings::default() };
    let err = Embedder::load(&cfg).unwrap_err().to_string();
    assert!(err.contains("descriptors") && err.contains("Uint8") && err.contains("contract"), "{err}");
}

/// An image described in overlapped parts on two sessions (`pipeline::describe_decoded`: FREAK in calls, ring
/// contexts and inference on two threads) and a set embedded in halves on two sessions give exactly what one
/// call of each stage on one session gives, bit for bit; with no idle session to spare, and below the size
/// the pipeline starts at, the stages run in turn (the stage times tell which ran) with the same result.
#[test]
fn the_pipelined_describe_and_the_split_embedding_are_the_one_session_path_bit_for_bit() {
    use scone::describe::pipeline::{describe_decoded, extract_for, StageTimes, PIPELINE_FROM};
    let one =
        Embedder::load(&EmbedderSettings { sessions: 1, intra_threads: 1, ..EmbedderSettings::default() }).unwrap();
    let two =
        Embedder::load(&EmbedderSettings { sessions: 2, intra_threads: 1, ..EmbedderSettings::default() }).unwrap();
    // Bit patterns; a difference is reported by its count and size, not as two lists of thousands.
    let bits = |e: &[f32]| e.iter().map(|v| v.to_bits()).collect::<Vec<u32>>();
    let same = |a: &[f32], b: &[f32], what: &str| {
        let diff = a.iter().zip(b).filter(|(x, y)| x.to_bits() != y.to_bits()).count();
        let max = a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0f32, f32::max);
        let rows: Vec<usize> =
            (0..a.len() / 48).filter(|r| (0..48).any(|c| a[r * 48 + c].to_bits() != b[r * 48 + c].to_bits())).collect();
        eprintln!("{what}: rows differing {:?}", rows);
        assert!(
            a.len() == b.len() && diff == 0,
            "{what}: {} vs {} values, {diff} differ, by up to {max:e}",
            a.len(),
            b.len()
        );
    };
    let stages = |t: &StageTimes| t.0.iter().map(|(s, _)| *s).collect::<Vec<_>>();
    for (name, max_keypoints) in [
        ("astronaut.jpg", 2000),
        ("coffee-640x480.jpg", 2000),
        ("coffee-640x480.jpg", 700),
        ("coffee-640x480.jpg", 1337),
        ("astronaut.jpg", 300),
    ] {
        let image = decode_grey(&std::fs::read(fixture(name)).unwrap(), &ImageLimitSettings::default()).unwrap();
        let cfg = ExtractorSettings { max_keypoints, ..one.extraction() };
        let f = extract_for(&image, &cfg, &one).unwrap();
        let e = one.embed(&f).unwrap();
        let mut times = StageTimes::default();
        let d = describe_decoded(&image, &cfg, &two, &mut times).unwrap();
        let pipelined = f.len() >= PIPELINE_FROM;
        assert_eq!(
            stages(&times),
            if pipelined { vec!["extract", "embed"] } else { vec!["extract", "context", "embed"] }
        );
        assert_eq!(d.features, f, "{name}, {max_keypoints} keypoints");
        same(&d.embeddings, &e, &format!("{name}, {max_keypoints} keypoints, pipelined"));
        same(&two.embed(&f).unwrap(), &e, &format!("{name}, {max_keypoints} keypoints, halves on two sessions"));
        // One session taken: the pipeline runs on the other one alone, overlapping FREAK all the same.
        let taken = two.try_lease().unwrap();
        let mut times = StageTimes::default();
        let d = describe_decoded(&image, &cfg, &two, &mut times).unwrap();
        drop(taken);
        assert_eq!(stages(&times).len(), if pipelined { 2 } else { 3 });
        assert_eq!((&d.features, bits(&d.embeddings)), (&f, bits(&e)));
        // An embedder of one session runs the stages in turn.
        let mut times = StageTimes::default();
        let d = describe_decoded(&image, &cfg, &one, &mut times).unwrap();
        assert_eq!(stages(&times), ["extract", "context", "embed"]);
        assert_eq!((d.features, bits(&d.embeddings)), (f, bits(&e)));
    }
    // A constellation model reads every keypoint's neighbours: no overlap, the same path.
    let k20 = Embedder::load(&EmbedderSettings {
        model: constellation_model_path(),
        sessions: 2,
        intra_threads: 1,
        ..EmbedderSettings::default()
    })
    .unwrap();
    let image = decode_grey(&std::fs::read(fixture("astronaut.jpg")).unwrap(), &ImageLimitSettings::default()).unwrap();
    let f = extract_for(&image, &k20.extraction(), &k20).unwrap();
    let mut times = StageTimes::default();
    let d = describe_decoded(&image, &k20.extraction(), &k20, &mut times).unwrap();
    assert_eq!(stages(&times), ["extract", "embed"]);
    assert_eq!((d.features, bits(&d.embeddings)), (f.clone(), bits(&k20.embed(&f).unwrap())));
}
