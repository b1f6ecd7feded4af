//! A keyframe's payload: its keypoints, FREAK descriptors and the SConE embedding of every keypoint. Only map
//! building, re-embedding, merging and exports read it; relocalisation reads the observations' embeddings,
//! which the map keeps in memory. So the payload stays in memory only until a snapshot holds it: from then
//! on a keyframe keeps where its payload is in that snapshot's file (a [`Span`] of its payload section), and
//! reads it from there when asked ([`MapKeyframe::load`]).
//!
//! A payload is in memory for a keyframe written since the last snapshot (at most the
//! journal's `compact_every` records of them), or one of a map decoded from bytes (an import, a format-2
//! snapshot) until its first snapshot. Once stored, its file stays open, so a snapshot
//! replaced by a compaction is still read until every keyframe points into the new one. Every payload's CRC-32
//! is checked when the snapshot loads, and again at each read, so a payload damaged later is an error of that
//! read, never a wrong keypoint. Object storage's copy of a snapshot gets its payload section after the map
//! is loaded ([`PayloadFile::arriving`]): its checksums are checked when it arrives, and reads wait for it.

use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Condvar, Mutex, MutexGuard, PoisonError};

use serde::{Deserialize, Serialize};

use crate::camera::{Camera, Pose};
use crate::describe::features::{from_precomputed, Features, Keypoint, KeypointLimitSettings, DESCRIPTOR_BYTES};
use crate::error::{FeatureError, MapError};
use crate::map::encoding::{encode, Encoding};

/// A keyframe with its payload, as records carry it and map building makes it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Keyframe {
    pub id: u64,
    pub pose: Pose,
    pub camera: Camera,
    pub keypoints: Vec<Keypoint>,
    /// FREAK descriptors, `keypoints.len() x 64` bytes. Read and written as bytes in one piece (in formats 1 to
    /// 3, bincode 1 encoded bytes exactly as a `Vec<u8>`: `map::tests::descriptors_as_bytes_encode_as_before`).
    #[serde(with = "serde_bytes")]
    pub descriptors: Vec<u8>,
    /// SConE embeddings of every keypoint, `keypoints.len() x dim` (matching new keyframes against this one).
    pub embeddings: Vec<f32>,
}

impl Keyframe {
    pub fn descriptor(&self, i: usize) -> &[u8] {
        &self.descriptors[i * DESCRIPTOR_BYTES..(i + 1) * DESCRIPTOR_BYTES]
    }

    pub fn embedding(&self, i: usize, dim: usize) -> &[f32] {
        &self.embeddings[i * dim..(i + 1) * dim]
    }

    /// The keypoints and FREAK descriptors the keyframe stores, as features a model embeds again (a map
    /// re-embedded after a model upgrade). They passed the keypoint checks when the keyframe was written; its
    /// keypoint count is not limited again.
    pub fn features(&self) -> Result<Features, FeatureError> {
        let limits = KeypointLimitSettings { max_keypoints: usize::MAX, ..Default::default() };
        from_precomputed(self.camera.width, self.camera.height, self.keypoints.clone(), &self.descriptors, &limits)
    }
}

/// The part of a [`Keyframe`] a snapshot's payload section holds, in the same order, in the encoding of the
/// snapshot's format ([`crate::map::encoding`]).
#[derive(Serialize)]
struct PayloadRef<'a> {
    keypoints: &'a [Keypoint],
    #[serde(with = "serde_bytes")]
    descriptors: &'a [u8],
    embeddings: &'a [f32],
}

#[derive(Deserialize)]
struct PayloadOwned {
    keypoints: Vec<Keypoint>,
    #[serde(with = "serde_bytes")]
    descriptors: Vec<u8>,
    embeddings: Vec<f32>,
}

/// Where a payload is in its file's payload section: byte offset from the section's start, length, CRC-32.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Span {
    pub offset: u64,
    pub len: u64,
    pub crc: u32,
}

/// A file that holds a payload section (a snapshot: the local map's, or object storage's copy in the cache
/// directory), open for reads at offsets.
#[derive(Debug)]
pub struct PayloadFile {
    path: PathBuf,
    file: std::fs::File,
    /// Byte offset of the section in the file, and its length.
    base: u64,
    len: u64,
    /// The encoding of the payloads in the section (the snapshot's format).
    encoding: Encoding,
    /// The section when it is still to arrive (object storage's copy, whose map is ready before it).
    pending: Option<Pending>,
}

