//! Maps on the local disk: `data_dir/maps/<id>/` holds one map's `snapshot.bin`, its write-ahead
//! `log.bin` (byte layouts in [`crate::map::storage::format`]) and its index dump.
//!
//! A write is acknowledged only after its record is appended and `fdatasync` returned, so an acknowledged
//! write survives `kill -9` and power loss (as far as the disk honours fsync). Loading replays the log
//! records newer than the snapshot. A torn last record (the normal result of a crash in the middle of an
//! append, never acknowledged) is cut off and the map loads. A bad record followed by more data is
//! corruption: the map is reported and held back; the caller keeps serving the others. After
//! `compact_every` records the map is snapshotted and the log restarted.
//!
//! **A failed write leaves the files as they were.** An append that fails (a full volume: `ENOSPC` in the
//! middle of the record, or a failed `fdatasync`) is cut back off the log before the error is returned, so
//! later records follow good data; if even the cut fails, the log refuses appends until a later one manages
//! it. A map is created in a hidden directory that is renamed into place once its snapshot and log are
//! durable; a failed create removes it, and one interrupted by a crash is removed at the next start (as are
//! the remains of an interrupted delete).
//!
//! A map of an older format (its snapshot or its log) is folded into a current-format snapshot with a fresh
//! log as soon as it is opened (the same crash-safe steps as compaction), so a record of a new kind never
//! lands in a file whose header promises an older format. A rewrite that fails (a full volume) leaves the old
//! files whole and the map opens from them: it answers reads, and its next write tries the rewrite again
//! before its record ([`MapJournal::needs_upgrade`]), answering the volume's error if it still fails.
//!
//! Keyframe payloads are read from `snapshot.bin` on demand ([`crate::map::payload`]): the keyframes of a
//! loaded map point into the file that was the snapshot when they were stored, kept open across the
//! compaction that replaces it until the store points them at the new one.

