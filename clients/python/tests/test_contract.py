"""The reference client against the real server: the client contract reproduces the server's extraction, and
frames of client keypoints localise and match like the images they come from."""

from __future__ import annotations

import dataclasses
import math
import os
import subprocess
import sys

import cv2
import numpy as np
import pytest
from conftest import FIXTURES, REPO

from scone_client import contract, extract, extract_encoded, tum
from scone_client.agreement import compare, deviation, grey_for
from scone_client.client import (
    Camera,
    covariance,
    extractor_config,
    features_from_describe,
    image_frame,
    keypoint_frame,
    pb,
)

#: The contract's acceptance figure: server keypoints with a client keypoint within 1 px and identical bytes.
MIN_AGREEMENT = 0.999
#: Localize from client keypoints vs from the image: the same support and a pose within 1 mm and 0.01 degree.
POSE_TOLERANCE_M = 1e-3
POSE_TOLERANCE_DEG = 0.01


def _blurred_png() -> bytes:
    """A heavily blurred frame: too few corners on the coarse levels to fill the budget."""
    img = cv2.imread(str(FIXTURES / "coffee-640x480.jpg"), cv2.IMREAD_UNCHANGED)
    ok, png = cv2.imencode(".png", cv2.GaussianBlur(img, (0, 0), 1.0))
    assert ok
    return png.tobytes()


IMAGES = {
    "coffee-640x480.jpg": lambda: (FIXTURES / "coffee-640x480.jpg").read_bytes(),
    "astronaut.jpg": lambda: (FIXTURES / "astronaut.jpg").read_bytes(),
    "rendered-000000.png": lambda: (FIXTURES / "rendered/rgb/000000.png").read_bytes(),
    "rendered-000007.png": lambda: (FIXTURES / "rendered/rgb/000007.png").read_bytes(),
    "coffee-blurred.png": _blurred_png,
}


def _server_features(client, data: bytes):
    grey = contract.decode_grey(data)
    response = client.describe(image_frame(data))
    return features_from_describe(response, grey.shape[1], grey.shape[0]), grey


def test_the_server_says_which_extraction_it_runs(client):
    """Describe names the server's extraction: the embedded model's, the contract's revision 3."""
    response = client.describe(image_frame((FIXTURES / "coffee-640x480.jpg").read_bytes()))
    assert extractor_config(response) == contract.ExtractorConfig()


@pytest.mark.parametrize("name", sorted(IMAGES))
def test_client_extraction_reproduces_the_servers(client, name):
    data = IMAGES[name]()
    server, grey = _server_features(client, data)
    assert len(server) > 200, f"{name}: only {len(server)} keypoints from the server"
    agreement = compare(server, extract(grey))
    print(f"{name}: {agreement}")
    assert agreement.fraction >= MIN_AGREEMENT, f"{name}: {agreement}"


def test_a_blurred_frame_leaves_the_unused_quota_unspent(client):
    """Unused quota moves to the coarsest level only, which cannot use it either: fewer than 2,000 keypoints."""
    server, grey = _server_features(client, _blurred_png())
    ours = extract(grey)
    assert len(ours) == len(server) < contract.ExtractorConfig().max_keypoints


def _fields(f) -> np.ndarray:
    return np.column_stack([f.xy, f.size, f.angle, f.response, f.octave.astype(np.float32)])


def test_golden_features_are_reproduced():
    """The committed golden features of the embedded model (made by the server's extractor at revision 3) equal
    the client's, ring contexts included, bit for bit."""
    golden = np.load(FIXTURES / "golden-ring" / "astronaut.ring.npz")
    ours = extract_encoded((FIXTURES / "astronaut.jpg").read_bytes())
    np.testing.assert_array_equal(_fields(ours), golden["keypoints"])
    np.testing.assert_array_equal(ours.descriptors, golden["descriptors"])
    np.testing.assert_array_equal(ours.context, golden["context"])


def test_revision_2_golden_features_are_reproduced():
    """The constellation model's golden features (revision 2: 6 levels, 1,500 keypoints), bit for bit."""
    golden = np.load(FIXTURES / "golden" / "astronaut.features.npz")
    ours = extract_encoded((FIXTURES / "astronaut.jpg").read_bytes(), contract.ExtractorConfig.revision_2(), False)
    np.testing.assert_array_equal(_fields(ours), golden["f0000_keypoints"])
    np.testing.assert_array_equal(ours.descriptors, golden["f0000_descriptors"])


