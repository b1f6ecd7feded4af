//! The bytes of stored maps, shared by both backends ([`crate::map::storage::local`], [`crate::map::storage::s3`]):
//!
//! * snapshot (`snapshot.bin`, an S3 snapshot object, and the map's export file, with its index section):
//!   [`crate::map::storage::snapshot`]. Written atomically on disk by [`write_atomic`]: temporary file,
//!   fsync, rename, fsync of the directory.
//! * log (`log.bin`): magic `SCONELOG`, format version, then records `[len u32][crc u32][version u64][payload]`
//!   (CRC over version and payload), read back one frame at a time by [`read_frame`].
//! * segment (an S3 object): one framed record behind the magic `SCONESEG` and the format version.
//! * index dumps: `index.json` and hnsw_rs's two files ([`read_dump`], [`install_dump`]).
//!
//! Format versions. Every file (snapshot, log, segment; the object-storage manifest too) carries the version
//! it was written in. This build writes [`FORMAT_VERSION`] 4 and reads 1 to 4:
//!
//! * 1: the first format.
//! * 2: [`crate::map::model::MapData`] gained `external_ids` (landmarks given by an external SfM, see
//!   [`crate::map::model`]), and [`Record`] the variant `AddExternalKeyframe`, appended last so a format-1
//!   record decodes unchanged. A format-1 snapshot decodes through its own layout with no external ids.
//! * 3: the snapshot split into a payload section and a core, so that a loaded map keeps its
//!   keyframes' payloads on disk ([`crate::map::payload`]) and loading decodes only the core. Records,
//!   segments and the log are unchanged (a record still carries its keyframe whole); their header says 3 so
//!   that a build that reads only format 2 refuses a map whose snapshot it could not read. A format-1/2
//!   snapshot decodes through its own layout, its payloads in memory until the map's next snapshot.
//! * 4: the bodies (records, the snapshot's core, payloads) are postcard instead of bincode 1
//!   ([`crate::map::encoding`]); headers, framing, lengths, checksums and the snapshot's sections are as in
//!   format 3. Each file's header says which encoding its bodies are in, so a log is in one encoding from
//!   its header to its end, and a segment's own header names its record's.
//!
//! An older map is upgraded as soon as it is opened: on a local disk its log is folded into a current
//! snapshot with a fresh log (the same crash-safe steps as compaction: the new snapshot is renamed over the
//! old one, then the fresh log over the old log; a crash between the two leaves a new snapshot and an old
//! log whose records it covers, read in the log's own encoding and skipped), so a record of a new kind or
//! encoding never lands in a file whose header promises an older format. A build that reads only older
//! formats refuses the upgraded files with a version message instead of misreading them. In object storage
//! the writer's next compaction rewrites the snapshot; until then a replica reads the older snapshot's
//! payloads in their own encoding, and a segment is read in the encoding its header names.

use std::fs::File;
use std::io::{BufReader, Read, Write};
use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::error::MapError;
use crate::map::encoding::{encode, Encoding};
use crate::map::model::Record;

/// The format this build writes.
pub const FORMAT_VERSION: u32 = 4;
/// The oldest format this build reads.
pub const OLDEST_FORMAT_VERSION: u32 = 1;
pub(crate) const LOG_MAGIC: &[u8; 8] = b"SCONELOG";
const SEGMENT_MAGIC: &[u8; 8] = b"SCONESEG";
pub(crate) const LOG_HEADER: u64 = 12;
/// Largest record accepted when reading (a guard against a corrupt length field).
const MAX_RECORD: u32 = 1 << 30;

/// The error of an I/O call on `path`: [`MapError::StorageFull`] when the volume is full (or over a quota), so
/// the transports can answer "insufficient storage" instead of an internal error; [`MapError::Io`] otherwise.
pub(crate) fn io_error(path: &Path, source: std::io::Error) -> MapError {
    use std::io::ErrorKind::{QuotaExceeded, StorageFull};
    match source.kind() {
        StorageFull | QuotaExceeded => MapError::StorageFull { path: path.to_path_buf() },
        _ => MapError::Io { path: path.to_path_buf(), source },
    }
}

pub(crate) fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> MapError + '_ {
    move |source| io_error(path, source)
}

