//! Durable storage of one map: a snapshot file plus an append-only write-ahead log, in the map's directory.
//!
//! * `snapshot.bin`: magic `SCONEMAP`, format version (u32), payload length (u64), CRC-32 of the payload,
//!   then the whole [`MapData`] (bincode). Written atomically: temporary file, fsync, rename, fsync of the
//!   directory. The same format is the map's export file.
//! * `log.bin`: magic `SCONELOG`, format version, then records `[len u32][crc u32][version u64][payload]`
//!   (CRC over version and payload). A write is acknowledged only after its record is appended and
//!   `fdatasync` returned, so an acknowledged write survives `kill -9` and power loss (as far as the disk
//!   honours fsync).
//!
//! Loading replays the log records newer than the snapshot. A torn last record (the normal result of a crash
//! in the middle of an append, never acknowledged) is cut off and the map loads. A bad record followed by
//! more data is corruption: the map is reported and held back; the caller keeps serving the others.
//! After `compact_every` records the map is snapshotted and the log restarted.
//!
//! The snapshot format and the record framing are shared with the object-storage backend
//! ([`crate::map::object_storage`]), whose segments are one framed record each behind the magic `SCONESEG`.
//!
//! Format versions. Every file (snapshot, log, segment; the object-storage manifest too) carries the version
//! it was written in. This build writes [`FORMAT_VERSION`] 2 and reads 1 and 2:
//!
//! * 1: the first format.
//! * 2: [`MapData`] gained `external_ids` (landmarks given by an external SfM, see
//!   [`crate::map::model`]), and [`Record`] the variant `AddExternalKeyframe`, appended last so a format-1
//!   record decodes unchanged. A format-1 snapshot decodes through its own layout ([`MapDataV1`]) with no
//!   external ids.
//!
//! A format-1 log is folded into a format-2 snapshot with a fresh format-2 log as soon as it is opened (the
//! same crash-safe steps as compaction), so a record of the new kind never lands in a file whose header
//! says 1. A build that reads only format 1 refuses the upgraded files with a version message instead of
//! misreading them.

use std::fs::{File, OpenOptions};
use std::io::{Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use crate::error::MapError;
use crate::map::model::{Keyframe, Landmark, MapData, MapMeta, Observation, Record};

/// The format this build writes.
pub const FORMAT_VERSION: u32 = 2;
/// The oldest format this build reads.
pub const OLDEST_FORMAT_VERSION: u32 = 1;
const SNAPSHOT_MAGIC: &[u8; 8] = b"SCONEMAP";
const LOG_MAGIC: &[u8; 8] = b"SCONELOG";
const SEGMENT_MAGIC: &[u8; 8] = b"SCONESEG";
const LOG_HEADER: u64 = 12;
/// Largest record accepted when reading (a guard against a corrupt length field).
const MAX_RECORD: u32 = 1 << 30;

fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> MapError + '_ {
    move |source| MapError::Io { path: path.to_path_buf(), source }
}

fn corrupt(path: &Path, reason: impl Into<String>) -> MapError {
    MapError::Corrupt { path: path.to_path_buf(), reason: reason.into() }
}

/// Whether this build reads files of format `version`.
pub fn readable_version(version: u32) -> bool {
    (OLDEST_FORMAT_VERSION..=FORMAT_VERSION).contains(&version)
}

fn unreadable(path: &Path, what: &str, version: u32) -> MapError {
    corrupt(
        path,
        format!("{what} format version {version}, this build reads {OLDEST_FORMAT_VERSION} to {FORMAT_VERSION}"),
    )
}

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

impl From<MapDataV1> for MapData {
    fn from(v: MapDataV1) -> Self {
        Self {
            meta: v.meta,
            keyframes: v.keyframes,
            landmarks: v.landmarks,
            observations: v.observations,
            embeddings: v.embeddings,
            next_landmark: v.next_landmark,
            version: v.version,
            external_ids: BTreeMap::new(),
        }
    }
}

