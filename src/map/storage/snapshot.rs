//! Snapshots: the whole map in one file (`snapshot.bin`, an object-storage snapshot, and the export file),
//! in the format this build writes and the older ones it reads ([`crate::map::storage::format`] lists the
//! versions).
//!
//! Formats 4 and 3: magic `SCONEMAP`, format version (u32), the payload section's length (u64), the core's
//! length (u64) and CRC-32, then the payload section (every keyframe's payload, in id order; see
//! [`crate::map::payload`]), then the core: the map without payloads, each keyframe with the span of its
//! payload in the section and that span's CRC-32 ([`encode_snapshot_spans`]). The two differ only in the
//! encoding of the core and the payloads ([`crate::map::encoding`]): postcard in format 4, bincode 1 in
//! format 3. Loading decodes the core and checks every payload's checksum, and the loaded keyframes point
//! into the file ([`read_snapshot`]), which reads their payloads in its format's encoding. Formats 1 and 2:
//! magic, version, the payload's length (u64) and CRC-32, then the whole map (bincode 1), payloads inline.
//!
//! An export (ExportMap, ImportMap) is a snapshot followed, when the map has an HNSW graph, by an index
//! section (magic `SCONEIDX`, its own version, lengths and CRC-32) carrying the graph's dump
//! ([`encode_export`]), so an import answers exactly as the exported map. A build before this section
//! refuses such an export (bytes after the snapshot); an export without it reads everywhere.

use std::collections::BTreeMap;
use std::fs::File;
use std::io::{BufReader, Read};
use std::path::Path;
use std::sync::Arc;

use serde::{Deserialize, Serialize};

use crate::camera::{Camera, Pose};
use crate::error::MapError;
use crate::map::encoding::{encode, encode_bincode1, Encoding};
use crate::map::model::{Keyframe, Landmark, MapData, MapKeyframe, MapMeta, Observation};
use crate::map::payload::{decode_payload, encode_payload_bincode1, PayloadFile, Span, StoredPayloads};
use crate::map::storage::format::{
    corrupt, io_err, readable_version, unreadable, Crc32Reader, DumpBytes, FORMAT_VERSION,
};

const SNAPSHOT_MAGIC: &[u8; 8] = b"SCONEMAP";
/// Header of a format-1/2 snapshot (magic, version, payload length, CRC) and of a format-3/4 one (magic,
/// version, section length, core length, core CRC).
const HEADER_V2: usize = 24;
const HEADER_V3: usize = 32;

/// [`MapData`] as format 1 stored it (before `external_ids`): the same fields in the same order.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MapDataV1 {
    pub meta: MapMeta,
    pub keyframes: BTreeMap<u64, Keyframe>,
    pub landmarks: BTreeMap<u64, Landmark>,
    pub observations: Vec<Observation>,
    pub embeddings: Vec<f32>,
    pub next_landmark: u64,
    pub version: u64,
}

/// [`MapData`] as format 2 stored it: every keyframe with its payload, in one piece.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MapDataV2 {
    pub meta: MapMeta,
    pub keyframes: BTreeMap<u64, Keyframe>,
    pub landmarks: BTreeMap<u64, Landmark>,
    pub observations: Vec<Observation>,
    pub embeddings: Vec<f32>,
    pub next_landmark: u64,
    pub version: u64,
    pub external_ids: BTreeMap<u64, u64>,
}

impl From<MapDataV1> for MapDataV2 {
    fn from(v: MapDataV1) -> Self {
        let MapDataV1 { meta, keyframes, landmarks, observations, embeddings, next_landmark, version } = v;
        Self {
            meta,
            keyframes,
            landmarks,
            observations,
            embeddings,
            next_landmark,
            version,
            external_ids: BTreeMap::new(),
        }
    }
}

