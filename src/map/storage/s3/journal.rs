//! The writer of one map in object storage: appends (a segment, then the manifest conditionally),
//! compaction, freshness checks, and fencing after another writer's manifest.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use object_store::path::Path as ObjectPath;
use object_store::{PutMode, UpdateVersion};

use crate::error::MapError;
use crate::map::model::{MapData, MapStats, Record};
use crate::map::payload::StoredPayloads;
use crate::map::storage::backend::{Freshness, MapJournal};
use crate::map::storage::format::{decode_segment, encode_segment, FORMAT_VERSION};
use crate::map::storage::s3::client::Shared;
use crate::map::storage::s3::manifest::{nonce, number_of, Manifest, SnapshotRef, INDEX_FILES, MANIFEST};
use crate::map::storage::snapshot::{encode_snapshot_spans, stored_payloads};

/// How a conditional manifest PUT ended.
pub(super) enum Outcome {
    Written(UpdateVersion),
    /// Someone else's manifest is there (or none: the map was deleted): its writer, and the manifest when it
    /// could be read (it may name what this writer just wrote: another replica that followed this writer's
    /// manifest, whose PUT answer was lost, and appended on top of it).
    Conflict(String, Option<Manifest>),
    /// The stored manifest could not be read back: as a conflict, but nothing written may be deleted.
    Unknown(String),
    /// The PUT failed and the manifest is still the previous one: nothing changed.
    NotWritten(MapError),
}

/// The writer of one map in object storage.
pub(super) struct ObjectJournal {
    pub(super) shared: Arc<Shared>,
    pub(super) id: String,
    /// The manifest as this writer last read or wrote it...
    pub(super) manifest: Manifest,
    /// ...and its ETag/version, the condition of the next manifest PUT.
    pub(super) version: UpdateVersion,
    pub(super) cache_dir: PathBuf,
    /// Set once this writer lost the map (or cannot tell whether it did): the other writer, named in the
    /// [`MapError::WriterConflict`] every later write fails with.
    pub(super) fenced: Option<String>,
    /// Whether this journal wrote a record: a replica that only loaded the map does not compact it.
    pub(super) wrote: bool,
    /// Where the snapshot written last keeps each payload (its copy in the cache directory), until the store
    /// takes it.
    pub(super) stored: Option<StoredPayloads>,
}

impl std::fmt::Debug for ObjectJournal {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ObjectJournal")
            .field("map", &self.id)
            .field("manifest", &self.manifest)
            .field("fenced", &self.fenced)
            .finish()
    }
}

impl ObjectJournal {
    /// The writer of map `id` whose manifest, as read or written, is `manifest` at `version`.
    pub(super) fn new(
        shared: &Arc<Shared>,
        id: &str,
        manifest: Manifest,
        version: UpdateVersion,
        cache_dir: PathBuf,
    ) -> Self {
        Self {
            shared: Arc::clone(shared),
            id: id.to_string(),
            manifest,
            version,
            cache_dir,
            fenced: None,
            wrote: false,
            stored: None,
        }
    }

    fn check_fence(&self) -> Result<(), MapError> {
        match &self.fenced {
            None => Ok(()),
            Some(writer) => Err(MapError::WriterConflict { map: self.id.clone(), writer: writer.clone() }),
        }
    }

    /// PUTs `next` as the manifest if it is still the one this writer knows, and finds out what happened when
    /// the answer is not clear.
    fn replace_manifest(&self, next: &Manifest) -> Outcome {
        let s = &self.shared;
        let path = s.object(&self.id, MANIFEST);
        let bytes = serde_json::to_vec_pretty(next).expect("manifest serialises");
        let err = match s.block_on(s.put(&path, bytes.clone(), PutMode::Update(self.version.clone()))) {
            Ok(v) => return Outcome::Written(v),
            Err(e) => e,
        };
        let precondition = matches!(err, object_store::Error::Precondition { .. });
        // Read back: a lost response to a PUT that was applied, a rival's manifest, or the previous one.
        match s.block_on(s.get(&path)) {
            Ok((current, v)) if current == bytes => Outcome::Written(v),
            Ok((_, v)) if !precondition && v.e_tag.is_some() && v.e_tag == self.version.e_tag => {
                Outcome::NotWritten(s.io(&path, err))
            }
            Ok((current, _)) => match serde_json::from_slice::<Manifest>(&current) {
                Ok(m) => Outcome::Conflict(m.writer.clone(), Some(m)),
                Err(_) => Outcome::Conflict("unknown (unreadable manifest)".into(), None),
            },
            Err(object_store::Error::NotFound { .. }) => Outcome::Conflict("none (the map was deleted)".into(), None),
            Err(e) => {
                tracing::error!(map = %self.id, error = %e, put_error = %err, "manifest write outcome unknown");
                // Not knowing what the stored manifest names, nothing of this write may be deleted.
                Outcome::Unknown(format!("unknown (the manifest could not be read back: {e})"))
            }
        }
    }

