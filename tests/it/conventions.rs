//! Issue 28, section 1: pose conventions declared, not converted by hand. The fixture's real poses are written
//! in each convention (converted here from their definitions, not with the server's code); the maps are the
//! same, and one query answered in each convention is the same pose once converted back.

use nalgebra::{Isometry3, Matrix3, Rotation3, UnitQuaternion};
use scone::offline::scene::Scene;
use scone::server::proto;
use tonic::Code;

use crate::common::{fixture, temp_dir};
use crate::service::{clients, image_frame, serve, settings};

/// OpenGL camera axes in OpenCV's: y and z flipped.
fn flip() -> Rotation3<f64> {
    Rotation3::from_matrix_unchecked(Matrix3::new(1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, -1.0))
}

/// An OpenCV camera-to-world pose written in `convention`, from the conventions' definitions.
fn express(c2w: &Isometry3<f64>, convention: &str) -> Isometry3<f64> {
    match convention {
        "opencv_camera_to_world" => *c2w,
        "opencv_world_to_camera" => c2w.inverse(),
        "opengl_camera_to_world" => Isometry3::from_parts(
            c2w.translation,
            UnitQuaternion::from_rotation_matrix(&(c2w.rotation.to_rotation_matrix() * flip())),
        ),
        other => panic!("{other}"),
    }
}

fn pose_json(p: &Isometry3<f64>) -> serde_json::Value {
    let (q, t) = (p.rotation.quaternion(), p.translation.vector);
    serde_json::json!({"tx": t.x, "ty": t.y, "tz": t.z, "qx": q.i, "qy": q.j, "qz": q.k, "qw": q.w})
}

fn pose_of(v: &serde_json::Value) -> Isometry3<f64> {
    let f = |k: &str| v[k].as_f64().unwrap();
    Isometry3::from_parts(
        nalgebra::Translation3::new(f("tx"), f("ty"), f("tz")),
        UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(f("qw"), f("qx"), f("qy"), f("qz"))),
    )
}

/// Translation and rotation (degrees) between two poses.
fn apart(a: &Isometry3<f64>, b: &Isometry3<f64>) -> (f64, f64) {
    ((a.translation.vector - b.translation.vector).norm(), a.rotation.angle_to(&b.rotation).to_degrees())
}

const CONVENTIONS: [&str; 3] = ["opencv_camera_to_world", "opencv_world_to_camera", "opengl_camera_to_world"];