impl From<MapDataV2> for MapData {
    /// The payloads stay in memory until the map's next snapshot.
    fn from(v: MapDataV2) -> Self {
        let mut data = MapData::new(v.meta);
        data.keyframes = v.keyframes.into_iter().map(|(id, k)| (id, MapKeyframe::inline(k))).collect();
        data.landmarks = v.landmarks;
        data.observations = v.observations;
        data.embeddings = v.embeddings;
        data.next_landmark = v.next_landmark;
        data.version = v.version;
        data.external_ids = v.external_ids;
        data.rebuild_derived();
        data
    }
}

/// A keyframe in a format-3/4 core: what stays in memory, and where its payload is in the section.
#[derive(Debug, Serialize, Deserialize)]
struct KeyframeHead {
    id: u64,
    pose: Pose,
    camera: Camera,
    keypoints: u64,
    span: Span,
}

/// A format-3/4 core as written: the map without its keyframes' payloads (borrowed, so encoding copies nothing).
#[derive(Serialize)]
struct CoreRef<'a> {
    meta: &'a MapMeta,
    keyframes: Vec<KeyframeHead>,
    landmarks: &'a BTreeMap<u64, Landmark>,
    observations: &'a [Observation],
    embeddings: &'a [f32],
    next_landmark: u64,
    version: u64,
    external_ids: &'a BTreeMap<u64, u64>,
}

/// A format-3/4 core as read.
#[derive(Deserialize)]
struct Core {
    meta: MapMeta,
    keyframes: Vec<KeyframeHead>,
    landmarks: BTreeMap<u64, Landmark>,
    observations: Vec<Observation>,
    embeddings: Vec<f32>,
    next_landmark: u64,
    version: u64,
    external_ids: BTreeMap<u64, u64>,
}

impl Core {
    /// The map, each keyframe's payload given by `payload` from its head.
    fn into_map(
        self,
        mut payload: impl FnMut(&KeyframeHead) -> Result<MapKeyframe, MapError>,
    ) -> Result<MapData, MapError> {
        let mut data = MapData::new(self.meta);
        for head in &self.keyframes {
            data.keyframes.insert(head.id, payload(head)?);
        }
        data.landmarks = self.landmarks;
        data.observations = self.observations;
        data.embeddings = self.embeddings;
        data.next_landmark = self.next_landmark;
        data.version = self.version;
        data.external_ids = self.external_ids;
        data.rebuild_derived();
        Ok(data)
    }

    /// The map, each keyframe's payload in `file` where its head says (`path` names the snapshot in errors).
    fn into_stored_map(self, file: &Arc<PayloadFile>, path: &Path) -> Result<MapData, MapError> {
        self.into_map(|h| {
            let keypoints = usize::try_from(h.keypoints).map_err(|_| corrupt(path, "keypoint count"))?;
            Ok(MapKeyframe::stored(h.id, h.pose, h.camera, keypoints, Arc::clone(file), h.span))
        })
    }
}

/// Frames a format-1/2 snapshot payload behind its header (for tests of the upgrade).
pub fn frame_snapshot(version: u32, payload: &[u8]) -> Vec<u8> {
    let mut out = Vec::with_capacity(payload.len() + HEADER_V2);
    out.extend_from_slice(SNAPSHOT_MAGIC);
    out.extend_from_slice(&version.to_le_bytes());
    out.extend_from_slice(&(payload.len() as u64).to_le_bytes());
    out.extend_from_slice(&crc32fast::hash(payload).to_le_bytes());
    out.extend_from_slice(payload);
    out
}

/// A map in format 2 (for tests of the upgrade from it).
#[cfg(test)]
pub fn encode_snapshot_v2(data: &MapData) -> Result<Vec<u8>, MapError> {
    let keyframes: Result<BTreeMap<u64, Keyframe>, MapError> =
        data.keyframes.iter().map(|(&id, k)| Ok((id, Keyframe::clone(&*k.load()?)))).collect();
    let v2 = MapDataV2 {
        meta: data.meta.clone(),
        keyframes: keyframes?,
        landmarks: data.landmarks.clone(),
        observations: data.observations.clone(),
        embeddings: data.embeddings.clone(),
        next_landmark: data.next_landmark,
        version: data.version,
        external_ids: data.external_ids.clone(),
    };
    Ok(frame_snapshot(2, &crate::map::encoding::encode_bincode1(&v2)))
}

