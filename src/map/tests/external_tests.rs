//! External landmarks (map building from observations a client or an SfM import supplies, with their links)
//! and the format upgrade of maps that hold them.

use nalgebra::Isometry3;
use opencv::core::{Mat, Scalar, CV_16U};

use super::*;
use crate::describe::features::Features;
use crate::map::builder::{plan, BuildSettings, Depth, ExternalObservation, KeyframeInput};
use crate::map::storage::format::{encode_record_bincode1, FORMAT_VERSION};
use crate::map::storage::snapshot::{frame_snapshot, MapDataV1};

const DIM: usize = 8;

fn camera() -> Camera {
    Camera { fx: 500.0, fy: 500.0, cx: 320.0, cy: 240.0, width: 640, height: 480 }
}

fn features(points: &[(f32, f32)]) -> Features {
    Features {
        width: 640,
        height: 480,
        keypoints: points
            .iter()
            .map(|&(x, y)| Keypoint { x, y, size: 7.0, angle: 0.0, response: 1.0, octave: 0 })
            .collect(),
        descriptors: vec![[0u8; DESCRIPTOR_BYTES]; points.len()],
        context: Vec::new(),
    }
}

/// The world point seen at pixel (x, y) at depth z by a camera at the origin looking along +z.
fn seen(x: f64, y: f64, z: f64, id: u64) -> ExternalObservation {
    let c = camera();
    ExternalObservation { x, y, landmark_id: id, point: [(x - c.cx) / c.fx * z, (y - c.cy) / c.fy * z, z] }
}

fn input<'a>(id: u64, f: &'a Features, e: &'a [f32], ext: &'a [ExternalObservation]) -> KeyframeInput<'a> {
    KeyframeInput {
        id,
        pose: Isometry3::identity(),
        camera: camera(),
        features: f,
        embeddings: e,
        depth: None,
        external: Some(ext),
    }
}

fn field_of(e: crate::error::MapError) -> String {
    match e {
        crate::error::MapError::InvalidInput { field, reason } => format!("{field}: {reason}"),
        other => panic!("expected invalid input, got {other}"),
    }
}

#[test]
fn external_observations_are_validated_associated_and_merged_by_id() {
    let mut data = MapData::new(meta(DIM));
    let f = features(&[(100.0, 100.0), (200.0, 100.0), (300.0, 100.0), (302.5, 100.0)]);
    let e = vectors(4, DIM, 3);
    let mut off = seen(200.0, 100.0, 4.0, 2);
    off.x += 10.0; // its point reprojects 10 px away: rejected
    let mut behind = seen(100.0, 100.0, 4.0, 4);
    behind.point[2] = -4.0;
    let ext = vec![
        seen(100.3, 100.0, 5.0, 1), // -> keypoint 0
        off,
        seen(400.0, 400.0, 5.0, 3), // no keypoint near: unassociated
        behind,
        seen(300.5, 100.0, 5.0, 5), // -> keypoint 2, nearest
        seen(301.2, 100.0, 5.0, 6), // nearest is keypoint 2 too, but farther: unassociated, not moved to 3
        seen(100.3, 100.0, 5.0, 1), // a second view of id 1: rejected
    ];
    let p = plan(&data, &input(0, &f, &e, &ext), &BuildSettings::default()).unwrap();
    assert_eq!((p.external.given, p.external.associated, p.external.rejected, p.external.unassociated), (7, 2, 3, 2));
    let Record::AddExternalKeyframe { new_landmarks, observations, external_ids, .. } = &p.record else {
        panic!("{:?}", p.record)
    };
    assert_eq!(observations.iter().map(|o| o.keypoint).collect::<Vec<_>>(), vec![0, 2]);
    assert_eq!(new_landmarks.len(), 2);
    assert_eq!(external_ids.iter().map(|l| l.0).collect::<Vec<_>>(), vec![1, 5]);
    data.check(&p.record).unwrap();
    data.apply(&p.record).unwrap();

    // A second keyframe's view of id 1 observes the same landmark.
    let f2 = features(&[(100.0, 100.0), (250.0, 250.0)]);
    let e2 = vectors(2, DIM, 4);
    let ext2 =
        vec![ExternalObservation { point: ext[0].point, ..seen(100.0, 100.0, 5.0, 1) }, seen(250.0, 250.0, 3.0, 7)];
    let p2 = plan(&data, &input(1, &f2, &e2, &ext2), &BuildSettings::default()).unwrap();
    let Record::AddExternalKeyframe { new_landmarks, observations, .. } = &p2.record else { unreachable!() };
    assert_eq!(new_landmarks.len(), 1, "only id 7 is new");
    assert_eq!(observations[0].landmark, data.external_ids[&1]);
    data.check(&p2.record).unwrap();
    data.apply(&p2.record).unwrap();
    assert_eq!(data.landmarks[&data.external_ids[&1]].observations.len(), 2);
    assert_eq!(data.landmarks.len(), 3);
    // A record may not link an id twice.
    assert!(data.check(&p2.record).is_err());
}