@pytest.mark.parametrize("wrong_rule", ["decoded straight to grey", "floor for W_l", "coordinates in double"])
def test_the_agreement_check_detects_a_wrong_rule(client, wrong_rule):
    """The acceptance figure is sensitive: each of these rules of the contract, done the other way, fails it."""
    data = IMAGES["coffee-640x480.jpg"]()
    server, _ = _server_features(client, data)
    with deviation(wrong_rule):
        agreement = compare(server, extract(grey_for(wrong_rule, data)))
    print(f"{wrong_rule}: {agreement}")
    assert agreement.fraction < MIN_AGREEMENT, f"{wrong_rule} went unnoticed: {agreement}"


def test_level_geometry_matches_the_contract_table():
    """The numbers the proto's contract text states: revision 3's quotas and level sizes, and revision 2's quotas."""
    assert contract.level_quotas() == [646, 449, 312, 216, 150, 104, 72, 50]
    assert contract.level_quotas(contract.ExtractorConfig.revision_2()) == [516, 358, 249, 173, 120, 83]
    assert [contract.level_size(640, 480, lvl) for lvl in range(8)] == [
        (640, 480),
        (533, 400),
        (444, 333),
        (370, 278),
        (309, 231),
        (257, 193),
        (214, 161),
        (179, 134),
    ]
    assert contract.round_half_away(2.5) == 3 and contract.round_half_away(-2.5) == -3
    sizes = [float(contract.keypoint_size(lvl)) for lvl in range(8)]
    assert sizes == [float(np.float32(7 * np.float32(contract.powi(1.2, lvl)))) for lvl in range(8)]


def test_grey_formula_equals_cvtcolor_on_every_colour():
    """The contract's integer grey formula (for ports without OpenCV's cvtColor) is exactly BGR2GRAY."""
    a = np.arange(1 << 24, dtype=np.uint32)
    bgr = np.stack([(a >> 16) & 255, (a >> 8) & 255, a & 255], axis=-1).astype(np.uint8).reshape(4096, 4096, 3)
    np.testing.assert_array_equal(contract.grey_from_rgb(bgr[..., ::-1]), cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY))


# -- Localisation and matching from client keypoints -----------------------------------------------------


def _pose_error(a: pb.Pose, b: pb.Pose) -> tuple[float, float]:
    """Translation and rotation (degrees) between two poses. The angle is that of the relative rotation
    conj(a) * b by atan2: acos of the quaternions' dot product cannot resolve less than ~1.7e-6 degrees (one
    ulp below 1 already reads as that)."""
    dt = math.dist((a.tx, a.ty, a.tz), (b.tx, b.ty, b.tz))
    aw, ax, ay, az = a.qw, -a.qx, -a.qy, -a.qz
    w = aw * b.qw - ax * b.qx - ay * b.qy - az * b.qz
    x = aw * b.qx + ax * b.qw + ay * b.qz - az * b.qy
    y = aw * b.qy - ax * b.qz + ay * b.qw + az * b.qx
    z = aw * b.qz + ax * b.qy - ay * b.qx + az * b.qw
    return dt, math.degrees(2 * math.atan2(math.hypot(x, y, z), abs(w)))


def _gt(frame: tum.Frame) -> pb.Pose:
    tx, ty, tz, qx, qy, qz, qw = frame.pose
    return pb.Pose(tx=tx, ty=ty, tz=tz, qx=qx, qy=qy, qz=qz, qw=qw)


@pytest.fixture(scope="module")
def rendered_map(client):
    """A map of the rendered fixture's even frames (image frames with depth), built through the API."""
    scene = tum.load(FIXTURES / "rendered")
    client.create_map("client-contract")
    keyframes = [i for i in range(0, len(scene.frames), 2)]
    requests = [
        pb.AddKeyframeRequest(
            map_id="client-contract",
            keyframe_id=i,
            frame=image_frame(scene.frames[i].rgb.read_bytes(), scene.camera),
            pose=_gt(scene.frames[i]),
            depth_png=scene.frames[i].depth.read_bytes(),
        )
        for i in keyframes
    ]
    acks = list(client.add_keyframes(requests))
    assert [a.keyframe_id for a in acks] == keyframes
    return scene


