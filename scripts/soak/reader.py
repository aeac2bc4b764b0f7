"""A sink that stops reading: reads stdin, and every PERIOD_S stops for BLOCK_S (a blocked
consumer), until end of file. Prints the bytes and whole FRAME_BYTES frames it read.

    python3 reader.py PERIOD_S BLOCK_S FRAME_BYTES
"""
import os
import sys
import time

period, block, frame_bytes = float(sys.argv[1]), float(sys.argv[2]), int(sys.argv[3])
t0 = time.monotonic()
nxt, total, blocks = t0 + period, 0, 0
while True:
    if time.monotonic() >= nxt:
        time.sleep(block)
        blocks += 1
        nxt += period
    b = os.read(0, 1 << 20)
    if not b:
        break
    total += len(b)
print(f"reader: {total} bytes = {total / frame_bytes:g} frames read, {blocks} blocks of {block:g} s", file=sys.stderr)