/// Fault injection for the durability tests: whether the `fail` point `site` is configured to `return` for
/// `path` (with an argument, only for paths that contain each of its comma-separated parts). Inert unless a
/// test configures the point (`fail::cfg`); the server never reads fail points from its environment.
pub(crate) fn injected(site: &str, path: &Path) -> bool {
    let path = path.to_string_lossy();
    fail::eval(site, |arg| arg.is_none_or(|a| a.split(',').all(|part| path.contains(part)))).unwrap_or(false)
}

/// The error an injected fault raises: the volume is full.
pub(crate) fn injected_full(path: &Path) -> MapError {
    io_error(path, std::io::Error::new(std::io::ErrorKind::StorageFull, "injected fault: no space left"))
}

pub(crate) fn corrupt(path: &Path, reason: impl Into<String>) -> MapError {
    MapError::Corrupt { path: path.to_path_buf(), reason: reason.into() }
}

/// Whether this build reads files of format `version`.
pub fn readable_version(version: u32) -> bool {
    (OLDEST_FORMAT_VERSION..=FORMAT_VERSION).contains(&version)
}

pub(crate) fn unreadable(path: &Path, what: &str, version: u32) -> MapError {
    corrupt(
        path,
        format!("{what} format version {version}, this build reads {OLDEST_FORMAT_VERSION} to {FORMAT_VERSION}"),
    )
}

/// fsync of a directory, so a rename or a new file in it is durable.
pub fn sync_dir(dir: &Path) -> Result<(), MapError> {
    File::open(dir).and_then(|d| d.sync_all()).map_err(io_err(dir))
}

/// A reader that hashes what passes through it.
pub(crate) struct Crc32Reader<R> {
    pub(crate) inner: R,
    pub(crate) hasher: crc32fast::Hasher,
}

impl<R: Read> Read for Crc32Reader<R> {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        let n = self.inner.read(buf)?;
        self.hasher.update(&buf[..n]);
        Ok(n)
    }
}

/// An index dump as bytes (to upload it, or to carry it in an export): `index.json` and hnsw_rs's two files
/// ([`crate::map::index`] writes and reads them).
#[derive(Debug, Clone, PartialEq)]
pub struct DumpBytes {
    pub manifest: Vec<u8>,
    pub graph: Vec<u8>,
    pub data: Vec<u8>,
}

/// Writes `bytes` to `path` atomically (temporary file, fsync, rename, fsync of the directory). On failure
/// the temporary file is removed and `path` is as it was. Fail point `map-write` (argument: part of the path).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), MapError> {
    let tmp = path.with_extension("tmp");
    let written = (|| {
        let mut f = File::create(&tmp).map_err(io_err(&tmp))?;
        if injected("map-write", path) {
            // Half the bytes, then the volume is full: what a real ENOSPC leaves behind.
            let _ = f.write_all(&bytes[..bytes.len() / 2]);
            return Err(injected_full(&tmp));
        }
        f.write_all(bytes).map_err(io_err(&tmp))?;
        f.sync_all().map_err(io_err(&tmp))?;
        std::fs::rename(&tmp, path).map_err(io_err(path))
    })();
    if let Err(e) = written {
        let _ = std::fs::remove_file(&tmp);
        return Err(e);
    }
    sync_dir(path.parent().unwrap_or(Path::new(".")))
}

/// Frames one record as `[len u32][crc u32][seq u64][payload]` (`len` counts the payload, the CRC covers
/// seq and payload): the unit of the local log and of an object-storage segment. A record larger than a log
/// may hold (`MAX_RECORD`, which reading enforces) is refused here, before anything is written: a write that
/// was acknowledged must load again.
pub fn encode_record(seq: u64, record: &Record) -> Result<Vec<u8>, MapError> {
    let payload = encode(record)
        .map_err(|e| MapError::InvalidInput { field: "record".into(), reason: format!("cannot encode: {e}") })?;
    if payload.len() > MAX_RECORD as usize {
        return Err(MapError::InvalidInput {
            field: "record".into(),
            reason: format!(
                "this write is {} MiB, more than the {} MiB one log record may hold (a merge of a large source: \
                 merge it in parts, e.g. from copies of the source with keyframes removed)",
                payload.len() >> 20,
                MAX_RECORD >> 20
            ),
        });
    }
    Ok(frame(seq, &payload))
}

/// A record framed in bincode 1's layout, as formats 1 to 3 hold it (for tests that make maps of those formats;
/// the service never writes it).
pub fn encode_record_bincode1(seq: u64, record: &Record) -> Vec<u8> {
    frame(seq, &crate::map::encoding::encode_bincode1(record))
}