#[test]
fn malformed_external_observations_refuse_the_request_naming_the_field() {
    let mut data = MapData::new(meta(DIM));
    let f = features(&[(100.0, 100.0)]);
    let e = vectors(1, DIM, 5);
    let params = BuildSettings::default();
    let mut nan = vec![seen(100.0, 100.0, 5.0, 1), seen(150.0, 100.0, 5.0, 2)];
    nan[1].point[1] = f64::NAN;
    let msg = field_of(plan(&data, &input(0, &f, &e, &nan), &params).unwrap_err());
    assert!(msg.starts_with("external_landmarks[1].point:") && msg.contains("not finite"), "{msg}");
    let mut px = vec![seen(100.0, 100.0, 5.0, 1)];
    px[0].x = f64::INFINITY;
    let msg = field_of(plan(&data, &input(0, &f, &e, &px), &params).unwrap_err());
    assert!(msg.starts_with("external_landmarks[0]:"), "{msg}");
    let mut dup = vec![seen(100.0, 100.0, 5.0, 1), seen(100.0, 100.0, 5.0, 1)];
    dup[1].point[0] += 0.01;
    let msg = field_of(plan(&data, &input(0, &f, &e, &dup), &params).unwrap_err());
    assert!(msg.starts_with("external_landmarks[1].point:") && msg.contains("external_landmarks[0]"), "{msg}");
    // Within the tolerance it is the same point.
    dup[1].point[0] -= 0.01 - 1e-6;
    assert!(plan(&data, &input(0, &f, &e, &dup), &params).is_ok());
    // Depth and external landmarks together.
    let depth = Mat::new_rows_cols_with_default(480, 640, CV_16U, Scalar::all(0.0)).unwrap();
    let mut both = input(0, &f, &e, &dup[..1]);
    both.depth = Some(Depth { image: &depth, scale: 1.0 / 5000.0 });
    let msg = field_of(plan(&data, &both, &params).unwrap_err());
    assert!(msg.starts_with("external_landmarks:") && msg.contains("not both"), "{msg}");
    // An id the map links already, given with another point.
    let ok = vec![seen(100.0, 100.0, 5.0, 1)];
    let p = plan(&data, &input(0, &f, &e, &ok), &params).unwrap();
    data.apply(&p.record).unwrap();
    let mut moved = vec![seen(100.0, 100.0, 5.0, 1)];
    moved[0].point[2] += 0.5;
    let msg = field_of(plan(&data, &input(1, &f, &e, &moved), &params).unwrap_err());
    assert!(msg.starts_with("external_landmarks[0].point:") && msg.contains("map 'm'"), "{msg}");
}

#[test]
fn a_format_1_map_loads_upgrades_its_files_and_takes_external_keyframes() {
    let dir = temp_dir("format1");
    // A format-1 snapshot and log, as the previous build wrote them.
    let v1 = MapDataV1 {
        meta: meta(DIM),
        keyframes: Default::default(),
        landmarks: Default::default(),
        observations: Vec::new(),
        embeddings: Vec::new(),
        next_landmark: 0,
        version: 0,
    };
    std::fs::write(dir.join("snapshot.bin"), frame_snapshot(1, &encode_bincode1(&v1))).unwrap();
    let mut log = b"SCONELOG".to_vec();
    log.extend_from_slice(&1u32.to_le_bytes());
    log.extend_from_slice(&encode_record_bincode1(1, &keyframe_record(0, 10, 0, DIM, 1)));
    std::fs::write(dir.join("log.bin"), &log).unwrap();

    let (mut data, mut log, report) = LocalJournal::open(&dir, 0).unwrap();
    assert_eq!(report.replayed, 1);
    assert_eq!(data.keyframes.len(), 1);
    assert!(data.external_ids.is_empty());
    for f in ["snapshot.bin", "log.bin"] {
        let bytes = std::fs::read(dir.join(f)).unwrap();
        assert_eq!(u32::from_le_bytes(bytes[8..12].try_into().unwrap()), FORMAT_VERSION, "{f} not upgraded");
    }
    // A keyframe with external landmarks goes into the upgraded log and replays.
    let f = features(&[(100.0, 100.0)]);
    let e = vectors(1, DIM, 9);
    let ext = [seen(100.0, 100.0, 5.0, 42)];
    let p = plan(&data, &input(7, &f, &e, &ext), &BuildSettings::default()).unwrap();
    super::write(&mut log, &mut data, p.record);
    drop(log);
    let (again, _, report) = LocalJournal::open(&dir, 0).unwrap();
    assert_eq!(report.replayed, 1);
    assert_eq!(again, data);
    assert_eq!(again.external_ids.len(), 1);
    // The format-1 snapshot bytes also import (the export format).
    let old = decode_snapshot(&frame_snapshot(1, &encode_bincode1(&v1)), &PathBuf::from("x")).unwrap();
    assert_eq!(old, MapData::new(meta(DIM)));
    // Snapshots round-trip with their links.
    assert_eq!(decode_snapshot(&encode_snapshot(&again).unwrap(), &PathBuf::from("x")).unwrap(), again);
}
