#!/usr/bin/env bash
# Soak under faults: the synthetic scene (default 1920x1200 mono8 at 60 fps) through the
# trigger-gated campaign (hil/campaigns/triggered-blooming.toml) into the null sink, while
#   - a trigger rig on a pseudo-terminal pair (socat) sends 1000 lines per second: valid
#     commands (START/STOP flash, SET, PING, MARK, ARM) mixed with garbage (random bytes,
#     over-long lines, unterminated fragments, bad numbers),
#   - the process is stopped and continued (SIGSTOP/SIGCONT, 2 s every 20 s): source, chain
#     and sink stall together and resume,
# then `faultcam log check` validates the log (every frame accounted for, a summary) and the
# resident memory sampled every 10 s must stay flat. Usage:
#
#   ./scripts/soak-faults.sh [MINUTES] [WxH] [FPS]     # default: 10 1920x1200 60
#
# Needs socat and python3. Prints the summary, the RSS samples and the log check.
set -euo pipefail
cd "$(dirname "$0")/.."
SOAK_NAME=soak-faults
. scripts/soak/setup.sh "$@"
echo "soak-faults: ${MINUTES} min, ${W}x${H} mono8 at ${FPS} fps, $(nproc) cores, $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2)"

socat pty,raw,echo=0,link="$OUT/rig" pty,raw,echo=0,link="$OUT/dut" 2>"$OUT/socat.log" &
SOCAT=$!
for _ in $(seq 50); do [ -e "$OUT/dut" ] && break; sleep 0.1; done

# The rig: 1 kHz, about one line in three garbage.
python3 - "$OUT/rig" "$MINUTES" >"$OUT/rig.log" 2>&1 <<'EOF' &
import os, random, signal, sys, time
stop = []
signal.signal(signal.SIGTERM, lambda *_: stop.append(1))
rig, minutes = sys.argv[1], float(sys.argv[2])
fd = os.open(rig, os.O_WRONLY | os.O_NOCTTY | os.O_NONBLOCK)
full = 0
rnd = random.Random(18)
valid = ["START flash", "STOP flash", "SET gaussian_noise.sigma_dn 3.5", "SET gaussian_noise.enabled true",
         "PING", "MARK soak", "ARM", "SET smear.strength 0.002"]
garbage = [lambda: bytes(rnd.getrandbits(8) for _ in range(rnd.randint(1, 40))) + b"\n",
           lambda: b"7 " + b"X" * 600 + b"\n",                     # over-long line
           lambda: b"12 STA",                                       # unterminated fragment
           lambda: b"abc START flash\n",                            # no sequence number
           lambda: b"9 SET gaussian_noise.sigma_dn NaN\n",          # bad value
           lambda: b"10 FIRE\r\n"]                                  # unknown command
seq, sent, junk, t0 = 0, 0, 0, time.monotonic()
end = t0 + minutes * 60
while time.monotonic() < end and not stop:
    seq += 1
    if rnd.random() < 0.33:
        line = rnd.choice(garbage)(); junk += 1
    else:
        line = f"{seq} {rnd.choice(valid)}\n".encode()
    try:
        os.write(fd, line)
    except BlockingIOError:
        full += 1  # the pty buffer is full: faultcam is stopped or behind
    except OSError as e:
        print("rig: write failed:", e); break
    sent += 1
    # 1 kHz, paced on the monotonic clock.
    delay = t0 + sent / 1000.0 - time.monotonic()
    if delay > 0:
        time.sleep(delay)
print(f"rig: {sent} lines written ({junk} garbage), {full} not written (pty buffer full), in {time.monotonic() - t0:.1f} s")
EOF
RIG=$!

"$FAULTCAM_BIN" run --source "synth:?width=$W&height=$H&format=mono8&frames=0&fps=$FPS" --fps "$FPS" \
  --sink null: --faults hil/campaigns/triggered-blooming.toml --trigger "$OUT/dut" \
  --duration "${MINUTES}m" --progress-s 60 --log "$OUT/groundtruth.jsonl" 2>"$OUT/run.stderr" &
PID=$!
trap 'kill -INT $PID 2>/dev/null || true; kill $RIG $SOCAT 2>/dev/null || true' INT TERM EXIT
T0=$SECONDS
NEXT_STOP=10
STOPS=0
while kill -0 "$PID" 2>/dev/null; do
  t=$((SECONDS - T0))
  RSS=$(awk '/VmRSS/{print $2}' "/proc/$PID/status" 2>/dev/null || true)
  [ -n "$RSS" ] && echo "soak-faults: t=${t}s rss ${RSS} kB, load $(cut -d' ' -f1-3 /proc/loadavg)"
  if [ "$t" -ge "$NEXT_STOP" ]; then
    kill -STOP "$PID" 2>/dev/null && sleep 2 && kill -CONT "$PID" 2>/dev/null && STOPS=$((STOPS + 1)) &&
      echo "soak-faults: t=${t}s SIGSTOP 2 s, SIGCONT"
    NEXT_STOP=$((NEXT_STOP + 20))
  fi
  for _ in $(seq 10); do kill -0 "$PID" 2>/dev/null || break; sleep 1; done
done
echo "soak-faults: $STOPS SIGSTOP/SIGCONT pairs"
set +e
wait "$PID"
RC=$?
# The rig runs for the same minutes; stop it (and let it print its counts) once faultcam is done.
kill -TERM "$RIG" 2>/dev/null
wait "$RIG"
set -e
cat "$OUT/rig.log"
tail -n 15 "$OUT/run.stderr"
echo "soak-faults: faultcam exit code $RC"
echo "soak-faults: events: $(grep -c '"event":"trigger"' "$OUT/groundtruth.jsonl") trigger, $(grep -c '"event":"nak"' "$OUT/groundtruth.jsonl") nak, $(grep -c '"event":"ack"' "$OUT/groundtruth.jsonl") ack"
"$FAULTCAM_BIN" log check "$OUT/groundtruth.jsonl"