/// A snapshot as bytes, with where each keyframe's payload is in it.
pub struct EncodedSnapshot {
    pub bytes: Vec<u8>,
    /// Keyframe id -> its payload's span in the section, which starts at byte [`Self::SECTION_START`].
    pub spans: Vec<(u64, Span)>,
}

impl EncodedSnapshot {
    pub const SECTION_START: u64 = HEADER_V3 as u64;

    /// The section's length.
    pub fn section_len(&self) -> u64 {
        u64::from_le_bytes(self.bytes[12..20].try_into().expect("8 bytes"))
    }
}

/// Encodes a whole map in the snapshot/export format (format 4): magic, version, the payload section's length
/// (u64), the core's length (u64) and its CRC-32, then the payload section (each keyframe's payload, in id
/// order, each with its own CRC-32 in the core), then the core (the map without payloads, postcard). Payloads
/// stored in this format are copied as they are, their checksums checked; those of an older one are encoded
/// again.
pub fn encode_snapshot_spans(data: &MapData) -> Result<EncodedSnapshot, MapError> {
    encode_split(data, FORMAT_VERSION, |k| k.payload_bytes(), |core| encode(core))
}

/// A map in format 3 (bincode 1), as the builds before format 4 wrote it: for tests of the upgrade from that
/// format (the service writes only [`FORMAT_VERSION`]).
pub fn encode_snapshot_v3(data: &MapData) -> Result<Vec<u8>, MapError> {
    let payload = |k: &MapKeyframe| Ok(encode_payload_bincode1(&*k.load()?));
    Ok(encode_split(data, 3, payload, |core| Ok(encode_bincode1(core)))?.bytes)
}

/// A format-3/4 snapshot of `data` (`version` in its header), each payload's bytes from `payload` and the
/// core's from `core`.
fn encode_split(
    data: &MapData,
    version: u32,
    payload: impl Fn(&MapKeyframe) -> Result<Vec<u8>, MapError>,
    core: impl FnOnce(&CoreRef) -> Result<Vec<u8>, String>,
) -> Result<EncodedSnapshot, MapError> {
    let mut bytes = vec![0u8; HEADER_V3];
    let mut heads = Vec::with_capacity(data.keyframes.len());
    let mut spans = Vec::with_capacity(data.keyframes.len());
    for k in data.keyframes.values() {
        let payload = payload(k)?;
        let span = Span {
            offset: (bytes.len() - HEADER_V3) as u64,
            len: payload.len() as u64,
            crc: crc32fast::hash(&payload),
        };
        bytes.extend_from_slice(&payload);
        heads.push(KeyframeHead { id: k.id, pose: k.pose, camera: k.camera, keypoints: k.keypoints as u64, span });
        spans.push((k.id, span));
    }
    let section_len = (bytes.len() - HEADER_V3) as u64;
    let core_ref = CoreRef {
        meta: &data.meta,
        keyframes: heads,
        landmarks: &data.landmarks,
        observations: &data.observations,
        embeddings: &data.embeddings,
        next_landmark: data.next_landmark,
        version: data.version,
        external_ids: &data.external_ids,
    };
    let core = core(&core_ref)
        .map_err(|e| MapError::InvalidInput { field: "map".into(), reason: format!("cannot encode: {e}") })?;
    bytes.extend_from_slice(&core);
    let mut header = SNAPSHOT_MAGIC.to_vec();
    header.extend_from_slice(&version.to_le_bytes());
    header.extend_from_slice(&section_len.to_le_bytes());
    header.extend_from_slice(&(core.len() as u64).to_le_bytes());
    header.extend_from_slice(&crc32fast::hash(&core).to_le_bytes());
    bytes[..HEADER_V3].copy_from_slice(&header);
    Ok(EncodedSnapshot { bytes, spans })
}

