//! Issue 28, sections 2-4: lens distortion, an unknown focal length, and the pose's covariance, as clients send
//! them, on the rendered fixture and (when the shared data is there) a real scene.
//!
//! Distortion is tested against exact data: the lens models are written here from their definitions (not with
//! the server's OpenCV calls), a query's keypoints are moved through them, and a query image is warped
//! through them pixel by pixel. Localize on the distorted query with its model must agree with Localize on the
//! original; without the model it must not (so the test fails without the feature).

use nalgebra::{Isometry3, UnitQuaternion, Vector3};
use opencv::core::{Mat, Scalar, Vector, CV_32F};
use opencv::prelude::*;
use scone::camera::Camera;
use scone::offline::scene::Scene;
use scone::server::proto::{self, frame::Source};
use tonic::Code;

use crate::common::{fixture, shared_data, temp_dir};
use crate::service::{add_keyframes, clients, image_frame, intrinsics, keyframe_requests, serve, settings};

#[derive(Clone, Copy, Debug)]
enum Lens {
    /// k1, k2, p1, p2, k3.
    RadTan([f64; 5]),
    /// k1..k4.
    Fisheye([f64; 4]),
}

impl Lens {
    /// Normalised pinhole coordinates through the lens (OpenCV's model definitions).
    fn distort(self, x: f64, y: f64) -> (f64, f64) {
        match self {
            Lens::RadTan([k1, k2, p1, p2, k3]) => {
                let r2 = x * x + y * y;
                let radial = 1.0 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2;
                (
                    x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
                    y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y,
                )
            }
            Lens::Fisheye([k1, k2, k3, k4]) => {
                let r = (x * x + y * y).sqrt();
                if r < 1e-12 {
                    return (x, y);
                }
                let t = r.atan();
                let t2 = t * t;
                let td = t * (1.0 + k1 * t2 + k2 * t2 * t2 + k3 * t2.powi(3) + k4 * t2.powi(4));
                (x * td / r, y * td / r)
            }
        }
    }

    /// The inverse of [`Lens::distort`], by fixed-point iteration (converges for these mild lenses).
    fn undistort(self, xd: f64, yd: f64) -> (f64, f64) {
        let (mut x, mut y) = (xd, yd);
        for _ in 0..200 {
            let (dx, dy) = self.distort(x, y);
            x += xd - dx;
            y += yd - dy;
        }
        (x, y)
    }

    fn wire(self) -> (i32, Vec<f64>) {
        match self {
            Lens::RadTan(c) => (proto::DistortionModel::RadialTangential as i32, c.to_vec()),
            Lens::Fisheye(c) => (proto::DistortionModel::Fisheye as i32, c.to_vec()),
        }
    }

    fn pixel(self, cam: &Camera, u: f64, v: f64) -> (f64, f64) {
        let (x, y) = self.distort((u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy);
        (x * cam.fx + cam.cx, y * cam.fy + cam.cy)
    }

    /// `image` as this lens would have seen it: each pixel of the result samples the original where its
    /// undistorted ray lands (bilinear).
    fn warp(self, cam: &Camera, image: &Mat) -> Mat {
        let (w, h) = (image.cols(), image.rows());
        let mut map_x = Mat::new_rows_cols_with_default(h, w, CV_32F, Scalar::all(0.0)).unwrap();
        let mut map_y = map_x.clone();
        for v in 0..h {
            for u in 0..w {
                let (x, y) = self.undistort((f64::from(u) - cam.cx) / cam.fx, (f64::from(v) - cam.cy) / cam.fy);
                *map_x.at_2d_mut::<f32>(v, u).unwrap() = (x * cam.fx + cam.cx) as f32;
                *map_y.at_2d_mut::<f32>(v, u).unwrap() = (y * cam.fy + cam.cy) as f32;
            }
        }
        let mut out = Mat::default();
        opencv::imgproc::remap(
            image,
            &mut out,
            &map_x,
            &map_y,
            opencv::imgproc::INTER_LINEAR,
            opencv::core::BORDER_CONSTANT,
            Scalar::all(0.0),
        )
        .unwrap();
        out
    }
}

/// Lenses strong enough that ignoring them moves corner pixels by tens of pixels.
const LENSES: [Lens; 2] =
    [Lens::RadTan([-0.28, 0.08, 0.0012, -0.0008, -0.01]), Lens::Fisheye([0.12, -0.04, 0.02, -0.005])];

fn pose_of(p: &proto::Pose) -> Isometry3<f64> {
    Isometry3::from_parts(
        nalgebra::Translation3::new(p.tx, p.ty, p.tz),
        UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(p.qw, p.qx, p.qy, p.qz)),
    )
}

