//! SConE embeddings with ONNX Runtime: one call per image (or per batch of keypoints) through `ort`.
//!
//! The model contract (checked when the model loads; any mismatch fails with a message naming it). Every
//! model reads each keypoint's FREAK bits, as the bytes `descriptors` uint8 [N, 64] or, a ring model only,
//! unpacked (below), and one of two contexts ([`ModelInputs`]), told apart by its input names:
//!
//! | context | input | dtype | shape |
//! |---|---|---|---|
//! | constellation (the paper's) | `keypoints` | float32 | [N, 2] central angle (degrees), size (pixels) |
//! | | `neighbours` | int64 | [N, k] |
//! | | `mask` | float32 | [N, k] |
//! | | `relative` | float32 | [N, k, 4] |
//! | ring ([`crate::describe::ring_context`]) | `context` | uint8 | [N, 113] |
//!
//! A ring model may read the FREAK bits unpacked instead of the bytes: `bits`, float32 [N, 512], whose element
//! i is bit i % 8 of byte i / 8 (least significant first) as -1.0 or +1.0, which the service fills from the
//! bytes. The graph then skips its own unpacking (a gather that takes about a tenth of the shipped network's
//! inference); `scone_train.model.bits_input` writes such a graph from an exported one, with the same output
//! bytes.
//!
//! Output `embeddings`, float32 [N, D] (D = 48 for the shipped models), L2-normalised. All normalisation of
//! the raw values happens inside the graph.
//!
//! What a model declares (its ONNX metadata, written by `scone_train.model.export` and, for the last key,
//! `scone_train.model.bits_input`): `scone.extraction`, the [`ExtractorSettings`] it was trained at, as JSON with
//! every field; `scone.matcher`, the MatchPair matcher it ships with (a `SconeMatcher` name); `scone.embeds_as`,
//! the id of another model file whose embeddings this graph gives byte for byte (`sha256:` and 64 hex digits; a
//! graph rewritten without changing its output, such as the bits-input graph above). The model's id
//! ([`Embedder::model_id`], which maps record and check) is the declared one, else the file's sha256; the
//! service cannot check the claim without the other file (`bits_input` checks it when it writes one), and an
//! approximate graph (int8) must not make it. The service runs the declared extraction unless `[extractor]` is
//! set, and answers MatchPair's default with the declared matcher. A model that declares neither extraction
//! nor matcher was made before models declared them (`scone-freak-k20`): it is served at the client contract's
//! revision 2 ([`ExtractorSettings::revision_2`]) and `scale-aware`. A declaration that does not parse fails
//! the load.
//!
//! Concurrency: `Session::run` needs exclusive access, so the embedder owns a small pool of sessions, one per
//! CPU worker of the service, each with its own intra-op thread count. Workers take a free session without
//! waiting when one exists ([`Lease`]); otherwise they wait for one. Sessions x intra-op threads should not
//! exceed the cores (default: two sessions of one thread, the service's two workers). On two or more cores, a
//! request that finds a second session idle uses it too, so one request may hold two: a ring model's set of
//! [`SPLIT_FROM`] keypoints or more is embedded in halves on both ([`Embedder::embed`]), and
//! `pipeline::describe_decoded` overlaps FREAK with the model.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;
use std::time::Instant;

use ort::session::builder::GraphOptimizationLevel;
use ort::session::Session;
use ort::value::{Tensor, TensorRef};
use parking_lot::Mutex;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::describe::constellation::{self, Constellations, GEOMETRY_DIM};
use crate::describe::features::{ExtractorSettings, Features, StageSink, DESCRIPTOR_BYTES};
use crate::describe::ring_context::SAMPLES;
use crate::error::EmbeddingError;

mod contract;
use contract::{check_contract, declaration, BitsInput, Declaration, BITS, BITS_INPUT};
pub use contract::{ModelInputs, EMBEDS_AS_KEY, EXTRACTION_KEY, MATCHER_KEY};

