#!/usr/bin/env python3
"""Held-out concealed-effect corpus for `faultcam diagnose` (issue 13, part 1).

Written from the effect vocabulary (EFFECTS.md: names, parameters, units, report contract) only:
it shares no code and no forms with faultcam's effects or with tests/support/realcam.rs. Nothing
in faultcam may be tuned on this corpus; it is generated and scored, that is all.

    python3 tools/corpus2/gen.py [OUT]          # write every case (default target/corpus2)
    python3 tools/corpus2/gen.py OUT CASE ...   # only the named cases
    python3 tools/corpus2/gen.py --check        # determinism + "hidden at or below the noise"
    python3 tools/corpus2/gen.py --list         # case names, scenes, formats, hidden effects

Each case is a folder `CASE/` with `sim/` (what a simulator renders: the noise-free scene in DN,
clipped to full scale and rounded to the case's bit depth), `real/` (the same scenes through the
camera below plus the hidden effects) with 4 frames each of 640x400, mono or RGB, and
`truth.json` (hidden effects with their EFFECTS.md parameters, the camera, the effect forms and
the measured size of each hidden effect against the noise).

Units: the scene is rendered in DN of an 8-bit image (full scale FS = 255, may exceed FS before
clipping); every parameter "in DN" in truth.json is in 8-bit DN, whatever the file's bit depth.
10- and 12-bit data are stored in 16-bit PNG by bit replication (code << (16 - b) | code >> (2b - 16)),
so full scale is 65535 and 16-bit DN / 257 = 8-bit DN.

Camera (the same for negative controls and effect cases):
  * photo-electrons Poisson with conversion gain g e-/DN (per 8-bit DN), read noise Gaussian
    sigma_r DN, ADC at b bits (8, 10 or 12) with a pedestal of P codes that the pipeline
    subtracts digitally; the analog pedestal differs from the nominal by a fraction of a code
    (at most 0.25 8-bit DN), below any tolerance;
  * a mild integral nonlinearity u' = u + beta u (1 - u) (u = signal / FS, |beta| <= 0.004, at most
    0.26 DN), below any tolerance;
  * the ADC clips at 0 and at full scale (the sensor's well is deeper than the ADC range).
Hidden effect forms (each a different form from the first corpus):
  defocus      Airy pattern (truth sigma_px = 0.42 lambda N, the best Gaussian; Airy first zero
               at 1.22 lambda N) or pillbox of radius R (truth sigma_px = R / 2, its per-axis std)
  motion_blur  continuous line segment of length L, 16x supersampled into the kernel
  vignetting   polynomial 1 - s (a r^2 + (1 - a) r^4) or natural cos^4 fall-off with the focal
               length chosen so the corner gain is 1 - s (r = 1 at the corners)
  stray_light  exponential lobe A exp(-d / L) of an off-frame source, scaled to its in-frame max
  lens_flare   hexagonal soft-edged ghosts on the source-centre line, plateaus i_k FS,
               truth intensity = mean i_k
  channel_shift  Fourier (band-limited) translation of R and B, reflect-padded
  prnu         per-pixel Gaussian gain 1 + sigma n, fixed per recording
  blooming     charge above W = f FS diffuses with a Gaussian of std spread_px, repeated until no
               pixel exceeds W (at most 60 rounds); saturated pixels read W
  smear        vertical/horizontal frame-transfer smear: strength FS per pixel whose charge
               reached FS in the column/row (Poisson like the rest of the charge)
  dark_current Poisson dark electrons of mean mean_dn, hot pixels (rate) with log-uniform
               20-120 DN extra dark signal, fixed per recording
  row_noise    per-frame row offsets with a 1/f power spectrum along y (no DC term), each frame
               scaled to RMS sigma_dn
  gain_offset  digital v = gain v + offset_dn after the ADC
  gamma        power law FS (v/FS)^gamma, or a generalised sRGB curve (linear toe, offset power
               segment (1 + a) x^(1/p) - a); for it the truth gamma is the least-squares power-law
               exponent on x in [0, 1]
  jpeg         Pillow/libjpeg at quality q with 4:2:0 or 4:4:4 chroma subsampling (8-bit only)
"""

import hashlib
import json
import math
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import bootstrap as _venv  # noqa: E402

_venv.ensure()

import numpy as np  # noqa: E402
from PIL import Image  # noqa: E402

W, H, FRAMES, FS = 640, 400, 4, 255.0
REPO = _venv.REPO

# ----------------------------------------------------------------------------------------------
# small numeric helpers


def bessel_j1(x):
    """J1 by its integral form (1/pi) int_0^pi cos(t - x sin t) dt (Simpson, 256 intervals)."""
    x = np.asarray(x, dtype=np.float64)
    t = np.linspace(0.0, math.pi, 257)
    w = np.ones(257)
    w[1:-1:2] = 4.0
    w[2:-1:2] = 2.0
    w *= (math.pi / 256) / 3.0
    vals = np.cos(t[None, :] - x.reshape(-1, 1) * np.sin(t)[None, :])
    return (vals @ w / math.pi).reshape(x.shape)


def erf(x):
    return np.vectorize(math.erf, otypes=[np.float64])(x)


def fft_convolve(img, kern):
    """2-D convolution of each channel with `kern` (odd size, centred), edge-replicated borders."""
    kh, kw = kern.shape
    py, px = kh // 2, kw // 2
    out = np.empty_like(img)
    ph, pw = img.shape[0] + 2 * py, img.shape[1] + 2 * px
    kpad = np.zeros((ph, pw))
    kpad[:kh, :kw] = kern
    kpad = np.roll(kpad, (-py, -px), axis=(0, 1))
    kf = np.fft.rfft2(kpad)
    for c in range(img.shape[2]):
        p = np.pad(img[:, :, c], ((py, py), (px, px)), mode="edge")
        r = np.fft.irfft2(np.fft.rfft2(p) * kf, s=p.shape)
        out[:, :, c] = r[py : py + img.shape[0], px : px + img.shape[1]]
    return out


def fourier_shift(plane, dx, dy, pad=24):
    """Translate a plane by (dx, dy) px (+dx right, +dy down), band-limited, reflect-padded."""
    p = np.pad(plane, pad, mode="reflect")
    fy = np.fft.fftfreq(p.shape[0])[:, None]
    fx = np.fft.rfftfreq(p.shape[1])[None, :]
    ph = np.exp(-2j * math.pi * (fx * dx + fy * dy))
    r = np.fft.irfft2(np.fft.rfft2(p) * ph, s=p.shape)
    return r[pad:-pad, pad:-pad]


