"""The Python binding against the CLI: same bytes as `faultcam apply`, errors, effect specs,
the GIL released while the chain runs, and the albumentations transform."""

from __future__ import annotations

import os
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
import pytest

import faultcam

ROOT = Path(__file__).resolve().parents[4]

CONFIG = """
seed = 3

[[effects]]
name = "vignetting"
strength = 0.4

[[effects]]
name = "defocus"
sigma_px = 1.3

[[effects]]
name = "shot_noise"
gain_e_per_dn = 2.0

[[effects]]
name = "hot_pixels"
rate = 0.002

[[effects]]
name = "gaussian_noise"
sigma_dn = 3.0

[[effects]]
name = "row_noise"
sigma_dn = 1.5

[[effects]]
name = "gain_offset"
gain = 1.1
offset_dn = 4.0

[[effects]]
name = "jpeg"
quality = 70
"""


@pytest.fixture(scope="session")
def faultcam_bin() -> Path:
    """The CLI of the same checkout (target/debug/faultcam, built if missing; or $FAULTCAM_BIN)."""
    if os.environ.get("FAULTCAM_BIN"):
        return Path(os.environ["FAULTCAM_BIN"])
    b = ROOT / "target" / "debug" / "faultcam"
    if not b.exists():
        subprocess.run(["cargo", "build", "--bin", "faultcam"], cwd=ROOT, check=True)
    return b


@pytest.fixture()
def config(tmp_path: Path) -> Path:
    p = tmp_path / "faults.toml"
    p.write_text(CONFIG)
    return p