/// What fetches a payload section into its file and checks it (every payload's CRC): object storage's
/// download of the snapshot's section.
pub type FetchSection = Box<dyn Fn() -> Result<(), MapError> + Send + Sync>;

/// A payload section that arrives after its map is loaded: the first read (or the backend's own thread)
/// fetches it, and every other read waits until it is there. A failed fetch fails the reads that waited for
/// it and is tried again by the next read, unless it found the section damaged, which every read then
/// reports.
struct Pending {
    state: Mutex<Arrival>,
    arrived: Condvar,
    fetch: FetchSection,
}

#[derive(Debug, Clone, PartialEq)]
enum Arrival {
    Waiting,
    /// Fetch number n (from 1) is running.
    Fetching(u64),
    Done,
    /// Fetch number n failed, as the message says.
    Failed(u64, String),
    /// The fetch's error, as it named the damage (the object, not the copy).
    Damaged(PathBuf, String),
}

impl std::fmt::Debug for Pending {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Pending").field("state", &*lock(&self.state)).finish_non_exhaustive()
    }
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(PoisonError::into_inner)
}

/// Puts a fetch that did not finish (it panicked) to [`Arrival::Failed`], so that readers do not wait for it
/// forever: the pending section, the fetch's number, and whether it finished.
struct FetchGuard<'a>(&'a Pending, u64, bool);

impl Drop for FetchGuard<'_> {
    fn drop(&mut self) {
        if !self.2 {
            *lock(&self.0.state) = Arrival::Failed(self.1, "the fetch panicked".into());
            self.0.arrived.notify_all();
        }
    }
}

impl PayloadFile {
    /// Opens `path`, whose payload section is `len` bytes from byte `base` (the file must hold them; the
    /// snapshot's core follows them), its payloads in `encoding`.
    pub fn open(path: &Path, base: u64, len: u64, encoding: Encoding) -> Result<Arc<Self>, MapError> {
        Self::open_at(path, base, len, encoding).map(Arc::new)
    }

    fn open_at(path: &Path, base: u64, len: u64, encoding: Encoding) -> Result<Self, MapError> {
        let file = std::fs::File::open(path).map_err(|source| MapError::Io { path: path.to_path_buf(), source })?;
        let size = file.metadata().map_err(|source| MapError::Io { path: path.to_path_buf(), source })?.len();
        if base.checked_add(len).is_none_or(|end| end > size) {
            return Err(MapError::Corrupt {
                path: path.to_path_buf(),
                reason: format!("payload section of {len} bytes at byte {base}, but the file is {size} bytes"),
            });
        }
        Ok(Self { path: path.to_path_buf(), file, base, len, encoding, pending: None })
    }

    /// [`PayloadFile::open`] of a file whose section is still to arrive: `fetch` writes it there and checks
    /// it, run by the first caller of [`PayloadFile::arrive`] (a read, or the backend's thread).
    pub fn arriving(
        path: &Path,
        base: u64,
        len: u64,
        encoding: Encoding,
        fetch: FetchSection,
    ) -> Result<Arc<Self>, MapError> {
        let pending = Pending { state: Mutex::new(Arrival::Waiting), arrived: Condvar::new(), fetch };
        Ok(Arc::new(Self { pending: Some(pending), ..Self::open_at(path, base, len, encoding)? }))
    }

