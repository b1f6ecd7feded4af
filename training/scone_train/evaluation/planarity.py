"""Where the correct matches of a pair lie: how many distinct corners, how much of the image they cover, and
what share of them one homography explains (a dominant plane makes the essential matrix ill-conditioned).

It re-runs the pair pipeline's matching on an exported scene (`scone features`): SConE embeddings from the ONNX
model, L2 for SConE and Hamming for FREAK, Lowe's ratio 0.8 with the same-corner rule (the competitor is the
nearest candidate more than 2 px from the nearest neighbour's keypoint, among the 10 nearest). A match is correct
when its symmetric epipolar distance under the ground-truth pose is within `--epipolar-px`.

    python -m scone_train.evaluation.planarity --scene DIR --features scene.npz --model models/scone-freak-k20.onnx \
        --min-deg 40 --max-deg 80
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from ..data.features import load_features
from ..data.scenes import load_scene

RATIO = 0.8
SAME_CORNER_PX = 2.0
CANDIDATES = 10


def embed(session, f) -> np.ndarray:
    """SConE embeddings of one exported frame, with each input cast to the dtype the model declares."""
    kinds = {"tensor(uint8)": np.uint8, "tensor(float)": np.float32, "tensor(int64)": np.int64, "tensor(int32)": np.int32}
    values = {
        "descriptors": f.descriptors,
        "keypoints": np.ascontiguousarray(f.keypoints[:, [3, 2]]),
        "neighbours": f.neighbours,
        "mask": f.mask,
        "relative": f.relative,
    }
    feeds = {i.name: values[i.name].astype(kinds[i.type]) for i in session.get_inputs()}
    return session.run(None, feeds)[0]


def distances(a: np.ndarray, b: np.ndarray, hamming: bool) -> np.ndarray:
    if hamming:
        x = np.unpackbits(a, axis=1).astype(np.int32)
        y = np.unpackbits(b, axis=1).astype(np.int32)
        return (x @ (1 - y).T + (1 - x) @ y.T).astype(np.float64)
    sq = (a * a).sum(1)[:, None] - 2.0 * a @ b.T + (b * b).sum(1)[None, :]
    return np.sqrt(np.maximum(sq, 0.0))


def ratio_matches(d: np.ndarray, b_points: np.ndarray) -> np.ndarray:
    """[M, 2] (query, train) pairs passing the same-corner ratio test."""
    order = np.argsort(d, axis=1, kind="stable")[:, :CANDIDATES]
    out = []
    for q, cand in enumerate(order):
        p0 = b_points[cand[0]]
        beyond = [j for j in cand[1:] if np.hypot(*(b_points[j] - p0)) > SAME_CORNER_PX]
        competitor = d[q, beyond[0]] if beyond else d[q, cand[-1]]
        if d[q, cand[0]] < RATIO * competitor:
            out.append((q, cand[0]))
    return np.array(out, dtype=np.int64).reshape(-1, 2)


def skew(t: np.ndarray) -> np.ndarray:
    return np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])


def fundamental(scene, a: int, b: int) -> np.ndarray:
    """F with x_b^T F x_a = 0, from the camera-to-world poses."""
    Ta, Tb = scene.T_wc[a], scene.T_wc[b]
    rel = np.linalg.inv(Tb) @ Ta  # camera a to camera b
    Kinv = np.linalg.inv(scene.K)
    return Kinv.T @ skew(rel[:3, 3]) @ rel[:3, :3] @ Kinv


def view_angle_deg(scene, a: int, b: int) -> float:
    za, zb = scene.T_wc[a][:3, 2], scene.T_wc[b][:3, 2]
    return float(np.degrees(np.arccos(np.clip(za @ zb, -1.0, 1.0))))


def layout(xa: np.ndarray, xb: np.ndarray, F: np.ndarray, epipolar_px: float, image_area: float) -> dict:
    ha = np.c_[xa, np.ones(len(xa))]
    hb = np.c_[xb, np.ones(len(xb))]
    la, lb = ha @ F.T, hb @ F
    num = np.abs((hb * la).sum(1))
    d = num / np.hypot(la[:, 0], la[:, 1]) + num / np.hypot(lb[:, 0], lb[:, 1])
    ok = d < epipolar_px
    ca, cb = xa[ok].astype(np.float32), xb[ok].astype(np.float32)
    r = {"matches": len(xa), "correct": int(ok.sum()), "distinct": len({(round(x / 3), round(y / 3)) for x, y in ca})}
    if ok.sum() >= 4:
        _, inl = cv2.findHomography(ca, cb, cv2.RANSAC, 3.0)
        r["one_plane"] = float(inl.sum()) / ok.sum() if inl is not None else float("nan")
        r["hull"] = cv2.contourArea(cv2.convexHull(ca)) / image_area
    else:
        r["one_plane"], r["hull"] = float("nan"), 0.0
    return r


def main(argv: list[str] | None = None) -> None:
    import onnxruntime as ort

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", type=Path, required=True)
    ap.add_argument("--features", type=Path, required=True, help="`scone features` export of the scene")
    ap.add_argument("--model", type=Path, required=True)
    ap.add_argument("--min-deg", type=float, default=0.0)
    ap.add_argument("--max-deg", type=float, default=180.0)
    ap.add_argument("--epipolar-px", type=float, default=2.0)
    args = ap.parse_args(argv)
    cv2.setNumThreads(1)
    cv2.setRNGSeed(0)
    scene = load_scene(args.scene)
    _, frames = load_features(args.features)
    session = ort.InferenceSession(str(args.model))
    area = float(scene.width * scene.height)
    emb0 = embed(session, frames[0])
    print("pair angle | method matches correct distinct one_plane hull")
    for b in range(1, len(frames)):
        angle = view_angle_deg(scene, 0, b)
        if not args.min_deg <= angle < args.max_deg:
            continue
        F = fundamental(scene, 0, b)
        pa, pb = frames[0].keypoints[:, :2], frames[b].keypoints[:, :2]
        for name, d in (
            ("SConE", distances(emb0, embed(session, frames[b]), False)),
            ("FREAK", distances(frames[0].descriptors, frames[b].descriptors, True)),
        ):
            m = ratio_matches(d, pb)
            r = layout(pa[m[:, 0]], pb[m[:, 1]], F, args.epipolar_px, area)
            print(
                f"0-{b} {angle:.0f} | {name} {r['matches']} {r['correct']} {r['distinct']} "
                f"{r['one_plane']:.2f} {r['hull']:.3f}"
            )


if __name__ == "__main__":
    main()
