#!/usr/bin/env python3
"""How much of the ring's sharing is lost to the keypoint's frame (a measurement, no choice).

On the selection warps that `score.sh` scores (`$SCONE_PREFIX/work/warps/selection-g2`, 80 sequences, 400 pairs),
keypoints extracted as the shipped model's (8 levels at 1.2, 2,000 keypoints, `scone features`), images
made grey as the service decodes them (`data.grey_image`) for G and S. For each pair
(1, k) and each keypoint i of image 1 with a keypoint of image k within 3 px of its image under the true H, the
ring's 112 samples (the centre left out) of i are sent through H and compared, slot by slot, with the samples of
k's keypoint placed by one of these frames:

  A  detected: the nearest keypoint of k within 3 px, its own size and FREAK angle (what `scone eval homography`
     reports as "ring above chance"; reproduced here as a check of this script);
  B  the best of k's keypoints within 3 px (the same corner found at another pyramid level), own size and angle;
  C  A's keypoint with the exact scale (i's size times the local area scale of H), its own angle;
  D  A's keypoint with the exact angle (i's angle plus H's local rotation), its own size;
  E  A's keypoint with the exact scale and angle (its own position);
  F  the exact frame: i's image under H, with the exact scale and angle;
  G  both keypoints' scales chosen again in each view on its own, between pyramid levels: the extremum of the
     scale-normalised Laplacian at the keypoint (sigma^2 times OpenCV's Laplacian of the Gaussian-blurred image,
     sigma in steps of 2^(1/8), parabola through the peak) within 1.5 levels of its detected size, the size being
     2.5 sigma (Harris-Laplace's scale selection on FAST's corners); their own FREAK angles;
  H  G's scales with the exact angle;
  S  another detector's frames: OpenCV's SIFT (2,000 features) in both views, the ring placed by its size (times
     one constant, the median FAST size over the median SIFT size, so that the radii are the same in pixels)
     and its angle (in FREAK's sense, checked below against the exact angle as FREAK's is); the best of the
     SIFT keypoints within 3 px, as B, since SIFT gives one location several orientations.

A sample counts as shared within 3 px, and (second figure) within its own box's half-width (the sampled box is
`floor(0.2 r s + 0.5)` pixels on each side, at least 1), each minus chance (the sent samples turned 90 degrees
about the centre). Pairs are binned by the zoom at image 1's centre, as `scone eval homography` bins them.

    $SCONE_PREFIX/venv-train/bin/python docs/results/training/frames/frames.py > docs/results/training/frames/frames.txt

(also writes frames.json beside it, which `limits_figure.py` draws).
"""

import json
import math
import sys
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial import cKDTree

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parents[3] / "training"))
from scone_train.data import ring_context as CX  # noqa: E402
from scone_train.data.features import export_features, extractor_args, grey_image, load_features  # noqa: E402
from scone_train.paths import prefix_dir  # noqa: E402

BINS = [("1-1.25x", 1.0, 1.25), ("1.25-1.6x", 1.25, 1.6), ("1.6-2x", 1.6, 2.0), ("2-2.5x", 2.0, 2.5), ("2.5-3x", 2.5, 3.0)]
VARIANTS = "ABCDEFGHS"
SIGMAS = 2.0 ** (np.arange(0, 44) / 8.0)  # 1 to 41 pixels
SIZE_PER_SIGMA = 2.5
PX = 3.0


def apply(h, xy):
    p = np.c_[xy, np.ones(len(xy))] @ h.T
    return p[:, :2] / p[:, 2:3]


def jacobian(h, x, y, d=0.5):
    c = apply(h, np.array([[x, y], [x + d, y], [x, y + d]], dtype=np.float64))
    return np.array([(c[1] - c[0]) / d, (c[2] - c[0]) / d]).T  # [[dx'/dx, dx'/dy], [dy'/dx, dy'/dy]]


def zoom_at(h, x, y):
    s = np.linalg.svd(jacobian(h, x, y), compute_uv=False)
    return max(s[0], 1.0 / s[0]) if s[0] > 0 else math.inf


def positions(x, y, size, angle):
    dx, dy, _ = CX._TABLE
    a = int(CX.angle_bin(np.array([angle]))[0])
    return np.c_[x + size * dx[a, 1:], y + size * dy[a, 1:]]


def box_half(size):
    return np.maximum(np.floor(CX._TABLE[2][1:] * size + 0.5), 1.0)