/// Settings of the embedding runtime.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct EmbedderSettings {
    /// ONNX model file.
    pub model: PathBuf,
    /// ONNX Runtime shared library (`libonnxruntime.so`).
    pub runtime_library: PathBuf,
    /// Sessions in the pool (concurrent inferences). With two or more (and two cores), a ring model's large set
    /// is embedded in halves on two idle sessions at once, and an image's description overlaps FREAK with the
    /// model (`pipeline::describe_decoded`); with one, each request's stages run in turn.
    pub sessions: usize,
    /// Intra-op threads per session.
    pub intra_threads: usize,
    /// Whether idle intra-op threads spin. Spinning saves a little latency on an idle machine and costs a lot
    /// when other work shares the cores (measured: 46 ms vs several hundred ms per 1,000 keypoints with a
    /// training job on the other core), so it is off by default.
    pub spinning: bool,
}

impl Default for EmbedderSettings {
    fn default() -> Self {
        Self {
            model: default_model_path(),
            runtime_library: PathBuf::from(env!("SCONE_DEFAULT_ORT_LIB")),
            sessions: 2,
            intra_threads: 1,
            spinning: false,
        }
    }
}

/// The committed model, next to the sources: the ring-context model (`models/scone-ring-e1-real.md`) as the
/// graph that reads unpacked bits (`models/scone-ring-e1-real-bits.onnx`: the same embeddings, the same id).
pub fn default_model_path() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("models/scone-ring-e1-real-bits.onnx")
}

/// The paper's constellation model (`models/scone-freak-k20.md`), kept for maps built with it, which the
/// ring-context model refuses.
pub fn constellation_model_path() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("models/scone-freak-k20.onnx")
}

/// The committed model's bytes, compiled into the binary. [`Embedder::load`] uses them when the configured model
/// is [`default_model_path`] and that file is gone (the checkout that built the binary was moved or removed), so
/// the built-in default keeps working; any other missing model is an error.
pub static BUILT_IN_MODEL: &[u8] =
    include_bytes!(concat!(env!("CARGO_MANIFEST_DIR"), "/models/scone-ring-e1-real-bits.onnx"));

/// The model file's bytes, or the built-in copy when `path` is `default_path` and does not exist.
fn model_bytes(path: &Path, default_path: &Path) -> Result<std::borrow::Cow<'static, [u8]>, EmbeddingError> {
    match std::fs::read(path) {
        Ok(bytes) => Ok(bytes.into()),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound && path == default_path => {
            tracing::info!(path = %path.display(), "default model file not found; using the copy built into the binary");
            Ok(BUILT_IN_MODEL.into())
        }
        Err(e) => Err(EmbeddingError::Model { path: path.to_path_buf(), reason: e.to_string() }),
    }
}

static ENVIRONMENT: OnceLock<Result<ort::environment::Environment, String>> = OnceLock::new();

fn environment(lib: &Path) -> Result<&'static ort::environment::Environment, EmbeddingError> {
    ENVIRONMENT
        .get_or_init(|| {
            let builder = ort::init_from(lib).map_err(|e| e.to_string())?;
            builder.with_name("scone").build().map_err(|e| e.to_string())
        })
        .as_ref()
        .map_err(|reason| EmbeddingError::Runtime { path: lib.to_path_buf(), reason: reason.clone() })
}

/// One session of the pool and the buffer a ring model's `bits` input is unpacked into, kept between calls
/// (4 MB for 2,000 keypoints, up to [`UNPACKED_KEPT`]: a fresh one per call cost its allocation and page faults
/// every time).
struct Slot {
    session: Session,
    unpacked: Vec<f32>,
}

/// Loaded model with a pool of sessions.
pub struct Embedder {
    sessions: Vec<Mutex<Slot>>,
    inputs: ModelInputs,
    bits: BitsInput,
    extraction: Option<ExtractorSettings>,
    matcher: Option<String>,
    dim: usize,
    model_id: String,
    path: PathBuf,
}

