#!/usr/bin/env python3
"""Builds a map from every other frame of a TUM-layout scene, then localises short tracks of the other frames
together (LocalizeTrack), each frame with its pose in a track frame of its own, the way an AR app sends a few
recent frames with its tracker's poses:

    python examples/localize_track.py --server 127.0.0.1:50051 --scene tests/fixtures/rendered --map track-demo

The track's frame here is the scene's world moved by a made-up rigid motion (a tracker's world is its own); the
answer's transform recovers that motion, and every frame's pose in the map is printed beside the truth.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from scone_client import tum  # noqa: E402
from scone_client.client import SconeClient, image_frame, pb  # noqa: E402


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    x, y, z, w = q / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def matrix_to_quat(r: np.ndarray) -> np.ndarray:
    w = math.sqrt(max(0.0, 1.0 + r[0, 0] + r[1, 1] + r[2, 2])) / 2.0
    x = math.copysign(math.sqrt(max(0.0, 1.0 + r[0, 0] - r[1, 1] - r[2, 2])) / 2.0, r[2, 1] - r[1, 2])
    y = math.copysign(math.sqrt(max(0.0, 1.0 - r[0, 0] + r[1, 1] - r[2, 2])) / 2.0, r[0, 2] - r[2, 0])
    z = math.copysign(math.sqrt(max(0.0, 1.0 - r[0, 0] - r[1, 1] + r[2, 2])) / 2.0, r[1, 0] - r[0, 1])
    return np.array([x, y, z, w])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--server", default="127.0.0.1:50051", help="gRPC address")
    ap.add_argument("--scene", required=True, help="directory with rgb.txt, depth.txt, groundtruth.txt, camera.txt")
    ap.add_argument("--map", default="track-demo", help="map id to create")
    ap.add_argument("--api-key", default=None)
    ap.add_argument("--frames", type=int, default=3, help="frames per track")
    args = ap.parse_args()

    scene = tum.load(args.scene)
    # The tracker's world in the map's: a made-up rotation about z and a shift.
    yaw = math.radians(40.0)
    world_r = np.array([[math.cos(yaw), -math.sin(yaw), 0.0], [math.sin(yaw), math.cos(yaw), 0.0], [0.0, 0.0, 1.0]])
    world_t = np.array([2.0, -1.0, 0.5])
    with SconeClient(args.server, api_key=args.api_key, timeout=120.0) as client:
        client.create_map(args.map)
        posed = [(i, f) for i, f in enumerate(scene.frames) if f.pose]
        mapped = [(i, f) for k, (i, f) in enumerate(posed) if k % 2 == 0 and f.depth]
        requests = (
            pb.AddKeyframeRequest(
                map_id=args.map,
                keyframe_id=int(i),
                frame=image_frame(f.rgb.read_bytes(), scene.camera),
                pose=pb.Pose(**dict(zip(("tx", "ty", "tz", "qx", "qy", "qz", "qw"), f.pose, strict=True))),
                depth_png=f.depth.read_bytes(),
            )
            for i, f in mapped
        )
        for ack in client.add_keyframes(requests):
            print(f"keyframe {ack.keyframe_id}: {ack.new_landmarks} new landmarks")
        queries = [(i, f) for k, (i, f) in enumerate(posed) if k % 2 == 1]
        for start in range(0, len(queries) - args.frames + 1, args.frames):
            chunk = queries[start : start + args.frames]
            frames = []
            for _, f in chunk:
                t, q = np.array(f.pose[:3]), np.array(f.pose[3:])
                # The frame's pose in the track's world: the inverse of the world motion applied to the truth.
                r_track = world_r.T @ quat_to_matrix(q)
                t_track = world_r.T @ (t - world_t)
                qx, qy, qz, qw = matrix_to_quat(r_track)
                pose = pb.Pose(tx=t_track[0], ty=t_track[1], tz=t_track[2], qx=qx, qy=qy, qz=qz, qw=qw)
                frames.append((image_frame(f.rgb.read_bytes(), scene.camera), pose))
            # These poses are the ground truth moved into the track's world: exact, as a rig's extrinsics are, so
            # the tracker's error is zero (a phone's tracker: leave it out, the server assumes 1 % and 0.5 degrees).
            r = client.localize_track(args.map, frames, tracker_error=(0.0, 0.0))
            names = ", ".join(str(i) for i, _ in chunk)
            if not r.localized:
                print(f"track [{names}]: not localised")
                continue
            s = r.map_from_track
            print(f"track [{names}]: transform t = ({s.tx:.3f}, {s.ty:.3f}, {s.tz:.3f}) (made-up: {world_t.tolist()}), "
                  f"{r.inliers} inliers, confidence {r.confidence:.2f}")
            for (i, f), fr in zip(chunk, r.frames, strict=True):
                err = math.dist((fr.pose.tx, fr.pose.ty, fr.pose.tz), f.pose[:3]) if fr.HasField("pose") else float("nan")
                note = " (dropped)" if fr.dropped else ""
                print(f"  frame {i}: {fr.inliers} inliers of {fr.matches} matches, position error {err:.3f}{note}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
