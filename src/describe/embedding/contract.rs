//! The model contract and what a model declares, checked when it loads (the parent module's documentation
//! gives both).

use std::path::Path;

use ort::session::Session;
use ort::value::{TensorElementType, ValueType};

use crate::describe::constellation::GEOMETRY_DIM;
use crate::describe::features::{ExtractorSettings, DESCRIPTOR_BYTES};
use crate::describe::ring_context::SAMPLES;
use crate::error::EmbeddingError;

/// The metadata key of a model's extraction.
pub const EXTRACTION_KEY: &str = "scone.extraction";
/// The metadata key of a model's MatchPair matcher.
pub const MATCHER_KEY: &str = "scone.matcher";
/// The metadata key of the model id a graph's embeddings are those of.
pub const EMBEDS_AS_KEY: &str = "scone.embeds_as";
/// The input of a ring model that reads the FREAK bits unpacked.
pub(super) const BITS_INPUT: &str = "bits";
/// FREAK's bits per keypoint.
pub(super) const BITS: usize = DESCRIPTOR_BYTES * 8;

/// What a model reads besides each keypoint's FREAK bytes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ModelInputs {
    /// The paper's constellation: each keypoint's `k` nearest keypoints with their relative geometry.
    Constellation { k: usize },
    /// The ring context: the image around each keypoint at fixed places in its frame ([`crate::describe::ring_context`]).
    RingContext,
}

/// How a model reads each keypoint's FREAK bytes: as they are (`descriptors`), or unpacked to ±1 (`bits`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum BitsInput {
    Bytes,
    Unpacked,
}

/// Dimensions of a tensor outlet, or a contract error naming it.
fn tensor_spec(path: &Path, name: &str, ty: &ValueType) -> Result<(TensorElementType, Vec<i64>), EmbeddingError> {
    match ty {
        ValueType::Tensor { ty, shape, .. } => Ok((*ty, shape.iter().copied().collect())),
        other => {
            Err(EmbeddingError::Contract { path: path.into(), reason: format!("{name} is {other:?}, not a tensor") })
        }
    }
}

/// Checks names, element types and static dimensions; returns what the model reads, how it reads the FREAK
/// bytes and its embedding dimension.
pub(super) fn check_contract(
    path: &Path,
    session: &Session,
) -> Result<(ModelInputs, BitsInput, usize), EmbeddingError> {
    let err = |reason: String| EmbeddingError::Contract { path: path.into(), reason };
    let inputs: Vec<(String, TensorElementType, Vec<i64>)> = session
        .inputs()
        .iter()
        .map(|o| tensor_spec(path, o.name(), o.dtype()).map(|(t, s)| (o.name().to_string(), t, s)))
        .collect::<Result<_, _>>()?;
    let find = |name: &str| {
        inputs.iter().find(|i| i.0 == name).ok_or_else(|| {
            err(format!("missing input '{name}' (inputs: {:?})", inputs.iter().map(|i| &i.0).collect::<Vec<_>>()))
        })
    };
    let expect = |name: &str, ty: TensorElementType, rank: usize| -> Result<Vec<i64>, EmbeddingError> {
        let (_, t, s) = find(name)?;
        if *t != ty {
            return Err(err(format!("input '{name}' has element type {t:?}, expected {ty:?}")));
        }
        if s.len() != rank {
            return Err(err(format!("input '{name}' has rank {} ({s:?}), expected {rank}", s.len())));
        }
        Ok(s.clone())
    };
    let fixed = |name: &str, s: &[i64], axis: usize, want: i64| -> Result<(), EmbeddingError> {
        if s[axis] != want {
            return Err(err(format!("input '{name}' has dimension {axis} = {}, expected {want}", s[axis])));
        }
        Ok(())
    };
    let bits = if inputs.iter().any(|i| i.0 == BITS_INPUT) {
        if inputs.iter().any(|i| i.0 == "descriptors") {
            return Err(err(format!("inputs '{BITS_INPUT}' and 'descriptors' both read the FREAK bits: one of them")));
        }
        if !inputs.iter().any(|i| i.0 == "context") {
            return Err(err(format!("input '{BITS_INPUT}' is read by ring-context models only (no input 'context')")));
        }
        let b = expect(BITS_INPUT, TensorElementType::Float32, 2)?;
        fixed(BITS_INPUT, &b, 1, BITS as i64)?;
        BitsInput::Unpacked
    } else {
        let d = expect("descriptors", TensorElementType::Uint8, 2)?;
        fixed("descriptors", &d, 1, DESCRIPTOR_BYTES as i64)?;
        BitsInput::Bytes
    };
    let kind = if inputs.iter().any(|i| i.0 == "context") {
        if inputs.len() != 2 {
            return Err(err(format!("a ring-context model has 2 inputs, found {}", inputs.len())));
        }
        let c = expect("context", TensorElementType::Uint8, 2)?;
        fixed("context", &c, 1, SAMPLES as i64)?;
        ModelInputs::RingContext
    } else {
        if inputs.len() != 5 {
            return Err(err(format!("expected 5 inputs, found {}", inputs.len())));
        }
        let kp = expect("keypoints", TensorElementType::Float32, 2)?;
        fixed("keypoints", &kp, 1, 2)?;
        let nb = expect("neighbours", TensorElementType::Int64, 2)?;
        if nb[1] < 1 {
            return Err(err(format!("input 'neighbours' needs a static k, found {}", nb[1])));
        }
        let k = nb[1];
        let m = expect("mask", TensorElementType::Float32, 2)?;
        fixed("mask", &m, 1, k)?;
        let rel = expect("relative", TensorElementType::Float32, 3)?;
        fixed("relative", &rel, 1, k)?;
        fixed("relative", &rel, 2, GEOMETRY_DIM as i64)?;
        ModelInputs::Constellation { k: k as usize }
    };
    let out = session.outputs();
    if out.len() != 1 || out[0].name() != "embeddings" {
        return Err(err(format!(
            "expected one output 'embeddings', found {:?}",
            out.iter().map(|o| o.name()).collect::<Vec<_>>()
        )));
    }
    let (ty, shape) = tensor_spec(path, "embeddings", out[0].dtype())?;
    if ty != TensorElementType::Float32 || shape.len() != 2 || shape[1] < 1 {
        return Err(err(format!("output 'embeddings' is {ty:?} {shape:?}, expected float32 [N, D]")));
    }
    Ok((kind, bits, shape[1] as usize))
}