def shares(sent, centre, theirs, size_b):
    """(within 3 px, within the box) minus chance, as fractions of the 112 ring samples."""
    turned = np.c_[centre[0] - (sent[:, 1] - centre[1]), centre[1] + (sent[:, 0] - centre[0])]
    d, dc = np.hypot(*(sent - theirs).T), np.hypot(*(turned - theirs).T)
    half = box_half(size_b)
    return np.array([(d <= PX).mean() - (dc <= PX).mean(), (d <= half).mean() - (dc <= half).mean()])


def refined_sizes(grey: np.ndarray, kps: np.ndarray) -> np.ndarray:
    """Each keypoint's size chosen again by the scale-normalised Laplacian (variant G of the module docs)."""
    img = grey.astype(np.float32)
    xi = np.clip(np.round(kps[:, 0]).astype(int), 0, img.shape[1] - 1)
    yi = np.clip(np.round(kps[:, 1]).astype(int), 0, img.shape[0] - 1)
    resp = np.empty((len(SIGMAS), len(kps)), np.float64)
    for k, sig in enumerate(SIGMAS):
        lap = cv2.Laplacian(cv2.GaussianBlur(img, (0, 0), float(sig)), cv2.CV_32F)
        resp[k] = np.abs(sig * sig * lap[yi, xi])
    logs = np.log(SIGMAS)
    out = kps[:, 2].astype(np.float64).copy()
    window = 1.5 * math.log(1.2)
    for i in range(len(kps)):
        centre = math.log(kps[i, 2] / SIZE_PER_SIGMA)
        ks = np.nonzero(np.abs(logs - centre) <= window)[0]
        if len(ks) < 3:
            continue
        k = ks[np.argmax(resp[ks, i])]
        if k in (ks[0], ks[-1]):
            out[i] = SIZE_PER_SIGMA * SIGMAS[k]
            continue
        r0, r1, r2 = resp[k - 1, i], resp[k, i], resp[k + 1, i]
        den = r0 - 2.0 * r1 + r2
        off = 0.5 * (r0 - r2) / den if den < 0 else 0.0
        out[i] = SIZE_PER_SIGMA * math.exp(logs[k] + off * (logs[1] - logs[0]))
    return out


def sift_keypoints(grey: np.ndarray) -> np.ndarray:
    """OpenCV SIFT's keypoints as rows x, y, size, angle."""
    kps = cv2.SIFT_create(nfeatures=2000).detect(grey, None)
    return np.array([[k.pt[0], k.pt[1], k.size, k.angle] for k in kps], dtype=np.float64)


def sift_shares(ka, kb, h, factor):
    """Variant S for one pair: mean (3 px, box) share above chance, and the angle errors."""
    tree = cKDTree(kb[:, :2])
    img = apply(h, ka[:, :2])
    rows, errs = [], []
    for i, cands in enumerate(tree.query_ball_point(img, PX)):
        if not cands:
            continue
        x, y, size, ang = ka[i]
        J = jacobian(h, x, y)
        rot = math.degrees(math.atan2(J[1, 0] - J[0, 1], J[0, 0] + J[1, 1]))
        errs.append(min(abs((kb[j, 3] - ang - rot + 180.0) % 360.0 - 180.0) for j in cands))
        sent = apply(h, positions(x, y, factor * size, ang))
        rows.append(max((shares(sent, img[i], positions(kb[j, 0], kb[j, 1], factor * kb[j, 2], kb[j, 3]), factor * kb[j, 2])
                         for j in cands), key=lambda r: r[0]))
    return (np.mean(rows, 0) if rows else None), errs


def pair_shares(ka, kb, h, ra, rb):
    """Per variant: mean (3 px, box) share above chance over the corresponding keypoints, and their count."""
    tree = cKDTree(kb[:, :2])
    img = apply(h, ka[:, :2].astype(np.float64))
    out = {v: [] for v in VARIANTS}
    angle_err = []
    for i, cands in enumerate(tree.query_ball_point(img, PX)):
        if not cands:
            continue
        x, y, s, ang = (float(v) for v in ka[i, :4])
        sent = apply(h, positions(x, y, s, ang))
        centre = img[i]
        J = jacobian(h, x, y)
        scale = math.sqrt(abs(np.linalg.det(J)))
        rot = math.degrees(math.atan2(J[1, 0] - J[0, 1], J[0, 0] + J[1, 1]))
        exact_s, exact_a = s * scale, ang + rot
        j = min(cands, key=lambda c: np.hypot(*(kb[c, :2] - centre)))
        xb, yb, sb, ab = (float(v) for v in kb[j, :4])
        angle_err.append((ab - exact_a + 180.0) % 360.0 - 180.0)
        out["A"].append(shares(sent, centre, positions(xb, yb, sb, ab), sb))
        out["B"].append(max((shares(sent, centre, positions(*(float(v) for v in kb[c, :4])), float(kb[c, 2]))
                             for c in cands), key=lambda r: r[0]))
        out["C"].append(shares(sent, centre, positions(xb, yb, exact_s, ab), exact_s))
        out["D"].append(shares(sent, centre, positions(xb, yb, sb, exact_a), sb))
        out["E"].append(shares(sent, centre, positions(xb, yb, exact_s, exact_a), exact_s))
        out["F"].append(shares(sent, centre, positions(centre[0], centre[1], exact_s, exact_a), exact_s))
        sent_g = apply(h, positions(x, y, ra[i], ang))
        out["G"].append(shares(sent_g, centre, positions(xb, yb, rb[j], ab), rb[j]))
        out["H"].append(shares(sent_g, centre, positions(xb, yb, rb[j], exact_a), rb[j]))
    return {v: np.mean(r, 0) for v, r in out.items() if r}, angle_err