fn keyframe(scene: &Scene, i: usize, convention: &str) -> reqwest::multipart::Form {
    let f = &scene.frames[i];
    let c = scene.camera;
    let request = serde_json::json!({
        "keyframe_id": i,
        "pose": pose_json(&express(&f.pose.unwrap(), convention)),
        "pose_convention": convention,
        "intrinsics": {"fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy},
    });
    let depth = std::fs::read(f.depth.as_ref().unwrap()).unwrap();
    reqwest::multipart::Form::new()
        .text("request", request.to_string())
        .part("image", reqwest::multipart::Part::bytes(std::fs::read(&f.rgb).unwrap()).mime_str("image/png").unwrap())
        .part("depth", reqwest::multipart::Part::bytes(depth).mime_str("image/png").unwrap())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn poses_written_and_answered_in_each_convention_agree_once_converted() {
    let scene = Scene::load(&fixture("rendered")).unwrap();
    let dir = temp_dir("conventions");
    let server = serve(settings(&dir)).await;
    let http = reqwest::Client::new();
    let base = format!("http://{}", server.http_addr);
    let c = scene.camera;
    let (map_frames, query) = ([0, 2, 4, 7, 9], 6);

    // The same keyframes, one map per convention (HTTP).
    for (n, convention) in CONVENTIONS.iter().enumerate() {
        let map = format!("m{n}");
        let r = http.post(format!("{base}/v1/maps")).json(&serde_json::json!({"map_id": map})).send().await.unwrap();
        assert_eq!(r.status(), 201);
        for i in map_frames {
            let r =
                http.post(format!("{base}/v1/maps/{map}/keyframes")).multipart(keyframe(&scene, i, convention)).send();
            let r = r.await.unwrap();
            assert_eq!(r.status(), 200, "{convention}: {}", r.text().await.unwrap());
        }
    }
    // The same maps: stored poses (asked for in OpenCV camera-to-world) and landmark counts agree.
    let contents = |map: String| {
        let (http, base) = (http.clone(), base.clone());
        async move {
            let r = http.get(format!("{base}/v1/maps/{map}/contents")).send().await.unwrap();
            r.json::<serde_json::Value>().await.unwrap()
        }
    };
    let reference = contents("m0".into()).await;
    for (n, convention) in CONVENTIONS.iter().enumerate().skip(1) {
        let other = contents(format!("m{n}")).await;
        assert_eq!(other["landmarks_total"], reference["landmarks_total"], "{convention}");
        for (a, b) in reference["keyframes"].as_array().unwrap().iter().zip(other["keyframes"].as_array().unwrap()) {
            let (dt, dr) = apart(&pose_of(&a["pose"]), &pose_of(&b["pose"]));
            assert!(dt < 1e-9 && dr < 1e-7, "{convention}: keyframe pose differs by {dt} m, {dr} deg");
        }
    }
    // The contents in another convention are the stored poses converted.
    let gl =
        http.get(format!("{base}/v1/maps/m0/contents?pose_convention=opengl_camera_to_world")).send().await.unwrap();
    let gl: serde_json::Value = gl.json().await.unwrap();
    let stored = pose_of(&reference["keyframes"][0]["pose"]);
    let (dt, dr) = apart(&pose_of(&gl["keyframes"][0]["pose"]), &express(&stored, "opengl_camera_to_world"));
    assert!(dt < 1e-9 && dr < 1e-7);

    // One query, answered in each convention (HTTP: query string and JSON body; gRPC): the same pose.
    let truth = scene.frames[query].pose.unwrap();
    let (_, mut matching) = clients(&server).await;
    for (n, convention) in CONVENTIONS.iter().enumerate() {
        let r = http
            .post(format!(
                "{base}/v1/maps/m{n}/localize?fx={}&fy={}&cx={}&cy={}&pose_convention={convention}",
                c.fx, c.fy, c.cx, c.cy
            ))
            .header("content-type", "image/png")
            .body(std::fs::read(&scene.frames[query].rgb).unwrap())
            .send()
            .await
            .unwrap();
        let got: serde_json::Value = r.json().await.unwrap();
        assert_eq!(got["localized"], true, "{convention}: {got}");
        let answered = pose_of(&got["pose"]);
        let expected = express(&truth, convention);
        let (dt, dr) = apart(&answered, &expected);
        assert!(dt < 0.05 && dr < 1.0, "{convention}: {dt} m, {dr} deg from the truth in that convention");
        // gRPC, on the first map, in this convention: the HTTP answer of the first map converted.
        let reply = matching
            .localize(proto::LocalizeRequest {
                map_id: "m0".into(),
                frame: Some(image_frame(&scene.frames[query].rgb, &c)),
                prior: None,
                pose_convention: n as i32,
            })
            .await
            .unwrap()
            .into_inner();
        let p = reply.pose.unwrap();
        let grpc = pose_of(
            &serde_json::json!({"tx": p.tx, "ty": p.ty, "tz": p.tz, "qx": p.qx, "qy": p.qy, "qz": p.qz, "qw": p.qw}),
        );
        let first = http
            .post(format!("{base}/v1/maps/m0/localize?fx={}&fy={}&cx={}&cy={}", c.fx, c.fy, c.cx, c.cy))
            .header("content-type", "image/png")
            .body(std::fs::read(&scene.frames[query].rgb).unwrap())
            .send()
            .await
            .unwrap()
            .json::<serde_json::Value>()
            .await
            .unwrap();
        let (dt, dr) = apart(&grpc, &express(&pose_of(&first["pose"]), convention));
        assert!(dt < 1e-9 && dr < 1e-7, "{convention}: gRPC {dt} m, {dr} deg from the converted answer");
    }
    // A query string and a body that disagree are refused; an unknown convention too (both transports).
    let r = http
        .post(format!("{base}/v1/maps/m0/localize?pose_convention=opengl_camera_to_world"))
        .multipart(
            reqwest::multipart::Form::new()
                .text(
                    "request",
                    serde_json::json!({"intrinsics": {"fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy},
                        "pose_convention": "opencv_world_to_camera"})
                    .to_string(),
                )
                .part(
                    "image",
                    reqwest::multipart::Part::bytes(std::fs::read(&scene.frames[1].rgb).unwrap())
                        .mime_str("image/png")
                        .unwrap(),
                ),
        )
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 400);
    assert!(r.text().await.unwrap().contains("pose_convention"));
    let st = matching
        .localize(proto::LocalizeRequest {
            map_id: "m0".into(),
            frame: Some(image_frame(&scene.frames[1].rgb, &c)),
            prior: None,
            pose_convention: 7,
        })
        .await
        .unwrap_err();
    assert_eq!(st.code(), Code::InvalidArgument);
    assert!(st.message().contains("pose_convention"), "{}", st.message());
    // MatchPair: the relative pose in OpenGL axes is the OpenCV one with y and z flipped on both sides.
    let pair = |convention: i32| proto::MatchPairRequest {
        frame1: Some(image_frame(&scene.frames[1].rgb, &c)),
        frame2: Some(image_frame(&scene.frames[3].rgb, &c)),
        pose_convention: convention,
        ..Default::default()
    };
    let cv = matching.match_pair(pair(0)).await.unwrap().into_inner().pose.unwrap();
    let gl = matching.match_pair(pair(2)).await.unwrap().into_inner().pose.unwrap();
    let rot = |p: &proto::RelativePose| {
        UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(p.qw, p.qx, p.qy, p.qz)).to_rotation_matrix()
    };
    // Each against the truth in its axes (the two calls run RANSAC apart, so they are compared through it).
    let (c2w_1, c2w_2) = (scene.frames[1].pose.unwrap(), scene.frames[3].pose.unwrap());
    let truth = c2w_2.inverse() * c2w_1;
    let (r_cv, t_cv) = (truth.rotation.to_rotation_matrix(), truth.translation.vector.normalize());
    let (r_gl, t_gl) = (flip() * r_cv * flip(), flip() * t_cv);
    assert!((t_cv - t_gl).norm() > 0.2, "the pair must tell the axes apart");
    let t = |p: &proto::RelativePose| nalgebra::Vector3::new(p.tx, p.ty, p.tz);
    assert!(rot(&cv).angle_to(&r_cv).to_degrees() < 2.0 && (t(&cv) - t_cv).norm() < 0.1, "{cv:?}");
    assert!(rot(&gl).angle_to(&r_gl).to_degrees() < 2.0 && (t(&gl) - t_gl).norm() < 0.1, "{gl:?}");
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_zero_or_non_unit_quaternion_is_refused_not_renormalised() {
    let scene = Scene::load(&fixture("rendered")).unwrap();
    let dir = temp_dir("conventions-quaternion");
    let server = serve(settings(&dir)).await;
    let http = reqwest::Client::new();
    let base = format!("http://{}", server.http_addr);
    let r = http.post(format!("{base}/v1/maps")).json(&serde_json::json!({"map_id": "m"})).send().await.unwrap();
    assert_eq!(r.status(), 201);
    for convention in CONVENTIONS {
        for q in [[0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 2.0]] {
            let f = &scene.frames[0];
            let c = scene.camera;
            let t = f.pose.unwrap().translation.vector;
            let request = serde_json::json!({
                "keyframe_id": 0,
                "pose": {"tx": t.x, "ty": t.y, "tz": t.z, "qx": q[0], "qy": q[1], "qz": q[2], "qw": q[3]},
                "pose_convention": convention,
                "intrinsics": {"fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy},
            });
            let form = reqwest::multipart::Form::new().text("request", request.to_string()).part(
                "image",
                reqwest::multipart::Part::bytes(std::fs::read(&f.rgb).unwrap()).mime_str("image/png").unwrap(),
            );
            let r = http.post(format!("{base}/v1/maps/m/keyframes")).multipart(form).send().await.unwrap();
            assert_eq!(r.status(), 400, "{convention} {q:?}");
            let body = r.text().await.unwrap();
            assert!(body.contains("quaternion has norm"), "{convention} {q:?}: {body}");
        }
    }
    let info: serde_json::Value = http.get(format!("{base}/v1/maps/m")).send().await.unwrap().json().await.unwrap();
    assert_eq!(info["keyframes"], 0);
    server.shutdown().await.unwrap();
}