    /// Applies an outcome: success updates the known manifest; anything else cleans up `written` (relative to
    /// the map's prefix) unless the stored manifest names it, and returns the error, fencing the writer on a
    /// conflict.
    fn settle(&mut self, next: Manifest, outcome: Outcome, written: &str) -> Result<(), MapError> {
        let s = Arc::clone(&self.shared);
        let path = s.object(&self.id, written);
        match outcome {
            Outcome::Written(v) => {
                self.manifest = next;
                self.version = v;
                Ok(())
            }
            Outcome::NotWritten(e) => {
                s.block_on(s.delete_quietly(vec![path]));
                Err(e)
            }
            Outcome::Conflict(writer, stored) => {
                if !stored.as_ref().is_some_and(|m| m.names(written)) {
                    s.block_on(s.delete_quietly(vec![path]));
                }
                tracing::error!(map = %self.id, other = %writer, "another writer replaced the manifest: fenced");
                self.fenced = Some(writer.clone());
                Err(MapError::WriterConflict { map: self.id.clone(), writer })
            }
            Outcome::Unknown(writer) => {
                tracing::error!(map = %self.id, other = %writer, "manifest write outcome unknown: fenced");
                self.fenced = Some(writer.clone());
                Err(MapError::WriterConflict { map: self.id.clone(), writer })
            }
        }
    }
}

impl MapJournal for ObjectJournal {
    fn append(&mut self, seq: u64, record: &Record, after: &MapStats) -> Result<(), MapError> {
        self.check_fence()?;
        if seq != self.manifest.next_seq {
            return Err(MapError::Unavailable {
                map: self.id.clone(),
                reason: format!("write {seq} does not follow the stored version {}", self.manifest.next_seq - 1),
            });
        }
        let s = Arc::clone(&self.shared);
        let name = format!("segments/{seq:020}-{}.rec", nonce());
        let path = s.object(&self.id, &name);
        s.block_on(s.put_new(&path, encode_segment(seq, record)?)).map_err(|e| s.io(&path, e))?;
        let mut next = self.manifest.clone();
        // The manifest names an object of this format from now on (objects carry their own versions).
        next.format_version = FORMAT_VERSION;
        next.writer = s.writer.clone();
        next.segments.push(name.clone());
        next.next_seq += 1;
        next.stats = Some(after.clone());
        let outcome = self.replace_manifest(&next);
        self.settle(next, outcome, &name)?;
        self.wrote = true;
        Ok(())
    }

    fn wants_compaction(&self) -> bool {
        self.shared.compact_every > 0 && self.manifest.segments.len() >= self.shared.compact_every
    }

