#!/usr/bin/env bash
# Soak of the I/O edges (issue 18 item 4): a source that stalls and resumes, a sink that blocks,
# the process stopped and continued, then sources that end or fail mid-stream.
#
#   ./scripts/soak-io.sh [MINUTES] [WxH] [FPS]     # default: 10 1920x1200 60
#
# Phase 1 (MINUTES): a camera on a pipe (scripts/soak/feeder.py: synthetic scenes, raw GRAY8 at FPS, a 2 s stall
#   every 20 s, end of stream at the end) → `gst:fdsrc ! rawvideoparse ! appsink` → the original
#   chain (hil/campaigns/original8.toml), `--live --budget-ms 16.7 --overrun drop` → `gst:appsrc !
#   queue ! fdsink` → a reader that stops reading for 3 s every 30 s (scripts/soak/reader.py);
#   faultcam is SIGSTOPped for 2 s every 45 s. Checked: frames in = frames the feeder wrote,
#   bytes the reader got = delivered frames x frame size, the log valid with nothing
#   unaccounted, resident memory flat (sampled every 10 s; see the check below).
# Phase 2: a GStreamer source that fails mid-stream (a corrupt PNG 20 frames into a
#   multifilesrc ! pngdec pipeline): the error names the element, frames before it accounted.
# Phase 3: the Aravis fake camera (in-process) for 60 s at 30 fps with SIGSTOP/SIGCONT: lost
#   buffers become skip records, nothing unaccounted, the log valid.
# SOAK_PHASES=23 runs only phases 2 and 3; FAULTCAM_BIN and SOAK_OUT as in scripts/soak-faults.sh.
set -euo pipefail
cd "$(dirname "$0")/.."
SOAK_NAME=soak-io
. scripts/soak/setup.sh "$@"
PHASES=${SOAK_PHASES:-123}   # e.g. SOAK_PHASES=23 skips phase 1
FAIL=0
fail() { echo "soak-io: FAIL: $*"; FAIL=1; }
field() { grep -o "\"$1\":[0-9]*" "$2" | tail -1 | cut -d: -f2; }
echo "soak-io: ${MINUTES} min, ${W}x${H} mono8 at ${FPS} fps, $(nproc) cores, $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2), load $(cut -d' ' -f1-3 /proc/loadavg)"

# ---- phase 1: stalling source, blocking sink, SIGSTOP/SIGCONT
if [[ $PHASES == *1* ]]; then
SECS=$((MINUTES * 60))
FIFO_IN="$OUT/in.fifo"
FIFO_OUT="$OUT/out.fifo"
mkfifo "$FIFO_IN" "$FIFO_OUT"
# The camera's frames: eight synthetic scenes (spacecraft, Earth limb, stars) as PGM.
printf 'seed = 0\n' >"$OUT/no-faults.toml"
"$FAULTCAM_BIN" run --source "synth:?width=$W&height=$H&format=mono8&frames=8&earth=true&seed=3" \
  --faults "$OUT/no-faults.toml" --sink "files:$OUT/scene?format=pgm" --log "$OUT/scene.jsonl" 2>"$OUT/scene.stderr"
python3 scripts/soak/feeder.py "$W" "$H" "$FPS" "$SECS" 20 2 "$OUT"/scene/*.pgm >"$FIFO_IN" 2>"$OUT/feeder.log" &
FEEDER=$!
python3 scripts/soak/reader.py 30 3 $((W * H)) <"$FIFO_OUT" 2>"$OUT/reader.log" &
READER=$!
"$FAULTCAM_BIN" run \
  --source "gst:fdsrc fd=0 blocksize=$((W * H)) ! rawvideoparse format=gray8 width=$W height=$H framerate=$FPS/1 ! appsink name=faultcam sync=false" \
  --live --budget-ms 16.7 --overrun drop --faults hil/campaigns/original8.toml \
  --sink "gst:appsrc name=faultcam ! queue max-size-buffers=4 ! fdsink fd=1" \
  --progress-s 60 --log "$OUT/phase1.jsonl" <"$FIFO_IN" >"$FIFO_OUT" 2>"$OUT/phase1.stderr" &
PID=$!
trap 'kill -INT $PID 2>/dev/null || true; kill $FEEDER $READER 2>/dev/null || true' INT TERM EXIT
T0=$SECONDS
NEXT_STOP=15
STOPS=0
RSS_LOG="$OUT/rss.txt"
while kill -0 "$PID" 2>/dev/null; do
  t=$((SECONDS - T0))
  RSS=$(awk '/VmRSS/{print $2}' "/proc/$PID/status" 2>/dev/null || true)
  [ -n "$RSS" ] && echo "$t $RSS" >>"$RSS_LOG" && echo "soak-io: t=${t}s rss ${RSS} kB, load $(cut -d' ' -f1-3 /proc/loadavg)"
  if [ "$t" -ge "$NEXT_STOP" ]; then
    kill -STOP "$PID" 2>/dev/null && sleep 2 && kill -CONT "$PID" 2>/dev/null && STOPS=$((STOPS + 1))
    NEXT_STOP=$((NEXT_STOP + 45))
  fi
  for _ in $(seq 10); do kill -0 "$PID" 2>/dev/null || break; sleep 1; done
done
set +e
wait "$PID"
RC=$?
wait "$FEEDER"
wait "$READER"
set -e
trap - INT TERM EXIT
tail -n 12 "$OUT/phase1.stderr"
cat "$OUT/feeder.log" "$OUT/reader.log"
echo "soak-io: phase 1: faultcam exit code $RC, $STOPS SIGSTOP/SIGCONT pairs"
[ "$RC" = 0 ] || fail "phase 1 exit code $RC"
"$FAULTCAM_BIN" log check "$OUT/phase1.jsonl" || fail "phase 1 log check"
WROTE=$(sed -n 's/^feeder: \([0-9]*\) frames written.*/\1/p' "$OUT/feeder.log")
READ_BYTES=$(sed -n 's/^reader: \([0-9]*\) bytes.*/\1/p' "$OUT/reader.log")
IN=$(field frames_in "$OUT/phase1.jsonl")
DELIVERED=$(field delivered "$OUT/phase1.jsonl")
UNACC=$(field unaccounted "$OUT/phase1.jsonl")
echo "soak-io: phase 1: feeder wrote $WROTE frames, faultcam took $IN in, delivered $DELIVERED, unaccounted $UNACC; the reader got $READ_BYTES bytes = $((READ_BYTES / (W * H))) frames"
[ "$WROTE" = "$IN" ] || fail "frames written ($WROTE) != frames in ($IN)"
[ "$UNACC" = 0 ] || fail "$UNACC frames unaccounted"
[ "$READ_BYTES" = "$((DELIVERED * W * H))" ] || fail "the reader got $READ_BYTES bytes, delivered frames make $((DELIVERED * W * H))"
# Flat = no growth in the last third of the run beyond 4 frames over the earlier peak. (glibc
# raises its mmap threshold after GStreamer frees a frame-sized buffer, so its heap may keep a
# few frame-sized holes: a bounded step, not a leak; MALLOC_MMAP_THRESHOLD_=131072 removes it.)
python3 - "$RSS_LOG" $((W * H / 1024)) <<'PY' || fail "memory grew"
import sys
s = [tuple(map(int, l.split())) for l in open(sys.argv[1])]
frame_kb = int(sys.argv[2])
s = [(t, r) for t, r in s if t >= 10]
end = s[-1][0]
early = [r for t, r in s if t < end * 2 / 3]
late = [r for t, r in s if t >= end * 2 / 3]
if not early or not late:
    sys.exit(0)
