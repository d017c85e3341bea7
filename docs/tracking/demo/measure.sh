#!/usr/bin/env bash
# The demo against a real `bb-align serve` on loopback, as docs/tracking.md reports it.
#   docs/tracking/demo/measure.sh OUT_NAME BUSY_LOOPS [demo options...]
# e.g. measure.sh quiet 0 --frames 30;  measure.sh busy 2 --frames 30;
#      measure.sh jump44 0 --frames 60 --odometry-jump ego:15:4,4
# Writes docs/tracking/demo/OUT_NAME.{txt,json}. Every process it starts is stopped by its id.
set -u
cd "$(dirname "$0")/../../.."
name=$1; busy=$2; shift 2
out=docs/tracking/demo
port=$(.venv/bin/python -c 'from bb_align.lab.harness import free_port; print(free_port())')
zport=$(.venv/bin/python -c 'from bb_align.lab.harness import free_port; print(free_port())')
.venv/bin/bb-align serve --demo --port "$port" --zenoh-listen "tcp/127.0.0.1:$zport" > "$out/$name.serve.log" 2>&1 &
serve=$!
loops=()
for _ in $(seq 1 "$busy"); do .venv/bin/python -c 'while 1: pass' & loops+=($!); done
for _ in $(seq 1 120); do curl -sf "http://127.0.0.1:$port/readyz" > /dev/null && break; sleep 0.5; done
{ echo "# $(date -u +%FT%TZ) busy loops: $busy; load: $(cut -d' ' -f1-3 /proc/loadavg)";
  echo "# bb-align demo --connect tcp/127.0.0.1:PORT --json $out/$name.json $*"; } > "$out/$name.txt"
COLUMNS=200 .venv/bin/bb-align demo --connect "tcp/127.0.0.1:$zport" --json "$out/$name.json" "$@" 2>/dev/null \
  | grep -v "^\s*$" | tail -n 40 >> "$out/$name.txt"
for p in "${loops[@]}"; do kill "$p"; done
kill -INT "$serve"; wait "$serve" 2>/dev/null
echo "# load after: $(cut -d' ' -f1-3 /proc/loadavg)" >> "$out/$name.txt"
.venv/bin/python - "$out/$name.json" >> "$out/$name.txt" <<'PY'
import json, sys
s = json.load(open(sys.argv[1]))["summary"]
keys = ("peer_frames_sent", "results", "success", "wrong_success", "wrong_seqs", "err_t_m_max", "err_r_deg_max",
        "err_t_m_median", "latency_ms_median", "latency_ms_p90")
print("summary:", json.dumps({k: s.get(k) for k in keys}))
PY
tail -n 3 "$out/$name.txt"