def fractal_noise(rng, h, w, beta):
    """Periodic Gaussian field with power spectrum f^-beta, zero mean, unit std (spectrum kept
    so it can be shifted by a phase ramp)."""
    fy = np.fft.fftfreq(h)[:, None]
    fx = np.fft.rfftfreq(w)[None, :]
    f = np.sqrt(fx**2 + fy**2)
    f[0, 0] = 1.0
    amp = f ** (-beta / 2.0)
    amp[0, 0] = 0.0
    spec = amp * (rng.standard_normal(amp.shape) + 1j * rng.standard_normal(amp.shape))
    field = np.fft.irfft2(spec, s=(h, w))
    s = field.std()
    return spec / s


def field_from_spec(spec, h, w, dx=0.0, dy=0.0):
    fy = np.fft.fftfreq(h)[:, None]
    fx = np.fft.rfftfreq(w)[None, :]
    return np.fft.irfft2(spec * np.exp(-2j * math.pi * (fx * dx + fy * dy)), s=(h, w))


def supersample(fn, h, w, ox, oy, ss=3):
    """Average fn(x, y) over ss x ss sub-pixel samples; (x, y) are pixel coordinates of the
    scene moved by (ox, oy)."""
    acc = None
    for j in range(ss):
        for i in range(ss):
            ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
            v = fn(xs + (i + 0.5) / ss - 0.5 - ox, ys + (j + 0.5) / ss - 0.5 - oy)
            acc = v if acc is None else acc + v
    return acc / (ss * ss)


def smoothstep_edge(d, width=0.7):
    """Soft indicator of d < 0 (d a signed distance in px)."""
    return np.clip(0.5 - d / width, 0.0, 1.0)


# ----------------------------------------------------------------------------------------------
# scenes: render(k) -> float (H, W, C) in 8-bit DN, may exceed FS


class Planet:
    """Planetary surface: fractal heightfield with craters, hill-shaded by a low sun, an albedo
    field, and a few saturated ice glints; drifts under the camera frame to frame."""

    def __init__(self, rng, channels):
        self.c = channels
        self.hspec = fractal_noise(rng, H, W, 4.4)
        self.aspec = fractal_noise(rng, H, W, 2.6)
        n = 38
        self.craters = np.column_stack(
            [rng.uniform(0, W, n), rng.uniform(0, H, n), np.exp(rng.uniform(np.log(10), np.log(55), n))]
        )
        az = rng.uniform(0, 2 * math.pi)
        el = math.radians(rng.uniform(22, 40))
        self.sun = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        self.glints = np.column_stack([rng.uniform(40, W - 40, 4), rng.uniform(40, H - 40, 4)])
        self.tint = np.array([1.0, 0.84, 0.68]) if channels == 3 else np.array([1.0])
        self.drift = rng.uniform(-1.2, 1.2, 2)

    def render(self, k):
        dx, dy = self.drift * k
        hgt = 5.0 * field_from_spec(self.hspec, H, W, dx, dy)
        ys, xs = np.mgrid[0:H, 0:W].astype(np.float64)
        for cx, cy, r in self.craters:
            ddx = (xs - cx - dx + W / 2) % W - W / 2
            ddy = (ys - cy - dy + H / 2) % H - H / 2
            rr = np.sqrt(ddx**2 + ddy**2) / r
            bowl = np.where(rr < 1, -(1 - rr**2), 0.0) * 0.5 * r
            rim = 0.12 * r * np.exp(-(((rr - 1.0) / 0.3) ** 2))
            hgt += bowl + rim
        gy, gx = np.gradient(hgt)
        nrm = np.sqrt(gx**2 + gy**2 + 1.0)
        shade = np.clip((-gx * self.sun[0] - gy * self.sun[1] + self.sun[2]) / nrm, 0.0, None)
        albedo = 0.75 + 0.12 * field_from_spec(self.aspec, H, W, dx, dy)
        base = 14.0 + 230.0 * albedo * shade
        for gxp, gyp in self.glints:
            d2 = (xs - gxp - dx) ** 2 + (ys - gyp - dy) ** 2
            base += 700.0 * np.exp(-d2 / (2 * 1.6**2))
        return base[:, :, None] * self.tint[None, None, :]


class Docking:
    """Docking target: dark space, a textured grey plate with concentric-ring and dot fiducials,
    a raised standoff cross and saturated retro-reflectors; plate drifts and turns slowly."""

    def __init__(self, rng, channels):
        self.c = channels
        self.cx, self.cy = W / 2 + rng.uniform(-40, 40), H / 2 + rng.uniform(-25, 25)
        self.ang0 = rng.uniform(-0.2, 0.2)
        self.half = rng.uniform(120, 150)
        self.tex = fractal_noise(rng, H, W, 2.0)
        self.motion = rng.uniform(-1.0, 1.0, 3) * np.array([1.0, 1.0, 0.004])
        self.reflector_r = rng.uniform(2.2, 3.2)

    def render(self, k):
        cx, cy = self.cx + self.motion[0] * k, self.cy + self.motion[1] * k
        ang = self.ang0 + self.motion[2] * k
        ca, sa = math.cos(ang), math.sin(ang)
        half, rr = self.half, self.reflector_r

        def fn(x, y):
            u = ca * (x - cx) + sa * (y - cy)
            v = -sa * (x - cx) + ca * (y - cy)
            val = np.full(x.shape, 5.0)
            plate = smoothstep_edge(np.maximum(np.abs(u), np.abs(v)) - half)
            val = val + plate * 85.0
            r = np.sqrt(u**2 + v**2)
            # concentric ring fiducial: alternating black/white rings out to 0.45 half
            ring = np.floor(r / (0.09 * half)).astype(int)
            inner = smoothstep_edge(r - 0.45 * half)
            val = np.where(inner > 0, val * (1 - inner) + inner * np.where(ring % 2 == 0, 215.0, 18.0), val)
            # standoff cross (bright arms with a dark shadow offset)
            arm = (np.abs(u) < 0.05 * half) & (np.abs(v) < 0.3 * half) | (np.abs(v) < 0.05 * half) & (
                np.abs(u) < 0.3 * half
            )
            sh = (np.abs(u - 6) < 0.05 * half) & (np.abs(v - 6) < 0.3 * half) | (np.abs(v - 6) < 0.05 * half) & (
                np.abs(u - 6) < 0.3 * half
            )
            val = np.where(sh & ~arm, 30.0, val)
            val = np.where(arm, 235.0, val)
            # corner dot fiducials (white) and retro-reflectors (saturated)
            for su, sv in ((-0.78, -0.78), (0.78, -0.78), (-0.78, 0.78), (0.78, 0.78)):
                d = np.sqrt((u - su * half) ** 2 + (v - sv * half) ** 2)
                m = smoothstep_edge(d - 0.08 * half)
                val = val * (1 - m) + 200.0 * m
            for su, sv in ((0.0, -0.66), (0.62, 0.2), (-0.62, 0.3)):
                d = np.sqrt((u - su * half) ** 2 + (v - sv * half) ** 2)
                m = smoothstep_edge(d - rr)
                val = val * (1 - m) + 450.0 * m
            return val

        img = supersample(fn, H, W, 0.0, 0.0)
        tex = field_from_spec(self.tex, H, W, self.motion[0] * k, self.motion[1] * k)
        img = img * (1.0 + 0.06 * tex * (img > 40) * (img < 300))
        if self.c == 3:
            return np.stack([img * 1.0, img * 0.97, img * 0.92], axis=2)
        return img[:, :, None]