/// Frames a snapshot payload behind the header of format `version` (format 1 only for tests of the upgrade).
pub fn frame_snapshot(version: u32, payload: &[u8]) -> Vec<u8> {
    let mut out = Vec::with_capacity(payload.len() + 24);
    out.extend_from_slice(SNAPSHOT_MAGIC);
    out.extend_from_slice(&version.to_le_bytes());
    out.extend_from_slice(&(payload.len() as u64).to_le_bytes());
    out.extend_from_slice(&crc32fast::hash(payload).to_le_bytes());
    out.extend_from_slice(payload);
    out
}

/// fsync of a directory, so a rename or a new file in it is durable.
pub fn sync_dir(dir: &Path) -> Result<(), MapError> {
    File::open(dir).and_then(|d| d.sync_all()).map_err(io_err(dir))
}

/// Encodes a whole map in the snapshot/export format.
pub fn encode_snapshot(data: &MapData) -> Result<Vec<u8>, MapError> {
    let payload = bincode::serialize(data)
        .map_err(|e| MapError::InvalidInput { field: "map".into(), reason: format!("cannot encode: {e}") })?;
    Ok(frame_snapshot(FORMAT_VERSION, &payload))
}

/// Decodes the snapshot/export format (format 1 or 2), checking magic, version, length and checksum.
pub fn decode_snapshot(bytes: &[u8], path: &Path) -> Result<MapData, MapError> {
    if bytes.len() < 24 || &bytes[..8] != SNAPSHOT_MAGIC {
        return Err(corrupt(path, "not a scone map file (bad magic)"));
    }
    let version = u32::from_le_bytes(bytes[8..12].try_into().expect("4 bytes"));
    if !readable_version(version) {
        return Err(unreadable(path, "map", version));
    }
    let len = u64::from_le_bytes(bytes[12..20].try_into().expect("8 bytes")) as usize;
    let crc = u32::from_le_bytes(bytes[20..24].try_into().expect("4 bytes"));
    let payload = &bytes[24..];
    if payload.len() != len {
        return Err(corrupt(path, format!("payload is {} bytes, header says {len}", payload.len())));
    }
    if crc32fast::hash(payload) != crc {
        return Err(corrupt(path, "checksum mismatch"));
    }
    let decoded = if version == 1 {
        bincode::deserialize::<MapDataV1>(payload).map(MapData::from)
    } else {
        bincode::deserialize::<MapData>(payload)
    };
    decoded.map_err(|e| corrupt(path, format!("cannot decode (format {version}): {e}")))
}

/// Writes `bytes` to `path` atomically (temporary file, fsync, rename, fsync of the directory).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), MapError> {
    let tmp = path.with_extension("tmp");
    {
        let mut f = File::create(&tmp).map_err(io_err(&tmp))?;
        f.write_all(bytes).map_err(io_err(&tmp))?;
        f.sync_all().map_err(io_err(&tmp))?;
    }
    std::fs::rename(&tmp, path).map_err(io_err(path))?;
    sync_dir(path.parent().unwrap_or(Path::new(".")))
}

/// Frames one record as `[len u32][crc u32][seq u64][payload]` (`len` counts the payload, the CRC covers
/// seq and payload): the unit of the local log and of an object-storage segment.
pub fn encode_record(seq: u64, record: &Record) -> Result<Vec<u8>, MapError> {
    let payload = bincode::serialize(record)
        .map_err(|e| MapError::InvalidInput { field: "record".into(), reason: format!("cannot encode: {e}") })?;
    let mut body = Vec::with_capacity(payload.len() + 8);
    body.extend_from_slice(&seq.to_le_bytes());
    body.extend_from_slice(&payload);
    let mut frame = Vec::with_capacity(body.len() + 8);
    frame.extend_from_slice(&((body.len() - 8) as u32).to_le_bytes());
    frame.extend_from_slice(&crc32fast::hash(&body).to_le_bytes());
    frame.extend_from_slice(&body);
    Ok(frame)
}