def scene(h: int, w: int, kind: str, k: int) -> np.ndarray:
    """A deterministic test scene (gradients, a bright disc, texture), different per frame k."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    base = 0.15 + 0.6 * x / w + 0.2 * np.sin(y / 5.0 + k)
    disc = ((x - w / 2 - 3 * k) ** 2 + (y - h / 2) ** 2) < (min(h, w) / 5) ** 2
    v = np.clip(base + 0.5 * disc, 0.0, 1.0)
    if kind == "mono16":
        return np.round(v * 65535).astype(np.uint16)
    if kind == "rgb8":
        return np.round(np.stack([v, v[::-1], 1.0 - v], axis=-1) * 255).astype(np.uint8)
    return np.round(v * 255).astype(np.uint8)


def write_pnm(path: Path, img: np.ndarray) -> None:
    h, w = img.shape[:2]
    if img.ndim == 3:
        path.write_bytes(f"P6\n{w} {h}\n255\n".encode() + img.tobytes())
    elif img.dtype == np.uint16:
        path.write_bytes(f"P5\n{w} {h}\n65535\n".encode() + img.astype(">u2").tobytes())
    else:
        path.write_bytes(f"P5\n{w} {h}\n255\n".encode() + img.tobytes())


def read_pnm(path: Path, like: np.ndarray) -> np.ndarray:
    data = path.read_bytes()
    # magic, width, height, maxval, then one whitespace byte
    fields, i = 0, 2
    while fields < 3:
        while data[i : i + 1].isspace():
            i += 1
        while not data[i : i + 1].isspace():
            i += 1
        fields += 1
    body = data[i + 1 :]
    dt = ">u2" if like.dtype == np.uint16 else np.uint8
    return np.frombuffer(body, dtype=dt).astype(like.dtype).reshape(like.shape)


@pytest.mark.parametrize("kind", ["mono8", "mono16", "rgb8"])
def test_same_bytes_as_faultcam_apply(tmp_path, config, faultcam_bin, kind):
    frames = [scene(48, 80, kind, k) for k in range(4)]
    src, dst = tmp_path / "in", tmp_path / "out"
    src.mkdir()
    for k, f in enumerate(frames):
        write_pnm(src / f"f{k:03}.pnm", f)
    subprocess.run(
        [str(faultcam_bin), "apply", "--in", str(src), "--out", str(dst), "--faults", str(config),
         "--seed", "11", "--format", "pgm"],
        check=True, capture_output=True,
    )
    chain = faultcam.Chain.from_toml(config, seed=11)
    assert chain.seed == 11
    ext = "ppm" if kind == "rgb8" else "pgm"
    # Out of order on purpose: each frame's faults depend only on (seed, index, effect).
    for k in [2, 0, 3, 1]:
        out, rec = chain.apply(frames[k], frame_index=k)
        want = read_pnm(dst / f"f{k:03}.{ext}", frames[k])
        assert out.dtype == frames[k].dtype and out.shape == frames[k].shape
        assert np.array_equal(out, want), f"{kind} frame {k}: {np.count_nonzero(out != want)} samples differ"
        assert np.count_nonzero(out != frames[k]) > out.size // 4, "the faults changed the image"
        assert rec["seq"] == k and rec["status"] == "delivered"
        assert [e["name"] for e in rec["effects"]] == chain.effects
        assert rec["effects"][4]["params"]["sigma_dn"] == 3.0
    # The input is not modified.
    assert np.array_equal(frames[0], scene(48, 80, kind, 0))


def test_grey_with_a_channel_axis_is_grey(config):
    img = scene(32, 40, "mono8", 0)
    chain = faultcam.Chain.from_toml(config)
    a, _ = chain.apply(img, 5)
    b, _ = chain.apply(img[:, :, None].copy(), 5)
    assert b.shape == (32, 40, 1) and np.array_equal(a, b[:, :, 0])


def test_wrong_dtype_and_shape_name_the_accepted_ones(config):
    chain = faultcam.Chain.from_toml(config)
    with pytest.raises(TypeError, match=r"float32.*uint8.*uint16"):
        chain.apply(np.zeros((8, 8), np.float32), 0)
    with pytest.raises(ValueError, match=r"\(8, 8, 4\).*\(H, W, 3\)"):
        chain.apply(np.zeros((8, 8, 4), np.uint8), 0)
    with pytest.raises(ValueError, match=r"\(H, W\)"):
        chain.apply(np.zeros((8, 8, 3), np.uint16), 0)
    with pytest.raises(ValueError, match=r"shape \(8,\)"):
        chain.apply(np.zeros(8, np.uint8), 0)
    with pytest.raises(ValueError, match="C-contiguous"):
        chain.apply(np.zeros((8, 16), np.uint8)[:, ::2], 0)
    with pytest.raises(TypeError, match="numpy.ndarray"):
        chain.apply([[0, 1]], 0)


def test_config_errors_name_file_line_and_range(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text('[[effects]]\nname = "gaussian_noise"\nsigma_dn = -4\n')
    with pytest.raises(ValueError, match=r"bad\.toml:3.*sigma_dn"):
        faultcam.Chain.from_toml(bad)
    with pytest.raises(ValueError, match="missing.toml"):
        faultcam.Chain.from_toml(tmp_path / "missing.toml")


def test_dropped_frames_return_none(tmp_path):
    p = tmp_path / "drop.toml"
    p.write_text('[[effects]]\nname = "frame_drop"\np = 1.0\n')
    out, rec = faultcam.Chain.from_toml(p).apply(np.zeros((4, 4), np.uint8), 0)
    assert out is None
    assert rec["status"] == "dropped_by_fault" and rec["dropped_by"] == "frame_drop"


def test_effects_list_with_parameter_specs():
    fx = {e["name"]: e for e in faultcam.effects()}
    assert len(fx) == 28
    g = {p["name"]: p for p in fx["gaussian_noise"]["params"]}["sigma_dn"]
    assert g["unit"] == "DN" and g["min"] <= g["default"] <= g["max"] and g["kind"] == "float"
    assert fx["gaussian_noise"]["stage"] == "readout"
    smear = {p["name"]: p for p in fx["smear"]["params"]}["direction"]
    assert smear["kind"] == "choice" and len(smear["choices"]) >= 2
    for e in fx.values():
        assert e["model"] and e["formats"]
        for p in e["params"]:
            assert p["min"] <= p["default"] <= p["max"], (e["name"], p["name"])


def test_threads_give_the_same_bytes_and_the_gil_is_released(tmp_path):
    p = tmp_path / "slow.toml"
    p.write_text('seed = 1\n[[effects]]\nname = "defocus"\nsigma_px = 6.0\n'
                 '[[effects]]\nname = "gaussian_noise"\nsigma_dn = 2.0\n')
    img = scene(700, 900, "rgb8", 0)
    serial = [faultcam.Chain.from_toml(p).apply(img, k)[0] for k in range(4)]
    results = [None] * 4

    def work(k):
        results[k] = faultcam.Chain.from_toml(p).apply(img, k)[0]

    ts = [threading.Thread(target=work, args=(k,)) for k in range(4)]
    for t in ts:
        t.start()
    for t in ts:
        t.join()
    assert all(np.array_equal(a, b) for a, b in zip(serial, results))

    # While one apply call runs, a pure-Python thread keeps counting (it could not if the
    # call held the GIL).
    chain = faultcam.Chain.from_toml(p)
    count, stop = [0], threading.Event()

    def spin():
        while not stop.is_set():
            count[0] += 1

    t = threading.Thread(target=spin)
    t.start()
    time.sleep(0.05)
    before = count[0]
    t0 = time.perf_counter()
    chain.apply(img, 0)
    dt = time.perf_counter() - t0
    during = count[0] - before
    stop.set()
    t.join()
    assert dt > 0.01, f"apply took only {dt:.4f} s: the check needs a longer call"
    assert during > 1000, f"the other thread advanced {during} times in {dt:.3f} s: GIL held?"


def test_albumentations_transform_gives_the_chain_bytes(config):
    A = pytest.importorskip("albumentations")
    imgs = [scene(40, 56, "rgb8", k) for k in range(3)]
    tf = A.Compose([faultcam.FaultcamTransform(config, seed=11)])
    chain = faultcam.Chain.from_toml(config, seed=11)
    for k, img in enumerate(imgs):
        got = tf(image=img)["image"]
        want, _ = chain.apply(img, k)
        assert np.array_equal(got, want), f"frame {k}"


CAMPAIGN = """
seed = 5

