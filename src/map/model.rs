//! The map's data: keyframes (pose, intrinsics, keypoints with FREAK descriptors, so a map can be re-embedded),
//! landmarks (3D points) and their observations (keyframe, keypoint, SConE embedding).
//!
//! Every change is a [`Record`]; [`MapData::apply`] is the only way state changes, both when a write is made
//! and when the log is replayed at start, so a replayed map equals the map that acknowledged the writes.
//!
//! Landmarks given by an external SfM (COLMAP and the like) keep their external id: [`MapData::external_ids`]
//! maps it to the landmark, so observations of one external id in several keyframes are one landmark. The
//! mapping is part of the map (snapshot, export) and changes only through [`Record::AddExternalKeyframe`].

use std::collections::{BTreeMap, HashMap};
use std::sync::Arc;

use serde::{Deserialize, Serialize};

use crate::describe::features::DESCRIPTOR_BYTES;
use crate::error::MapError;
use crate::map::payload::{inline_memory_bytes, StoredPayloads};
pub use crate::map::payload::{Keyframe, MapKeyframe};

/// Map ids: 1-64 characters from `[A-Za-z0-9_-]`.
pub fn validate_map_id(id: &str) -> Result<(), MapError> {
    let ok =
        !id.is_empty() && id.len() <= 64 && id.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'_' || b == b'-');
    if ok {
        Ok(())
    } else {
        Err(MapError::InvalidMapId { map: id.chars().take(80).collect() })
    }
}

/// What the HNSW graph indexes (the exact search below `exact_below` always reads every observation). The
/// service's default is one point per landmark (chosen by its rule in BENCHMARKS.md); dump manifests written
/// before the setting existed read as one point per observation, which is what they hold. Here, beside the
/// data it names, so the index ([`crate::map::index`]) and its dump's manifest share it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum IndexPoints {
    /// One point per live observation: every view of a landmark.
    #[default]
    Observations,
    /// One point per landmark: its medoid view (the live view nearest, in embedding space, to its other
    /// views, as ORB-SLAM picks a map point's descriptor). It is chosen when the landmark is first indexed and
    /// chosen again each time its live views reach a power of two (2, 4, 8, ...) or its view's keyframe is
    /// removed; the replaced point stays in the graph, passed over by searches, until a rebuild.
    Landmarks,
}

/// Identity of a map and of the model that embedded it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MapMeta {
    pub id: String,
    pub model_id: String,
    pub k: usize,
    pub dim: usize,
    pub created_unix_ms: u64,
}

/// One sighting of a landmark: a keypoint of a keyframe and its embedding.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Observation {
    pub landmark: u64,
    pub keyframe: u64,
    pub keypoint: u32,
    /// False once its keyframe was removed (a tombstone for the index).
    pub live: bool,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Landmark {
    pub point: [f64; 3],
    /// Observation ids.
    pub observations: Vec<u64>,
}

/// A new observation carried by a record: keypoint `keypoint` of keyframe `keyframe` (the new keyframe or an
/// earlier one) sees `landmark`. Its embedding is the keyframe's embedding of that keypoint.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct NewObservation {
    pub landmark: u64,
    pub keyframe: u64,
    pub keypoint: u32,
}

/// A change to a map: the unit of the write-ahead log.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum Record {
    /// A keyframe with the landmarks it creates and the observations it adds (to new or existing landmarks).
    AddKeyframe { keyframe: Keyframe, new_landmarks: Vec<(u64, [f64; 3])>, observations: Vec<NewObservation> },
    /// Removes a keyframe; its observations become tombstones.
    RemoveKeyframe { id: u64 },
    /// Replaces every keyframe's embeddings (and so every observation's) after a model change.
    Reembed { model_id: String, k: usize, dim: usize, keyframes: Vec<(u64, Vec<f32>)> },
    /// A keyframe whose landmarks an external SfM gave: as `AddKeyframe`, plus `external_ids`, the
    /// (external id, landmark id) links of the landmarks it creates. Observations of external ids the map
    /// already links are in `observations` and name the linked landmark.
    ///
    /// Appended as the last variant so that records of format 1 (which bincode 1 tags by variant index, as
    /// postcard does from format 4) decode unchanged.
    AddExternalKeyframe {
        keyframe: Keyframe,
        new_landmarks: Vec<(u64, [f64; 3])>,
        observations: Vec<NewObservation>,
        external_ids: Vec<(u64, u64)>,
    },
    /// Another map merged into this one (`MergeMaps`), as one record so that it is all or nothing: its
    /// keyframes (re-expressed in this map's frame, ids moved past this map's), the landmarks it adds, and
    /// every observation of its keyframes (of new landmarks, or of this map's landmarks it was fused with).
    /// Appended last, so that earlier records keep their tags.
    Merge {
        source: String,
        keyframes: Vec<Keyframe>,
        new_landmarks: Vec<(u64, [f64; 3])>,
        observations: Vec<NewObservation>,
    },
}