/// What [`read_frame`] found at a position.
#[derive(Debug)]
pub enum Frame {
    /// A whole record whose checksum matches; the next frame starts at `end`.
    Record { seq: u64, record: Box<Record>, end: usize },
    /// The buffer ends inside the frame.
    Torn,
    /// A whole frame whose checksum does not match; it would end at `end`.
    BadChecksum { end: usize },
}

/// Reads the frame starting at byte `pos` of `buf`. A length beyond the limit or a payload that does not
/// decode is corruption (named by `path`).
pub fn read_frame(buf: &[u8], pos: usize, path: &Path) -> Result<Frame, MapError> {
    if buf.len().saturating_sub(pos) < 16 {
        return Ok(Frame::Torn);
    }
    let len = u32::from_le_bytes(buf[pos..pos + 4].try_into().expect("4 bytes"));
    let crc = u32::from_le_bytes(buf[pos + 4..pos + 8].try_into().expect("4 bytes"));
    if len > MAX_RECORD {
        return Err(corrupt(path, format!("record at byte {pos} claims {len} bytes")));
    }
    let end = pos + 16 + len as usize;
    if end > buf.len() {
        return Ok(Frame::Torn);
    }
    let body = &buf[pos + 8..end];
    if crc32fast::hash(body) != crc {
        return Ok(Frame::BadChecksum { end });
    }
    let seq = u64::from_le_bytes(body[..8].try_into().expect("8 bytes"));
    let record: Box<Record> =
        bincode::deserialize(&body[8..]).map_err(|e| corrupt(path, format!("record at byte {pos}: {e}")))?;
    Ok(Frame::Record { seq, record, end })
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
    match read_frame(bytes, 12, path)? {
        Frame::Record { seq, record, end } if end == bytes.len() => Ok((seq, *record)),
        Frame::Record { end, .. } => Err(corrupt(path, format!("{} bytes after the record", bytes.len() - end))),
        Frame::Torn => Err(corrupt(path, "the record is cut short")),
        Frame::BadChecksum { .. } => Err(corrupt(path, "checksum mismatch")),
    }
}

/// What loading found.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct LoadReport {
    pub replayed: usize,
    /// Bytes cut off the end of the log (a torn, unacknowledged record).
    pub truncated_bytes: u64,
}

/// The open log of one map.
#[derive(Debug)]
pub struct MapLog {
    dir: PathBuf,
    file: File,
    records: usize,
    compact_every: usize,
}

impl MapLog {
    fn log_path(dir: &Path) -> PathBuf {
        dir.join("log.bin")
    }

    fn snapshot_path(dir: &Path) -> PathBuf {
        dir.join("snapshot.bin")
    }

    fn fresh_log(dir: &Path) -> Result<File, MapError> {
        let path = Self::log_path(dir);
        let tmp = path.with_extension("tmp");
        {
            let mut f = File::create(&tmp).map_err(io_err(&tmp))?;
            f.write_all(LOG_MAGIC).map_err(io_err(&tmp))?;
            f.write_all(&FORMAT_VERSION.to_le_bytes()).map_err(io_err(&tmp))?;
            f.sync_all().map_err(io_err(&tmp))?;
        }
        std::fs::rename(&tmp, &path).map_err(io_err(&path))?;
        sync_dir(dir)?;
        let mut f = OpenOptions::new().read(true).append(true).open(&path).map_err(io_err(&path))?;
        f.seek(SeekFrom::End(0)).map_err(io_err(&path))?;
        Ok(f)
    }

    /// Creates the directory, a snapshot of `data` and an empty log.
    pub fn create(dir: &Path, data: &MapData, compact_every: usize) -> Result<Self, MapError> {
        std::fs::create_dir_all(dir).map_err(io_err(dir))?;
        write_atomic(&Self::snapshot_path(dir), &encode_snapshot(data)?)?;
        let file = Self::fresh_log(dir)?;
        if let Some(parent) = dir.parent() {
            sync_dir(parent)?;
        }
        Ok(Self { dir: dir.to_path_buf(), file, records: 0, compact_every })
    }