fn frame(seq: u64, payload: &[u8]) -> Vec<u8> {
    let mut body = Vec::with_capacity(payload.len() + 8);
    body.extend_from_slice(&seq.to_le_bytes());
    body.extend_from_slice(payload);
    let mut frame = Vec::with_capacity(body.len() + 8);
    frame.extend_from_slice(&((body.len() - 8) as u32).to_le_bytes());
    frame.extend_from_slice(&crc32fast::hash(&body).to_le_bytes());
    frame.extend_from_slice(&body);
    frame
}

/// What [`read_frame`] found at a position.
#[derive(Debug)]
pub enum LogEntry {
    /// A whole record whose checksum matches; the next frame starts at `end`.
    Record { seq: u64, record: Box<Record>, end: usize },
    /// The buffer ends inside the frame.
    Torn,
    /// A whole frame whose checksum does not match; it would end at `end`.
    BadChecksum { end: usize },
}

/// Reads the frame starting at byte `pos` of `buf`, a file of format `version` (which says the record's
/// encoding). A length beyond the limit or a payload that does not decode is corruption (named by `path`).
pub fn read_frame(buf: &[u8], pos: usize, version: u32, path: &Path) -> Result<LogEntry, MapError> {
    if buf.len().saturating_sub(pos) < 16 {
        return Ok(LogEntry::Torn);
    }
    let len = u32::from_le_bytes(buf[pos..pos + 4].try_into().expect("4 bytes"));
    let crc = u32::from_le_bytes(buf[pos + 4..pos + 8].try_into().expect("4 bytes"));
    if len > MAX_RECORD {
        return Err(corrupt(path, format!("record at byte {pos} claims {len} bytes")));
    }
    let end = pos + 16 + len as usize;
    if end > buf.len() {
        return Ok(LogEntry::Torn);
    }
    let body = &buf[pos + 8..end];
    if crc32fast::hash(body) != crc {
        return Ok(LogEntry::BadChecksum { end });
    }
    let seq = u64::from_le_bytes(body[..8].try_into().expect("8 bytes"));
    let record: Box<Record> = Encoding::of_format(version)
        .decode(&body[8..])
        .map_err(|e| corrupt(path, format!("record at byte {pos}: {e}")))?;
    Ok(LogEntry::Record { seq, record, end })
}

/// Encodes an object-storage segment: magic `SCONESEG`, format version (u32), then exactly one record frame.
pub fn encode_segment(seq: u64, record: &Record) -> Result<Vec<u8>, MapError> {
    let frame = encode_record(seq, record)?;
    let mut out = Vec::with_capacity(frame.len() + 12);
    out.extend_from_slice(SEGMENT_MAGIC);
    out.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
    out.extend_from_slice(&frame);
    Ok(out)
}

/// Decodes a segment: magic, version, one whole record with a matching checksum and nothing after it. A
/// segment is written whole by a single PUT, so anything else is corruption (named by `path`).
pub fn decode_segment(bytes: &[u8], path: &Path) -> Result<(u64, Record), MapError> {
    if bytes.len() < 12 || &bytes[..8] != SEGMENT_MAGIC {
        return Err(corrupt(path, "not a scone segment (bad magic)"));
    }
    let version = u32::from_le_bytes(bytes[8..12].try_into().expect("4 bytes"));
    if !readable_version(version) {
        return Err(unreadable(path, "segment", version));
    }
    match read_frame(bytes, 12, version, path)? {
        LogEntry::Record { seq, record, end } if end == bytes.len() => Ok((seq, *record)),
        LogEntry::Record { end, .. } => Err(corrupt(path, format!("{} bytes after the record", bytes.len() - end))),
        LogEntry::Torn => Err(corrupt(path, "the record is cut short")),
        LogEntry::BadChecksum { .. } => Err(corrupt(path, "checksum mismatch")),
    }
}

// ---------------------------------------------------------------------------------------------------------
// Index dumps on disk (written and checked by crate::map::index, moved by the object-storage backend)
// ---------------------------------------------------------------------------------------------------------