    fn compact(&mut self, data: &MapData) -> Result<(), MapError> {
        self.check_fence()?;
        // Nothing to fold, or not this replica's to fold: the writer compacts, a replica that only loaded the
        // map must not replace its manifest (that would fence the writer).
        if !self.wrote || (self.manifest.segments.is_empty() && self.manifest.snapshot.version == data.version) {
            return Ok(());
        }
        if data.version + 1 != self.manifest.next_seq {
            return Err(MapError::Unavailable {
                map: self.id.clone(),
                reason: format!(
                    "snapshot of version {} does not match the stored {}",
                    data.version,
                    self.manifest.next_seq - 1
                ),
            });
        }
        let s = Arc::clone(&self.shared);
        let name = format!("snapshots/{:020}-{}.bin", data.version, nonce());
        let path = s.object(&self.id, &name);
        let encoded = encode_snapshot_spans(data)?;
        // The local copy first, so that the bytes then go to the PUT without a copy in memory. It holds this
        // map's payloads whatever becomes of the object: the keyframes point there once the compaction is done.
        let stored = match s.keep_snapshot(&self.cache_dir, &name, &encoded.bytes) {
            Ok(copy) => Some(stored_payloads(&copy, &encoded, data.version)?),
            Err(e) => {
                tracing::warn!(map = %self.id, error = %e, "cannot copy the snapshot; payloads stay in memory");
                None
            }
        };
        s.block_on(s.put_new(&path, encoded.bytes)).map_err(|e| s.io(&path, e))?;
        // The dump is an optimisation for other replicas: a failed upload leaves the map without one.
        let index = s.block_on(s.upload_index(&self.id, data.version, &self.cache_dir)).unwrap_or_else(|e| {
            tracing::warn!(map = %self.id, error = %e, "cannot upload the index dump; replicas will rebuild it");
            None
        });
        let old = self.manifest.clone();
        let mut next = old.clone();
        next.format_version = FORMAT_VERSION;
        next.writer = s.writer.clone();
        next.snapshot = SnapshotRef { object: name.clone(), version: data.version };
        next.segments.clear();
        next.stats = Some(data.stats());
        next.index = index.clone();
        let outcome = self.replace_manifest(&next);
        if let (Some(ix), Outcome::NotWritten(_) | Outcome::Conflict(_, _)) = (&index, &outcome) {
            let stored_names_it = matches!(&outcome, Outcome::Conflict(_, Some(m)) if m.names(&ix.dir));
            if !stored_names_it {
                let files = INDEX_FILES.iter().map(|f| s.object(&self.id, &format!("{}/{f}", ix.dir))).collect();
                s.block_on(s.delete_quietly(files));
            }
        }
        self.settle(next, outcome, &name)?;
        self.stored = stored;
        // The new manifest is in place: the replaced objects, and orphans it covers, are garbage. No valid
        // manifest can name a segment numbered <= data.version or a snapshot older than this one again.
        let prefix = s.map_prefix(&self.id);
        let listed: Vec<ObjectPath> = s.block_on(s.list_under(&prefix)).unwrap_or_else(|e| {
            tracing::warn!(map = %self.id, error = %e, "cannot list objects to collect garbage");
            Vec::new()
        });
        let depth = prefix.parts().count();
        let current = s.object(&self.id, &name);
        let current_index = index.as_ref().map(|ix| ix.dir.trim_start_matches("index/").to_string());
        let mut garbage: Vec<ObjectPath> = listed
            .into_iter()
            .filter(|p| {
                let parts: Vec<_> = p.parts().skip(depth).map(|x| x.as_ref().to_string()).collect();
                match parts.as_slice() {
                    [dir, file] if dir == "segments" => number_of(file).is_some_and(|n| n <= data.version),
                    [dir, file] if dir == "snapshots" => {
                        *p != current && number_of(file).is_some_and(|n| n <= data.version)
                    }
                    [dir, sub, _] if dir == "index" => {
                        current_index.as_deref() != Some(sub.as_str())
                            && number_of(sub).is_some_and(|n| n <= data.version)
                    }
                    _ => false,
                }
            })
            .collect();
        garbage.push(s.object(&self.id, &old.snapshot.object));
        garbage.extend(old.segments.iter().map(|n| s.object(&self.id, n)));
        garbage.sort();
        garbage.dedup();
        s.block_on(s.delete_quietly(garbage));
        Ok(())
    }

    fn index_dir(&self) -> &Path {
        &self.cache_dir
    }

    fn take_stored_payloads(&mut self) -> Option<StoredPayloads> {
        self.stored.take()
    }

    /// A GET of the manifest conditional on its ETag (`If-None-Match`): not modified, the copy is current;
    /// a manifest that only appended segments to the known one, those records (fetched and checked here,
    /// the journal then follows the new manifest); anything else (a new snapshot, another map under the id),
    /// replaced; no manifest, gone.
    fn refresh(&mut self) -> Result<Freshness, MapError> {
        let s = Arc::clone(&self.shared);
        let path = s.object(&self.id, MANIFEST);
        let fetched = match self.version.e_tag.clone() {
            Some(tag) => s.block_on(s.get_changed(&path, tag)),
            None => s.block_on(s.get(&path)).map(Some),
        };
        let (bytes, version) = match fetched {
            Ok(None) => return Ok(Freshness::Current),
            Ok(Some(got)) => got,
            Err(object_store::Error::NotFound { .. }) => return Ok(Freshness::Gone),
            Err(e) => return Err(s.io(&path, e)),
        };
        let next = s.parse_manifest(&self.id, &bytes)?;
        if next == self.manifest {
            self.version = version;
            return Ok(Freshness::Current);
        }
        let known = &self.manifest;
        if next.map_uid != known.map_uid
            || next.snapshot != known.snapshot
            || !next.segments.starts_with(&known.segments)
        {
            return Ok(Freshness::Replaced);
        }
        let first = known.next_seq;
        let fetched = s.fetch_all(&self.id, &next.segments[known.segments.len()..])?;
        let mut records = Vec::with_capacity(fetched.len());
        for (i, (path, bytes)) in fetched.into_iter().enumerate() {
            let (seq, record) = decode_segment(&bytes, &s.name(&path))?;
            if seq != first + i as u64 {
                return Err(s.corrupt(&path, format!("holds record {seq}, expected {}", first + i as u64)));
            }
            records.push(record);
        }
        self.manifest = next;
        self.version = version;
        self.fenced = None;
        Ok(Freshness::Appended(records))
    }
}
