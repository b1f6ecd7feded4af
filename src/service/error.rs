//! What went wrong, for a client ([`ServiceError`]), and the one classification of every failure of the core
//! into the kinds the transports map to their codes ([`ErrorKind`]: gRPC codes, HTTP statuses).

use crate::describe::pipeline::DescribeError;
use crate::error::{EmbeddingError, FeatureError, MapError, PoseError};

/// What a write's deadline answer adds: the outcome is unknown, and how a client learns it.
pub const WRITE_OUTCOME: &str = "; the write may still complete: read the map (GetMap, or GET \
     /v1/maps/{map_id}/contents for its keyframes) to see whether it did, or send it again, which is answered \
     ALREADY_EXISTS (HTTP 409) once it has";

/// What went wrong, for a client; [`ServiceError::kind`] classifies it for the transports.
#[derive(Debug, thiserror::Error)]
pub enum ServiceError {
    #[error("invalid {field}: {reason}")]
    InvalidArgument { field: String, reason: String },
    #[error("the keypoints were computed for model {client}, this service runs {server}")]
    ModelMismatch { client: String, server: String },
    #[error(transparent)]
    Feature(#[from] FeatureError),
    #[error(transparent)]
    Embedding(#[from] EmbeddingError),
    #[error(transparent)]
    Pose(#[from] PoseError),
    #[error(transparent)]
    Map(#[from] MapError),
    #[error("the service is starting: maps are still loading")]
    NotReady,
    #[error("the service is shutting down")]
    ShuttingDown,
    #[error("the service is saturated ({queued} requests waiting): retry later")]
    Overloaded { queued: usize },
    /// The deadline passed while the request was queued or running. A write may still complete after it
    /// (its work is not interrupted half way, which could lose what it had acknowledged to storage), so its
    /// answer says how to find out.
    #[error("the request did not finish within {ms} ms{}", if *write { WRITE_OUTCOME } else { "" })]
    DeadlineExceeded { ms: u64, write: bool },
    #[error("missing or unknown API key: send one in the x-api-key header")]
    Unauthenticated,
    #[error("this API key is read-only; {operation} needs a write key")]
    PermissionDenied { operation: String },
    #[error("{what} is larger than the limit of {limit} bytes")]
    TooLarge { what: String, limit: usize },
    #[error("internal error: {0}")]
    Internal(String),
}

impl From<DescribeError> for ServiceError {
    fn from(e: DescribeError) -> Self {
        match e {
            DescribeError::Feature(f) => Self::Feature(f),
            DescribeError::Embedding(e) => Self::Embedding(e),
        }
    }
}

/// The classes of failure a transport distinguishes (gRPC codes, HTTP statuses).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ErrorKind {
    InvalidArgument,
    NotFound,
    AlreadyExists,
    FailedPrecondition,
    Unavailable,
    ResourceExhausted,
    /// The data volume is full: the write was not made (gRPC RESOURCE_EXHAUSTED, HTTP 507).
    InsufficientStorage,
    PayloadTooLarge,
    DeadlineExceeded,
    Unauthenticated,
    PermissionDenied,
    Internal,
}

fn feature_kind(e: &FeatureError) -> ErrorKind {
    match e {
        FeatureError::EmptyImage
        | FeatureError::UnsupportedFormat
        | FeatureError::CorruptImage { .. }
        | FeatureError::ImageTooLarge { .. }
        | FeatureError::TooManyKeypoints { .. }
        | FeatureError::InvalidKeypoint { .. }
        | FeatureError::InvalidDescriptors { .. }
        | FeatureError::InvalidContext { .. } => ErrorKind::InvalidArgument,
        FeatureError::InvalidConfig { .. } | FeatureError::OpenCv(_) => ErrorKind::Internal,
    }
}

fn embedding_kind(e: &EmbeddingError) -> ErrorKind {
    match e {
        EmbeddingError::Input { .. } => ErrorKind::InvalidArgument,
        EmbeddingError::Runtime { .. }
        | EmbeddingError::Model { .. }
        | EmbeddingError::Contract { .. }
        | EmbeddingError::Inference(_) => ErrorKind::Internal,
    }
}

fn pose_kind(e: &PoseError) -> ErrorKind {
    match e {
        PoseError::Intrinsics { .. } => ErrorKind::InvalidArgument,
        PoseError::Mismatch { .. } | PoseError::OpenCv(_) => ErrorKind::Internal,
    }
}

fn map_kind(e: &MapError) -> ErrorKind {
    match e {
        MapError::UnknownMap { .. } | MapError::UnknownKeyframe { .. } => ErrorKind::NotFound,
        MapError::MapExists { .. } | MapError::KeyframeExists { .. } => ErrorKind::AlreadyExists,
        MapError::InvalidMapId { .. } | MapError::InvalidInput { .. } => ErrorKind::InvalidArgument,
        MapError::ModelMismatch { .. } => ErrorKind::FailedPrecondition,
        MapError::Unavailable { .. }
        | MapError::WriterConflict { .. }
        | MapError::StorageUnavailable { .. }
        | MapError::NoBucket { .. } => ErrorKind::Unavailable,
        MapError::Corrupt { .. } | MapError::Io { .. } => ErrorKind::Internal,
        MapError::StorageFull { .. } => ErrorKind::InsufficientStorage,
        MapError::Feature(f) => feature_kind(f),
        MapError::Embedding(e) => embedding_kind(e),
        MapError::Pose(p) => pose_kind(p),
    }
}

impl ServiceError {
    pub fn invalid(field: impl Into<String>, reason: impl Into<String>) -> Self {
        Self::InvalidArgument { field: field.into(), reason: reason.into() }
    }

    /// The class of the error. Exhaustive on purpose: a new variant anywhere below must be classified.
    pub fn kind(&self) -> ErrorKind {
        match self {
            Self::InvalidArgument { .. } => ErrorKind::InvalidArgument,
            Self::ModelMismatch { .. } => ErrorKind::FailedPrecondition,
            Self::Feature(e) => feature_kind(e),
            Self::Embedding(e) => embedding_kind(e),
            Self::Pose(e) => pose_kind(e),
            Self::Map(e) => map_kind(e),
            Self::NotReady | Self::ShuttingDown => ErrorKind::Unavailable,
            Self::Overloaded { .. } => ErrorKind::ResourceExhausted,
            Self::DeadlineExceeded { .. } => ErrorKind::DeadlineExceeded,
            Self::Unauthenticated => ErrorKind::Unauthenticated,
            Self::PermissionDenied { .. } => ErrorKind::PermissionDenied,
            Self::TooLarge { .. } => ErrorKind::PayloadTooLarge,
            Self::Internal(_) => ErrorKind::Internal,
        }
    }

    /// What the client is told: the precise message for its own mistakes, a generic one for ours (the real
    /// error goes to the log).
    pub fn client_message(&self) -> String {
        if let Self::Map(MapError::StorageUnavailable { .. }) = self {
            return "the map storage did not complete the request; nothing of it was acknowledged: retry it".into();
        }
        match self.kind() {
            ErrorKind::Internal => "internal error; the server log has the details".to_string(),
            ErrorKind::InsufficientStorage => "insufficient storage: the data volume (store.data_dir) is full; \
                                               nothing of this write was stored, and writes resume once space \
                                               is freed"
                .to_string(),
            _ => self.to_string(),
        }
    }

    /// Seconds a client should wait before retrying, for errors where retrying helps.
    pub fn retry_after_s(&self) -> Option<u64> {
        match self {
            Self::Overloaded { .. } => Some(1),
            Self::NotReady | Self::ShuttingDown => Some(5),
            Self::Map(MapError::StorageUnavailable { .. }) => Some(1),
            _ => None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_write_past_its_deadline_says_it_may_still_complete_and_how_to_find_out() {
        let write = ServiceError::DeadlineExceeded { ms: 10_000, write: true }.client_message();
        assert!(write.starts_with("the request did not finish within 10000 ms; the write may still complete"));
        assert!(write.contains("/v1/maps/{map_id}/contents") && write.contains("ALREADY_EXISTS (HTTP 409)"), "{write}");
        let read = ServiceError::DeadlineExceeded { ms: 10_000, write: false }.client_message();
        assert_eq!(read, "the request did not finish within 10000 ms");
        assert_eq!(ServiceError::DeadlineExceeded { ms: 1, write: true }.kind(), ErrorKind::DeadlineExceeded);
    }
}
