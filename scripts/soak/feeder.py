"""A camera on a pipe: raw GRAY8 frames to stdout at FPS for SECONDS, stalling STALL_S every
PERIOD_S (a source that stops delivering and resumes on its own), then end of stream. The frames
are the given binary PGM files, cycled (e.g. synthetic scenes written by faultcam), or else four
ramps (a worst case for blooming: a sixth of the pixels over the full well).

    python3 feeder.py W H FPS SECONDS PERIOD_S STALL_S [FRAME.pgm ...]

Prints to stderr how many frames it wrote and how many stalls it made.
"""
import os
import signal
import sys
import time

w, h = int(sys.argv[1]), int(sys.argv[2])
fps, seconds, period, stall = (float(a) for a in sys.argv[3:7])
stop = []
signal.signal(signal.SIGTERM, lambda *_: stop.append(1))


def read_pgm(path):
    """A binary 8-bit PGM (P5): its pixels, checked against W x H."""
    data = open(path, "rb").read()
    fields, pos = [], 0
    while len(fields) < 4:
        while data[pos:pos + 1].isspace():
            pos += 1
        if data[pos:pos + 1] == b"#":
            pos = data.index(b"\n", pos)
            continue
        end = pos
        while not data[end:end + 1].isspace():
            end += 1
        fields.append(data[pos:end])
        pos = end
    magic, fw, fh, maxval = fields[0], int(fields[1]), int(fields[2]), int(fields[3])
    if magic != b"P5" or maxval > 255 or (fw, fh) != (w, h):
        sys.exit(f"feeder: {path}: need an 8-bit P5 PGM of {w}x{h}, got {magic!r} {fw}x{fh} maxval {maxval}")
    return data[pos + 1:pos + 1 + w * h]


if len(sys.argv) > 7:
    frames = [read_pgm(p) for p in sys.argv[7:]]
else:
    # Four distinct frames (a ramp shifted per frame), cycled.
    row = bytes(range(256)) * (w // 256 + 2)
    frames = [b"".join(row[(i * 37 + y) % 256:(i * 37 + y) % 256 + w] for y in range(h)) for i in range(4)]
assert all(len(f) == w * h for f in frames), "frame size"
t0 = time.monotonic()
n, stalls, shift = 0, 0, 0.0
next_stall = t0 + period
try:
    while time.monotonic() - t0 < seconds and not stop:
        if time.monotonic() >= next_stall:
            time.sleep(stall)
            stalls += 1
            shift += stall
            next_stall += period
        mv = memoryview(frames[n % len(frames)])
        while mv:
            k = os.write(1, mv)
            mv = mv[k:]
        n += 1
        delay = t0 + shift + n / fps - time.monotonic()
        if delay > 0:
            time.sleep(delay)
except BrokenPipeError:
    print("feeder: the reader closed the pipe", file=sys.stderr)
print(f"feeder: {n} frames written, {stalls} stalls of {stall:g} s", file=sys.stderr)