class Stars:
    """Star field: faint sky with a zodiacal gradient, power-law star fluxes through a Gaussian
    optical PSF (pixel-integrated), a few saturated stars and a lit planet limb in a corner."""

    def __init__(self, rng, channels):
        self.c = channels
        n = 420
        self.pos = np.column_stack([rng.uniform(-10, W + 10, n), rng.uniform(-10, H + 10, n)])
        self.flux = 60.0 * rng.pareto(1.1, n) + 40.0  # DN*px^2
        bright = rng.choice(n, 3, replace=False)
        self.flux[bright] = rng.uniform(9000, 20000, 3)
        self.col = np.clip(rng.normal(1.0, 0.12, (n, 3)), 0.7, 1.3)
        self.psf = rng.uniform(0.8, 1.05)
        self.drift = rng.uniform(-0.6, 0.6, 2)
        self.limb = (rng.uniform(0.0, 1.0) < 0.5, rng.uniform(180, 260))

    def render(self, k):
        img = np.zeros((H, W, self.c))
        ys, xs = np.mgrid[0:H, 0:W].astype(np.float64)
        sky = 4.0 + 3.0 * xs / W + 1.5 * ys / H
        img += sky[:, :, None]
        left, rad = self.limb
        ccx = -0.55 * rad if left else W + 0.55 * rad
        d = np.sqrt((xs - ccx) ** 2 + (ys - (H + 0.3 * rad)) ** 2) - 1.7 * rad
        limb = smoothstep_edge(d, 1.2) * (40.0 + 110.0 * np.clip(-d / (0.4 * rad), 0, 1) ** 0.5)
        img += limb[:, :, None]
        s = self.psf * math.sqrt(2.0)
        for (x0, y0), f, col in zip(self.pos + self.drift * k, self.flux, self.col):
            r = int(min(14, 4 + 2 * math.log10(max(f, 1))))
            ix, iy = int(round(x0)), int(round(y0))
            xa, xb, ya, yb = max(ix - r, 0), min(ix + r + 1, W), max(iy - r, 0), min(iy + r + 1, H)
            if xa >= xb or ya >= yb:
                continue
            ex = np.arange(xa, xb + 1) - 0.5 - x0
            ey = np.arange(ya, yb + 1) - 0.5 - y0
            px = np.diff(erf(ex / s)) / 2
            py = np.diff(erf(ey / s)) / 2
            stamp = f * np.outer(py, px)
            cc = col if self.c == 3 else np.array([1.0])
            img[ya:yb, xa:xb, :] += stamp[:, :, None] * cc[None, None, :]
        return img


class Lab:
    """Lab backdrop: a lamp-lit wall, a bench, a grey step wedge and a colour chart, a
    checkerboard plate, boxes, a cable, and a saturated lamp; small camera shake per frame."""

    def __init__(self, rng, channels):
        self.c = channels
        self.lamp = (rng.uniform(0.15, 0.85) * W, rng.uniform(0.08, 0.3) * H)
        self.wall = np.array([1.0, 0.93, 0.82]) if channels == 3 else np.array([1.0])
        self.patches = rng.uniform(0.15, 1.0, (6, 3)) if channels == 3 else np.ones((6, 1))
        self.shake = rng.normal(0, 0.6, (FRAMES, 2))
        self.bench = rng.uniform(0.68, 0.76) * H
        self.boxes = [(rng.uniform(0.05, 0.35) * W, rng.uniform(50, 110), rng.uniform(40, 90), rng.uniform(60, 170))]
        self.boxes.append((rng.uniform(0.6, 0.8) * W, rng.uniform(50, 100), rng.uniform(40, 80), rng.uniform(60, 170)))

    def render(self, k):
        ox, oy = self.shake[k]
        lx, ly = self.lamp
        bench, boxes, patches = self.bench, self.boxes, self.patches
        chans = []
        for c in range(self.c):

            def fn(x, y, c=c):
                d2 = (x - lx) ** 2 + (y - ly) ** 2
                wall = (55.0 + 120.0 / (1.0 + d2 / (260.0**2))) * self.wall[c]
                val = np.where(y < bench, wall, 38.0 + 10.0 * (x / W))
                # step wedge: 10 grey patches 8..245 DN
                for i in range(10):
                    x0 = 0.18 * W + i * 26
                    m = (x >= x0) & (x < x0 + 24) & (y >= 0.52 * H) & (y < 0.52 * H + 30)
                    val = np.where(m, 8.0 + i * 26.3, val)
                # colour chart
                for i in range(6):
                    x0 = 0.18 * W + i * 43
                    m = (x >= x0) & (x < x0 + 40) & (y >= 0.61 * H) & (y < 0.61 * H + 22)
                    val = np.where(m, 30.0 + 170.0 * patches[i, c], val)
                # checkerboard plate
                cx0, cy0 = 0.72 * W, 0.18 * H
                inb = (x >= cx0) & (x < cx0 + 120) & (y >= cy0) & (y < cy0 + 90)
                chk = ((np.floor((x - cx0) / 15) + np.floor((y - cy0) / 15)) % 2 == 0)
                val = np.where(inb, np.where(chk, 190.0, 25.0), val)
                # boxes on the bench (lit top face, darker front)
                for bx, bw, bh, lvl in boxes:
                    front = (x >= bx) & (x < bx + bw) & (y >= bench - bh) & (y < bench)
                    top = (x >= bx + 8) & (x < bx + bw + 8) & (y >= bench - bh - 8) & (y < bench - bh)
                    val = np.where(top, lvl * 1.25, np.where(front, lvl * 0.7, val))
                # cable: dark sinuous curve
                cy = 0.9 * H + 10.0 * np.sin(x / 37.0)
                val = np.where(np.abs(y - cy) < 2.5, 12.0, val)
                # lamp bulb
                d = np.sqrt(d2)
                m = smoothstep_edge(d - 7.0)
                return val * (1 - m) + 1400.0 * m

            chans.append(supersample(fn, H, W, ox, oy, ss=2))
        return np.stack(chans, axis=2)


