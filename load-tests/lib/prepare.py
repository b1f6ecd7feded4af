"""One-time inputs for the load tests, cached under $SCONE_LOAD_CACHE (default ~/.cache/scone/load-tests).

- queries/: the scene's RGB frames encoded as JPEG (quality 90) + manifest.json (intrinsics, file list);
- writes/: the frames (PNG + 16-bit depth + camera-to-world pose) the keyframe writer of the mixed scenario sends;
- grpc/: Python stubs generated from proto/scone/v1/scone.proto with grpcio-tools (regenerated when the
  proto changes).

Usage: python prepare.py --scene DIR --writes-scene DIR --proto-root DIR --cache DIR
"""

import argparse
import hashlib
import json
import os
import shutil
import sys

from PIL import Image


def read_list(path):
    """Non-comment lines of a TUM-style list file, split on whitespace."""
    rows = []
    with open(path) as f:
        for line in f:
            line = line.strip()
            if line and not line.startswith("#"):
                rows.append(line.split())
    return rows


def read_camera(scene):
    fx, fy, cx, cy, w, h = read_list(os.path.join(scene, "camera.txt"))[0][:6]
    return {"fx": float(fx), "fy": float(fy), "cx": float(cx), "cy": float(cy), "width": int(w), "height": int(h)}


def scene_frames(scene):
    """(stamp, rgb path, depth path or None, pose dict or None) for each frame of a TUM-layout scene."""
    rgb = read_list(os.path.join(scene, "rgb.txt"))
    depth = {}
    if os.path.exists(os.path.join(scene, "depth.txt")):
        depth = {r[0]: r[1] for r in read_list(os.path.join(scene, "depth.txt"))}
    poses = {}
    if os.path.exists(os.path.join(scene, "groundtruth.txt")):
        for r in read_list(os.path.join(scene, "groundtruth.txt")):
            v = [float(x) for x in r[1:8]]
            poses[r[0]] = dict(zip(["tx", "ty", "tz", "qx", "qy", "qz", "qw"], v))
    out = []
    for stamp, name in rgb:
        d = depth.get(stamp)
        out.append((stamp, os.path.join(scene, name), os.path.join(scene, d) if d else None, poses.get(stamp)))
    return out


def stamp_of(path):
    """Content hash of the inputs, so a changed scene or script re-encodes."""
    h = hashlib.sha256()
    h.update(open(__file__, "rb").read())
    h.update(path.encode())
    for root, _, files in sorted(os.walk(path)):
        for f in sorted(files):
            p = os.path.join(root, f)
            st = os.stat(p)
            h.update(f"{p}:{st.st_size}:{int(st.st_mtime)}".encode())
    return h.hexdigest()[:16]


def make_queries(scene, out):
    key = stamp_of(scene)
    manifest = os.path.join(out, "manifest.json")
    if os.path.exists(manifest) and json.load(open(manifest)).get("key") == key:
        return
    shutil.rmtree(out, ignore_errors=True)
    os.makedirs(out)
    files = []
    for stamp, rgb, _, _ in scene_frames(scene):
        dst = os.path.join(out, f"{stamp}.jpg")
        Image.open(rgb).convert("RGB").save(dst, "JPEG", quality=90)
        files.append(dst)
    cam = read_camera(scene)
    json.dump({"key": key, "scene": os.path.abspath(scene), "intrinsics": cam, "files": files},
              open(manifest, "w"), indent=1)
    print(f"prepare: {len(files)} JPEG queries (q90, {cam['width']}x{cam['height']}) in {out}")


def make_writes(scene, out):
    key = stamp_of(scene)
    manifest = os.path.join(out, "manifest.json")
    if os.path.exists(manifest) and json.load(open(manifest)).get("key") == key:
        return
    shutil.rmtree(out, ignore_errors=True)
    os.makedirs(out)
    frames = []
    for stamp, rgb, depth, pose in scene_frames(scene):
        if pose is None:
            continue
        frames.append({"image": os.path.abspath(rgb), "depth": os.path.abspath(depth) if depth else None, "pose": pose})
    cam = read_camera(scene)
    json.dump({"key": key, "scene": os.path.abspath(scene), "intrinsics": cam, "frames": frames},
              open(manifest, "w"), indent=1)
    print(f"prepare: {len(frames)} keyframes ({cam['width']}x{cam['height']}) for the writer from {scene}")


def make_stubs(proto_root, out):
    proto = os.path.join(proto_root, "scone", "v1", "scone.proto")
    key = hashlib.sha256(open(proto, "rb").read()).hexdigest()[:16]
    stampfile = os.path.join(out, "STAMP")
    if os.path.exists(stampfile) and open(stampfile).read().strip() == key:
        return
    from grpc_tools import protoc  # noqa: PLC0415 (only needed here)

    shutil.rmtree(out, ignore_errors=True)
    os.makedirs(out)
    rc = protoc.main(["protoc", f"-I{proto_root}", f"--python_out={out}", f"--grpc_python_out={out}", proto])
    if rc != 0:
        sys.exit(f"prepare: protoc failed on {proto}")
    for d in ["scone", os.path.join("scone", "v1")]:
        open(os.path.join(out, d, "__init__.py"), "a").close()
    open(stampfile, "w").write(key + "\n")
    print(f"prepare: gRPC stubs for {proto} in {out}")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--scene", required=True)
    ap.add_argument("--writes-scene", required=True)
    ap.add_argument("--proto-root", required=True)
    ap.add_argument("--cache", required=True)
    a = ap.parse_args()
    make_queries(a.scene, os.path.join(a.cache, "queries"))
    make_writes(a.writes_scene, os.path.join(a.cache, "writes"))
    make_stubs(a.proto_root, os.path.join(a.cache, "grpc"))


if __name__ == "__main__":
    main()
