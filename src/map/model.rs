//! The map's data: keyframes (pose, intrinsics, keypoints with FREAK descriptors, so a map can be re-embedded),
//! landmarks (3D points) and their observations (keyframe, keypoint, SConE embedding).
//!
//! Every change is a [`Record`]; [`MapData::apply`] is the only way state changes, both when a write is made
//! and when the log is replayed at start, so a replayed map equals the map that acknowledged the writes.

use std::collections::BTreeMap;

use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};
use serde::{Deserialize, Serialize};

use crate::features::{Keypoint, DESCRIPTOR_BYTES};
use crate::scene::Camera;

/// A camera-to-world pose as translation + unit quaternion (x, y, z, w).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Pose {
    pub translation: [f64; 3],
    pub rotation: [f64; 4],
}

impl Pose {
    pub fn from_isometry(p: &Isometry3<f64>) -> Self {
        let q = p.rotation.quaternion();
        Self { translation: p.translation.vector.into(), rotation: [q.i, q.j, q.k, q.w] }
    }

    pub fn isometry(&self) -> Isometry3<f64> {
        let [x, y, z, w] = self.rotation;
        Isometry3::from_parts(
            Translation3::new(self.translation[0], self.translation[1], self.translation[2]),
            UnitQuaternion::from_quaternion(Quaternion::new(w, x, y, z)),
        )
    }

    /// Finite values and a quaternion of unit length (within 1e-3).
    pub fn validate(&self) -> Result<(), String> {
        if !self.translation.iter().chain(self.rotation.iter()).all(|v| v.is_finite()) {
            return Err("pose has a non-finite value".into());
        }
        let n = self.rotation.iter().map(|v| v * v).sum::<f64>().sqrt();
        if (n - 1.0).abs() > 1e-3 {
            return Err(format!("pose quaternion has norm {n:.6}, expected 1"));
        }
        Ok(())
    }
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

/// A posed image of the map with all its keypoints.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Keyframe {
    pub id: u64,
    pub pose: Pose,
    pub camera: Camera,
    pub keypoints: Vec<Keypoint>,
    /// FREAK descriptors, `keypoints.len() x 64` bytes.
    pub descriptors: Vec<u8>,
}

impl Keyframe {
    pub fn descriptor(&self, i: usize) -> &[u8] {
        &self.descriptors[i * DESCRIPTOR_BYTES..(i + 1) * DESCRIPTOR_BYTES]
    }
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

/// A new observation carried by a record.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct NewObservation {
    pub landmark: u64,
    pub keypoint: u32,
    pub embedding: Vec<f32>,
}

/// A change to a map: the unit of the write-ahead log.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum Record {
    /// A keyframe with the landmarks it creates and the observations it adds (to new or existing landmarks).
    AddKeyframe { keyframe: Keyframe, new_landmarks: Vec<(u64, [f64; 3])>, observations: Vec<NewObservation> },
    /// Removes a keyframe; its observations become tombstones.
    RemoveKeyframe { id: u64 },
    /// Replaces every observation's embedding (same order) after a model change.
    Reembed { model_id: String, k: usize, dim: usize, embeddings: Vec<f32> },
}

/// The whole state of one map.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MapData {
    pub meta: MapMeta,
    pub keyframes: BTreeMap<u64, Keyframe>,
    pub landmarks: BTreeMap<u64, Landmark>,
    pub observations: Vec<Observation>,
    /// Row-major `[observations, dim]`.
    pub embeddings: Vec<f32>,
    pub next_landmark: u64,
    /// Records applied since creation: the map's version.
    pub version: u64,
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
        }
    }

    pub fn embedding(&self, observation: usize) -> &[f32] {
        let d = self.meta.dim;
        &self.embeddings[observation * d..(observation + 1) * d]
    }

    pub fn live_observations(&self) -> usize {
        self.observations.iter().filter(|o| o.live).count()
    }

    /// Checks that a record can be applied (ids, sizes); `apply` assumes it was.
    pub fn check(&self, record: &Record) -> Result<(), String> {
        match record {
            Record::AddKeyframe { keyframe, new_landmarks, observations } => {
                if self.keyframes.contains_key(&keyframe.id) {
                    return Err(format!("keyframe {} exists", keyframe.id));
                }
                if keyframe.descriptors.len() != keyframe.keypoints.len() * DESCRIPTOR_BYTES {
                    return Err("descriptor bytes do not match the keypoint count".into());
                }
                keyframe.pose.validate()?;
                for (id, p) in new_landmarks {
                    if self.landmarks.contains_key(id) || !p.iter().all(|v| v.is_finite()) {
                        return Err(format!("new landmark {id} exists or is not finite"));
                    }
                }
                for o in observations {
                    let known =
                        self.landmarks.contains_key(&o.landmark) || new_landmarks.iter().any(|l| l.0 == o.landmark);
                    if !known || o.keypoint as usize >= keyframe.keypoints.len() || o.embedding.len() != self.meta.dim {
                        return Err(format!("observation of landmark {} is inconsistent", o.landmark));
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
            Record::Reembed { dim, embeddings, .. } => {
                if embeddings.len() != self.observations.len() * dim {
                    return Err("re-embedding size does not match the observations".into());
                }
                Ok(())
            }
        }
    }

    /// Applies a record (already checked).
    pub fn apply(&mut self, record: &Record) {
        match record {
            Record::AddKeyframe { keyframe, new_landmarks, observations } => {
                for (id, p) in new_landmarks {
                    self.landmarks.insert(*id, Landmark { point: *p, observations: Vec::new() });
                    self.next_landmark = self.next_landmark.max(id + 1);
                }
                for o in observations {
                    let oid = self.observations.len() as u64;
                    self.observations.push(Observation {
                        landmark: o.landmark,
                        keyframe: keyframe.id,
                        keypoint: o.keypoint,
                        live: true,
                    });
                    self.embeddings.extend_from_slice(&o.embedding);
                    if let Some(l) = self.landmarks.get_mut(&o.landmark) {
                        l.observations.push(oid);
                    }
                }
                self.keyframes.insert(keyframe.id, keyframe.clone());
            }
            Record::RemoveKeyframe { id } => {
                self.keyframes.remove(id);
                for o in self.observations.iter_mut().filter(|o| o.keyframe == *id) {
                    o.live = false;
                }
            }
            Record::Reembed { model_id, k, dim, embeddings } => {
                self.meta.model_id = model_id.clone();
                self.meta.k = *k;
                self.meta.dim = *dim;
                self.embeddings = embeddings.clone();
            }
        }
        self.version += 1;
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
