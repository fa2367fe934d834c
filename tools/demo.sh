#!/usr/bin/env bash
# `make demo`: the daemon on the built-in simulated vehicle, driven from the bench socket
# the way an operator drives the panel: engage steering, lock speed hold at 0 m/s and
# step it up, look at `dbw status`, hand back, e-stop, reset. The daemon's own log runs
# in the same terminal.
set -euo pipefail
BIN=${BIN:-.venv/bin}
SECONDS_TOTAL=${DEMO_SECONDS:-25}
say() { printf '\n\033[1m== demo: %s ==\033[0m\n' "$*"; }

"$BIN/dbw" --log-format console run --config sim --duration-s "$SECONDS_TOTAL" --record &
daemon=$!
trap 'kill "$daemon" 2>/dev/null || true' EXIT

for _ in $(seq 50); do  # wait for the socket and READY
  if "$BIN/dbw" status --json 2>/dev/null | grep -q '"mode": "ready"'; then break; fi
  sleep 0.2
done
say "the daemon is READY"; "$BIN/dbw" status || true
say "engage steering (the panel's engage button)"; "$BIN/dbw" engage || true
say "lock speed hold at the current speed (0 m/s), then step it up to 1 m/s"
for _ in 1 2 3 4 5; do "$BIN/dbw" speed-up || true; done
sleep 5
say "driving in speed hold"; "$BIN/dbw" status || true
say "manual override: everything back to the operator"; "$BIN/dbw" disengage || true
say "e-stop, then the reset procedure"; "$BIN/dbw" estop || true; sleep 1
"$BIN/dbw" estop-reset || true
say "back in READY"; "$BIN/dbw" status || true
wait "$daemon"
trap - EXIT
say "finished: the daemon stopped cleanly after ${SECONDS_TOTAL} s and commanded the safe state"
recording=$(ls -t var/dbw/recordings/*.mcap 2>/dev/null | head -1 || true)
if [ -n "$recording" ]; then
  say "the flight recorder's file: what it holds"; "$BIN/dbw" record check "$recording" || true
  say "and the same run replayed through the control core"; "$BIN/dbw" replay "$recording" || true
fi