impl std::fmt::Debug for Embedder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Embedder")
            .field("path", &self.path)
            .field("model_id", &self.model_id)
            .field("inputs", &self.inputs)
            .field("bits", &self.bits)
            .field("extraction", &self.extraction)
            .field("matcher", &self.matcher)
            .field("dim", &self.dim)
            .field("sessions", &self.sessions.len())
            .finish()
    }
}

impl Embedder {
    /// Loads the runtime and the model, checks the contract and runs one warm-up inference per session.
    pub fn load(config: &EmbedderSettings) -> Result<Self, EmbeddingError> {
        let path = config.model.clone();
        let bytes = model_bytes(&path, &default_model_path())?;
        let file_id = format!("sha256:{:x}", Sha256::digest(&bytes));
        let env = environment(&config.runtime_library)?;
        let model_err = |e: ort::Error| EmbeddingError::Model { path: path.clone(), reason: e.to_string() };
        let mut sessions = Vec::new();
        let mut dims = None;
        for _ in 0..config.sessions.max(1) {
            let session = Session::builder(env)
                .map_err(model_err)?
                .with_optimization_level(GraphOptimizationLevel::Level3)
                .map_err(|e| model_err(e.into()))?
                .with_intra_threads(config.intra_threads.max(1))
                .map_err(|e| model_err(e.into()))?
                .with_inter_threads(1)
                .map_err(|e| model_err(e.into()))?
                .with_intra_op_spinning(config.spinning)
                .map_err(|e| model_err(e.into()))?
                .commit_from_memory(&bytes)
                .map_err(model_err)?;
            dims = Some(check_contract(&path, &session)?);
            sessions.push(Mutex::new(Slot { session, unpacked: Vec::new() }));
        }
        let (inputs, bits, dim) = dims.expect("at least one session");
        // One read of the metadata: every session holds the same model.
        let Declaration { extraction, matcher, embeds_as } = declaration(&path, &sessions[0].lock().session)?;
        let model_id = match embeds_as {
            Some(id) => {
                tracing::info!(file = %file_id, model_id = %id, "the model declares the embeddings of another file");
                id
            }
            None => file_id,
        };
        let embedder = Self { sessions, inputs, bits, extraction, matcher, dim, model_id, path };
        embedder.warm_up()?;
        Ok(embedder)
    }

    fn warm_up(&self) -> Result<(), EmbeddingError> {
        let features = synthetic_features(64);
        let context = self.context_of(&features)?;
        for s in &self.sessions {
            run(&mut s.lock(), &features, &context, self.bits, self.dim)?;
        }
        Ok(())
    }

    /// What the model reads besides the FREAK bytes.
    pub fn inputs(&self) -> ModelInputs {
        self.inputs
    }

    /// The extraction the model declares it was trained at, if it declares one.
    pub fn declared_extraction(&self) -> Option<&ExtractorSettings> {
        self.extraction.as_ref()
    }

    /// The extraction to run for this model: the declared one, or revision 2's for a model that declares none.
    pub fn extraction(&self) -> ExtractorSettings {
        self.extraction.clone().unwrap_or_else(ExtractorSettings::revision_2)
    }

    /// The MatchPair matcher the model declares it ships with (a `SconeMatcher` name), if any.
    pub fn declared_matcher(&self) -> Option<&str> {
        self.matcher.as_deref()
    }

    /// Whether the model reads the ring context ([`crate::describe::ring_context`]), which then must come with the features.
    pub fn needs_context(&self) -> bool {
        self.inputs == ModelInputs::RingContext
    }

    /// Constellation size the model was exported for (0 for a ring-context model).
    pub fn k(&self) -> usize {
        match self.inputs {
            ModelInputs::Constellation { k } => k,
            ModelInputs::RingContext => 0,
        }
    }

    /// Embedding dimension.
    pub fn dim(&self) -> usize {
        self.dim
    }