    /// Loads snapshot + log, cutting a torn tail.
    pub fn open(dir: &Path, compact_every: usize) -> Result<(MapData, Self, LoadReport), MapError> {
        let snap_path = Self::snapshot_path(dir);
        let bytes = std::fs::read(&snap_path).map_err(io_err(&snap_path))?;
        let mut data = decode_snapshot(&bytes, &snap_path)?;
        let log_path = Self::log_path(dir);
        let mut report = LoadReport::default();
        if !log_path.exists() {
            let file = Self::fresh_log(dir)?;
            return Ok((data, Self { dir: dir.to_path_buf(), file, records: 0, compact_every }, report));
        }
        let mut file = OpenOptions::new().read(true).append(true).open(&log_path).map_err(io_err(&log_path))?;
        let mut buf = Vec::new();
        file.read_to_end(&mut buf).map_err(io_err(&log_path))?;
        if buf.len() < LOG_HEADER as usize || &buf[..8] != LOG_MAGIC {
            return Err(corrupt(&log_path, "not a scone log (bad magic)"));
        }
        let version = u32::from_le_bytes(buf[8..12].try_into().expect("4 bytes"));
        if !readable_version(version) {
            return Err(unreadable(&log_path, "log", version));
        }
        let mut pos = LOG_HEADER as usize;
        let mut records = 0;
        while pos < buf.len() {
            let (seq, record, end) = match read_frame(&buf, pos, &log_path)? {
                Frame::Torn => break,
                Frame::BadChecksum { end } if end == buf.len() => break, // the last record is torn
                Frame::BadChecksum { .. } => {
                    return Err(corrupt(
                        &log_path,
                        format!("checksum mismatch in the record at byte {pos}, more records follow"),
                    ))
                }
                Frame::Record { seq, record, end } => (seq, record, end),
            };
            if seq > data.version {
                if seq != data.version + 1 {
                    return Err(corrupt(&log_path, format!("record {seq} follows version {}", data.version)));
                }
                data.check(&record).map_err(|reason| corrupt(&log_path, format!("record {seq}: {reason}")))?;
                data.apply(&record);
                report.replayed += 1;
            }
            records += 1;
            pos = end;
        }
        if pos < buf.len() {
            report.truncated_bytes = (buf.len() - pos) as u64;
            file.set_len(pos as u64).map_err(io_err(&log_path))?;
            file.sync_all().map_err(io_err(&log_path))?;
            tracing::warn!(log = %log_path.display(), bytes = report.truncated_bytes, "cut a torn record off the log");
        }
        file.seek(SeekFrom::End(0)).map_err(io_err(&log_path))?;
        let mut log = Self { dir: dir.to_path_buf(), file, records, compact_every };
        if version < FORMAT_VERSION {
            // New kinds of record must not go into a file whose header promises the old format.
            log.compact(&data)?;
            tracing::info!(map = %dir.display(), from = version, to = FORMAT_VERSION, "upgraded the map's files");
        }
        Ok((data, log, report))
    }

    /// Appends the record that takes `data` to version `seq` and waits until it is on disk.
    pub fn append(&mut self, seq: u64, record: &Record) -> Result<(), MapError> {
        let path = Self::log_path(&self.dir);
        let frame = encode_record(seq, record)?;
        self.file.write_all(&frame).map_err(io_err(&path))?;
        self.file.sync_data().map_err(io_err(&path))?;
        self.records += 1;
        Ok(())
    }

    /// Whether the log has grown enough to be folded into a snapshot.
    pub fn wants_compaction(&self) -> bool {
        self.compact_every > 0 && self.records >= self.compact_every
    }

    /// Snapshots `data` and restarts the log. Safe at any crash point: records not newer than the snapshot
    /// are skipped at load.
    pub fn compact(&mut self, data: &MapData) -> Result<(), MapError> {
        write_atomic(&Self::snapshot_path(&self.dir), &encode_snapshot(data)?)?;
        self.file = Self::fresh_log(&self.dir)?;
        self.records = 0;
        Ok(())
    }

    pub fn dir(&self) -> &Path {
        &self.dir
    }
}