def main():
    root = prefix_dir() / "work" / "warps" / "selection-g2"
    cache = prefix_dir() / "work" / "i39" / "frames-features"
    args = extractor_args({"levels": 8, "max_keypoints": 2000})
    seqs = sorted(p.parent for p in root.glob("*/H_1_2"))[: int(sys.argv[1]) if len(sys.argv) > 1 else None]
    by_bin = {b[0]: {v: [] for v in VARIANTS} for b in BINS}
    angle_errs = []
    fast_sizes, sift_sizes, sifts, pairs_seen = [], [], [], []
    for seq in seqs:
        _, frames = load_features(export_features(seq, cache / f"{seq.name}.features.npz", args))
        greys = [grey_image(seq / f"{k + 1}.png") for k in range(len(frames))]
        hgt, w = greys[0].shape
        refined = [refined_sizes(g, f.keypoints) for g, f in zip(greys, frames)]
        sift = [sift_keypoints(g) for g in greys]
        fast_sizes += [f.keypoints[:, 2] for f in frames]
        sift_sizes += [k[:, 2] for k in sift]
        sifts.append(sift)
        for k in range(1, len(frames)):
            h = np.loadtxt(seq / f"H_1_{k + 1}")
            z = zoom_at(h, w / 2.0, hgt / 2.0)
            label = next((b[0] for b in BINS if b[1] <= z < b[2]), None)
            res, errs = pair_shares(frames[0].keypoints, frames[k].keypoints, h, refined[0], refined[k])
            angle_errs += errs
            if label is None or not res:
                continue
            for v in VARIANTS[:-1]:
                by_bin[label][v].append(res[v])
            pairs_seen.append((label, len(sifts) - 1, k, h))
    factor = float(np.median(np.concatenate(fast_sizes)) / np.median(np.concatenate(sift_sizes)))
    sift_errs = []
    for label, n, k, h in pairs_seen:
        sift = sifts[n]
        res, errs = sift_shares(sift[0], sift[k], h, factor)
        sift_errs += errs
        if res is not None:
            by_bin[label]["S"].append(res)
    print(f"{len(seqs)} sequences; ring samples (centre left out) shared above chance, within 3 px / within the")
    print("sample's own box half-width; mean over pairs of the mean over corresponding keypoints\n")
    print("| zoom | pairs | " + " | ".join(VARIANTS) + " |")
    print("|---|---|" + "---|" * len(VARIANTS))
    for label, _, _ in BINS:
        rows = by_bin[label]
        n = len(rows["A"])
        if not n:
            continue
        cells = [f"{np.mean([r[0] for r in rows[v]]):.3f} / {np.mean([r[1] for r in rows[v]]):.3f}" for v in VARIANTS]
        print(f"| {label} | {n} | " + " | ".join(cells) + " |")
    table = {label: {"pairs": len(by_bin[label]["A"]), **{v: np.mean(by_bin[label][v], 0).tolist() for v in VARIANTS}}
             for label, _, _ in BINS if by_bin[label]["A"]}
    (HERE / "frames.json").write_text(json.dumps(table, indent=1) + "\n")
    e = np.abs(np.array(angle_errs))
    print(f"\nFREAK angle of A's keypoint against the exact angle, |error| in degrees over {len(e)} keypoints: "
          f"median {np.median(e):.1f}, 75th percentile {np.percentile(e, 75):.1f}, 90th {np.percentile(e, 90):.1f}")
    e = np.abs(np.array(sift_errs))
    print(f"SIFT angle nearest the exact one among S's candidates, |error| in degrees, over {len(e)} keypoints: median {np.median(e):.1f}, "
          f"75th percentile {np.percentile(e, 75):.1f}, 90th {np.percentile(e, 90):.1f}; S's size factor {factor:.3f}")


if __name__ == "__main__":
    main()