SCENES = {"planet": Planet, "docking": Docking, "stars": Stars, "lab": Lab}

# ----------------------------------------------------------------------------------------------
# effect kernels and fields


def airy_kernel(sigma):
    """Airy intensity (2 J1(v)/v)^2 with first zero r0 = 1.22 lambda N, lambda N = sigma / 0.42,
    integrated over pixels by 5x5 supersampling, truncated at 4 r0, normalised."""
    ln = sigma / 0.42
    r0 = 1.22 * ln
    rad = int(math.ceil(4 * r0)) + 1
    ss = 5
    o = (np.arange(ss) + 0.5) / ss - 0.5
    g = np.arange(-rad, rad + 1, dtype=np.float64)
    X = (g[None, :, None, None] + o[None, None, None, :]).repeat(2 * rad + 1, 0).repeat(ss, 2)
    Y = (g[:, None, None, None] + o[None, None, :, None]).repeat(2 * rad + 1, 1).repeat(ss, 3)
    r = np.sqrt(X**2 + Y**2)
    v = math.pi * r / ln
    vs = np.where(v < 1e-9, 1e-9, v)
    j = bessel_j1(vs.ravel()).reshape(vs.shape)
    inten = (2 * j / vs) ** 2
    k = inten.mean(axis=(2, 3))
    return k / k.sum()


def pillbox_kernel(radius):
    rad = int(math.ceil(radius)) + 1
    ss = 8
    o = (np.arange(ss) + 0.5) / ss - 0.5
    k = np.zeros((2 * rad + 1, 2 * rad + 1))
    for j, y in enumerate(range(-rad, rad + 1)):
        for i, x in enumerate(range(-rad, rad + 1)):
            xx = x + o[None, :]
            yy = y + o[:, None]
            k[j, i] = np.mean(xx**2 + yy**2 <= radius**2)
    return k / k.sum()


def line_kernel(length, angle_deg):
    """Normalised segment of `length` px at `angle_deg` counter-clockwise from +x as displayed
    (image y down, so the segment's y component is -sin)."""
    a = math.radians(angle_deg)
    dxu, dyu = math.cos(a), -math.sin(a)
    rad = int(math.ceil(length / 2)) + 2
    k = np.zeros((2 * rad + 1, 2 * rad + 1))
    n = max(16, int(16 * length))
    t = (np.arange(n) + 0.5) / n - 0.5
    xs, ys = t * length * dxu + rad, t * length * dyu + rad
    x0, y0 = np.floor(xs).astype(int), np.floor(ys).astype(int)
    fx, fy = xs - x0, ys - y0
    for ddx, ddy, w in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
        np.add.at(k, (y0 + ddy, x0 + ddx), w)
    return k / k.sum()


def radius_norm():
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float64)
    cx, cy = (W - 1) / 2, (H - 1) / 2
    return np.sqrt((xs - cx) ** 2 + (ys - cy) ** 2) / math.hypot(cx, cy)


def vignette_gain(form, strength, a=0.6):
    r = radius_norm()
    if form == "poly":
        return 1.0 - strength * (a * r**2 + (1 - a) * r**4)
    theta_c = math.acos((1.0 - strength) ** 0.25)
    t = np.arctan(r * math.tan(theta_c))
    return np.cos(t) ** 4


def stray_field(amplitude, src, length):
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float64)
    d = np.sqrt((xs - src[0]) ** 2 + (ys - src[1]) ** 2)
    f = np.exp(-d / length)
    return f * (amplitude / f.max())


def hexagon_ghost(cx, cy, radius, plateau, rot):
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float64)
    u, v = xs - cx, ys - cy
    d = np.full(u.shape, -np.inf)
    for i in range(6):
        a = rot + i * math.pi / 3
        d = np.maximum(d, u * math.cos(a) + v * math.sin(a))
    m = np.clip(0.5 - (d - radius * math.cos(math.pi / 6)) / 2.0, 0.0, 1.0)  # 2 px soft edge
    return plateau * m


def srgb_toe(p, a):
    """Break point x0 and slope s of the linear toe of srgb_like (p > 1, a > 0): the line from
    the origin tangent to (1 + a) x^(1/p) - a, i.e. s = (1+a)/p x0^(1/p-1) and s x0 = (1+a) x0^(1/p) - a."""
    # g(x0) = s x0 - ((1+a) x0^(1/p) - a) = a - (1+a)(1 - 1/p) x0^(1/p): positive below the
    # tangent point, negative above it. (Until 2026-11-26 the bisection moved the wrong way and
    # stopped at the bracket's end, 0.5: a toe that was neither tangent nor continuous, a jump of
    # about 3.5 DN at mid-scale; `--check` now tests continuity.)
    lo, hi = 1e-9, 1.0
    for _ in range(200):
        x0 = 0.5 * (lo + hi)
        s = (1 + a) / p * x0 ** (1 / p - 1)
        g = s * x0 - ((1 + a) * x0 ** (1 / p) - a)
        if g > 0:
            lo = x0
        else:
            hi = x0
    return x0, s


def srgb_like(x, p, a):
    """Generalised sRGB: (1 + a) x^(1/p) - a above the toe, linear below, value and slope
    continuous at the toe."""
    x0, s = srgb_toe(p, a)
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= x0, s * x, (1 + a) * np.power(np.maximum(x, x0), 1 / p) - a)