    /// Returns once the section is in the file (at once for one that was always there), fetching it when no
    /// one else is; the fetch's error otherwise.
    pub fn arrive(&self) -> Result<(), MapError> {
        let Some(p) = &self.pending else { return Ok(()) };
        let mut state = lock(&p.state);
        let mut waited_for = None;
        let attempt = loop {
            match &*state {
                Arrival::Done => return Ok(()),
                Arrival::Damaged(path, reason) => {
                    return Err(MapError::Corrupt { path: path.clone(), reason: reason.clone() })
                }
                Arrival::Fetching(n) => {
                    waited_for = Some(*n);
                    state = p.arrived.wait(state).unwrap_or_else(PoisonError::into_inner);
                }
                // The fetch this read waited for failed: so does the read (the next one tries again).
                Arrival::Failed(n, detail) if waited_for == Some(*n) => {
                    return Err(MapError::StorageUnavailable {
                        detail: format!("the payload section did not arrive: {detail}"),
                    })
                }
                Arrival::Failed(n, _) => break n + 1,
                Arrival::Waiting => break 1,
            }
        };
        *state = Arrival::Fetching(attempt);
        drop(state);
        let mut guard = FetchGuard(p, attempt, false);
        let fetched = (p.fetch)();
        *lock(&p.state) = match &fetched {
            Ok(()) => Arrival::Done,
            Err(MapError::Corrupt { path, reason }) => Arrival::Damaged(path.clone(), reason.clone()),
            Err(e) => Arrival::Failed(attempt, e.to_string()),
        };
        guard.2 = true;
        p.arrived.notify_all();
        fetched
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    fn corrupt(&self, reason: String) -> MapError {
        MapError::Corrupt { path: self.path.clone(), reason }
    }

    /// Checks every payload `spans` names (read in file order, one at a time): a map whose payloads are
    /// damaged is refused when it loads, as one whose core is, not at the first write that reads them.
    pub fn verify(&self, spans: impl Iterator<Item = Span>) -> Result<(), MapError> {
        let mut spans: Vec<Span> = spans.collect();
        spans.sort_by_key(|s| s.offset);
        for span in spans {
            self.read_raw(span)?;
        }
        Ok(())
    }

    /// The bytes of `span`, once their CRC matched (and the section arrived).
    pub fn read_raw(&self, span: Span) -> Result<Vec<u8>, MapError> {
        self.arrive()?;
        if span.offset.checked_add(span.len).is_none_or(|end| end > self.len) {
            return Err(self.corrupt(format!("payload span {span:?} beyond the section's {} bytes", self.len)));
        }
        let mut buf = vec![0u8; span.len as usize];
        self.file
            .read_exact_at(&mut buf, self.base + span.offset)
            .map_err(|source| MapError::Io { path: self.path.clone(), source })?;
        if crc32fast::hash(&buf) != span.crc {
            return Err(self.corrupt(format!("payload at byte {}: checksum mismatch", self.base + span.offset)));
        }
        Ok(buf)
    }
}

/// Where a keyframe's payload is.
#[derive(Debug, Clone)]
enum Payload {
    /// In memory.
    Inline(Arc<Keyframe>),
    /// In a payload section on disk.
    Stored { file: Arc<PayloadFile>, span: Span },
}

/// A keyframe of a loaded map: pose, camera and keypoint count in memory, the payload in memory or on disk.
#[derive(Debug, Clone)]
pub struct MapKeyframe {
    pub id: u64,
    pub pose: Pose,
    pub camera: Camera,
    /// How many keypoints (and so descriptors and embeddings) the payload holds.
    pub keypoints: usize,
    payload: Payload,
}

impl MapKeyframe {
    /// A keyframe whose payload is in memory.
    pub fn inline(keyframe: Keyframe) -> Self {
        Self {
            id: keyframe.id,
            pose: keyframe.pose,
            camera: keyframe.camera,
            keypoints: keyframe.keypoints.len(),
            payload: Payload::Inline(Arc::new(keyframe)),
        }
    }

    /// A keyframe whose payload is `span` of `file`.
    pub fn stored(id: u64, pose: Pose, camera: Camera, keypoints: usize, file: Arc<PayloadFile>, span: Span) -> Self {
        Self { id, pose, camera, keypoints, payload: Payload::Stored { file, span } }
    }

    /// The keyframe when its payload is in memory.
    pub fn inline_keyframe(&self) -> Option<&Keyframe> {
        match &self.payload {
            Payload::Inline(k) => Some(k),
            Payload::Stored { .. } => None,
        }
    }

    /// Points the keyframe at a stored copy of its payload (after a snapshot that holds it is durable).
    pub fn set_stored(&mut self, file: Arc<PayloadFile>, span: Span) {
        self.payload = Payload::Stored { file, span };
    }

