#!/usr/bin/env python3
"""Agreement of this client's extraction with a running server's Describe, on the committed fixtures, for the
contract and for each rule done the other way (BENCHMARKS.md, "Client contract").

    python tools/agreement.py --server 127.0.0.1:50051
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from scone_client import configure_opencv, contract  # noqa: E402
from scone_client.agreement import DEVIATIONS, compare, deviation, grey_for  # noqa: E402
from scone_client.client import SconeClient, features_from_describe, image_frame  # noqa: E402

FIXTURES = Path(__file__).resolve().parents[3] / "tests" / "fixtures"


def images() -> dict[str, bytes]:
    out = {
        "coffee-640x480.jpg": (FIXTURES / "coffee-640x480.jpg").read_bytes(),
        "astronaut.jpg": (FIXTURES / "astronaut.jpg").read_bytes(),
    }
    for p in sorted((FIXTURES / "rendered" / "rgb").glob("*.png")):
        out[f"rendered/{p.name}"] = p.read_bytes()
    colour = cv2.imread(str(FIXTURES / "coffee-640x480.jpg"), cv2.IMREAD_UNCHANGED)
    out["coffee blurred (sigma 1)"] = cv2.imencode(".png", cv2.GaussianBlur(colour, (0, 0), 1.0))[1].tobytes()
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--server", default="127.0.0.1:50051")
    args = ap.parse_args()
    configure_opencv()
    data = images()
    with SconeClient(args.server, timeout=120.0) as client:
        server = {}
        for name, blob in data.items():
            grey = contract.decode_grey(blob)
            server[name] = features_from_describe(client.describe(image_frame(blob)), grey.shape[1], grey.shape[0])
    print("| rule | images bit-exact | server keypoints | within 1 px, same bytes | within 1 px | worst image |")
    print("| --- | --- | --- | --- | --- | --- |")
    for rule in ["contract", *DEVIATIONS]:
        total = same = near = exact = 0
        worst = (2.0, "")
        for name, blob in data.items():
            with deviation(rule):
                a = compare(server[name], contract.extract(grey_for(rule, blob)))
            total, same, near, exact = (
                total + a.server,
                same + a.within_1px_same_bytes,
                near + a.within_1px,
                exact + a.bit_exact,
            )
            worst = min(worst, (a.fraction, name))
        print(
            f"| {rule} | {exact}/{len(data)} | {total} | {same} ({100 * same / total:.2f} %) | "
            f"{near} ({100 * near / total:.2f} %) | {worst[1]}: {100 * worst[0]:.2f} % |"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