def best_power(curve):
    """Least-squares power-law exponent of a tone curve on x in [0, 1] (uniform grid)."""
    x = np.linspace(0.0, 1.0, 2001)
    y = curve(x)
    lo, hi = 0.5, 1.5
    gs = np.linspace(lo, hi, 2001)
    errs = [np.sum((x**g - y) ** 2) for g in gs]
    return float(gs[int(np.argmin(errs))])


def one_over_f_rows(rng, sigma):
    f = np.fft.rfftfreq(H)
    amp = np.zeros_like(f)
    amp[1:] = f[1:] ** -0.5
    spec = amp * (rng.standard_normal(f.shape) + 1j * rng.standard_normal(f.shape))
    rows = np.fft.irfft(spec, n=H)
    return rows * (sigma / math.sqrt(np.mean(rows**2)))


def bloom(q, wfull, spread):
    """Charge above wfull diffuses with a Gaussian of std `spread`, until nothing exceeds it."""
    rad = int(math.ceil(3 * spread)) + 1
    g = np.arange(-rad, rad + 1, dtype=np.float64)
    k1 = np.exp(-0.5 * (g / spread) ** 2)
    k1 /= k1.sum()
    kern = np.outer(k1, k1)
    q = q.copy()
    for _ in range(60):
        ex = np.clip(q - wfull, 0.0, None)
        if ex.max() <= 1e-3:
            break
        q = np.minimum(q, wfull) + fft_convolve(ex, kern)
    return np.minimum(q, wfull)


# ----------------------------------------------------------------------------------------------
# cases


def case_list():
    """(name, scene, channels, bits, seed, camera (g e-/DN, read sigma DN), hidden effects).

    Hidden effect: (effect, params in EFFECTS.md units, form, form params). Strengths are chosen
    so that each hidden effect's noise-free change has an RMS over the frame at or below the RMS
    per-pixel camera noise (checked by --check and recorded in truth.json)."""
    C = []

    def add(name, scene, ch, bits, cam, hidden=()):
        C.append((name, scene, ch, bits, 1300 + len(C) * 17, cam, list(hidden)))

    # negative controls: camera only
    add("neg_planet_mono8", "planet", 1, 8, (6.0, 1.4))
    add("neg_planet_rgb10", "planet", 3, 10, (18.0, 0.9))
    add("neg_docking_mono12", "docking", 1, 12, (40.0, 0.7))
    add("neg_docking_rgb8", "docking", 3, 8, (4.0, 1.8))
    add("neg_stars_mono10", "stars", 1, 10, (12.0, 1.1))
    add("neg_stars_rgb8", "stars", 3, 8, (8.0, 1.2))
    add("neg_lab_mono12", "lab", 1, 12, (25.0, 0.8))
    add("neg_lab_rgb8", "lab", 3, 8, (5.0, 1.5))
    add("neg_planet_mono12_noisy", "planet", 1, 12, (2.5, 2.4))
    add("neg_docking_mono10", "docking", 1, 10, (10.0, 1.0))
    add("neg_lab_rgb12", "lab", 3, 12, (30.0, 0.9))
    # one hidden effect
    add("defocus_airy_planet_mono10", "planet", 1, 10, (12.0, 1.2),
        [("defocus", {"sigma_px": 0.55}, "airy", {})])
    add("defocus_pillbox_lab_rgb8", "lab", 3, 8, (6.0, 1.5),
        [("defocus", {"sigma_px": 0.7}, "pillbox", {"radius_px": 1.4})])
    add("vignetting_poly_lab_mono12", "lab", 1, 12, (20.0, 0.9),
        [("vignetting", {"strength": 0.06}, "polynomial", {"a": 0.6})])
    add("vignetting_cos4_planet_rgb8", "planet", 3, 8, (6.0, 1.4),
        [("vignetting", {"strength": 0.05}, "cos4", {})])
    add("gamma_power_lab_mono8", "lab", 1, 8, (6.0, 1.3),
        [("gamma", {"gamma": 0.96}, "power", {})])
    add("gamma_srgb_lab_rgb10", "lab", 3, 10, (15.0, 1.0),
        [("gamma", {}, "srgb", {"p": 1.045, "a": 0.008})])
    add("row_noise_docking_mono12", "docking", 1, 12, (20.0, 0.9),
        [("row_noise", {"sigma_dn": 0.8}, "1/f", {})])
    add("jpeg_q85_420_lab_rgb8", "lab", 3, 8, (6.0, 1.4),
        [("jpeg", {"quality": 85}, "pillow", {"subsampling": "4:2:0"})])
    add("jpeg_q92_444_planet_rgb8", "planet", 3, 8, (6.0, 1.4),
        [("jpeg", {"quality": 92}, "pillow", {"subsampling": "4:4:4"})])
    add("jpeg_q75_docking_mono8", "docking", 1, 8, (5.0, 1.6),
        [("jpeg", {"quality": 75}, "pillow", {"subsampling": "4:2:0"})])
    add("smear_docking_mono10", "docking", 1, 10, (12.0, 1.0),
        [("smear", {"strength": 0.0015, "direction": "vertical"}, "frame_transfer", {})])
    add("dark_hot_stars_mono12", "stars", 1, 12, (20.0, 0.9),
        [("dark_current", {"mean_dn": 1.2, "hot_pixel_rate": 3e-4}, "poisson", {})])
    add("channel_shift_docking_rgb8", "docking", 3, 8, (4.0, 1.6),
        [("channel_shift", {"dx_r": 0.3, "dy_r": -0.2, "dx_b": -0.25, "dy_b": 0.25}, "fourier", {})])
    add("stray_light_stars_rgb10", "stars", 3, 10, (12.0, 1.0),
        [("stray_light", {"amplitude_dn": 2.5}, "exp_lobe", {"src": [-120.0, 60.0], "length_px": 260.0})])
    add("motion_blur_planet_mono8", "planet", 1, 8, (6.0, 1.4),
        [("motion_blur", {"length_px": 2.2, "angle_deg": 35.0}, "segment", {})])
    add("blooming_docking_mono8", "docking", 1, 8, (4.0, 1.5),
        [("blooming", {"full_well_fraction": 0.93, "spread_px": 1.5}, "gaussian_diffusion", {})])
    add("lens_flare_stars_mono10", "stars", 1, 10, (12.0, 1.0),
        [("lens_flare", {"ghosts": 3, "intensity": 0.012}, "hexagon", {})])
    add("prnu_lab_mono10", "lab", 1, 10, (12.0, 1.0),
        [("prnu", {"sigma": 0.02}, "gaussian", {})])
    add("gain_offset_lab_mono12", "lab", 1, 12, (8.0, 1.2),
        [("gain_offset", {"gain": 1.03, "offset_dn": -2.5}, "digital", {})])
    # two hidden effects
    add("blooming_smear_docking_mono8", "docking", 1, 8, (4.0, 1.5),
        [("blooming", {"full_well_fraction": 0.94, "spread_px": 1.2}, "gaussian_diffusion", {}),
         ("smear", {"strength": 0.0012, "direction": "vertical"}, "frame_transfer", {})])
    add("dark_gamma_lab_mono10", "lab", 1, 10, (15.0, 1.0),
        [("dark_current", {"mean_dn": 2.0, "hot_pixel_rate": 0.0}, "poisson", {}),
         ("gamma", {}, "srgb", {"p": 1.04, "a": 0.006})])
    add("vignetting_defocus_planet_mono12", "planet", 1, 12, (14.0, 1.0),
        [("vignetting", {"strength": 0.05}, "cos4", {}),
         ("defocus", {"sigma_px": 0.45}, "airy", {})])
    add("prnu_row_noise_lab_rgb8", "lab", 3, 8, (8.0, 1.2),
        [("prnu", {"sigma": 0.025}, "gaussian", {}),
         ("row_noise", {"sigma_dn": 0.7}, "1/f", {})])
    add("flare_dark_stars_mono12", "stars", 1, 12, (20.0, 0.9),
        [("lens_flare", {"ghosts": 2, "intensity": 0.01}, "hexagon", {}),
         ("dark_current", {"mean_dn": 1.2, "hot_pixel_rate": 2e-4}, "poisson", {})])
    return C