/// A map's counts and version, as listings report them; also recorded in object storage's manifest, so a
/// replica lists maps it has not loaded.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct MapStats {
    pub model_id: String,
    pub version: u64,
    pub keyframes: usize,
    pub landmarks: usize,
    pub observations: usize,
    pub live_observations: usize,
    /// Estimated memory of the loaded map's data ([`MapData::memory_bytes`]; a server that loads it adds its
    /// index's graph, which follows `store.index.points`).
    #[serde(default)]
    pub memory_bytes: u64,
}

/// The whole state of one map. Its keyframes' payloads are in memory or in the file of the snapshot that
/// holds them ([`crate::map::payload`]); the rest is in memory.
#[derive(Debug, Clone, PartialEq)]
pub struct MapData {
    pub meta: MapMeta,
    pub keyframes: BTreeMap<u64, MapKeyframe>,
    pub landmarks: BTreeMap<u64, Landmark>,
    pub observations: Vec<Observation>,
    /// Row-major `[observations, dim]`.
    pub embeddings: Vec<f32>,
    pub next_landmark: u64,
    /// Records applied since creation: the map's version.
    pub version: u64,
    /// External landmark id (the SfM's point id) -> landmark id, for landmarks given by an external SfM.
    pub external_ids: BTreeMap<u64, u64>,
    /// Observation ids of each keyframe, in order: derived from `observations`, so map building and
    /// relocalisation reach a keyframe's observations without scanning them all. Not stored; rebuilt when a
    /// snapshot is decoded ([`MapData::rebuild_derived`]). A removed keyframe's entry goes with it.
    by_keyframe: HashMap<u64, Vec<u64>>,
}

impl MapData {
    pub fn new(meta: MapMeta) -> Self {
        Self {
            meta,
            keyframes: BTreeMap::new(),
            landmarks: BTreeMap::new(),
            observations: Vec::new(),
            embeddings: Vec::new(),
            next_landmark: 0,
            version: 0,
            external_ids: BTreeMap::new(),
            by_keyframe: HashMap::new(),
        }
    }

    /// Points the keyframes at their payloads in a snapshot just made durable: their payloads leave memory.
    /// Only a snapshot of this map as it is now (its version) is used; a keyframe it does not hold keeps its
    /// payload.
    pub fn store_payloads(&mut self, stored: &StoredPayloads) {
        if stored.version != self.version {
            return;
        }
        for (id, span) in &stored.spans {
            if let Some(k) = self.keyframes.get_mut(id) {
                k.set_stored(Arc::clone(&stored.file), *span);
            }
        }
    }

    /// Rebuilds what is derived from the stored fields (after decoding them).
    pub(crate) fn rebuild_derived(&mut self) {
        self.by_keyframe.clear();
        // Observations stay live until their keyframe is removed, and the removal drops its entry.
        for (i, o) in self.observations.iter().enumerate() {
            if o.live {
                self.by_keyframe.entry(o.keyframe).or_default().push(i as u64);
            }
        }
    }

    /// Ids of the observations keyframe `id` makes (live while the keyframe exists; none once removed).
    pub fn keyframe_observations(&self, id: u64) -> &[u64] {
        self.by_keyframe.get(&id).map_or(&[], Vec::as_slice)
    }