    /// `sha256:<hex>` of the model file, or of the file whose embeddings it declares it gives (`scone.embeds_as`):
    /// maps record it, and refuse queries embedded by another model.
    pub fn model_id(&self) -> &str {
        &self.model_id
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The context the model reads, built for `features` (constellations) or taken from them (ring contexts,
    /// which must be there).
    fn context_of<'a>(&self, features: &'a Features) -> Result<Context<'a>, EmbeddingError> {
        match self.inputs {
            ModelInputs::Constellation { k } => {
                Ok(Context::Constellations(constellation::build(&features.keypoints, k)))
            }
            ModelInputs::RingContext if features.context.len() == features.len() => {
                Ok(Context::Rings(features.context.as_flattened()))
            }
            ModelInputs::RingContext => Err(EmbeddingError::Input {
                reason: format!(
                    "the model reads each keypoint's ring context: {} contexts for {} keypoints",
                    features.context.len(),
                    features.len()
                ),
            }),
        }
    }

    /// Embeddings of every keypoint, row-major `[N, dim]`. A ring model's rows are independent of each other,
    /// so on two or more cores a set of [`SPLIT_FROM`] keypoints or more is split in two halves when a second
    /// session is idle, the second half run on a thread of its own: the same embeddings, bit for bit.
    pub fn embed(&self, features: &Features) -> Result<Vec<f32>, EmbeddingError> {
        let context = self.context_of(features)?;
        if features.is_empty() {
            return Ok(Vec::new());
        }
        let mut first = self.lease();
        if let Context::Rings(rings) = context {
            if features.len() >= SPLIT_FROM && crate::cpu_pool::cores() > 1 {
                if let Some(mut second) = self.try_lease() {
                    let descriptors = features.descriptors.as_flattened();
                    let (a, b) = (&mut first.slot, &mut second.slot);
                    return run_split(a, b, descriptors, rings, self.bits, self.dim);
                }
            }
        }
        run(&mut first.slot, features, &context, self.bits, self.dim)
    }

    /// Sessions in the pool.
    pub fn sessions(&self) -> usize {
        self.sessions.len()
    }

    /// An idle session, without waiting; `None` when every session is in use.
    pub fn try_lease(&self) -> Option<Lease<'_>> {
        self.sessions.iter().find_map(|s| s.try_lock()).map(|slot| Lease { embedder: self, slot })
    }

    /// An idle session, or else the one this thread hashes to, once it is free.
    pub fn lease(&self) -> Lease<'_> {
        self.try_lease().unwrap_or_else(|| {
            let slot = thread_slot() % self.sessions.len();
            Lease { embedder: self, slot: self.sessions[slot].lock() }
        })
    }
}

/// Keypoints from which [`Embedder::embed`] splits a ring model's set over two idle sessions (in halves cut at a
/// multiple of [`ROW_GROUP`] rows).
pub const SPLIT_FROM: usize = 256;

/// Where a ring model's set may be cut into parts run apart, bit for bit the whole: at a multiple of this many
/// rows. onnxruntime's matrix products take rows in small groups, and a part that starts inside one of the
/// whole set's groups can differ from it in the last bit (measured: halves of 350 rows changed values by up to
/// 1.8e-7, halves of 348 none; 64 leaves room for other kernels' groups).
pub const ROW_GROUP: usize = 64;

/// One session of an [`Embedder`]'s pool, held until dropped: a caller that runs several inferences at once
/// (the pipelined describe, `crate::describe::pipeline`) holds one per thread.
pub struct Lease<'a> {
    embedder: &'a Embedder,
    slot: parking_lot::MutexGuard<'a, Slot>,
}

