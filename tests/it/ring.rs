//! The embedded model, the ring-context model (`models/scone-ring-e1-real-bits.onnx`, the graph of
//! `scone-ring-e1-real.onnx` that reads unpacked bits), served end to end
//! with no `[extractor]` and no matcher set: the service runs the extraction the model declares (8 levels,
//! 2,000 keypoints), Describe answers the context with the embeddings, a map built with it localises a held-out
//! frame of the rendered fixture, MatchPair's default is the model's `union` and finds the relative pose, and a
//! keypoint set sent back with its context embeds as the image did. The model made before it (the paper's
//! constellation, kept for maps built with it) is served at revision 2's extraction when it is configured.

use scone::offline::scene::Scene;
use scone::server::proto;

use crate::common::{fixture, temp_dir};
use crate::service::{add_keyframes, clients, image_frame, intrinsics, keyframe_requests, pose_error, serve, settings};

type Matching = proto::matching_client::MatchingClient<tonic::transport::Channel>;

/// Describe of the fixture's frame 3, as an image.
async fn describe_3(matching: &mut Matching, scene: &Scene) -> proto::DescribeResponse {
    let frame = Some(image_frame(&scene.frames[3].rgb, &scene.camera));
    matching.describe(proto::DescribeRequest { frame }).await.unwrap().into_inner()
}

/// MatchPair of the fixture's frames 3 and 5 with no matcher named (the model's).
async fn match_3_and_5(matching: &mut Matching, scene: &Scene) -> proto::MatchPairResponse {
    let request = proto::MatchPairRequest {
        frame1: Some(image_frame(&scene.frames[3].rgb, &scene.camera)),
        frame2: Some(image_frame(&scene.frames[5].rgb, &scene.camera)),
        ..Default::default()
    };
    matching.match_pair(request).await.unwrap().into_inner()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_ring_model_describes_maps_localises_and_matches() {
    let data = temp_dir("ring");
    let s = settings(&data);
    assert_eq!(s.model.model, scone::describe::embedding::default_model_path());
    assert_eq!(s.extractor, scone::settings::ExtractorOverrides::default());
    let server = serve(s).await;
    let (mut maps, mut matching) = clients(&server).await;
    let scene = Scene::load(&fixture("rendered")).unwrap();

    // Describe: the context comes with the embeddings, 113 bytes per keypoint.
    let d = describe_3(&mut matching, &scene).await;
    let n = d.keypoints.len();
    assert!(n > 100, "{n} keypoints");
    // Eight levels ran (the declared extraction; revision 2's has six), and the answer says so.
    assert_eq!(d.keypoints.iter().map(|k| k.octave).max(), Some(7));
    let e = d.extraction.as_ref().expect("the extraction");
    assert_eq!((e.levels, e.max_keypoints, e.fast_threshold, e.grid_cell), (8, 2000, 20, 32));
    assert_eq!(d.context.len(), 113 * n);
    assert_eq!(d.embeddings.len(), 48 * n);
    assert!(d.model_id.starts_with("sha256:8cace533"), "{}", d.model_id);

    // The same keypoints sent back as a keypoint set, with their context: the same embeddings.
    let set = proto::KeypointSet {
        keypoints: d.keypoints.clone(),
        descriptors: d.descriptors.clone(),
        context: d.context.clone(),
        width: scene.camera.width,
        height: scene.camera.height,
        ..Default::default()
    };
    let frame = proto::Frame {
        intrinsics: Some(intrinsics(&scene.camera)),
        source: Some(proto::frame::Source::Keypoints(set)),
    };
    let again = matching.describe(proto::DescribeRequest { frame: Some(frame) }).await.unwrap().into_inner();
    let worst = d.embeddings.iter().zip(&again.embeddings).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
    assert!(worst < 1e-5, "embeddings of the keypoint set differ by {worst}");

    // A map of every other frame; a held-out frame localises where the truth is.
    maps.create_map(proto::CreateMapRequest { map_id: "ring".into() }).await.unwrap();
    add_keyframes(&mut maps, keyframe_requests("ring", &scene, &[0, 2, 4, 6, 8, 9]), None).await;
    let r = matching
        .localize(proto::LocalizeRequest {
            map_id: "ring".into(),
            frame: Some(image_frame(&scene.frames[5].rgb, &scene.camera)),
            prior: None,
            pose_convention: 0,
        })
        .await
        .unwrap()
        .into_inner();
    assert!(r.localized, "{r:?}");
    let (dt, dr) = pose_error(r.pose.as_ref().unwrap(), &scene.frames[5].pose.unwrap());
    assert!(dt < 0.05 && dr < 1.0, "{dt} m, {dr} deg from the truth");

    // MatchPair with no matcher named: the model's.
    let pair = match_3_and_5(&mut matching, &scene).await;
    assert!(pair.pose.is_some() && pair.inliers > 50, "{} inliers", pair.inliers);
    assert_eq!(pair.matcher, proto::PairMatcher::Union as i32);
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_constellation_model_is_served_at_revision_2_with_scale_aware() {
    let data = temp_dir("constellation-model");
    let mut s = settings(&data);
    s.model.model = scone::describe::embedding::constellation_model_path();
    let server = serve(s).await;
    let (_, mut matching) = clients(&server).await;
    let scene = Scene::load(&fixture("rendered")).unwrap();
    let d = describe_3(&mut matching, &scene).await;
    assert_eq!(d.keypoints.iter().map(|k| k.octave).max(), Some(5), "six levels");
    assert_eq!(d.extraction.as_ref().map(|e| (e.levels, e.max_keypoints)), Some((6, 1500)));
    assert!(d.context.is_empty());
    let pair = match_3_and_5(&mut matching, &scene).await;
    assert_eq!(pair.matcher, proto::PairMatcher::ScaleAware as i32);
    server.shutdown().await.unwrap();
}