print(f"soak-io: RSS {min(early)} .. {max(early)} kB up to {end * 2 // 3} s, {min(late)} .. {max(late)} kB after ({len(s)} samples)")
sys.exit(0 if max(late) <= max(early) + 4 * frame_kb else 1)
PY
fi

# ---- phase 2: a GStreamer source failing mid-stream
if [[ $PHASES == *2* ]]; then
mkdir -p "$OUT/png"
"$FAULTCAM_BIN" run --source "synth:?width=320&height=240&format=mono8&frames=30" --faults hil/campaigns/original8.toml \
  --sink "files:$OUT/png" --log "$OUT/png.jsonl" 2>"$OUT/png.stderr"
N=0
for f in $(ls "$OUT/png"/*.png | sort); do mv "$f" "$OUT/png/f$(printf %04d $N).png"; N=$((N + 1)); done
# A corrupt file 20 frames in: the image chunk of f0020.png garbled (the PNG signature kept).
python3 -c '
import sys
p = sys.argv[1]; b = bytearray(open(p, "rb").read()); i = b.index(b"IDAT")
for k in range(i + 8, min(len(b) - 12, i + 200)): b[k] ^= 0x5A
open(p, "wb").write(b)' "$OUT/png/f0020.png"
set +e
"$FAULTCAM_BIN" run --source "gst:multifilesrc location=$OUT/png/f%04d.png index=0 stop-index=$((N - 1)) caps=image/png ! pngdec ! videoconvert ! appsink name=faultcam sync=false" \
  --faults hil/campaigns/original8.toml --sink null: --log "$OUT/phase2.jsonl" 2>"$OUT/phase2.stderr"
RC=$?
set -e
tail -n 3 "$OUT/phase2.stderr"
echo "soak-io: phase 2: exit code $RC (an error is expected), $(field frames_in "$OUT/phase2.jsonl") frames in"
[ "$(field frames_in "$OUT/phase2.jsonl")" = 20 ] || fail "phase 2: expected the 20 frames before the corrupt file"
grep -q '"stopped_by":"error"' "$OUT/phase2.jsonl" || fail "phase 2: the log does not say the stream ended by an error"
"$FAULTCAM_BIN" log check "$OUT/phase2.jsonl" || fail "phase 2 log check"
fi

# ---- phase 3: the Aravis fake camera, stopped and continued
if [[ $PHASES == *3* ]]; then
if ldconfig -p 2>/dev/null | grep libaravis >/dev/null; then
  "$FAULTCAM_BIN" run --source "aravis:Fake_1?width=640&height=480&fps=30&pixel_format=Mono8" --faults hil/campaigns/original8.toml \
    --sink null: --duration 60s --log "$OUT/phase3.jsonl" 2>"$OUT/phase3.stderr" &
  PID=$!
  for _ in 1 2 3 4 5; do sleep 10; kill -STOP "$PID" 2>/dev/null; sleep 1; kill -CONT "$PID" 2>/dev/null; done
  set +e
  wait "$PID"
  RC=$?
  set -e
  tail -n 3 "$OUT/phase3.stderr"
  echo "soak-io: phase 3: exit code $RC, $(field frames_in "$OUT/phase3.jsonl") frames in, $(grep -c '"record":"skip"' "$OUT/phase3.jsonl" || true) skips"
  "$FAULTCAM_BIN" log check "$OUT/phase3.jsonl" || fail "phase 3 log check"
else
  echo "soak-io: phase 3 SKIPPED: libaravis not found"
fi
fi

[ "$FAIL" = 0 ] && echo "soak-io: ok" || { echo "soak-io: FAILED"; exit 1; }