impl Lease<'_> {
    /// Embeddings of every keypoint of `features`, on this lease's session alone.
    pub fn embed(&mut self, features: &Features) -> Result<Vec<f32>, EmbeddingError> {
        let e = self.embedder;
        let context = e.context_of(features)?;
        if features.is_empty() {
            return Ok(Vec::new());
        }
        run(&mut self.slot, features, &context, e.bits, e.dim)
    }

    /// [`Lease::embed`] for a ring model, telling `stage` the time of building the input tensors
    /// (`assembly`), of ONNX Runtime's run (`inference`) and of copying the embeddings out (`output`): the
    /// per-stage accounting of the `stages` bench.
    pub fn embed_rings_staged(&mut self, features: &Features, stage: StageSink) -> Result<Vec<f32>, EmbeddingError> {
        let t = Instant::now();
        let Context::Rings(rings) = self.embedder.context_of(features)? else {
            return Err(EmbeddingError::Input { reason: "not a ring-context model".into() });
        };
        let Slot { session, unpacked } = &mut *self.slot;
        let dim = self.embedder.dim;
        with_ring_inputs(features.descriptors.as_flattened(), rings, self.embedder.bits, unpacked, |inputs| {
            stage("assembly", t.elapsed());
            let t = Instant::now();
            let outputs = session.run(inputs).map_err(inference)?;
            stage("inference", t.elapsed());
            let t = Instant::now();
            let embeddings = embeddings_of(&outputs, features.len(), dim);
            drop(outputs);
            stage("output", t.elapsed());
            embeddings
        })
    }
}

/// `n` made-up keypoints on a grid with their descriptors and ring contexts (the warm-up's inputs).
fn synthetic_features(n: usize) -> Features {
    Features {
        width: 640,
        height: 480,
        keypoints: (0..n)
            .map(|i| crate::describe::features::Keypoint {
                x: 10.0 + (i % 8) as f32 * 20.0,
                y: 10.0 + (i / 8) as f32 * 20.0,
                size: 7.0,
                angle: (i * 37 % 360) as f32,
                response: 1.0,
                octave: 0,
            })
            .collect(),
        descriptors: (0..n).map(|i| [(i * 7) as u8; DESCRIPTOR_BYTES]).collect(),
        context: (0..n).map(|i| [(i * 3) as u8; SAMPLES]).collect(),
    }
}

/// A model's context input for one frame.
enum Context<'a> {
    Constellations(Constellations),
    /// `SAMPLES` bytes per keypoint.
    Rings(&'a [u8]),
}

fn thread_slot() -> usize {
    use std::hash::{Hash, Hasher};
    let mut h = std::collections::hash_map::DefaultHasher::new();
    std::thread::current().id().hash(&mut h);
    h.finish() as usize
}

fn inference(e: ort::Error) -> EmbeddingError {
    EmbeddingError::Inference(e.to_string())
}

fn run(
    slot: &mut Slot,
    f: &Features,
    context: &Context,
    bits: BitsInput,
    dim: usize,
) -> Result<Vec<f32>, EmbeddingError> {
    let n = f.len();
    let c = match context {
        Context::Rings(rings) => return run_rings(slot, f.descriptors.as_flattened(), rings, bits, dim),
        Context::Constellations(c) => c,
    };
    let descriptors =
        Tensor::from_array(([n, DESCRIPTOR_BYTES], f.descriptors.as_flattened().to_vec())).map_err(inference)?;
    let k = c.k;
    let keypoints: Vec<f32> = f.keypoints.iter().flat_map(|p| [p.angle, p.size]).collect();
    let keypoints = Tensor::from_array(([n, 2], keypoints)).map_err(inference)?;
    let neighbours =
        Tensor::from_array(([n, k], c.neighbours.iter().map(|&j| j as i64).collect::<Vec<_>>())).map_err(inference)?;
    let mask = Tensor::from_array(([n, k], c.mask.iter().map(|&m| m as f32).collect::<Vec<_>>())).map_err(inference)?;
    let relative = Tensor::from_array(([n, k, GEOMETRY_DIM], c.relative.as_flattened().to_vec())).map_err(inference)?;
    let outputs = slot
        .session
        .run(ort::inputs![
            "descriptors" => descriptors,
            "keypoints" => keypoints,
            "neighbours" => neighbours,
            "mask" => mask,
            "relative" => relative,
        ])
        .map_err(inference)?;
    embeddings_of(&outputs, n, dim)
}

/// Row v: the 8 bits of the byte value v as -1.0 or +1.0, least significant first (the `bits` input's order).
static BIT_SIGNS: [[f32; 8]; 256] = {
    let mut table = [[-1.0f32; 8]; 256];
    let mut v = 0;
    while v < 256 {
        let mut i = 0;
        while i < 8 {
            if (v >> i) & 1 == 1 {
                table[v][i] = 1.0;
            }
            i += 1;
        }
        v += 1;
    }
    table
};

