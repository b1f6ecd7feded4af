"""Golden fixture for the Rust parity test: features the Rust code extracts from a committed real image, and
the embeddings Python onnxruntime computes for exactly those features with the committed model.

`python -m scone_train.model.golden [--model ../models/scone-freak-k20.onnx] [--image ../tests/fixtures/astronaut.jpg]`
writes `tests/fixtures/golden/<image>.features.npz` (the export layout) and `<image>.embeddings.npy`, plus
`golden.json` with the model's sha256. The Rust test re-extracts the image and requires identical features,
then runs the model through `ort` and requires max |difference| <= 1e-4.

A ring-context model (`--model ../models/scone-ring-e1-real.onnx --out ../tests/fixtures/golden-ring`) is
extracted at the extraction its metadata declares, and its fixture is one file, `<image>.ring.npz`: keypoints,
descriptors, ring contexts and embeddings (the export layout's constellations are not what it reads).
"""

from __future__ import annotations

import argparse
import json
import subprocess
from pathlib import Path

import numpy as np
import onnx

from ..data.features import REVISION_2_EXTRACTION, extractor_args, load_features
from ..paths import REPO, scone_binary
from .export import EXTRACTION_KEY, run_onnx, session, sha256


def declared_extraction(model: Path) -> dict:
    """The extraction the model's metadata declares; revision 2's for a model that declares none."""
    props = {p.key: p.value for p in onnx.load(str(model), load_external_data=False).metadata_props}
    return json.loads(props[EXTRACTION_KEY]) if EXTRACTION_KEY in props else dict(REVISION_2_EXTRACTION)


def make_golden(model: Path, image: Path, out_dir: Path) -> dict:
    out_dir.mkdir(parents=True, exist_ok=True)
    stem = image.stem
    extraction = declared_extraction(model)
    feats_path = out_dir / f"{stem}.features.npz"
    subprocess.run(
        [str(scone_binary()), "extract", str(image), "--out", str(feats_path), "--opencv-threads", "1"]
        + extractor_args(extraction),
        check=True,
        stdout=subprocess.DEVNULL,
    )
    _, frames = load_features(feats_path)
    f = frames[0]
    sess = session(model, threads=1)
    if "context" in [i.name for i in sess.get_inputs()]:
        emb = run_onnx(sess, f.descriptors, f.context)
        feats_path.unlink()
        np.savez(out_dir / f"{stem}.ring.npz", keypoints=f.keypoints, descriptors=f.descriptors, context=f.context,
                 embeddings=emb.astype(np.float32))
    else:
        emb = run_onnx(sess, f.descriptors, f.keypoints[:, [3, 2]], f.neighbours, f.mask, f.relative)
        np.save(out_dir / f"{stem}.embeddings.npy", emb.astype(np.float32))
    info = {"image": image.name, "model": model.name, "model_sha256": sha256(model), "extraction": extraction,
            "keypoints": int(len(f)), "dim": int(emb.shape[1])}
    (out_dir / "golden.json").write_text(json.dumps(info, indent=2) + "\n")
    return info


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--model", default=str(REPO / "models" / "scone-freak-k20.onnx"))
    ap.add_argument("--image", default=str(REPO / "tests" / "fixtures" / "astronaut.jpg"))
    ap.add_argument("--out", default=str(REPO / "tests" / "fixtures" / "golden"))
    a = ap.parse_args()
    print(json.dumps(make_golden(Path(a.model), Path(a.image), Path(a.out)), indent=2))


if __name__ == "__main__":
    main()
