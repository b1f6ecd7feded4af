"""The real-data split: which frames of each training scene train, and which form the selection split.

Each part was written down before any model was trained on its scene (docs/model-experiments.md). The selection
parts are contiguous blocks (7-Scenes, SUN3D, templeRing) or the last images in file order (liberty, castle);
nothing of the validation scenes appears here. `python -m scone_train.data.splits --out DIR` writes each selection
part as a scene directory (a subset `rgb.txt`, the source's poses, camera and images by symlink), so
`scone eval pairs` runs on it like on any scene.

Frame specs are "a-b" (stamps a..b inclusive, in `rgb.txt` order) or "a-b:s" (every s-th of them), joined by
commas.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from ..paths import prefix_dir, shared_data
from .features import load_features
from .scenes import load_scene

# scene -> (source, training frames, selection frames, eval window of the selection part, geometry overrides).
# "refined" sources are written by scone_train.data.refine_camera under $SCONE_PREFIX/data/refined.
#
# Labelling tolerances come from the residuals measured by scone_train.data.residuals at the frame gaps the labels
# link (the rule: 75th percentile, at least 1 px epipolar / 2 px depth; third view 1.5 times the band):
# - castle: 0.30 px over all pairs -> 1 px, frames at most 3 apart (castle_window, session 4);
# - 7-Scenes: 3.4 px median over wide pairs, but 0.46 / 0.74 / 1.35 px at 3 / 10 / 30 frames apart (the error
#   is per frame, not a shared calibration: a fitted 9-value camera model and offset only took it from 3.62
#   to 3.45 px on held-out pairs). Frames every 3rd, linked at most 4 apart (12 frames): p75 at 10 frames is
#   1.52 px -> 1.6 px. Tracks chain through the links, so wide pairs still share landmarks;
# - SUN3D: depth reprojection p75 7.2 px -> radius 7.2 (depth links, every pair of the subset);
# - templeRing stamps 1-31: 0.1-0.3 px -> 1 px. Stamps 32-47 disagree with 1-31 by 170-350 px (another
#   world frame) and among themselves by 2-6 px: left out;
# - liberty: p75 3.0 px over sampled pairs -> 3.0 px; each photo linked to the 8 with the nearest optical axes.
SPLIT = {
    "strecha-castle-P30": {"source": "shared", "train": "0-19", "select": "20-29", "window": 10,
                           "geometry": {"window": 3}},
    "7scenes-redkitchen": {"source": "shared", "train": "0-799:3", "select": "800-999:10", "window": 20,
                           "geometry": {"window": 4, "epi_px": 1.6, "third_px": 2.4}},
    "sun3d-studyroom": {"source": "shared", "train": "935-974,3160-3199", "select": "975-984,3200-3209",
                        "window": 20, "geometry": {"radius": 7.2}},
    "middlebury-templeRing": {"source": "shared", "train": "1-21", "select": "22-31", "window": 10,
                              "geometry": {}},
    "liberty-internet": {"source": "shared", "train": "0-107", "select": "108-134", "window": 27,
                         "geometry": {"epi_px": 3.0, "third_px": 4.5, "neighbours": 8}},
}


# The four object and room orbits added to the training scenes (SfM or turntable poses, no depth), each split into
# a training part and a selection arc of about a quarter of the orbit, with unused frames between them so that
# no selection view lies within about 18 degrees of a training view (azimuths of the camera centres in the plane
# they span; between optical axes the nearest are 13-14 degrees). llff-blowtorch's file order is not the
# orbit's, so its parts are listed by stamp: the selection arc is the views at 95-150 degrees of azimuth, the
# unused buffer 75-95 and 150-170. Labelling tolerances by the
# rule above, from `python -m scone_train.data.residuals --gaps 1,2,3,5` (p75 of the epipolar error): the LLFF
# scenes 0.31-0.50 px at gaps up to 5 -> 1 px, linked 5 frames apart along the orbit (about 21 degrees for
# ethiopianhead, 14 for lemontea-office) or, for blowtorch, to the 8 views with the nearest optical axes;
# turntable-squirrel 0.83 / 1.61 / 2.69 px at gaps 1 / 2 / 3 -> 1.6 px, linked 2 frames (20 degrees) apart.
ORBITS = {
    "llff-ethiopianhead": {"source": "shared", "train": "0-46", "select": "50-62", "window": 13,
                           "geometry": {"window": 5}},
    "llff-blowtorch": {"source": "shared",
                       "train": "0-3,9-21,25-28,31-46,48,57-66",
                       "select": "4-6,22-24,30,47,49-56", "window": 16,
                       "geometry": {"neighbours": 8}},
    "llff-lemontea-office": {"source": "shared", "train": "0-40", "select": "44-56", "window": 13,
                             "geometry": {"window": 5}},
    "turntable-squirrel": {"source": "shared", "train": "0-23", "select": "26-33", "window": 8,
                           "geometry": {"window": 2, "epi_px": 1.6, "third_px": 2.4}},
}

# Which real training scenes a config trains on (`data.real_split`): `true` or "five" for the five above (the
# shipped model's recipe), "nine" for those and the four orbits.
SCENE_SETS = {"five": SPLIT, "nine": {**SPLIT, **ORBITS}}


def scene_set(which: bool | str = "five") -> dict:
    """The split of the real training scenes a config names (`data.real_split`)."""
    key = "five" if which is True else which
    if key not in SCENE_SETS:
        raise ValueError(f"real_split: {which!r}; known: true, {', '.join(SCENE_SETS)}")
    return SCENE_SETS[key]


def scene_dir(name: str) -> Path:
    if SCENE_SETS["nine"][name]["source"] == "refined":
        refined = prefix_dir() / "data" / "refined" / name
        if not (refined / "groundtruth.txt").exists():
            raise FileNotFoundError(f"{refined}: run python -m scone_train.data.refine_camera --scene {name} first")
        return refined
    return shared_data() / "scenes" / name


def frames(spec: str, stamps: list[str]) -> list[int]:
    """Indices into `stamps` (rgb.txt order) of the frames a spec names."""
    pos = {float(s): k for k, s in enumerate(stamps)}
    out: list[int] = []
    for part in spec.split(","):
        rng, _, step = part.partition(":")
        lo, _, hi = rng.partition("-")
        lo_f, hi_f = float(lo), float(hi or lo)
        inside = [k for s, k in sorted(pos.items()) if lo_f <= s <= hi_f]
        out += inside[:: int(step or 1)]
    return sorted(set(out))


def part(name: str, which: str) -> tuple[Path, list[int]]:
    """A scene's source directory and the `rgb.txt` indices of its "train" or "select" part."""
    src = scene_dir(name)
    stamps = [r.split()[0] for r in (src / "rgb.txt").read_text().splitlines() if r.strip() and r[0] != "#"]
    return src, frames(SCENE_SETS["nine"][name][which], stamps)