/// FREAK bytes unpacked to the `bits` input into `out`, whose allocation is reused: 8 floats of ±1 per byte,
/// least significant bit first.
fn unpack_bits_into(descriptors: &[u8], out: &mut Vec<f32>) {
    out.clear();
    out.reserve_exact(descriptors.len() * 8);
    for &byte in descriptors {
        out.extend_from_slice(&BIT_SIGNS[byte as usize]);
    }
}

/// The most a session keeps of its unpacking buffer between calls, in floats: 16 MB, the bits of 8,192
/// keypoints.
const UNPACKED_KEPT: usize = 8192 * BITS;

/// A ring model's inputs, borrowed rather than copied.
type RingInputs<'v> = Vec<(std::borrow::Cow<'static, str>, ort::session::SessionInputValue<'v>)>;

/// Calls `f` with a ring model's two inputs, views of `descriptors` (`DESCRIPTOR_BYTES` per keypoint; when the
/// model reads `bits`, unpacked into `unpacked`, a session's buffer, which keeps its allocation up to
/// [`UNPACKED_KEPT`]) and of `rings` (`SAMPLES` per keypoint).
fn with_ring_inputs<T>(
    descriptors: &[u8],
    rings: &[u8],
    bits: BitsInput,
    unpacked: &mut Vec<f32>,
    f: impl for<'v> FnOnce(RingInputs<'v>) -> Result<T, EmbeddingError>,
) -> Result<T, EmbeddingError> {
    let n = descriptors.len() / DESCRIPTOR_BYTES;
    let context = TensorRef::from_array_view(([n, SAMPLES], rings)).map_err(inference)?;
    match bits {
        BitsInput::Bytes => {
            let descriptors = TensorRef::from_array_view(([n, DESCRIPTOR_BYTES], descriptors)).map_err(inference)?;
            f(ort::inputs!["descriptors" => descriptors, "context" => context])
        }
        BitsInput::Unpacked => {
            unpack_bits_into(descriptors, unpacked);
            let result = match TensorRef::from_array_view(([n, BITS], &unpacked[..])) {
                Ok(view) => f(ort::inputs![BITS_INPUT => view, "context" => context]),
                Err(e) => Err(inference(e)),
            };
            if unpacked.capacity() > UNPACKED_KEPT {
                *unpacked = Vec::new();
            }
            result
        }
    }
}

/// A ring model on `descriptors` (`DESCRIPTOR_BYTES` per keypoint) and `rings` (`SAMPLES` per keypoint).
fn run_rings(
    slot: &mut Slot,
    descriptors: &[u8],
    rings: &[u8],
    bits: BitsInput,
    dim: usize,
) -> Result<Vec<f32>, EmbeddingError> {
    let n = descriptors.len() / DESCRIPTOR_BYTES;
    let Slot { session, unpacked } = slot;
    with_ring_inputs(descriptors, rings, bits, unpacked, |inputs| {
        let outputs = session.run(inputs).map_err(inference)?;
        embeddings_of(&outputs, n, dim)
    })
}

/// [`run_rings`] with the first half of the rows on `first` (this thread) and the second on `second` (a scoped
/// thread); a thread the system refuses leaves both halves to this one.
fn run_split(
    first: &mut Slot,
    second: &mut Slot,
    descriptors: &[u8],
    rings: &[u8],
    bits: BitsInput,
    dim: usize,
) -> Result<Vec<f32>, EmbeddingError> {
    let half = descriptors.len() / DESCRIPTOR_BYTES / 2 / ROW_GROUP * ROW_GROUP;
    let (d1, d2) = descriptors.split_at(half * DESCRIPTOR_BYTES);
    let (r1, r2) = rings.split_at(half * SAMPLES);
    std::thread::scope(|scope| {
        let other = std::thread::Builder::new().spawn_scoped(scope, || run_rings(second, d2, r2, bits, dim));
        let a = run_rings(first, d1, r1, bits, dim);
        let b = match other {
            Ok(t) => t.join().expect("an embedding thread panicked"),
            Err(e) => {
                tracing::debug!(error = %e, "no second thread for the embedding");
                run_rings(first, d2, r2, bits, dim)
            }
        };
        let (mut a, b) = (a?, b?);
        a.extend(b);
        Ok(a)
    })
}

