"""faultcam vs albumentations in the same Python process, on the same images.

    ./scripts/build-python.sh --release
    target/py-venv/bin/python crates/pyfaultcam/python/bench.py [--size 1024] [--frames 30]

Three comparable operations, each alone and as one chain: Gaussian blur (faultcam `defocus`,
sigma 1.5 px / albumentations GaussianBlur sigma 1.5), additive Gaussian noise (faultcam
`gaussian_noise`, sigma 5 DN / GaussNoise std 5/255) and JPEG at quality 70 (faultcam `jpeg` /
ImageCompression). Prints the median wall time per frame (ms) over --frames calls after two
warm-up calls, for 8-bit grey and RGB. Both libraries use their default threading.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

import faultcam

try:
    import albumentations as A
except ImportError:
    A = None

FAULTS = {
    "blur": '[[effects]]\nname = "defocus"\nsigma_px = 1.5\n',
    "noise": '[[effects]]\nname = "gaussian_noise"\nsigma_dn = 5.0\n',
    "jpeg": '[[effects]]\nname = "jpeg"\nquality = 70\n',
}


def albu(name: str):
    if name == "blur":
        return A.GaussianBlur(blur_limit=(0, 0), sigma_limit=(1.5, 1.5), p=1.0)
    if name == "noise":
        return A.GaussNoise(std_range=(5 / 255, 5 / 255), mean_range=(0.0, 0.0), p=1.0)
    return A.ImageCompression(quality_range=(70, 70), p=1.0)


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def median_ms(fn, frames: int) -> float:
    fn(0)
    fn(1)
    times = []
    for k in range(frames):
        t0 = time.perf_counter()
        fn(k)
        times.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--frames", type=int, default=30)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    n = args.size
    y, x = np.mgrid[0:n, 0:n]
    grey = np.clip(128 + 80 * np.sin(x / 17.0) * np.cos(y / 23.0) + rng.normal(0, 4, (n, n)), 0, 255).astype(np.uint8)
    images = {"mono8": grey, "rgb8": np.ascontiguousarray(np.stack([grey, grey[::-1], 255 - grey], -1))}
    print(f"# {n}x{n}, median of {args.frames} frames, CPU {cpu_model()} ({os.cpu_count()} logical cores)")
    print(f"# faultcam {faultcam.__version__}, albumentations {A.__version__ if A else 'not installed'}")
    print("| operation | format | faultcam ms/frame | albumentations ms/frame |")
    print("|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        cases = list(FAULTS) + ["blur+noise+jpeg"]
        for case in cases:
            parts = case.split("+")
            cfg = Path(tmp) / f"{case}.toml"
            cfg.write_text("seed = 1\n" + "\n".join(FAULTS[p] for p in parts))
            chain = faultcam.Chain.from_toml(cfg)
            pipe = A.Compose([albu(p) for p in parts], seed=1) if A else None
            for fmt, img in images.items():
                fc = median_ms(lambda k: chain.apply(img, k), args.frames)
                al = median_ms(lambda k: pipe(image=img), args.frames) if pipe else float("nan")
                print(f"| {case} | {fmt} | {fc:.2f} | {al:.2f} |")


if __name__ == "__main__":
    main()