    /// The whole keyframe, its payload read from disk when it is stored there.
    pub fn load(&self) -> Result<Arc<Keyframe>, MapError> {
        match &self.payload {
            Payload::Inline(k) => Ok(Arc::clone(k)),
            Payload::Stored { file, span } => {
                let bytes = file.read_raw(*span)?;
                let k = decode_payload(self.id, self.pose, self.camera, &bytes, file.encoding)
                    .map_err(|e| file.corrupt(format!("payload of keyframe {}: {e}", self.id)))?;
                if k.keypoints.len() != self.keypoints {
                    return Err(file.corrupt(format!(
                        "payload of keyframe {} holds {} keypoints, the map says {}",
                        self.id,
                        k.keypoints.len(),
                        self.keypoints
                    )));
                }
                Ok(Arc::new(k))
            }
        }
    }

    /// The payload as a payload section of the current format holds it: read as it is (its CRC checked) when
    /// stored in that format, decoded and encoded again when stored in an older one (an upgrade), encoded when
    /// in memory.
    pub fn payload_bytes(&self) -> Result<Vec<u8>, MapError> {
        match &self.payload {
            Payload::Inline(k) => Ok(encode_payload(k)),
            Payload::Stored { file, span } if file.encoding == Encoding::CURRENT => file.read_raw(*span),
            Payload::Stored { .. } => Ok(encode_payload(&*self.load()?)),
        }
    }

    /// Memory the keyframe takes while loaded: its head, and its payload when that is in memory.
    pub fn memory_bytes(&self) -> usize {
        match &self.payload {
            Payload::Inline(k) => inline_memory_bytes(k),
            Payload::Stored { .. } => std::mem::size_of::<Self>(),
        }
    }
}

/// Memory a keyframe takes while loaded with its payload in memory (a keyframe written since the last
/// snapshot).
pub fn inline_memory_bytes(k: &Keyframe) -> usize {
    std::mem::size_of::<MapKeyframe>()
        + std::mem::size_of::<Keyframe>()
        + k.keypoints.len() * std::mem::size_of::<Keypoint>()
        + k.descriptors.len()
        + k.embeddings.len() * 4
}

/// Two keyframes are equal when their heads and payloads are, wherever the payloads are (an unreadable
/// payload equals nothing).
impl PartialEq for MapKeyframe {
    fn eq(&self, other: &Self) -> bool {
        if (self.id, self.pose, self.camera, self.keypoints) != (other.id, other.pose, other.camera, other.keypoints) {
            return false;
        }
        match (&self.payload, &other.payload) {
            (Payload::Inline(a), Payload::Inline(b)) if Arc::ptr_eq(a, b) => true,
            _ => matches!((self.load(), other.load()), (Ok(a), Ok(b)) if a == b),
        }
    }
}

/// A keyframe from its head and the bytes of its payload in `encoding` ([`encode_payload`]).
pub fn decode_payload(
    id: u64,
    pose: Pose,
    camera: Camera,
    bytes: &[u8],
    encoding: Encoding,
) -> Result<Keyframe, String> {
    let p: PayloadOwned = encoding.decode(bytes)?;
    Ok(Keyframe { id, pose, camera, keypoints: p.keypoints, descriptors: p.descriptors, embeddings: p.embeddings })
}

/// Where a snapshot just written keeps each keyframe's payload: its file, and keyframe id -> span.
#[derive(Debug, Clone)]
pub struct StoredPayloads {
    pub file: Arc<PayloadFile>,
    pub spans: Vec<(u64, Span)>,
    /// The map version the snapshot holds.
    pub version: u64,
}

/// The bytes of a keyframe's payload in a payload section of the current format (keypoints, descriptors,
/// embeddings).
pub fn encode_payload(k: &Keyframe) -> Vec<u8> {
    let p = PayloadRef { keypoints: &k.keypoints, descriptors: &k.descriptors, embeddings: &k.embeddings };
    encode(&p).expect("vectors of plain values encode")
}

/// [`encode_payload`] in bincode 1's layout, as a format-3 payload section holds it (for tests that make maps
/// of that format; the service never writes it).
pub fn encode_payload_bincode1(k: &Keyframe) -> Vec<u8> {
    let p = PayloadRef { keypoints: &k.keypoints, descriptors: &k.descriptors, embeddings: &k.embeddings };
    crate::map::encoding::encode_bincode1(&p)
}