def exported_frames(cache: Path, which: str, per_scene: int, skip: int = 0, spread: int = 1,
                    scenes: dict = SPLIT) -> dict[str, list]:
    """Each real training scene's Rust-exported frames (`<cache>/<scene>.features.npz`) of its `which` part
    ("train" or "select"): at most `per_scene`, evenly spaced with a step of len(part) // (per_scene * spread),
    starting at `skip`. Scenes without exported features are left out; none at all is an error."""
    out = {}
    for name in scenes:
        npz = cache / f"{name}.features.npz"
        if not npz.exists():
            continue
        _, frames = load_features(npz)
        idx = part(name, which)[1]
        step = max(len(idx) // (per_scene * spread), 1)
        out[name] = [frames[i] for i in idx[skip::step][:per_scene]]
    if not out:
        raise FileNotFoundError(f"no exported features under {cache}: run a training config with real_split first")
    return out


def write_selection_scenes(out: Path, scenes: dict = SPLIT) -> dict[str, tuple[Path, int]]:
    """Each scene's selection part as a scene directory under `out`: name -> (directory, eval window)."""
    made = {}
    for name, spec in scenes.items():
        if name in ORBITS and not scene_dir(name).is_dir():
            continue  # a copy of the shared data without the orbits; the five are always there
        src = scene_dir(name)
        scene = load_scene(src)
        keep = frames(spec["select"], scene.stamps)
        d = out / f"{name}-sel"
        d.mkdir(parents=True, exist_ok=True)
        rows = [f"{scene.stamps[k]} {scene.rgb[k].relative_to(src)}" for k in keep]
        (d / "rgb.txt").write_text("# selection part of " + name + " (scone_train.data.splits)\n" + "\n".join(rows) + "\n")
        for f in ("groundtruth.txt", "camera.txt", "depth.txt", "rgb", "depth"):
            target = src / f
            link = d / f
            if (target.exists() or target.is_symlink()) and not (link.exists() or link.is_symlink()):
                os.symlink(target.resolve(), link)
        made[name] = (d, spec["window"])
    return made


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", required=True)
    ap.add_argument("--scenes", default="five", choices=sorted(SCENE_SETS), help="which real training scenes")
    args = ap.parse_args()
    for name, (d, window) in write_selection_scenes(Path(args.out), SCENE_SETS[args.scenes]).items():
        print(f"{name}\t{d}\t{window}")


if __name__ == "__main__":
    main()