class Case:
    def __init__(self, spec):
        self.name, self.scene_name, self.c, self.bits, self.seed, cam, hidden = spec
        self.gain, self.read = cam
        self.hidden = []
        for eff, params, form, fparams in hidden:
            params = dict(params)
            if eff == "gamma" and form == "srgb":
                p, a = fparams["p"], fparams["a"]
                params["gamma"] = round(best_power(lambda x: srgb_like(x, p, a)), 4)
            self.hidden.append((eff, params, form, dict(fparams)))
        rng = np.random.default_rng(self.seed)
        self.scene = SCENES[self.scene_name](np.random.default_rng(self.seed + 1), self.c)
        # camera constants of this unit
        self.pedestal = int(rng.integers(16, 64)) * (1 << max(self.bits - 8, 0))
        self.ped_residual = float(rng.uniform(-0.25, 0.25)) * (2**self.bits - 1) / FS  # in codes
        self.beta = float(rng.uniform(-0.004, 0.004))
        # fixed patterns of this unit
        fp = np.random.default_rng(self.seed + 2)
        self.prnu_n = fp.standard_normal((H, W, self.c))
        self.hot_u = fp.uniform(0, 1, (H, W, self.c))
        self.hot_amp = np.exp(fp.uniform(math.log(15), math.log(60), (H, W, self.c)))
        self.flare_geom = fp.uniform(0, 1, 16)

    def has(self, eff):
        return next((h for h in self.hidden if h[0] == eff), None)

    def ext(self):
        return "jpg" if self.has("jpeg") else "png"

    # -- optics (deterministic, on the irradiance) ---------------------------------------------
    def optics(self, e, only=None):
        def on(name):
            return (only is None or name in only) and self.has(name)

        if on("defocus"):
            _, p, form, fp = self.has("defocus")
            k = airy_kernel(p["sigma_px"]) if form == "airy" else pillbox_kernel(fp["radius_px"])
            e = fft_convolve(e, k)
        if on("motion_blur"):
            _, p, _, _ = self.has("motion_blur")
            e = fft_convolve(e, line_kernel(p["length_px"], p["angle_deg"]))
        if on("channel_shift") and self.c == 3:
            _, p, _, _ = self.has("channel_shift")
            e = e.copy()
            e[:, :, 0] = fourier_shift(e[:, :, 0], p["dx_r"], p["dy_r"])
            e[:, :, 2] = fourier_shift(e[:, :, 2], p["dx_b"], p["dy_b"])
        if on("lens_flare"):
            _, p, _, _ = self.has("lens_flare")
            # the brightest source: maximum of the luminance smoothed over a few px (flux, not
            # peak, so the same source is chosen on every frame)
            g1 = np.exp(-0.5 * (np.arange(-9, 10) / 3.0) ** 2)
            lum = fft_convolve(e.mean(axis=2, keepdims=True), np.outer(g1, g1) / g1.sum() ** 2)[:, :, 0]
            sy, sx = np.unravel_index(int(np.argmax(lum)), lum.shape)
            cx, cy = (W - 1) / 2, (H - 1) / 2
            g = self.flare_geom
            n = int(p["ghosts"])
            # ghost positions t along source -> centre (t = 1 at the source, 0 at the centre,
            # negative beyond it); only ghosts whose centre lies inside the frame are used
            cand = [-0.55 - 0.5 * g[0], 0.35 + 0.2 * g[1], -1.0 - 0.3 * g[2], 0.6 + 0.2 * g[3], -0.25, 0.2]
            ts = [t for t in cand if 30 <= cx + t * (sx - cx) <= W - 30 and 30 <= cy + t * (sy - cy) <= H - 30][:n]
            assert len(ts) == n, f"{self.name}: only {len(ts)} lens-flare ghosts fit in the frame"
            w = 0.7 + 0.6 * g[4 : 4 + n]
            w = w / w.mean()
            add = np.zeros((H, W))
            for i, t in enumerate(ts):
                gx, gy = cx + t * (sx - cx), cy + t * (sy - cy)
                add += hexagon_ghost(gx, gy, 14 + 22 * g[8 + i], p["intensity"] * w[i] * FS, g[12] * math.pi)
            e = e + add[:, :, None]
        if on("stray_light"):
            _, p, _, fp = self.has("stray_light")
            e = e + stray_field(p["amplitude_dn"], fp["src"], fp["length_px"])[:, :, None]
        if on("vignetting"):
            _, p, form, fp = self.has("vignetting")
            e = e * vignette_gain("poly" if form == "polynomial" else "cos4", p["strength"], fp.get("a", 0.6))[:, :, None]
        return e

    # -- sensor, readout, transmission ---------------------------------------------------------
    def expose(self, e, rng, noise=True, only=None):
        """Irradiance after optics (8-bit DN) -> file codes (float if not noise). With
        noise=False: expected values, no shot/read/row noise, no quantisation (for visibility)."""

        def on(name):
            return (only is None or name in only) and self.has(name)

        lam = np.clip(e, 0.0, None)
        if on("prnu"):
            lam = lam * (1.0 + self.has("prnu")[1]["sigma"] * self.prnu_n)
        sat = lam >= FS
        if on("smear"):
            _, p, _, _ = self.has("smear")
            if p["direction"] == "vertical":
                cnt = sat.sum(axis=0, keepdims=True)
            else:
                cnt = sat.sum(axis=1, keepdims=True)
            lam = lam + p["strength"] * FS * cnt
        if on("dark_current"):
            _, p, _, _ = self.has("dark_current")
            hot = (self.hot_u < p["hot_pixel_rate"]) * self.hot_amp
            lam = lam + p["mean_dn"] + hot
        q = rng.poisson(lam * self.gain) / self.gain if noise else lam
        wfull = FS
        if on("blooming"):
            _, p, _, _ = self.has("blooming")
            wfull = p["full_well_fraction"] * FS
            q = bloom(q, wfull, p["spread_px"])
        v = q
        if noise:
            v = v + rng.normal(0.0, self.read, v.shape)
        if noise and on("row_noise"):
            s = self.has("row_noise")[1]["sigma_dn"]
            v = v + np.stack([one_over_f_rows(rng, s) for _ in range(self.c)], axis=1)[:, None, :]
        # ADC: nonlinearity, pedestal (with its residual), quantise, clip, subtract nominal pedestal
        top = 2**self.bits - 1
        u = v / FS
        u = u + self.beta * np.clip(u, 0, 1) * (1 - np.clip(u, 0, 1))
        code = u * top + self.pedestal + self.ped_residual
        if noise:
            code = np.round(code)
        code = np.clip(code - self.pedestal, 0, min(top, wfull / FS * top if wfull < FS else top))
        x = code * FS / top
        digital = False
        if on("gain_offset"):
            _, p, _, _ = self.has("gain_offset")
            x = p["gain"] * x + p["offset_dn"]
            digital = True
        if on("gamma"):
            _, p, form, fp = self.has("gamma")
            xc = np.clip(x, 0, FS) / FS
            x = FS * (srgb_like(xc, fp["p"], fp["a"]) if form == "srgb" else xc ** p["gamma"])
            digital = True
        code = x * top / FS
        if digital and noise:
            code = np.round(code)
        return np.clip(code, 0, top)

    def sim_codes(self, e):
        top = 2**self.bits - 1
        return np.round(np.clip(e, 0, FS) * top / FS)

    # -- files ----------------------------------------------------------------------------------
    def to_image(self, code):
        code = code.astype(np.int64)
        if self.bits == 8:
            arr = code.astype(np.uint8)
        else:
            b = self.bits
            arr = ((code << (16 - b)) | (code >> (2 * b - 16))).astype(np.uint16)
        if self.c == 1:
            a = arr[:, :, 0]
            return Image.fromarray(a) if self.bits == 8 else Image.fromarray(a.astype(np.uint16))
        if self.bits == 8:
            return Image.fromarray(arr, "RGB")
        return None  # 16-bit RGB: written by write_png16

    def save(self, code, path, jpeg=None):
        if self.bits == 8:
            img = self.to_image(code)
            if jpeg:
                sub = {"4:4:4": 0, "4:2:2": 1, "4:2:0": 2}[jpeg["subsampling"]]
                img.save(path, "JPEG", quality=int(jpeg["quality"]), subsampling=sub, optimize=False)
            else:
                img.save(path, "PNG", optimize=False, compress_level=6)
            return
        b = self.bits
        code = code.astype(np.int64)
        arr = ((code << (16 - b)) | (code >> (2 * b - 16))).astype(np.uint16)
        write_png16(path, arr)

    def frames(self):
        """Yield (k, sim codes, real codes, irradiance) for the 4 frames."""
        rng = np.random.default_rng(self.seed + 3)
        for k in range(FRAMES):
            e = self.scene.render(k)
            yield k, self.sim_codes(e), self.expose(self.optics(e), rng), e

    def noise_rms(self, e):
        """RMS per-pixel camera noise (8-bit DN) on the clean scene: shot + read + quantisation."""
        lv = np.clip(e, 0, FS)
        step = FS / (2**self.bits - 1)
        var = lv / self.gain + self.read**2 + step**2 / 12
        return float(np.sqrt(np.mean(var)))

    def visibility(self, e):
        """Per hidden effect: RMS and max |change| of the noise-free file values (8-bit DN) caused
        by that effect alone, against the RMS camera noise."""
        top = 2**self.bits - 1
        rng = np.random.default_rng(0)
        base = self.expose(self.optics(e, only=()), rng, noise=False, only=()) * FS / top
        out = {}
        for eff, p, form, fp in self.hidden:
            if eff == "row_noise":
                out[eff] = {"rms_dn": p["sigma_dn"], "max_dn": p["sigma_dn"]}
                continue
            if eff == "jpeg":
                clean = np.round(base)
                img = self.to_image(clean)
                import io

                buf = io.BytesIO()
                sub = {"4:4:4": 0, "4:2:2": 1, "4:2:0": 2}[fp["subsampling"]]
                img.save(buf, "JPEG", quality=int(p["quality"]), subsampling=sub)
                back = np.asarray(Image.open(io.BytesIO(buf.getvalue()))).astype(np.float64)
                d = back.reshape(clean.shape) - clean
            else:
                one = self.expose(self.optics(e, only=(eff,)), rng, noise=False, only=(eff,)) * FS / top
                d = one - base
            out[eff] = {"rms_dn": float(np.sqrt(np.mean(d**2))), "max_dn": float(np.abs(d).max())}
        return out

    def truth(self, vis, noise):
        hidden = []
        for eff, p, form, fp in self.hidden:
            hidden.append({"effect": eff, "params": p, "form": form, "form_params": fp, "visibility": vis.get(eff)})
        return {
            "name": self.name,
            "scene": self.scene_name,
            "channels": self.c,
            "bits": self.bits,
            "frames": FRAMES,
            "size": [W, H],
            "seed": self.seed,
            "negative_control": not self.hidden,
            "hidden": hidden,
            "camera": {
                "gain_e_per_dn": self.gain,
                "read_sigma_dn": self.read,
                "adc_pedestal_codes": self.pedestal,
                "adc_pedestal_residual_dn": self.ped_residual * FS / (2**self.bits - 1),
                "nonlinearity_beta": self.beta,
                "noise_rms_dn": noise,
            },
            "units": "parameters in DN are 8-bit DN (FS = 255); 16-bit files are bit-replicated",
        }

    def write(self, root):
        d = os.path.join(root, self.name)
        for sub in ("sim", "real"):
            os.makedirs(os.path.join(d, sub), exist_ok=True)
        jpeg = None
        if self.has("jpeg"):
            _, p, _, fp = self.has("jpeg")
            jpeg = {"quality": p["quality"], "subsampling": fp["subsampling"]}
        vis = noise = None
        for k, sim, real, e in self.frames():
            self.save(sim, os.path.join(d, "sim", f"frame{k:02d}.png"))
            self.save(real, os.path.join(d, "real", f"frame{k:02d}.{self.ext()}"), jpeg)
            if k == 0:
                vis, noise = self.visibility(e), self.noise_rms(e)
        with open(os.path.join(d, "truth.json"), "w") as f:
            json.dump(self.truth(vis, noise), f, indent=1, sort_keys=True)
            f.write("\n")
        return d


