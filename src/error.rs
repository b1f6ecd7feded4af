//! Error types of the core, one enum per layer, each variant carrying the context a caller needs.

/// Errors of the feature layer: decoding, detection, description, client-supplied keypoints.
#[derive(Debug, thiserror::Error)]
pub enum FeatureError {
    #[error("the image is empty (0 bytes)")]
    EmptyImage,
    #[error("unsupported image format: only PNG and JPEG are accepted")]
    UnsupportedFormat,
    #[error("corrupt image: {reason}")]
    CorruptImage { reason: String },
    #[error("image too large: {what} is {value}, the limit is {max}")]
    ImageTooLarge { what: &'static str, value: u64, max: u64 },
    #[error("too many keypoints: {count}, the limit is {max}")]
    TooManyKeypoints { count: usize, max: usize },
    #[error("keypoint {index}: {field} {reason}")]
    InvalidKeypoint { index: usize, field: &'static str, reason: String },
    #[error("descriptors: {reason}")]
    InvalidDescriptors { reason: String },
    /// A client's ring contexts ([`crate::describe::ring_context`]): missing where the model reads them, or the wrong size.
    #[error("context: {reason}")]
    InvalidContext { reason: String },
    #[error("invalid extractor setting {field}: {reason}")]
    InvalidConfig { field: &'static str, reason: String },
    #[error("OpenCV failed: {0}")]
    OpenCv(#[from] opencv::Error),
}

/// Errors reading a scene on disk (TUM RGB-D layout).
#[derive(Debug, thiserror::Error)]
pub enum SceneError {
    #[error("{path}: {source}")]
    Io { path: std::path::PathBuf, source: std::io::Error },
    #[error("{path}:{line}: {reason}")]
    Parse { path: std::path::PathBuf, line: usize, reason: String },
    #[error("{path}: {reason}")]
    Invalid { path: std::path::PathBuf, reason: String },
    #[error("frame {frame}: {source}")]
    Feature { frame: String, source: FeatureError },
}

/// Errors of the embedding layer (ONNX Runtime and the model contract).
#[derive(Debug, thiserror::Error)]
pub enum EmbeddingError {
    #[error("cannot load the ONNX Runtime library {path}: {reason}")]
    Runtime { path: std::path::PathBuf, reason: String },
    #[error("cannot load the model {path}: {reason}")]
    Model { path: std::path::PathBuf, reason: String },
    #[error("the model {path} does not follow the SConE input contract: {reason}")]
    Contract { path: std::path::PathBuf, reason: String },
    #[error("inputs do not fit the model: {reason}")]
    Input { reason: String },
    #[error("inference failed: {0}")]
    Inference(String),
}

/// Errors of pose estimation.
#[derive(Debug, thiserror::Error)]
pub enum PoseError {
    #[error("invalid intrinsics: {reason}")]
    Intrinsics { reason: String },
    #[error("{what} has {got} points, {other} has {expected}")]
    Mismatch { what: &'static str, got: usize, other: &'static str, expected: usize },
    #[error("OpenCV failed: {0}")]
    OpenCv(#[from] opencv::Error),
}

/// Errors of the map layer: storage, model mismatches, unknown ids.
#[derive(Debug, thiserror::Error)]
pub enum MapError {
    #[error("map '{map}' does not exist")]
    UnknownMap { map: String },
    #[error("map '{map}' already exists")]
    MapExists { map: String },
    #[error("invalid map id '{map}': use 1-64 characters from [A-Za-z0-9_-]")]
    InvalidMapId { map: String },
    #[error("map '{map}' has no keyframe {keyframe}")]
    UnknownKeyframe { map: String, keyframe: u64 },
    #[error("map '{map}' already has keyframe {keyframe}")]
    KeyframeExists { map: String, keyframe: u64 },
    #[error("map '{map}' was embedded by model {map_model}, this service runs {model}: re-embed it first (scone map reembed)")]
    ModelMismatch { map: String, map_model: String, model: String },
    #[error("map '{map}' is unavailable: {reason}")]
    Unavailable { map: String, reason: String },
    /// The map's manifest in object storage was replaced by another writer: this copy is stale and refuses
    /// writes (one writer per map).
    #[error(
        "map '{map}' was written by another writer ({writer}) since this replica loaded it: this copy refuses \
         writes until the map is reloaded"
    )]
    WriterConflict { map: String, writer: String },
    #[error("invalid {field}: {reason}")]
    InvalidInput { field: String, reason: String },
    #[error("{path}: {reason}")]
    Corrupt { path: std::path::PathBuf, reason: String },
    #[error("{path}: {source}")]
    Io { path: std::path::PathBuf, source: std::io::Error },
    /// Object storage did not complete a call: unreachable, an error answer after the client's own retries,
    /// or a write whose outcome it could not confirm. Nothing of the request was acknowledged, and a retry
    /// can succeed. `detail` (the object and the storage service's answer) is for the log, not the client.
    #[error("the map storage did not complete the request ({detail}); nothing of it was acknowledged: retry it")]
    StorageUnavailable { detail: String },
    /// The object storage bucket the maps are configured to live in does not exist.
    #[error("the object storage bucket '{bucket}' does not exist: create it, or set store.backend.bucket")]
    NoBucket { bucket: String },
    /// The volume that holds the maps (or their index dumps) has no space left (ENOSPC, or a quota). The write
    /// that met it was undone: nothing of it is stored.
    #[error("no space left on the data volume: {path} could not be written")]
    StorageFull { path: std::path::PathBuf },
    #[error(transparent)]
    Feature(#[from] FeatureError),
    #[error(transparent)]
    Embedding(#[from] EmbeddingError),
    #[error(transparent)]
    Pose(#[from] PoseError),
}

/// Errors of importing a map made by an external SfM (a COLMAP model, [`crate::offline::colmap`]).
#[derive(Debug, thiserror::Error)]
pub enum ImportError {
    /// The model's files (file and line named).
    #[error(transparent)]
    Model(#[from] SceneError),
    #[error("image {image} ({path}): {reason}")]
    Image { image: u32, path: std::path::PathBuf, reason: String },
    #[error(transparent)]
    Map(#[from] MapError),
}