/// [`encode_snapshot_spans`]'s bytes.
pub fn encode_snapshot(data: &MapData) -> Result<Vec<u8>, MapError> {
    Ok(encode_snapshot_spans(data)?.bytes)
}

/// What a snapshot's header says.
enum Header {
    /// Format 1 or 2: the payload (the whole map) and its CRC follow.
    Whole { version: u32, crc: u32 },
    /// Format 3 or 4: the payload section, then the core.
    Split { version: u32, section_len: u64, core_len: u64, core_crc: u32 },
}

impl Header {
    fn len(&self) -> usize {
        match self {
            Header::Whole { .. } => HEADER_V2,
            Header::Split { .. } => HEADER_V3,
        }
    }
}

/// Reads a snapshot's header from its first bytes (at least [`HEADER_V3`], or the whole file when shorter),
/// checking magic, version and lengths against the file's `size`.
fn snapshot_header(first: &[u8], size: u64, path: &Path) -> Result<Header, MapError> {
    if first.len() < HEADER_V2 || &first[..8] != SNAPSHOT_MAGIC {
        return Err(corrupt(path, "not a scone map file (bad magic)"));
    }
    let version = u32::from_le_bytes(first[8..12].try_into().expect("4 bytes"));
    if !readable_version(version) {
        return Err(unreadable(path, "map", version));
    }
    let u64_at = |at: usize| u64::from_le_bytes(first[at..at + 8].try_into().expect("8 bytes"));
    if version < 3 {
        let len = u64_at(12);
        if size - HEADER_V2 as u64 != len {
            return Err(corrupt(path, format!("payload is {} bytes, header says {len}", size - HEADER_V2 as u64)));
        }
        return Ok(Header::Whole { version, crc: u32::from_le_bytes(first[20..24].try_into().expect("4 bytes")) });
    }
    if first.len() < HEADER_V3 {
        return Err(corrupt(path, "the header is cut short"));
    }
    let (section_len, core_len) = (u64_at(12), u64_at(20));
    let declared = section_len.checked_add(core_len).and_then(|n| n.checked_add(HEADER_V3 as u64));
    if declared != Some(size) {
        return Err(corrupt(path, format!("the file is {size} bytes, its header says {section_len} + {core_len}")));
    }
    Ok(Header::Split {
        version,
        section_len,
        core_len,
        core_crc: u32::from_le_bytes(first[28..32].try_into().expect("4 bytes")),
    })
}

/// The snapshot's length in bytes as its header declares it (`None` when the header is not readable): where
/// an export's index section starts.
fn declared_snapshot_len(bytes: &[u8]) -> Option<usize> {
    let u64_at = |at: usize| bytes.get(at..at + 8).map(|b| u64::from_le_bytes(b.try_into().expect("8 bytes")));
    let version = u32::from_le_bytes(bytes.get(8..12)?.try_into().expect("4 bytes"));
    let len = if version < 3 {
        u64_at(12)?.checked_add(HEADER_V2 as u64)?
    } else {
        u64_at(12)?.checked_add(u64_at(20)?)?.checked_add(HEADER_V3 as u64)?
    };
    usize::try_from(len).ok().filter(|&e| e <= bytes.len())
}

/// Decodes a format-1/2 payload.
fn decode_whole(version: u32, payload: &[u8], path: &Path) -> Result<MapData, MapError> {
    let legacy = Encoding::of_format(version);
    let decoded = if version == 1 {
        legacy.decode::<MapDataV1>(payload).map(MapDataV2::from)
    } else {
        legacy.decode::<MapDataV2>(payload)
    };
    decoded.map(MapData::from).map_err(|e| corrupt(path, format!("cannot decode (format {version}): {e}")))
}