[[effects]]
name = "gaussian_noise"
sigma_dn = 2.0

[[effects]]
name = "gain_offset"

[[events]]
name = "dim"
effect = "gain_offset"
at_frame = 2
duration_frames = 3
[events.params]
gain = 0.5

[[events]]
name = "blur"
effect = "defocus"
at_s = 0.2
duration_s = 0.1
[events.params]
sigma_px = { keyframes = [[0.0, 0.5], [0.1, 2.0]] }

[[effects]]
name = "defocus"
sigma_px = 0.0
"""


def test_timeline_gives_the_bytes_of_faultcam_run_in_any_order(tmp_path, faultcam_bin):
    cfg = tmp_path / "campaign.toml"
    cfg.write_text(CAMPAIGN)
    frames = [scene(40, 64, "mono8", k) for k in range(12)]
    src, dst = tmp_path / "in", tmp_path / "out"
    src.mkdir()
    for k, f in enumerate(frames):
        write_pnm(src / f"f{k:03}.pgm", f)
    log = tmp_path / "gt.jsonl"
    subprocess.run(
        [str(faultcam_bin), "run", "--source", f"files:{src}?fps=20", "--faults", str(cfg),
         "--sink", f"files:{dst}?format=pgm", "--log", str(log)],
        check=True, capture_output=True,
    )
    chain = faultcam.Chain.from_toml(cfg, timeline=True, fps=20)
    plain = faultcam.Chain.from_toml(cfg)
    # Backwards and forwards jumps: every index still gets the states of a sequential run.
    for k in [7, 2, 3, 11, 0, 5, 4, 1, 6, 10, 8, 9]:
        out, rec = chain.apply(frames[k], frame_index=k)
        want = read_pnm(dst / f"f{k:03}.pgm", frames[k])
        assert np.array_equal(out, want), f"frame {k}: {np.count_nonzero(out != want)} samples differ"
        names = [e["name"] for e in rec["effects"]]
        assert ("gain_offset" in names) == (2 <= k < 5), f"frame {k}: {names}"
        assert ("defocus" in names) == (4 <= k < 6), f"frame {k}: {names}"  # 0.2 s .. 0.3 s at 20 fps
        assert rec["pts_ns"] == k * 50_000_000
        # Without the timeline the events never run: the same effects at their configured
        # parameters on every frame.
        plain_out, plain_rec = plain.apply(frames[k], frame_index=k)
        assert [e["name"] for e in plain_rec["effects"]] == plain.effects
        assert all(e["params"].get("gain", 1.0) == 1.0 for e in plain_rec["effects"])
    # Run in order, the events the record carries are the log's event lines.
    seq_chain = faultcam.Chain.from_toml(cfg, timeline=True, fps=20)
    got = [e for k in range(12) for e in seq_chain.apply(frames[k], frame_index=k)[1]["events"]]
    import json as _json
    logged = [r for r in map(_json.loads, log.read_text().splitlines()) if r["record"] == "event"]
    for r in logged:
        del r["record"]
    # (the run log also has the pipeline's own events, e.g. start)
    kinds = {e["event"] for e in got}
    assert [e for e in logged if e["event"] in kinds] == got
    assert any(e["event"] == "event_start" for e in got)


def test_timeline_refuses_a_bad_fps(tmp_path):
    cfg = tmp_path / "campaign.toml"
    cfg.write_text(CAMPAIGN)
    with pytest.raises(ValueError, match="fps 0"):
        faultcam.Chain.from_toml(cfg, timeline=True, fps=0)


def test_drain_returns_the_frames_reorder_holds(tmp_path):
    cfg = tmp_path / "reorder.toml"
    cfg.write_text('seed = 2\n[[effects]]\nname = "reorder"\ndepth = 3\n')
    chain = faultcam.Chain.from_toml(cfg)
    frames = [np.full((8, 10), k * 10, np.uint8) for k in range(8)]
    out = [chain.apply(f, frame_index=k) for k, f in enumerate(frames)]
    held = [rec["seq"] for img, rec in out if img is None]
    assert len(held) == 3 and all(rec["dropped_by"] == "reorder" for img, rec in out if img is None)
    rest = chain.drain()
    assert len(rest) == 3 and chain.drain() == []
    # Every input comes out exactly once: in the stream or at the end.
    values = sorted(int(img[0, 0]) for img, _ in out + rest if img is not None)
    assert values == [k * 10 for k in range(8)]
    for img, rec in rest:
        assert img.shape == (8, 10) and img.dtype == np.uint8 and rec["status"] == "delivered"
        assert int(img[0, 0]) == rec["seq"] * 10