def write_png16(path, arr):
    """16-bit grey or RGB PNG (Pillow's 16-bit RGB support is limited): zlib + struct."""
    import struct
    import zlib

    h, w = arr.shape[:2]
    c = 1 if arr.ndim == 2 or arr.shape[2] == 1 else 3
    a = arr.reshape(h, w, c).astype(">u2")
    raw = b"".join(b"\x00" + a[y].tobytes() for y in range(h))

    def chunk(t, data):
        return struct.pack(">I", len(data)) + t + data + struct.pack(">I", zlib.crc32(t + data) & 0xFFFFFFFF)

    ihdr = struct.pack(">IIBBBBB", w, h, 16, 0 if c == 1 else 2, 0, 0, 0)
    with open(path, "wb") as f:
        f.write(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(raw, 6)) + chunk(b"IEND", b""))


# ----------------------------------------------------------------------------------------------


def cases(names=()):
    cs = [Case(s) for s in case_list()]
    if names:
        unknown = set(names) - {c.name for c in cs}
        if unknown:
            sys.exit(f"gen.py: unknown case(s) {sorted(unknown)}; --list shows them")
        cs = [c for c in cs if c.name in names]
    return cs


def digest_dir(d):
    h = hashlib.sha256()
    for root, _, files in sorted(os.walk(d)):
        for fn in sorted(files):
            p = os.path.join(root, fn)
            h.update(os.path.relpath(p, d).encode())
            with open(p, "rb") as f:
                h.update(f.read())
    return h.hexdigest()