/// Translation (scene units) and rotation (degrees) between two poses.
fn apart(a: &Isometry3<f64>, b: &Isometry3<f64>) -> (f64, f64) {
    ((a.translation.vector - b.translation.vector).norm(), a.rotation.angle_to(&b.rotation).to_degrees())
}

fn png(image: &Mat) -> Vec<u8> {
    let mut buf = Vector::<u8>::new();
    opencv::imgcodecs::imencode(".png", image, &mut buf, &Vector::new()).unwrap();
    buf.to_vec()
}

/// A scene, the frames its map is made of, the queries, and how far (units, degrees) a query may land from
/// the original's answer when its lens is declared.
struct Case {
    scene: Scene,
    map: Vec<usize>,
    queries: Vec<usize>,
}

fn cases() -> Vec<Case> {
    let mut out =
        vec![Case { scene: Scene::load(&fixture("rendered")).unwrap(), map: vec![0, 2, 4, 6, 8], queries: vec![3, 5] }];
    if let Some(data) = shared_data() {
        out.push(Case {
            scene: Scene::load(&data.join("scenes/tum-fr3-long-office")).unwrap(),
            map: (0..30).step_by(3).collect(),
            queries: vec![7, 13],
        });
    }
    out
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn localize_with_a_declared_lens_equals_localize_on_the_undistorted_frame() {
    let dir = temp_dir("lenses");
    let server = serve(settings(&dir)).await;
    let (mut maps, mut matching) = clients(&server).await;
    for (n, case) in cases().iter().enumerate() {
        let (scene, cam) = (&case.scene, case.scene.camera);
        let map = format!("m{n}");
        maps.create_map(proto::CreateMapRequest { map_id: map.clone() }).await.unwrap();
        add_keyframes(&mut maps, keyframe_requests(&map, scene, &case.map), None).await;
        let localize = |frame: proto::Frame| proto::LocalizeRequest {
            map_id: map.clone(),
            frame: Some(frame),
            ..Default::default()
        };
        for &q in &case.queries {
            let truth = scene.frames[q].pose.unwrap();
            let original =
                matching.localize(localize(image_frame(&scene.frames[q].rgb, &cam))).await.unwrap().into_inner();
            assert!(original.localized, "{}: query {q} localises undistorted", scene.name);
            let reference = pose_of(original.pose.as_ref().unwrap());
            let (dt, dr) = apart(&reference, &truth);
            eprintln!("{} q{q}: undistorted image {dt:.4} / {dr:.3}°", scene.name);

            // The service's own keypoints of the query, moved exactly through each lens.
            let described = matching
                .describe(proto::DescribeRequest { frame: Some(image_frame(&scene.frames[q].rgb, &cam)) })
                .await
                .unwrap()
                .into_inner();
            let keypoint_frame = |lens: Option<Lens>| {
                let keypoints = described
                    .keypoints
                    .iter()
                    .map(|k| {
                        let (x, y) = lens.map_or((k.x.into(), k.y.into()), |l| l.pixel(&cam, k.x.into(), k.y.into()));
                        proto::Keypoint { x: x as f32, y: y as f32, ..*k }
                    })
                    .collect();
                let mut i = intrinsics(&cam);
                if let Some(l) = lens {
                    (i.distortion_model, i.distortion) = l.wire();
                }
                proto::Frame {
                    source: Some(Source::Keypoints(proto::KeypointSet {
                        keypoints,
                        descriptors: described.descriptors.clone(),
                        width: cam.width,
                        height: cam.height,
                        model_id: String::new(),
                        context: described.context.clone(),
                    })),
                    intrinsics: Some(i),
                }
            };
            let plain = matching.localize(localize(keypoint_frame(None))).await.unwrap().into_inner();
            let plain_pose = pose_of(plain.pose.as_ref().expect("the keypoints localise as the image does"));
            let image =
                opencv::imgcodecs::imread(scene.frames[q].rgb.to_str().unwrap(), opencv::imgcodecs::IMREAD_UNCHANGED)
                    .unwrap();
            for lens in LENSES {
                // Exact keypoints: the same pose, up to the undistortion's precision.
                let declared = matching.localize(localize(keypoint_frame(Some(lens)))).await.unwrap().into_inner();
                let pose = pose_of(declared.pose.as_ref().expect("distorted keypoints with their model localise"));
                let (dt, dr) = apart(&pose, &plain_pose);
                let extent = truth.translation.vector.norm().max(1.0);
                assert!(
                    dt < 1e-3 * extent && dr < 0.02,
                    "{} q{q} {lens:?}: {dt} / {dr}° from the pinhole keypoints",
                    scene.name
                );
                assert!(declared.inliers.abs_diff(plain.inliers) <= plain.inliers / 50 + 1, "{lens:?}: inliers");

                // The same keypoints without their model: the pose moves (or is lost) by an order of magnitude
                // more than the declared model's tolerance. (The mild fisheye moved TUM's q7 by 0.063 units at an
                // extent of ~3.2 with one index point per landmark: 20 times the tolerance, as this once asked,
                // is on the edge of what that lens costs there.)
                let mut undeclared = keypoint_frame(Some(lens));
                if let Some(i) = undeclared.intrinsics.as_mut() {
                    (i.distortion_model, i.distortion) = (0, Vec::new());
                }
                let wrong = matching.localize(localize(undeclared)).await.unwrap().into_inner();
                if let Some(p) = wrong.pose.as_ref() {
                    let (dt, dr) = apart(&pose_of(p), &plain_pose);
                    assert!(
                        dt > 10.0 * 1e-3 * extent || dr > 0.2,
                        "{lens:?}: ignoring the lens should cost ({dt}, {dr}°)"
                    );
                }

                // A warped image, detected anew: as close to the truth as the original image is.
                let mut frame = image_frame(&scene.frames[q].rgb, &cam);
                frame.source = Some(Source::Image(proto::Image { data: png(&lens.warp(&cam, &image)) }));
                if let Some(i) = frame.intrinsics.as_mut() {
                    (i.distortion_model, i.distortion) = lens.wire();
                }
                let warped = matching.localize(localize(frame)).await.unwrap().into_inner();
                assert!(warped.localized, "{} q{q} {lens:?}: the warped image localises with its model", scene.name);
                let (wt, wr) = apart(&pose_of(warped.pose.as_ref().unwrap()), &truth);
                eprintln!("{} q{q} {lens:?}: warped image {wt:.4} / {wr:.3}°", scene.name);
                assert!(wt <= 2.0 * dt + 0.02 * extent && wr <= 2.0 * dr + 0.5, "{lens:?}: warped {wt} / {wr}°");
            }
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn lens_and_focal_length_errors_are_clear() {
    let dir = temp_dir("lens-errors");
    let server = serve(settings(&dir)).await;
    let (mut maps, mut matching) = clients(&server).await;
    let scene = Scene::load(&fixture("rendered")).unwrap();
    maps.create_map(proto::CreateMapRequest { map_id: "m".into() }).await.unwrap();
    let cam = scene.camera;
    let with = |f: &dyn Fn(&mut proto::Intrinsics)| {
        let mut frame = image_frame(&scene.frames[0].rgb, &cam);
        f(frame.intrinsics.as_mut().unwrap());
        frame
    };
    let cases: Vec<(proto::Frame, &str)> = vec![
        (with(&|i| (i.distortion_model, i.distortion) = (1, vec![0.1, 0.0, 0.0])), "4, 5 or 8 coefficients"),
        (with(&|i| (i.distortion_model, i.distortion) = (2, vec![0.1; 5])), "4 coefficients"),
        (with(&|i| (i.distortion_model, i.distortion) = (0, vec![0.1; 4])), "without a distortion model"),
        (with(&|i| (i.distortion_model, i.distortion) = (1, vec![f64::NAN, 0.0, 0.0, 0.0])), "finite"),
        (with(&|i| i.distortion_model = 7), "not a DistortionModel"),
        (
            with(&|i| {
                (i.fx, i.fy, i.distortion_model, i.distortion) = (0.0, 0.0, 1, vec![0.1, 0.0, 0.0, 0.0]);
            }),
            "needs fx and fy",
        ),
    ];
    for (frame, expected) in cases {
        let r = matching
            .localize(proto::LocalizeRequest { map_id: "m".into(), frame: Some(frame), ..Default::default() })
            .await
            .unwrap_err();
        assert_eq!(r.code(), Code::InvalidArgument, "{}", r.message());
        assert!(r.message().contains(expected), "{} lacks {expected}", r.message());
    }
    // Only Localize estimates a focal length.
    let no_focal = with(&|i| (i.fx, i.fy) = (0.0, 0.0));
    let r = matching
        .match_pair(proto::MatchPairRequest {
            frame1: Some(no_focal.clone()),
            frame2: Some(no_focal),
            ..Default::default()
        })
        .await
        .unwrap_err();
    assert_eq!(r.code(), Code::InvalidArgument);
    assert!(r.message().contains("only Localize estimates"), "{}", r.message());
    // Depth with a lens model: refused, nothing stored.
    let mut req = keyframe_requests("m", &scene, &[0]).remove(0);
    if let Some(i) = req.frame.as_mut().and_then(|f| f.intrinsics.as_mut()) {
        (i.distortion_model, i.distortion) = (1, vec![0.1, 0.0, 0.0, 0.0]);
    }
    let mut acks = maps.add_keyframes(tokio_stream::iter(vec![req])).await.unwrap().into_inner();
    let e = acks.message().await.unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument);
    assert!(e.message().contains("depth with a distortion model"), "{}", e.message());
    let info = maps.get_map(proto::GetMapRequest { map_id: "m".into() }).await.unwrap().into_inner();
    assert_eq!(info.keyframes, 0);
}

/// Localize without a focal length: it is estimated with the pose, close to the truth, on gRPC (intrinsics
/// without fx, fy) and HTTP (a raw image with no intrinsics at all).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_unknown_focal_length_is_estimated_with_the_pose() {
    let dir = temp_dir("focal");
    let server = serve(settings(&dir)).await;
    let (mut maps, mut matching) = clients(&server).await;
    let http = reqwest::Client::new();
    for (n, case) in cases().iter().enumerate() {
        let (scene, cam) = (&case.scene, case.scene.camera);
        let map = format!("m{n}");
        maps.create_map(proto::CreateMapRequest { map_id: map.clone() }).await.unwrap();
        add_keyframes(&mut maps, keyframe_requests(&map, scene, &case.map), None).await;
        let truth_f = (cam.fx + cam.fy) / 2.0;
        for &q in &case.queries {
            let truth = scene.frames[q].pose.unwrap();
            let mut frame = image_frame(&scene.frames[q].rgb, &cam);
            if let Some(i) = frame.intrinsics.as_mut() {
                (i.fx, i.fy) = (0.0, 0.0);
            }
            let r = matching
                .localize(proto::LocalizeRequest { map_id: map.clone(), frame: Some(frame), ..Default::default() })
                .await
                .unwrap()
                .into_inner();
            assert!(r.localized && r.focal_estimated, "{} q{q}", scene.name);
            let (dt, dr) = apart(&pose_of(r.pose.as_ref().unwrap()), &truth);
            let ferr = (r.focal_length - truth_f).abs() / truth_f;
            eprintln!("{} q{q}: focal {:.1} (true {truth_f:.1}), pose {dt:.4} / {dr:.3}°", scene.name, r.focal_length);
            assert!(ferr < 0.05, "{} q{q}: focal {} against {truth_f}", scene.name, r.focal_length);
            let extent = truth.translation.vector.norm().max(1.0);
            assert!(dt < 0.05 * extent && dr < 2.0, "{} q{q}: {dt} / {dr}°", scene.name);

            // HTTP, a raw image body and no intrinsics at all.
            let url = format!("http://{}/v1/maps/{map}/localize", server.http_addr);
            let body = std::fs::read(&scene.frames[q].rgb).unwrap();
            let j: serde_json::Value = http
                .post(&url)
                .header("content-type", "image/png")
                .body(body)
                .send()
                .await
                .unwrap()
                .json()
                .await
                .unwrap();
            assert_eq!(j["localized"], true, "{j}");
            assert_eq!(j["focal_estimated"], true);
            let f = j["focal_length"].as_f64().unwrap();
            assert!((f - truth_f).abs() / truth_f < 0.05, "HTTP focal {f}");
        }
    }
}

/// The covariance a response carries is a covariance (symmetric, positive definite), expressed in the
/// request's convention: the same uncertainty, seen through each convention's parameters.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_pose_covariance_is_in_the_requests_convention() {
    let dir = temp_dir("covariance");
    let server = serve(settings(&dir)).await;
    let (mut maps, mut matching) = clients(&server).await;
    let scene = Scene::load(&fixture("rendered")).unwrap();
    maps.create_map(proto::CreateMapRequest { map_id: "m".into() }).await.unwrap();
    add_keyframes(&mut maps, keyframe_requests("m", &scene, &[0, 2, 4, 6, 8]), None).await;
    let mut answers = Vec::new();
    for convention in 0..3 {
        let r = matching
            .localize(proto::LocalizeRequest {
                map_id: "m".into(),
                frame: Some(image_frame(&scene.frames[5].rgb, &scene.camera)),
                pose_convention: convention,
                ..Default::default()
            })
            .await
            .unwrap()
            .into_inner();
        assert!(r.localized);
        assert_eq!(r.covariance.len(), 36);
        let c = nalgebra::Matrix6::from_row_slice(&r.covariance);
        assert!((c - c.transpose()).abs().max() <= 1e-9 * c.abs().max(), "symmetric");
        assert!(c.cholesky().is_some(), "positive definite");
        answers.push((pose_of(r.pose.as_ref().unwrap()), c));
    }
    let (c2w, cov_c2w) = &answers[0];
    // Camera-to-world against OpenGL camera-to-world: the same centre and world-frame rotation perturbation
    // (the camera axes flip on the right, which a left perturbation does not see): the same covariance.
    assert!((answers[2].1 - cov_c2w).abs().max() <= 1e-6 * cov_c2w.abs().max());
    // World-to-camera: the position is -Rᵀ t, the rotation Rᵀ: its rotation block is the same rotation's
    // uncertainty seen from the camera, so the traces of the rotation blocks agree, and the centre recovered
    // from the world-to-camera pose has the camera-to-world translation's variance (sampled, first order).
    let (w2c, cov_w2c) = &answers[1];
    assert!((w2c.inverse().translation.vector - c2w.translation.vector).norm() < 1e-9);
    let rot_trace = |c: &nalgebra::Matrix6<f64>| c.fixed_view::<3, 3>(3, 3).trace();
    assert!((rot_trace(cov_w2c) - rot_trace(cov_c2w)).abs() <= 1e-6 * rot_trace(cov_c2w));
    let l = cov_w2c.cholesky().unwrap().l();
    let mut sampled = nalgebra::Matrix3::<f64>::zeros();
    let mut rng = 0x2545_f491_4f6c_dd1du64;
    let mut gauss = || {
        // Box-Muller on a xorshift stream: enough for a second-moment check.
        let mut u = || {
            rng ^= rng << 13;
            rng ^= rng >> 7;
            rng ^= rng << 17;
            (rng >> 11) as f64 / (1u64 << 53) as f64
        };
        let (a, b) = (u().max(1e-300), u());
        (-2.0 * a.ln()).sqrt() * (std::f64::consts::TAU * b).cos()
    };
    let n = 4000;
    for _ in 0..n {
        let z = nalgebra::Vector6::from_fn(|_, _| gauss());
        let e = l * z;
        let perturbed = Isometry3::from_parts(
            nalgebra::Translation3::from(w2c.translation.vector + Vector3::new(e[0], e[1], e[2])),
            UnitQuaternion::from_scaled_axis(Vector3::new(e[3], e[4], e[5])) * w2c.rotation,
        );
        let d = perturbed.inverse().translation.vector - c2w.translation.vector;
        sampled += d * d.transpose() / n as f64;
    }
    let analytic = cov_c2w.fixed_view::<3, 3>(0, 0).into_owned();
    assert!(
        (sampled.trace() - analytic.trace()).abs() <= 0.1 * analytic.trace(),
        "sampled {} against {}",
        sampled.trace(),
        analytic.trace()
    );
}