/// `index.json`: which files hold the dump, and what it was built from.
#[derive(Debug, Serialize, Deserialize, PartialEq)]
pub(crate) struct DumpManifest {
    /// Base name of the two files (`<base>.hnsw.graph`, `<base>.hnsw.data`), as hnsw_rs wrote them.
    pub(crate) base: String,
    /// Observations `[0, points)` were offered to the graph...
    pub(crate) points: usize,
    /// ...of which this many (the live ones then) are in it.
    pub(crate) in_graph: usize,
    pub(crate) model_id: String,
    pub(crate) graph_crc: u32,
    pub(crate) data_crc: u32,
    /// CRC-32 of the embeddings of observations `[0, points)` at the dump.
    pub(crate) embeddings_crc: u32,
    /// What the graph's points are (absent in dumps before the setting: one per observation).
    #[serde(default)]
    pub(crate) index_points: crate::map::model::IndexPoints,
    /// With one point per landmark: the observation that stands for each landmark now, in id order (the
    /// graph also holds points it has replaced since, which searches pass over).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub(crate) representatives: Vec<usize>,
}

/// The manifest of a dump, and the suffixes hnsw_rs gives its two files.
pub const DUMP_MANIFEST: &str = "index.json";
pub(crate) const GRAPH_SUFFIX: &str = ".hnsw.graph";
pub(crate) const DATA_SUFFIX: &str = ".hnsw.data";

/// The dump in `dir`, read (`None` when there is none or it cannot be read whole).
pub fn read_dump(dir: &Path) -> Option<DumpBytes> {
    let manifest = std::fs::read(dir.join(DUMP_MANIFEST)).ok()?;
    let base = serde_json::from_slice::<DumpManifest>(&manifest).ok()?.base;
    if !valid_base(&base) {
        return None;
    }
    let graph = std::fs::read(dir.join(format!("{base}{GRAPH_SUFFIX}"))).ok()?;
    let data = std::fs::read(dir.join(format!("{base}{DATA_SUFFIX}"))).ok()?;
    Some(DumpBytes { manifest, graph, data })
}

/// Writes a dump read elsewhere ([`read_dump`]) into `dir`: the two files under the manifest's base name, the
/// manifest last, then the other dumps there are deleted. The loader checks it against the map, so a dump
/// that does not match is rebuilt, not used.
pub fn install_dump(dir: &Path, dump: &DumpBytes) -> Result<(), MapError> {
    let base = serde_json::from_slice::<DumpManifest>(&dump.manifest)
        .ok()
        .map(|m| m.base)
        .filter(|b| valid_base(b))
        .ok_or_else(|| corrupt(&dir.join(DUMP_MANIFEST), "not an index manifest"))?;
    let write = write_atomic;
    write(&dir.join(format!("{base}{GRAPH_SUFFIX}")), &dump.graph)?;
    write(&dir.join(format!("{base}{DATA_SUFFIX}")), &dump.data)?;
    write(&dir.join(DUMP_MANIFEST), &dump.manifest)?;
    remove_dumps_except(dir, Some(&base));
    Ok(())
}

/// A base name this module writes (`index-<hex>`, or `index-<n>` as hnsw_rs may pick): no path, no dots.
pub(crate) fn valid_base(base: &str) -> bool {
    !base.is_empty() && base.len() <= 64 && base.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'-' || b == b'_')
}

/// CRC-32 of a whole file, read a block at a time.
pub(crate) fn file_crc(path: &Path) -> Result<u32, MapError> {
    let mut hasher = Crc32Reader { inner: File::open(path).map_err(io_err(path))?, hasher: crc32fast::Hasher::new() };
    std::io::copy(&mut BufReader::with_capacity(1 << 20, &mut hasher), &mut std::io::sink()).map_err(io_err(path))?;
    Ok(hasher.hasher.finalize())
}

/// Removes the two files of the dump `base` in `dir`.
pub(crate) fn remove_dump(dir: &Path, base: &str) {
    for suffix in [GRAPH_SUFFIX, DATA_SUFFIX] {
        let _ = std::fs::remove_file(dir.join(format!("{base}{suffix}")));
    }
}

/// Removes every dump file in `dir` but those of `keep` (replaced dumps, and any a crash left behind).
pub(crate) fn remove_dumps_except(dir: &Path, keep: Option<&str>) {
    let Ok(entries) = std::fs::read_dir(dir) else { return };
    for entry in entries.flatten() {
        let name = entry.file_name().to_string_lossy().into_owned();
        let base = name.strip_suffix(GRAPH_SUFFIX).or_else(|| name.strip_suffix(DATA_SUFFIX));
        if base.is_some_and(|b| Some(b) != keep) {
            let _ = std::fs::remove_file(entry.path());
        }
    }
}