def check(names=()):
    """Determinism (two cases written twice give identical bytes) and the noise condition on
    every case: each hidden effect's noise-free RMS change <= the RMS camera noise, >= 10
    negative controls. Exit 1 with the failing case named."""
    import tempfile

    bad = []
    # Tone curves: the generalised sRGB form is continuous in value and slope at its toe and
    # fixes 0 and full scale (a jump there once made a curve no camera has).
    for p, a in ((1.04, 0.006), (1.05, 0.008), (1.1, 0.02), (2.4, 0.055)):
        x0, s = srgb_toe(p, a)
        eps = 1e-7
        v = srgb_like(np.array([x0 - eps, x0 + eps, 0.0, 1.0]), p, a)
        slope_hi = (1 + a) / p * (x0 + eps) ** (1 / p - 1)
        ok = abs(v[1] - v[0]) < 1e-5 and abs(slope_hi - s) < 1e-4 * s and v[2] == 0.0 and abs(v[3] - 1.0) < 1e-12
        print(f"srgb_like p {p} a {a}: toe x0 {x0:.4f}, jump {255 * (v[1] - v[0]):.2e} DN {'ok' if ok else 'NOT CONTINUOUS'}")
        if not ok:
            bad.append(f"srgb_like(p {p}, a {a}) is not continuous at its toe x0 {x0:.4f}")
    cs = cases()
    neg = sum(1 for c in cs if not c.hidden)
    if neg < 10:
        bad.append(f"only {neg} negative controls (need >= 10)")
    for c in cs:
        if not c.hidden or (names and c.name not in names):
            continue
        e = c.scene.render(0)
        vis, noise = c.visibility(e), c.noise_rms(e)
        for eff, v in vis.items():
            ok = v["rms_dn"] <= noise
            print(f"{c.name:36} {eff:14} rms {v['rms_dn']:.3f} DN (max {v['max_dn']:.2f}) vs noise {noise:.3f} DN {'ok' if ok else 'TOO STRONG'}")
            if not ok:
                bad.append(f"{c.name}: {eff} rms {v['rms_dn']:.3f} DN > noise {noise:.3f} DN")
    with tempfile.TemporaryDirectory() as t1, tempfile.TemporaryDirectory() as t2:
        for c in cases(["neg_lab_rgb12", "jpeg_q85_420_lab_rgb8"]):
            a = digest_dir(c.write(t1))
        for c in cases(["neg_lab_rgb12", "jpeg_q85_420_lab_rgb8"]):
            b = digest_dir(c.write(t2))
        da, db = digest_dir(t1), digest_dir(t2)
        print(f"determinism: {da[:16]} vs {db[:16]}")
        if da != db or a != b:
            bad.append("two writes of the same cases differ")
    if bad:
        print("gen.py --check FAILED:\n  " + "\n  ".join(bad), file=sys.stderr)
        return 1
    print(f"gen.py --check ok: {len(cs)} cases, {neg} negative controls")
    return 0


def main(argv):
    if "--check" in argv:
        return check([a for a in argv if a != "--check"])
    if "--list" in argv:
        for c in cases():
            hid = ", ".join(f"{e}({form})" for e, _, form, _ in c.hidden) or "(none)"
            print(f"{c.name:36} {c.scene_name:8} {'rgb' if c.c == 3 else 'mono'}{c.bits:<3} {hid}")
        return 0
    out = argv[0] if argv else os.path.join(REPO, "target", "corpus2")
    names = argv[1:]
    for c in cases(names):
        d = c.write(out)
        print(d, file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