use std::fs::{File, OpenOptions};
use std::io::{Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

use crate::error::MapError;
use crate::map::model::{validate_map_id, MapData, MapStats, Record};
use crate::map::payload::StoredPayloads;
use crate::map::storage::backend::{EarlyIndex, LoadReport, MapBackend, MapJournal};
use crate::map::storage::format::{
    corrupt, encode_record, injected, injected_full, io_err, io_error, read_frame, readable_version, sync_dir,
    unreadable, write_atomic, LogEntry, FORMAT_VERSION, LOG_HEADER, LOG_MAGIC,
};
use crate::map::storage::snapshot::{encode_snapshot_spans, read_snapshot, snapshot_version, stored_payloads};

/// The open log of one map.
#[derive(Debug)]
pub struct LocalJournal {
    dir: PathBuf,
    file: File,
    /// Bytes of the log that hold whole, durable records (and the header): where the next record goes.
    len: u64,
    /// A failed append could not be cut back off: the file is longer than `len` until a later cut succeeds.
    torn_tail: bool,
    records: usize,
    compact_every: usize,
    /// Where the last snapshot written keeps each payload, until the store takes it.
    stored: Option<StoredPayloads>,
    /// The format in the open log's header: an older one until the map's files are rewritten, and no record
    /// is appended to it before they are.
    log_format: u32,
}

impl LocalJournal {
    fn log_path(dir: &Path) -> PathBuf {
        dir.join("log.bin")
    }

    fn snapshot_path(dir: &Path) -> PathBuf {
        dir.join("snapshot.bin")
    }

    /// Replaces the log with an empty one (header only), atomically.
    fn fresh_log(dir: &Path) -> Result<File, MapError> {
        let path = Self::log_path(dir);
        let mut header = LOG_MAGIC.to_vec();
        header.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
        write_atomic(&path, &header)?;
        let mut f = OpenOptions::new().read(true).append(true).open(&path).map_err(io_err(&path))?;
        f.seek(SeekFrom::End(0)).map_err(io_err(&path))?;
        Ok(f)
    }

    fn new(dir: &Path, file: File, len: u64, records: usize, compact_every: usize) -> Self {
        let log_format = FORMAT_VERSION;
        Self { dir: dir.to_path_buf(), file, len, torn_tail: false, records, compact_every, stored: None, log_format }
    }

    /// Writes the snapshot of `data` (atomically); returns where it keeps each payload.
    fn write_snapshot(dir: &Path, data: &MapData) -> Result<StoredPayloads, MapError> {
        let path = Self::snapshot_path(dir);
        let encoded = encode_snapshot_spans(data)?;
        write_atomic(&path, &encoded.bytes)?;
        stored_payloads(&path, &encoded, data.version)
    }

    /// Creates the directory, a snapshot of `data` and an empty log.
    pub fn create(dir: &Path, data: &MapData, compact_every: usize) -> Result<Self, MapError> {
        std::fs::create_dir_all(dir).map_err(io_err(dir))?;
        let stored = Self::write_snapshot(dir, data)?;
        let file = Self::fresh_log(dir)?;
        if let Some(parent) = dir.parent() {
            sync_dir(parent)?;
        }
        let mut log = Self::new(dir, file, LOG_HEADER, 0, compact_every);
        log.stored = Some(stored);
        Ok(log)
    }

    /// Loads snapshot + log, cutting a torn tail; upgrades a map of an older format (see
    /// [`crate::map::storage::format`]).
    pub fn open(dir: &Path, compact_every: usize) -> Result<(MapData, Self, LoadReport), MapError> {
        let snap_path = Self::snapshot_path(dir);
        let snapshot_version = snapshot_version(&snap_path)?;
        let mut data = read_snapshot(&snap_path)?;
        let log_path = Self::log_path(dir);
        let mut report = LoadReport::default();
        if !log_path.exists() {
            let file = Self::fresh_log(dir)?;
            let mut log = Self::new(dir, file, LOG_HEADER, 0, compact_every);
            if snapshot_version < FORMAT_VERSION {
                log.upgrade(&mut data, snapshot_version);
            }
            return Ok((data, log, report));
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
            let (seq, record, end) = match read_frame(&buf, pos, version, &log_path)? {
                LogEntry::Torn => break,
                LogEntry::BadChecksum { end } if end == buf.len() => break, // the last record is torn
                LogEntry::BadChecksum { .. } => {
                    return Err(corrupt(
                        &log_path,
                        format!("checksum mismatch in the record at byte {pos}, more records follow"),
                    ))
                }
                LogEntry::Record { seq, record, end } => (seq, record, end),
            };
            if seq > data.version {
                if seq != data.version + 1 {
                    return Err(corrupt(&log_path, format!("record {seq} follows version {}", data.version)));
                }
                data.check(&record).map_err(|reason| corrupt(&log_path, format!("record {seq}: {reason}")))?;
                data.apply(&record)?;
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
        let mut log = Self::new(dir, file, pos as u64, records, compact_every);
        log.log_format = version;
        if version.min(snapshot_version) < FORMAT_VERSION {
            log.upgrade(&mut data, version.min(snapshot_version));
        }
        Ok((data, log, report))
    }

    /// Rewrites an older map in the current format, by a compaction (crash-safe at every step: the old
    /// snapshot and log stay whole until the new snapshot is renamed over the old one, and records it covers
    /// are skipped at load; a crash before the fresh log upgrades again at the next open). New kinds of record
    /// must not go into a file whose header promises an older format; the map's payloads then leave memory.
    /// A rewrite that fails (a full volume) is logged, not the open's error: the map is read from its files as
    /// they are, and the next write rewrites them first ([`MapJournal::needs_upgrade`]).
    fn upgrade(&mut self, data: &mut MapData, from: u32) {
        match self.compact(data) {
            Ok(()) => {
                if let Some(stored) = self.stored.take() {
                    data.store_payloads(&stored);
                }
                tracing::info!(map = %self.dir.display(), from, to = FORMAT_VERSION, "upgraded the map's files");
            }
            Err(e) => tracing::warn!(
                map = %self.dir.display(), from, to = FORMAT_VERSION, error = %e,
                "cannot rewrite the map's files in the current format; it is read as it is, and its next write tries again"
            ),
        }
    }

    /// Whether the open log is of an older format, so the map's files must be rewritten (a compaction) before
    /// a record is appended.
    pub fn needs_upgrade(&self) -> bool {
        self.log_format < FORMAT_VERSION
    }

    /// Appends the record that takes `data` to version `seq` and waits until it is on disk. On failure the
    /// log is cut back to the records before it (fail point `map-append`: half the record, then a full volume).
    pub fn append(&mut self, seq: u64, record: &Record) -> Result<(), MapError> {
        let path = Self::log_path(&self.dir);
        if self.needs_upgrade() {
            // The caller compacts first (`MapJournal::needs_upgrade`); this record's encoding is not the log's.
            return Err(MapError::Unavailable {
                map: self.dir.display().to_string(),
                reason: format!("its log is of format {} and must be rewritten before a write", self.log_format),
            });
        }
        let frame = encode_record(seq, record)?;
        if self.torn_tail {
            self.cut_back()?;
        }
        let written = if injected("map-append", &path) {
            let _ = self.file.write_all(&frame[..frame.len() / 2]);
            Err(injected_full(&path))
        } else {
            self.file.write_all(&frame).and_then(|()| self.file.sync_data()).map_err(io_err(&path))
        };
        if let Err(e) = written {
            // Whatever reached the file of this record goes, so the next record follows good data.
            self.torn_tail = true;
            if let Err(cut) = self.cut_back() {
                tracing::error!(log = %path.display(), error = %cut, "cannot cut a failed append off the log; appends wait for the cut");
            }
            return Err(e);
        }
        self.len += frame.len() as u64;
        self.records += 1;
        Ok(())
    }

    /// Truncates the log to its last whole record (after a failed append) and makes that durable.
    fn cut_back(&mut self) -> Result<(), MapError> {
        let path = Self::log_path(&self.dir);
        self.file.set_len(self.len).map_err(io_err(&path))?;
        self.file.sync_all().map_err(io_err(&path))?;
        self.torn_tail = false;
        Ok(())
    }

    /// Whether the log has grown enough to be folded into a snapshot.
    pub fn wants_compaction(&self) -> bool {
        self.compact_every > 0 && self.records >= self.compact_every
    }

    /// Snapshots `data` and restarts the log. Safe at any crash point: records not newer than the snapshot
    /// are skipped at load.
    pub fn compact(&mut self, data: &MapData) -> Result<(), MapError> {
        let stored = Self::write_snapshot(&self.dir, data)?;
        self.stored = Some(stored);
        self.file = Self::fresh_log(&self.dir)?;
        self.log_format = FORMAT_VERSION;
        self.len = LOG_HEADER;
        self.torn_tail = false;
        self.records = 0;
        Ok(())
    }

    pub fn dir(&self) -> &Path {
        &self.dir
    }
}

/// Prefixes of the hidden directories of an unfinished create and an unfinished delete.
const CREATING: &str = ".creating-";
const DELETED: &str = ".deleted-";

fn unique_suffix(id: &str) -> String {
    format!("{id}-{:016x}", rand::random::<u64>())
}

/// Maps in `data_dir/maps/<id>/`, each a [`LocalJournal`].
#[derive(Debug)]
pub struct LocalBackend {
    root: PathBuf,
    compact_every: usize,
}

impl LocalBackend {
    /// Creates `data_dir/maps` if needed, and removes what an interrupted create or delete left there.
    pub fn new(data_dir: &Path, compact_every: usize) -> Result<Self, MapError> {
        let root = data_dir.join("maps");
        std::fs::create_dir_all(&root).map_err(io_err(&root))?;
        for entry in std::fs::read_dir(&root).map_err(io_err(&root))? {
            let path = entry.map_err(io_err(&root))?.path();
            let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
            if path.is_dir() && (name.starts_with(CREATING) || name.starts_with(DELETED)) {
                match std::fs::remove_dir_all(&path) {
                    Ok(()) => {
                        tracing::info!(dir = %path.display(), "removed what an interrupted create or delete left")
                    }
                    Err(e) => {
                        tracing::warn!(dir = %path.display(), error = %e, "cannot remove an unfinished create or delete")
                    }
                }
            }
        }
        Ok(Self { root, compact_every })
    }

    fn dir(&self, id: &str) -> PathBuf {
        self.root.join(id)
    }
}

impl MapJournal for LocalJournal {
    fn append(&mut self, seq: u64, record: &Record, _after: &MapStats) -> Result<(), MapError> {
        LocalJournal::append(self, seq, record)
    }

    fn wants_compaction(&self) -> bool {
        LocalJournal::wants_compaction(self)
    }

    fn needs_upgrade(&self) -> bool {
        LocalJournal::needs_upgrade(self)
    }

    fn compact(&mut self, data: &MapData) -> Result<(), MapError> {
        LocalJournal::compact(self, data)
    }

    fn index_dir(&self) -> &Path {
        self.dir()
    }

    fn take_stored_payloads(&mut self) -> Option<StoredPayloads> {
        self.stored.take()
    }
}

impl MapBackend for LocalBackend {
    fn location(&self) -> String {
        self.root.display().to_string()
    }

    fn list(&self) -> Result<Vec<String>, MapError> {
        let io = io_err(&self.root);
        let mut ids = Vec::new();
        for entry in std::fs::read_dir(&self.root).map_err(io)? {
            let entry = entry.map_err(|e| io_error(&self.root, e))?;
            let name = entry.file_name().to_string_lossy().into_owned();
            // Skips the `.deleted-*` directories of an interrupted delete, among others.
            if entry.path().is_dir() && validate_map_id(&name).is_ok() {
                ids.push(name);
            }
        }
        ids.sort();
        Ok(ids)
    }

    fn exists(&self, id: &str) -> Result<bool, MapError> {
        Ok(self.dir(id).exists())
    }

    /// Writes the map in a hidden directory and renames it into place: a map directory is whole or absent.
    fn create(&self, id: &str, data: &MapData) -> Result<Box<dyn MapJournal>, MapError> {
        let dir = self.dir(id);
        if dir.exists() {
            return Err(MapError::MapExists { map: id.to_string() });
        }
        let staging = self.root.join(format!("{CREATING}{}", unique_suffix(id)));
        let created = LocalJournal::create(&staging, data, self.compact_every).and_then(|mut log| {
            if dir.exists() {
                return Err(MapError::MapExists { map: id.to_string() });
            }
            std::fs::rename(&staging, &dir).map_err(io_err(&dir))?;
            log.dir = dir.clone();
            Ok(log)
        });
        match created {
            Ok(log) => match sync_dir(&self.root) {
                Ok(()) => Ok(Box::new(log)),
                Err(e) => {
                    // Not known to be durable: not acknowledged, and not left half there.
                    let _ = std::fs::remove_dir_all(&dir);
                    Err(e)
                }
            },
            Err(e) => {
                let _ = std::fs::remove_dir_all(&staging);
                Err(e)
            }
        }
    }

    fn open(&self, id: &str) -> Result<(MapData, Box<dyn MapJournal>, LoadReport), MapError> {
        let (data, log, report) = LocalJournal::open(&self.dir(id), self.compact_every)?;
        Ok((data, Box::new(log), report))
    }

    /// The map's directory, which holds its index dump ([`LocalJournal`]'s `index_dir`).
    fn index_before_open(&self, id: &str) -> Option<EarlyIndex> {
        Some(EarlyIndex { dir: self.dir(id), fetch: None })
    }

    /// Renames the directory away (atomic), then removes it.
    fn delete(&self, id: &str) -> Result<(), MapError> {
        let dir = self.dir(id);
        let millis = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_millis() as u64)
            .unwrap_or(0);
        let trash = self.root.join(format!("{DELETED}{id}-{millis}"));
        std::fs::rename(&dir, &trash).map_err(io_err(&dir))?;
        sync_dir(&self.root)?;
        std::fs::remove_dir_all(&trash).map_err(io_err(&trash))
    }
}