fn embeddings_of(outputs: &ort::session::SessionOutputs, n: usize, dim: usize) -> Result<Vec<f32>, EmbeddingError> {
    let (shape, data) = outputs["embeddings"].try_extract_tensor::<f32>().map_err(inference)?;
    if shape.len() != 2 || shape[0] as usize != n || shape[1] as usize != dim {
        return Err(EmbeddingError::Inference(format!("output shape {shape:?}, expected [{n}, {dim}]")));
    }
    Ok(data.to_vec())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn unpack_bits(descriptors: &[u8]) -> Vec<f32> {
        let mut out = Vec::new();
        unpack_bits_into(descriptors, &mut out);
        out
    }

    #[test]
    fn bits_unpack_least_significant_first_as_plus_or_minus_one() {
        let u = unpack_bits(&[0b0000_0101, 0xff, 0]);
        assert_eq!(u.len(), 24);
        assert_eq!(&u[..8], &[1.0, -1.0, 1.0, -1.0, -1.0, -1.0, -1.0, -1.0]);
        assert!(u[8..16].iter().all(|&v| v == 1.0) && u[16..].iter().all(|&v| v == -1.0));
    }

    /// A session's unpacking buffer is reused: a dirty, longer buffer gives a fresh one's bits; a set beyond
    /// [`UNPACKED_KEPT`] leaves it released; the embeddings are a fresh session's throughout.
    #[test]
    fn a_sessions_unpacking_buffer_is_reused_and_released_beyond_its_cap() {
        let bytes = [0b0000_0101, 0xff, 0];
        let mut buffer = vec![7.0f32; 1000];
        unpack_bits_into(&bytes, &mut buffer);
        assert_eq!(buffer, unpack_bits(&bytes));

        let settings = EmbedderSettings { sessions: 1, ..EmbedderSettings::default() };
        let (e, fresh) = (Embedder::load(&settings).unwrap(), Embedder::load(&settings).unwrap());
        assert!(matches!(e.bits, BitsInput::Unpacked));
        let capacity = || e.sessions[0].lock().unpacked.capacity();
        let (small, large) = (synthetic_features(300), synthetic_features(UNPACKED_KEPT / BITS + 1));
        let first = e.embed(&small).unwrap();
        assert!((300 * BITS..=UNPACKED_KEPT).contains(&capacity()), "{}", capacity());
        assert_eq!(e.embed(&large).unwrap(), fresh.embed(&large).unwrap());
        assert_eq!(capacity(), 0);
        let again = e.embed(&small).unwrap();
        assert!(first == again && again == fresh.embed(&small).unwrap());
    }

    #[test]
    fn built_in_model_is_the_committed_file() {
        assert_eq!(std::fs::read(default_model_path()).unwrap(), BUILT_IN_MODEL);
    }

    #[test]
    fn a_missing_default_model_falls_back_to_the_built_in_copy_and_nothing_else_does() {
        let dir = crate::test_dir::temp_dir("model-bytes");
        let gone = dir.join("scone-freak-k20.onnx");
        assert_eq!(&*model_bytes(&gone, &gone).unwrap(), BUILT_IN_MODEL);
        let other = dir.join("other.onnx");
        match model_bytes(&other, &gone) {
            Err(EmbeddingError::Model { path, reason }) => {
                assert_eq!(path, other);
                assert!(reason.contains("No such file"), "{reason}");
            }
            r => panic!("expected a model error, got {:?}", r.map(|b| b.len())),
        }
        std::fs::write(&gone, b"not a model").unwrap();
        assert_eq!(&*model_bytes(&gone, &gone).unwrap(), b"not a model");
    }
}