/// Decodes the snapshot/export format (formats 1 to 4) from bytes, checking magic, version, lengths and
/// checksums; every payload is decoded into memory (an import: the map's first snapshot then stores them).
pub fn decode_snapshot(bytes: &[u8], path: &Path) -> Result<MapData, MapError> {
    let header = snapshot_header(bytes, bytes.len() as u64, path)?;
    let body = &bytes[header.len()..];
    match header {
        Header::Whole { version, crc } => {
            if crc32fast::hash(body) != crc {
                return Err(corrupt(path, "checksum mismatch"));
            }
            decode_whole(version, body, path)
        }
        Header::Split { version, section_len, core_len: _, core_crc } => {
            let (section, core) = body.split_at(section_len as usize);
            if crc32fast::hash(core) != core_crc {
                return Err(corrupt(path, "checksum mismatch"));
            }
            let encoding = Encoding::of_format(version);
            let core: Core = encoding.decode(core).map_err(|e| corrupt(path, format!("cannot decode: {e}")))?;
            core.into_map(|h| {
                let span = h.span;
                let bytes = span
                    .offset
                    .checked_add(span.len)
                    .filter(|&end| end <= section_len)
                    .map(|end| &section[span.offset as usize..end as usize])
                    .filter(|b| crc32fast::hash(b) == span.crc)
                    .ok_or_else(|| corrupt(path, format!("payload of keyframe {}: bad span or checksum", h.id)))?;
                let k = decode_payload(h.id, h.pose, h.camera, bytes, encoding)
                    .map_err(|e| corrupt(path, format!("payload of keyframe {}: {e}", h.id)))?;
                Ok(MapKeyframe::inline(k))
            })
        }
    }
}

/// [`decode_snapshot`] of the snapshot file at `path`, read as it is decoded. A format-3/4 file's core is
/// decoded and its payloads stay in the file (the keyframes point into it); every checksum is checked, the
/// payloads' a payload at a time. An older file is decoded whole, its bytes never all in memory beside
/// the map they decode to; its payloads stay in memory until the map's next snapshot.
pub fn read_snapshot(path: &Path) -> Result<MapData, MapError> {
    use std::io::{Seek, SeekFrom};
    let mut file = File::open(path).map_err(io_err(path))?;
    let size = file.metadata().map_err(io_err(path))?.len();
    let mut first = vec![0u8; (size as usize).min(HEADER_V3)];
    file.read_exact(&mut first).map_err(io_err(path))?;
    let header = snapshot_header(&first, size, path)?;
    let (start, len, crc) = match header {
        Header::Whole { crc, .. } => (HEADER_V2 as u64, size - HEADER_V2 as u64, crc),
        Header::Split { section_len, core_len, core_crc, .. } => (HEADER_V3 as u64 + section_len, core_len, core_crc),
    };
    file.seek(SeekFrom::Start(start)).map_err(io_err(path))?;
    // The checksum is taken below the buffer, a block at a time; the limit keeps a damaged length inside the file.
    let mut reader =
        BufReader::with_capacity(1 << 20, Crc32Reader { inner: file.take(len), hasher: crc32fast::Hasher::new() });
    let version = match header {
        Header::Whole { version, .. } | Header::Split { version, .. } => version,
    };
    let encoding = Encoding::of_format(version);
    // Decoded into the stored layout; converted only once the checksum matched.
    let decoded = match version {
        1 => encoding.decode_from::<MapDataV1, _>(&mut reader, len).map(|v| Stored::Whole(v.into())),
        2 => encoding.decode_from::<MapDataV2, _>(&mut reader, len).map(Stored::Whole),
        _ => encoding.decode_from::<Core, _>(&mut reader, len).map(Stored::Split),
    };
    // What the decode did not read (all of it after an error) is in the checksum too.
    let rest = std::io::copy(&mut reader, &mut std::io::sink()).map_err(io_err(path))?;
    if reader.into_inner().hasher.finalize() != crc {
        return Err(corrupt(path, "checksum mismatch"));
    }
    let decoded = match decoded {
        // A postcard core fills its span: bytes after it are refused (bincode 1's readers ignored them).
        Ok(_) if rest > 0 && encoding == Encoding::Postcard => Err(format!("{rest} bytes after the core")),
        other => other,
    };
    match decoded.map_err(|e| corrupt(path, format!("cannot decode (format {version}): {e}")))? {
        Stored::Whole(v2) => Ok(MapData::from(v2)),
        Stored::Split(core) => {
            let Header::Split { section_len, .. } = header else { unreachable!("formats 3 and 4 are split") };
            let payloads = PayloadFile::open(path, HEADER_V3 as u64, section_len, encoding)?;
            payloads.verify(core.keyframes.iter().map(|h| h.span))?;
            core.into_stored_map(&payloads, path)
        }
    }
}