def test_localize_from_client_keypoints_equals_localize_from_the_image(client, rendered_map):
    scene = rendered_map
    model_id = client.model_id()
    for i in range(1, len(scene.frames), 2):
        frame = scene.frames[i]
        data = frame.rgb.read_bytes()
        by_image = client.localize("client-contract", image_frame(data, scene.camera))
        ours = extract_encoded(data)
        by_keypoints = client.localize("client-contract", keypoint_frame(ours, scene.camera, model_id))
        assert by_image.localized, f"frame {i}: the image route did not localise: {by_image}"
        dt_gt, dr_gt = _pose_error(by_image.pose, _gt(frame))
        assert dt_gt < 0.05 and dr_gt < 1.0, f"frame {i}: image route off by {dt_gt} m, {dr_gt} deg"
        assert by_keypoints.localized, f"frame {i}: client keypoints did not localise: {by_keypoints}"
        dt, dr = _pose_error(by_keypoints.pose, by_image.pose)
        print(
            f"frame {i}: image {by_image.inliers}/{by_image.matches} inliers, keypoints "
            f"{by_keypoints.inliers}/{by_keypoints.matches}; poses differ by {dt * 1000:.4f} mm, {dr:.5f} deg"
        )
        assert dt <= POSE_TOLERANCE_M and dr <= POSE_TOLERANCE_DEG, f"frame {i}: {dt} m, {dr} deg apart"
        assert abs(by_keypoints.inliers - by_image.inliers) <= max(2, by_image.inliers // 100), f"frame {i}"


def test_localize_answers_in_the_requested_pose_convention(client, rendered_map):
    """World-to-camera is the inverse of the default camera-to-world: the same rotation conjugated, and the
    camera centre mapped to the origin."""
    scene = rendered_map
    frame = image_frame(scene.frames[1].rgb.read_bytes(), scene.camera)
    c2w = client.localize("client-contract", frame)
    w2c = client.localize("client-contract", frame, pose_convention=pb.POSE_CONVENTION_OPENCV_WORLD_TO_CAMERA)
    assert c2w.localized and w2c.localized
    inverse_rotation = pb.Pose(qx=-c2w.pose.qx, qy=-c2w.pose.qy, qz=-c2w.pose.qz, qw=c2w.pose.qw)
    _, dr = _pose_error(
        pb.Pose(qx=w2c.pose.qx, qy=w2c.pose.qy, qz=w2c.pose.qz, qw=w2c.pose.qw), inverse_rotation
    )
    assert dr < 1e-6, dr
    q = w2c.pose
    r = np.array(
        [
            [1 - 2 * (q.qy**2 + q.qz**2), 2 * (q.qx * q.qy - q.qz * q.qw), 2 * (q.qx * q.qz + q.qy * q.qw)],
            [2 * (q.qx * q.qy + q.qz * q.qw), 1 - 2 * (q.qx**2 + q.qz**2), 2 * (q.qy * q.qz - q.qx * q.qw)],
            [2 * (q.qx * q.qz - q.qy * q.qw), 2 * (q.qy * q.qz + q.qx * q.qw), 1 - 2 * (q.qx**2 + q.qy**2)],
        ]
    )
    centre = np.array([c2w.pose.tx, c2w.pose.ty, c2w.pose.tz])
    assert np.linalg.norm(r @ centre + np.array([q.tx, q.ty, q.tz])) < 1e-9


def test_a_declared_lens_and_an_unknown_focal_length(client, rendered_map):
    """Client keypoints moved through a fisheye lens localise, with the lens declared, where the pinhole
    keypoints do; a query without a focal length gets the focal length estimated; the answer carries a 6x6
    covariance."""
    scene = rendered_map
    cam = scene.camera
    data = scene.frames[3].rgb.read_bytes()
    ours = extract_encoded(data)
    pinhole = client.localize("client-contract", keypoint_frame(ours, cam))
    assert pinhole.localized
    k = (0.1, -0.03, 0.01, 0.0)
    normalised = (ours.xy - [cam.cx, cam.cy]) / [cam.fx, cam.fy]
    distorted = cv2.fisheye.distortPoints(
        normalised.reshape(-1, 1, 2).astype(np.float64),
        np.array([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1]]),
        np.array(k),
    ).reshape(-1, 2)
    moved = dataclasses.replace(ours, xy=distorted.astype(np.float32))
    lens = Camera(cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height, pb.DISTORTION_MODEL_FISHEYE, k)
    declared = client.localize("client-contract", keypoint_frame(moved, lens))
    assert declared.localized
    dt, dr = _pose_error(declared.pose, pinhole.pose)
    assert dt < 1e-3 and dr < 0.02, (dt, dr)
    sigma = covariance(declared)
    assert sigma is not None and np.all(np.linalg.eigvalsh(sigma) > 0)

    unknown = Camera(0.0, 0.0, 0.0, 0.0, cam.width, cam.height)
    estimated = client.localize("client-contract", image_frame(data, unknown))
    assert estimated.localized and estimated.focal_estimated
    assert abs(estimated.focal_length - cam.fx) < 0.05 * cam.fx, estimated.focal_length


