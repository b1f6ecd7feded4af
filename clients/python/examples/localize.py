#!/usr/bin/env python3
"""Builds a map from a TUM-layout scene through the API, then localises the other frames from keypoints
extracted on this side (the client contract), the way a phone app would.

    python examples/localize.py --server 127.0.0.1:50051 --scene tests/fixtures/rendered --map demo
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from scone_client import configure_opencv, extract_encoded, tum  # noqa: E402
from scone_client.client import SconeClient, image_frame, keypoint_frame, pb  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--server", default="127.0.0.1:50051", help="gRPC address")
    ap.add_argument("--scene", required=True, help="directory with rgb.txt, depth.txt, groundtruth.txt, camera.txt")
    ap.add_argument("--map", default="demo", help="map id to create")
    ap.add_argument("--api-key", default=None)
    ap.add_argument("--stride", type=int, default=2, help="every S-th frame is a keyframe, the others are queries")
    args = ap.parse_args()

    configure_opencv()
    scene = tum.load(args.scene)
    with SconeClient(args.server, api_key=args.api_key, timeout=120.0) as client:
        client.create_map(args.map)
        keyframes = [f for i, f in enumerate(scene.frames) if i % args.stride == 0 and f.pose and f.depth]
        requests = (
            pb.AddKeyframeRequest(
                map_id=args.map,
                keyframe_id=int(i),
                frame=keypoint_frame(extract_encoded(f.rgb.read_bytes()), scene.camera),
                pose=pb.Pose(**dict(zip(("tx", "ty", "tz", "qx", "qy", "qz", "qw"), f.pose, strict=True))),
                depth_png=f.depth.read_bytes(),
            )
            for i, f in enumerate(keyframes)
        )
        for ack in client.add_keyframes(requests):
            print(f"keyframe {ack.keyframe_id}: {ack.new_landmarks} new landmarks, {ack.observations} observations")
        for i, f in enumerate(scene.frames):
            if i % args.stride == 0:
                continue
            r = client.localize(args.map, keypoint_frame(extract_encoded(f.rgb.read_bytes()), scene.camera))
            if not r.localized:
                print(f"frame {f.stamp}: not localised ({r.matches} matches)")
                continue
            err = ""
            if f.pose:
                err = f", {1000 * math.dist(f.pose[:3], (r.pose.tx, r.pose.ty, r.pose.tz)):.1f} mm from ground truth"
            print(f"frame {f.stamp}: localised, {r.inliers}/{r.matches} inliers{err}")
        # The same query as an image, for comparison with the server's own extraction.
        f = scene.frames[1]
        r = client.localize(args.map, image_frame(f.rgb.read_bytes(), scene.camera))
        print(f"frame {f.stamp} sent as an image: localised={r.localized}, {r.inliers}/{r.matches} inliers")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