/// A decoded snapshot before it becomes a map.
enum Stored {
    Whole(MapDataV2),
    Split(Core),
}

/// The format of the snapshot file at `path` (its header's version).
pub fn snapshot_version(path: &Path) -> Result<u32, MapError> {
    let mut first = [0u8; 12];
    File::open(path).and_then(|mut f| f.read_exact(&mut first)).map_err(io_err(path))?;
    if &first[..8] != SNAPSHOT_MAGIC {
        return Err(corrupt(path, "not a scone map file (bad magic)"));
    }
    Ok(u32::from_le_bytes(first[8..12].try_into().expect("4 bytes")))
}

/// Where a format-3/4 snapshot's parts are (object storage fetches them apart: the core first, the payload
/// section after the map is ready).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SplitLayout {
    pub section_len: u64,
    pub core_len: u64,
    core_crc: u32,
    version: u32,
}

impl SplitLayout {
    /// How many bytes of a snapshot [`split_layout`] reads.
    pub const HEADER_LEN: u64 = HEADER_V3 as u64;

    /// The payload section's bytes in the file.
    pub fn section(&self) -> std::ops::Range<u64> {
        Self::HEADER_LEN..Self::HEADER_LEN + self.section_len
    }

    /// The encoding of the core and the payloads (the snapshot's format's).
    pub fn encoding(&self) -> Encoding {
        Encoding::of_format(self.version)
    }

    /// The core's bytes in the file.
    pub fn core(&self) -> std::ops::Range<u64> {
        self.section().end..self.section().end + self.core_len
    }
}

/// A snapshot's layout from its first bytes (the whole object when shorter than [`SplitLayout::HEADER_LEN`])
/// and its size: `None` for formats 1 and 2 (one piece). Checks magic, version and lengths as a load does.
pub fn split_layout(first: &[u8], size: u64, path: &Path) -> Result<Option<SplitLayout>, MapError> {
    Ok(match snapshot_header(first, size, path)? {
        Header::Whole { .. } => None,
        Header::Split { version, section_len, core_len, core_crc } => {
            Some(SplitLayout { section_len, core_len, core_crc, version })
        }
    })
}

/// A format-3/4 map from its core's bytes (`path` names the snapshot in errors). `payloads` gets every
/// keyframe's span in the section and gives the file the keyframes are to read their payloads from; its
/// section may still be on its way ([`PayloadFile::arriving`]), so nothing of it is read here.
pub fn map_from_core(
    layout: &SplitLayout,
    core: &[u8],
    path: &Path,
    payloads: impl FnOnce(Vec<Span>) -> Result<Arc<PayloadFile>, MapError>,
) -> Result<MapData, MapError> {
    if core.len() as u64 != layout.core_len || crc32fast::hash(core) != layout.core_crc {
        return Err(corrupt(path, "checksum mismatch"));
    }
    let core: Core = layout.encoding().decode(core).map_err(|e| corrupt(path, format!("cannot decode: {e}")))?;
    let file = payloads(core.keyframes.iter().map(|h| h.span).collect())?;
    core.into_stored_map(&file, path)
}