def test_merge_maps_estimates_the_shift_between_two_runs(client):
    """The odd frames, mapped in a world shifted by a known translation, merge into a map of the even frames:
    the estimated transform undoes the shift and the target then holds every frame."""
    scene = tum.load(FIXTURES / "rendered")
    shift = (1.0, -2.0, 0.5)

    def keyframes(map_id, frames, offset):
        for i in frames:
            pose = _gt(scene.frames[i])
            pose.tx, pose.ty, pose.tz = pose.tx + offset[0], pose.ty + offset[1], pose.tz + offset[2]
            yield pb.AddKeyframeRequest(
                map_id=map_id,
                keyframe_id=i,
                frame=image_frame(scene.frames[i].rgb.read_bytes(), scene.camera),
                pose=pose,
                depth_png=scene.frames[i].depth.read_bytes(),
            )

    client.create_map("merge-even")
    client.create_map("merge-odd")
    even, odd = range(0, len(scene.frames), 2), range(1, len(scene.frames), 2)
    assert len(list(client.add_keyframes(keyframes("merge-even", even, (0.0, 0.0, 0.0))))) == len(even)
    assert len(list(client.add_keyframes(keyframes("merge-odd", odd, shift)))) == len(odd)
    merged = client.merge_maps("merge-even", "merge-odd")
    assert merged.transform_estimated and merged.keyframes_localised == len(odd)
    t = merged.transform
    assert abs(t.scale - 1.0) < 0.01, t
    assert math.dist((t.tx, t.ty, t.tz), tuple(-v for v in shift)) < 0.03, t
    assert merged.target.keyframes == len(scene.frames)
    assert client.get_map("merge-odd").keyframes == len(odd)


def test_match_pair_from_client_keypoints_equals_match_pair_from_images(client):
    scene = tum.load(FIXTURES / "rendered")
    a, b = scene.frames[2].rgb.read_bytes(), scene.frames[4].rgb.read_bytes()
    by_image = client.match_pair(image_frame(a, scene.camera), image_frame(b, scene.camera))
    by_keypoints = client.match_pair(
        keypoint_frame(extract_encoded(a), scene.camera), keypoint_frame(extract_encoded(b), scene.camera)
    )
    assert by_image.inliers > 30, by_image.inliers
    assert by_keypoints.HasField("pose")
    assert abs(by_keypoints.inliers - by_image.inliers) <= max(2, by_image.inliers // 100)
    qa, qb = by_image.pose, by_keypoints.pose
    dot = abs(qa.qx * qb.qx + qa.qy * qb.qy + qa.qz * qb.qz + qa.qw * qb.qw)
    t_dot = qa.tx * qb.tx + qa.ty * qb.ty + qa.tz * qb.tz
    assert math.degrees(2 * math.acos(min(1.0, dot))) <= 0.05
    assert math.degrees(math.acos(max(-1.0, min(1.0, t_dot)))) <= 0.1


# -- Stubs ------------------------------------------------------------------------------------------------


def test_committed_stubs_match_the_proto(tmp_path):
    """The committed stubs are what clients/python/generate-stubs makes from today's proto."""
    package = REPO / "clients" / "python"
    env = dict(os.environ, STUBS_OUT=str(tmp_path))
    subprocess.run([str(package / "generate-stubs"), sys.executable], check=True, env=env)
    generated = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*") if p.is_file())
    committed = sorted(
        p.relative_to(package)
        for p in (package / "scone_client" / "_proto").rglob("*")
        if p.is_file() and "__pycache__" not in p.parts
    )
    assert generated == committed
    for rel in generated:
        assert (tmp_path / rel).read_bytes() == (package / rel).read_bytes(), f"{rel} is stale: run generate-stubs"


def test_example_script_runs(server):
    out = subprocess.run(
        [
            sys.executable,
            str(REPO / "clients/python/examples/localize.py"),
            "--server",
            server[0],
            "--scene",
            str(FIXTURES / "rendered"),
            "--map",
            "example",
        ],
        check=True,
        capture_output=True,
        text=True,
        timeout=300,
    ).stdout
    assert "localised" in out, out


def test_track_example_script_runs_and_recovers_the_made_up_motion(server):
    out = subprocess.run(
        [
            sys.executable,
            str(REPO / "clients/python/examples/localize_track.py"),
            "--server",
            server[0],
            "--scene",
            str(FIXTURES / "rendered"),
            "--map",
            "track-example",
        ],
        check=True,
        capture_output=True,
        text=True,
        timeout=300,
    ).stdout
    tracks = [line for line in out.splitlines() if line.startswith("track [")]
    assert tracks and all("not localised" not in t for t in tracks), out
    errors = [float(line.rsplit("position error ", 1)[1].split()[0]) for line in out.splitlines() if "position error" in line]
    assert errors and max(errors) < 0.05, out