    /// The live observations of keyframes `ids` (each keyframe once, in id order).
    pub fn observations_of_keyframes<'a>(&'a self, ids: &[u64]) -> impl Iterator<Item = &'a Observation> + 'a {
        let mut unique = ids.to_vec();
        unique.sort_unstable();
        unique.dedup();
        unique
            .into_iter()
            .flat_map(move |k| self.keyframe_observations(k).iter())
            .map(move |&o| &self.observations[o as usize])
            .filter(|o| o.live)
    }

    /// Keypoint -> landmark for the live observations of keyframe `id`.
    pub fn keypoint_landmarks(&self, id: u64) -> HashMap<u32, u64> {
        self.observations_of_keyframes(&[id]).map(|o| (o.keypoint, o.landmark)).collect()
    }

    /// Counts of the map as it is now, for listings.
    pub fn stats(&self) -> MapStats {
        MapStats {
            model_id: self.meta.model_id.clone(),
            version: self.version,
            keyframes: self.keyframes.len(),
            landmarks: self.landmarks.len(),
            observations: self.observations.len(),
            live_observations: self.live_observations(),
            memory_bytes: self.memory_bytes() as u64,
        }
    }

    /// The counts once `record` (checked against this map) is applied, without applying it.
    pub fn stats_after(&self, record: &Record) -> MapStats {
        let mut s = self.stats();
        s.version += 1;
        match record {
            Record::AddKeyframe { keyframe, new_landmarks, observations }
            | Record::AddExternalKeyframe { keyframe, new_landmarks, observations, .. } => {
                s.keyframes += 1;
                s.landmarks += new_landmarks.len();
                s.observations += observations.len();
                s.live_observations += observations.len();
                s.memory_bytes +=
                    self.added_bytes(std::slice::from_ref(keyframe), new_landmarks.len(), observations.len());
            }
            Record::RemoveKeyframe { id } => {
                s.keyframes -= usize::from(self.keyframes.contains_key(id));
                s.live_observations -= self.observations_of_keyframes(&[*id]).count();
            }
            Record::Reembed { model_id, .. } => s.model_id = model_id.clone(),
            Record::Merge { keyframes, new_landmarks, observations, .. } => {
                s.keyframes += keyframes.len();
                s.landmarks += new_landmarks.len();
                s.observations += observations.len();
                s.live_observations += observations.len();
                s.memory_bytes += self.added_bytes(keyframes, new_landmarks.len(), observations.len());
            }
        }
        s
    }

    /// Bytes an observation costs beyond its embedding: the observation and its id in the landmark's list.
    /// The index's graph is counted by the index ([`crate::map::index::EmbeddingIndex::memory_bytes`]).
    const OBSERVATION_BYTES: usize = std::mem::size_of::<Observation>() + 8;
    /// A landmark's point, list header and map node.
    const LANDMARK_BYTES: usize = std::mem::size_of::<Landmark>() + 48;

    /// What a record adding `keyframes` (their payloads in memory until the next snapshot), `landmarks` and
    /// `observations` adds to [`MapData::memory_bytes`].
    fn added_bytes(&self, keyframes: &[Keyframe], landmarks: usize, observations: usize) -> u64 {
        (keyframes.iter().map(inline_memory_bytes).sum::<usize>()
            + observations * (Self::OBSERVATION_BYTES + self.meta.dim * 4)
            + landmarks * Self::LANDMARK_BYTES) as u64
    }

    /// An estimate of the memory the map's data takes when loaded: keyframes (with their payload while it is
    /// in memory), landmarks, observations and their embeddings. The map cache adds its index's graph
    /// ([`crate::map::index::EmbeddingIndex::memory_bytes`]), which depends on what the graph holds.
    pub fn memory_bytes(&self) -> usize {
        let keyframes: usize = self.keyframes.values().map(MapKeyframe::memory_bytes).sum();
        keyframes
            + self.landmarks.len() * Self::LANDMARK_BYTES
            + self.observations.len() * Self::OBSERVATION_BYTES
            + self.embeddings.len() * 4
    }

    /// Keyframe `id` with its payload, read where it is stored at most once per `loaded`; `None` when the map
    /// has no such keyframe.
    fn load_once<'a>(
        &self,
        loaded: &'a mut HashMap<u64, Arc<Keyframe>>,
        id: u64,
    ) -> Result<Option<&'a Keyframe>, MapError> {
        let Some(k) = self.keyframes.get(&id) else { return Ok(None) };
        Ok(Some(match loaded.entry(id) {
            std::collections::hash_map::Entry::Occupied(e) => e.into_mut(),
            std::collections::hash_map::Entry::Vacant(e) => e.insert(k.load()?),
        }))
    }

    /// The FREAK bits of observations `views`, in order, read from their keyframes' payloads (where those are
    /// stored); `None` when one of those keyframes has no descriptors (keypoints of another detector).
    pub fn observation_descriptors(&self, views: &[usize]) -> Result<Option<Vec<u8>>, MapError> {
        let mut loaded = HashMap::new();
        let mut out = Vec::with_capacity(views.len() * DESCRIPTOR_BYTES);
        for &o in views {
            let ob = &self.observations[o];
            let Some(k) = self.load_once(&mut loaded, ob.keyframe)? else { return Ok(None) };
            if k.descriptors.len() != k.keypoints.len() * DESCRIPTOR_BYTES {
                return Ok(None);
            }
            out.extend_from_slice(k.descriptor(ob.keypoint as usize));
        }
        Ok(Some(out))
    }

    pub fn embedding(&self, observation: usize) -> &[f32] {
        let d = self.meta.dim;
        &self.embeddings[observation * d..(observation + 1) * d]
    }

    pub fn live_observations(&self) -> usize {
        self.observations.iter().filter(|o| o.live).count()
    }

    /// The checks shared by the records that add keyframes (one, or a merged map's).
    fn check_keyframes(
        &self,
        keyframes: &[Keyframe],
        new_landmarks: &[(u64, [f64; 3])],
        observations: &[NewObservation],
    ) -> Result<(), String> {
        let mut sizes = std::collections::HashMap::new();
        for keyframe in keyframes {
            if self.keyframes.contains_key(&keyframe.id) || sizes.contains_key(&keyframe.id) {
                return Err(format!("keyframe {} exists", keyframe.id));
            }
            let n = keyframe.keypoints.len();
            // Empty descriptors: keypoints of another detector (evaluation baselines); no re-embedding then.
            if !keyframe.descriptors.is_empty() && keyframe.descriptors.len() != n * DESCRIPTOR_BYTES {
                return Err("descriptor bytes do not match the keypoint count".into());
            }
            if keyframe.embeddings.len() != n * self.meta.dim {
                return Err(format!(
                    "expected {} embedding values, got {}",
                    n * self.meta.dim,
                    keyframe.embeddings.len()
                ));
            }
            keyframe.pose.validate().map_err(|problem| format!("keyframe {} pose {problem}", keyframe.id))?;
            sizes.insert(keyframe.id, n);
        }
        let mut fresh_landmarks = std::collections::HashSet::new();
        for (id, p) in new_landmarks {
            if self.landmarks.contains_key(id) || !fresh_landmarks.insert(*id) || !p.iter().all(|v| v.is_finite()) {
                return Err(format!("new landmark {id} exists or is not finite"));
            }
        }
        let mut seen = std::collections::HashSet::new();
        // The keypoints already observed, of the existing keyframes these observations name.
        let mut observed: HashMap<u64, HashMap<u32, u64>> = HashMap::new();
        for o in observations {
            if self.keyframes.contains_key(&o.keyframe) && !observed.contains_key(&o.keyframe) {
                observed.insert(o.keyframe, self.keypoint_landmarks(o.keyframe));
            }
        }
        for o in observations {
            let known = self.landmarks.contains_key(&o.landmark) || fresh_landmarks.contains(&o.landmark);
            let size = sizes.get(&o.keyframe).copied().or_else(|| self.keyframes.get(&o.keyframe).map(|k| k.keypoints));
            let in_range = size.is_some_and(|s| (o.keypoint as usize) < s);
            let fresh = seen.insert((o.keyframe, o.keypoint))
                && !observed.get(&o.keyframe).is_some_and(|k| k.contains_key(&o.keypoint));
            if !known || !in_range || !fresh {
                return Err(format!(
                    "observation of landmark {} by keyframe {} keypoint {} is inconsistent",
                    o.landmark, o.keyframe, o.keypoint
                ));
            }
        }
        Ok(())
    }

    /// Checks that a record can be applied (ids, sizes); `apply` assumes it was.
    pub fn check(&self, record: &Record) -> Result<(), String> {
        match record {
            Record::AddKeyframe { keyframe, new_landmarks, observations } => {
                self.check_keyframes(std::slice::from_ref(keyframe), new_landmarks, observations)
            }
            Record::Merge { keyframes, new_landmarks, observations, .. } => {
                self.check_keyframes(keyframes, new_landmarks, observations)?;
                // A merge adds observations of its own keyframes only, and points within the bound of poses.
                let added: std::collections::HashSet<u64> = keyframes.iter().map(|k| k.id).collect();
                if let Some(o) = observations.iter().find(|o| !added.contains(&o.keyframe)) {
                    return Err(format!("a merge observes keyframe {}, which it does not add", o.keyframe));
                }
                let bound = crate::camera::MAX_COORDINATE;
                if let Some((id, _)) = new_landmarks.iter().find(|(_, p)| p.iter().any(|v| v.abs() > bound)) {
                    return Err(format!("merged landmark {id} lies beyond {bound} map units"));
                }
                Ok(())
            }
            Record::AddExternalKeyframe { keyframe, new_landmarks, observations, external_ids } => {
                self.check_keyframes(std::slice::from_ref(keyframe), new_landmarks, observations)?;
                let mut seen = std::collections::HashSet::new();
                for (external, landmark) in external_ids {
                    if self.external_ids.contains_key(external) || !seen.insert(*external) {
                        return Err(format!("external landmark {external} is linked already"));
                    }
                    if !new_landmarks.iter().any(|l| l.0 == *landmark) {
                        return Err(format!("external landmark {external} links {landmark}, not a new landmark"));
                    }
                }
                Ok(())
            }
            Record::RemoveKeyframe { id } => {
                if self.keyframes.contains_key(id) {
                    Ok(())
                } else {
                    Err(format!("no keyframe {id}"))
                }
            }
            Record::Reembed { dim, keyframes, .. } => {
                if keyframes.len() != self.keyframes.len() {
                    return Err("re-embedding must cover every keyframe".into());
                }
                for (id, e) in keyframes {
                    let Some(k) = self.keyframes.get(id) else { return Err(format!("no keyframe {id}")) };
                    if e.len() != k.keypoints * dim {
                        return Err(format!("keyframe {id}: embedding size does not match its keypoints"));
                    }
                }
                Ok(())
            }
        }
    }

    /// The `n` keyframes holding the most live observations of `landmarks` (a landmark listed twice counts
    /// twice), among those `keep` admits; ties go to the lower id. The covisibility vote of relocalisation and
    /// of map building.
    pub fn covisible_keyframes(
        &self,
        landmarks: impl Iterator<Item = u64>,
        keep: impl Fn(u64) -> bool,
        n: usize,
    ) -> Vec<u64> {
        let mut votes: std::collections::HashMap<u64, usize> = std::collections::HashMap::new();
        for lm in landmarks {
            let Some(l) = self.landmarks.get(&lm) else { continue };
            for &o in &l.observations {
                let o = &self.observations[o as usize];
                if o.live && keep(o.keyframe) {
                    *votes.entry(o.keyframe).or_default() += 1;
                }
            }
        }
        let mut ranked: Vec<(u64, usize)> = votes.into_iter().collect();
        ranked.sort_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(&b.0)));
        ranked.into_iter().take(n).map(|(k, _)| k).collect()
    }

    /// (keyframe, keypoint) -> landmark for every live observation.
    pub fn observed_keypoints(&self) -> std::collections::HashMap<(u64, u32), u64> {
        self.observations.iter().filter(|o| o.live).map(|o| ((o.keyframe, o.keypoint), o.landmark)).collect()
    }

    /// The embeddings of the new observations `observations`, in order: from the keyframes the record adds,
    /// or from this map's keyframes (their payloads read where they are stored). Read before anything
    /// changes, so that a failed read leaves the map as it was.
    fn new_observation_embeddings(
        &self,
        keyframes: &[Keyframe],
        observations: &[NewObservation],
    ) -> Result<Vec<f32>, MapError> {
        let dim = self.meta.dim;
        let mut loaded = HashMap::new();
        let mut out = Vec::with_capacity(observations.len() * dim);
        for o in observations {
            let keyframe = match keyframes.iter().find(|k| k.id == o.keyframe) {
                Some(k) => k,
                None => self.load_once(&mut loaded, o.keyframe)?.ok_or_else(|| MapError::Corrupt {
                    path: self.meta.id.clone().into(),
                    reason: format!("an observation names keyframe {}, which the map lacks", o.keyframe),
                })?,
            };
            out.extend_from_slice(keyframe.embedding(o.keypoint as usize, dim));
        }
        Ok(out)
    }

    fn apply_keyframes(
        &mut self,
        keyframes: &[Keyframe],
        new_landmarks: &[(u64, [f64; 3])],
        observations: &[NewObservation],
    ) -> Result<(), MapError> {
        let embeddings = self.new_observation_embeddings(keyframes, observations)?;
        for (id, p) in new_landmarks {
            self.landmarks.insert(*id, Landmark { point: *p, observations: Vec::new() });
            self.next_landmark = self.next_landmark.max(id + 1);
        }
        for keyframe in keyframes {
            self.keyframes.insert(keyframe.id, MapKeyframe::inline(keyframe.clone()));
        }
        for o in observations {
            let oid = self.observations.len() as u64;
            self.observations.push(Observation {
                landmark: o.landmark,
                keyframe: o.keyframe,
                keypoint: o.keypoint,
                live: true,
            });
            self.by_keyframe.entry(o.keyframe).or_default().push(oid);
            if let Some(l) = self.landmarks.get_mut(&o.landmark) {
                l.observations.push(oid);
            }
        }
        self.embeddings.extend_from_slice(&embeddings);
        Ok(())
    }

    /// Applies a record (already checked). The payloads of stored keyframes it needs (the embeddings of the
    /// keypoints it observes, the keypoints a re-embedding keeps) are read first: an error (a read that
    /// failed, a payload whose checksum does not match) leaves the map as it was.
    pub fn apply(&mut self, record: &Record) -> Result<(), MapError> {
        match record {
            Record::AddKeyframe { keyframe, new_landmarks, observations } => {
                self.apply_keyframes(std::slice::from_ref(keyframe), new_landmarks, observations)?
            }
            Record::Merge { keyframes, new_landmarks, observations, .. } => {
                self.apply_keyframes(keyframes, new_landmarks, observations)?
            }
            Record::AddExternalKeyframe { keyframe, new_landmarks, observations, external_ids } => {
                self.apply_keyframes(std::slice::from_ref(keyframe), new_landmarks, observations)?;
                self.external_ids.extend(external_ids.iter().copied());
            }
            Record::RemoveKeyframe { id } => {
                self.keyframes.remove(id);
                for o in self.by_keyframe.remove(id).unwrap_or_default() {
                    self.observations[o as usize].live = false;
                }
            }
            Record::Reembed { model_id, k, dim, keyframes } => {
                // Every keyframe's payload in memory with its new embeddings, until the next snapshot.
                let mut replaced = BTreeMap::new();
                for (id, e) in keyframes {
                    if let Some(kf) = self.keyframes.get(id) {
                        let mut whole = Keyframe::clone(&*kf.load()?);
                        whole.embeddings = e.clone();
                        replaced.insert(*id, whole);
                    }
                }
                let mut embeddings = Vec::with_capacity(self.observations.len() * dim);
                for o in &self.observations {
                    match replaced.get(&o.keyframe) {
                        Some(kf) => embeddings.extend_from_slice(kf.embedding(o.keypoint as usize, *dim)),
                        None => embeddings.extend(std::iter::repeat_n(0.0, *dim)),
                    }
                }
                self.meta.model_id = model_id.clone();
                self.meta.k = *k;
                self.meta.dim = *dim;
                self.keyframes.extend(replaced.into_iter().map(|(id, k)| (id, MapKeyframe::inline(k))));
                self.embeddings = embeddings;
            }
        }
        self.version += 1;
        Ok(())
    }

    /// Live observations of a landmark (their keyframes still exist).
    pub fn live_observations_of(&self, landmark: u64) -> impl Iterator<Item = &Observation> {
        self.landmarks
            .get(&landmark)
            .into_iter()
            .flat_map(|l| l.observations.iter())
            .map(|&o| &self.observations[o as usize])
            .filter(|o| o.live)
    }
}