/// The payloads of a snapshot of map version `version` just written to `path` ([`encode_snapshot_spans`]),
/// for the map it was encoded from to point into ([`MapData::store_payloads`]).
pub fn stored_payloads(path: &Path, encoded: &EncodedSnapshot, version: u64) -> Result<StoredPayloads, MapError> {
    let file = PayloadFile::open(path, EncodedSnapshot::SECTION_START, encoded.section_len(), Encoding::CURRENT)?;
    Ok(StoredPayloads { file, spans: encoded.spans.clone(), version })
}

const INDEX_SECTION_MAGIC: &[u8; 8] = b"SCONEIDX";
const INDEX_SECTION_VERSION: u32 = 1;

/// Encodes an export: the map's snapshot, followed (when `dump` is given) by the index section: magic
/// `SCONEIDX`, section version (u32), the lengths of the manifest, the graph and the data file (u64 each),
/// a CRC-32 of the three, then the three. An import loads that graph instead of building another (hnsw_rs
/// inserts in parallel, so two builds of one map differ, and so would their answers).
pub fn encode_export(data: &MapData, dump: Option<&DumpBytes>) -> Result<Vec<u8>, MapError> {
    let mut out = encode_snapshot(data)?;
    if let Some(d) = dump {
        let parts = [&d.manifest, &d.graph, &d.data];
        let mut crc = crc32fast::Hasher::new();
        out.extend_from_slice(INDEX_SECTION_MAGIC);
        out.extend_from_slice(&INDEX_SECTION_VERSION.to_le_bytes());
        for p in parts {
            out.extend_from_slice(&(p.len() as u64).to_le_bytes());
            crc.update(p);
        }
        out.extend_from_slice(&crc.finalize().to_le_bytes());
        for p in parts {
            out.extend_from_slice(p);
        }
    }
    Ok(out)
}

/// Decodes an export ([`encode_export`]): the map, and the index dump when the file carries one.
pub fn decode_export(bytes: &[u8], path: &Path) -> Result<(MapData, Option<DumpBytes>), MapError> {
    let Some(end) = declared_snapshot_len(bytes) else {
        // Let the snapshot decoder say what is wrong.
        return decode_snapshot(bytes, path).map(|d| (d, None));
    };
    let data = decode_snapshot(&bytes[..end], path)?;
    let rest = &bytes[end..];
    if rest.is_empty() {
        return Ok((data, None));
    }
    let bad = |reason: &str| corrupt(path, format!("index section: {reason}"));
    if rest.len() < 40 || &rest[..8] != INDEX_SECTION_MAGIC {
        return Err(bad("bad magic after the map"));
    }
    let version = u32::from_le_bytes(rest[8..12].try_into().expect("4 bytes"));
    if version != INDEX_SECTION_VERSION {
        return Err(bad(&format!("version {version}, this build reads {INDEX_SECTION_VERSION}")));
    }
    let len = |at: usize| u64::from_le_bytes(rest[at..at + 8].try_into().expect("8 bytes"));
    let lens = [len(12), len(20), len(28)];
    let crc = u32::from_le_bytes(rest[36..40].try_into().expect("4 bytes"));
    let body = &rest[40..];
    if lens.iter().try_fold(0u64, |a, &n| a.checked_add(n)) != Some(body.len() as u64) {
        return Err(bad("its lengths do not add up to its size"));
    }
    let (manifest, tail) = body.split_at(lens[0] as usize);
    let (graph, file) = tail.split_at(lens[1] as usize);
    let mut h = crc32fast::Hasher::new();
    for p in [manifest, graph, file] {
        h.update(p);
    }
    if h.finalize() != crc {
        return Err(bad("checksum mismatch"));
    }
    Ok((data, Some(DumpBytes { manifest: manifest.to_vec(), graph: graph.to_vec(), data: file.to_vec() })))
}