/// What a model declares in its metadata.
pub(super) struct Declaration {
    pub(super) extraction: Option<ExtractorSettings>,
    pub(super) matcher: Option<String>,
    pub(super) embeds_as: Option<String>,
}

/// The model's declared extraction, matcher and embedding id ([`EXTRACTION_KEY`], [`MATCHER_KEY`],
/// [`EMBEDS_AS_KEY`]); an extraction that does not parse or validate, or an id that is not `sha256:` and 64
/// lowercase hex digits, is a contract error.
pub(super) fn declaration(path: &Path, session: &Session) -> Result<Declaration, EmbeddingError> {
    let err = |reason: String| EmbeddingError::Contract { path: path.into(), reason };
    let meta = session.metadata().map_err(|e| err(format!("reading the model's metadata: {e}")))?;
    let extraction = match meta.custom(EXTRACTION_KEY) {
        None => None,
        Some(text) => {
            let bad = |why: String| err(format!("metadata '{EXTRACTION_KEY}' is not an extraction ({why}): {text}"));
            // Every field, so that a default of this build cannot stand in for what the model was trained at.
            let value: serde_json::Value = serde_json::from_str(&text).map_err(|e| bad(e.to_string()))?;
            let fields = |v: &serde_json::Value| v.as_object().map_or(0, |o| o.len());
            let given = fields(&value);
            let all = serde_json::to_value(ExtractorSettings::default()).map_or(0, |v| fields(&v));
            if given != all {
                return Err(bad(format!("{given} fields, every field of the extraction is needed")));
            }
            let e: ExtractorSettings = serde_json::from_value(value).map_err(|e| bad(e.to_string()))?;
            e.validate().map_err(|e| err(format!("metadata '{EXTRACTION_KEY}': {e}")))?;
            Some(e)
        }
    };
    let embeds_as = meta.custom(EMBEDS_AS_KEY);
    if let Some(id) = &embeds_as {
        let hex = id.strip_prefix("sha256:").unwrap_or("");
        if hex.len() != 64 || !hex.bytes().all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b)) {
            return Err(err(format!("metadata '{EMBEDS_AS_KEY}' is not a model id (sha256: and 64 hex digits): {id}")));
        }
    }
    Ok(Declaration { extraction, matcher: meta.custom(MATCHER_KEY), embeds_as })
}
