# `make test` and `make run` bootstrap .venv on a fresh machine (only python3 needed), then run.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: venv test run bench-accuracy bench-real bench-icp bench-sim-real bench-sim-places bench-engine bench-flood clean

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[lab,test]'
	touch $(STAMP)

venv: $(STAMP)

# The formatter and linter first (ruff, configured in pyproject.toml), then the suite.
test: $(STAMP)
	$(VENV)/bin/ruff format --check .
	$(VENV)/bin/ruff check .
	$(PY) -m pytest -q

# The embedded demo profile: authentication OFF, loopback only (the banner says so). Secure: docs/security.md.
run: $(STAMP)
	$(VENV)/bin/bb-align serve --demo

clean:
	rm -rf $(VENV) build *.egg-info service/*.egg-info

# Benchmarks write their results under out/ (the checkout stays as it was: `git status` clean); RECORD=1 writes them
# into docs/ instead, the recorded output the docs cite (e.g. `make bench-real RECORD=1`).
RECORD ?=
RESULTS := $(if $(filter 1 yes true,$(RECORD)),docs,out)
RECORD_FLAG := $(if $(filter 1 yes true,$(RECORD)),--record,)

# Accuracy benchmark: 200 seeded simulated pairs (0-100 m, heterogeneous LiDARs, self-motion distortion),
# summary JSON, per-pair records and figures into $(RESULTS)/accuracy/ (see docs/accuracy.md).
BENCH_ACC_DIR ?= out/bench_accuracy
bench-accuracy: $(STAMP)
	rm -rf $(BENCH_ACC_DIR)
	$(VENV)/bin/bb-align sim $(BENCH_ACC_DIR) --scenarios 200 --seed 2024 --workers 2
	$(VENV)/bin/bb-align eval $(BENCH_ACC_DIR) --workers 2 --pose-noise 2,2 --json $(RESULTS)/accuracy/summary.json \
		--records $(RESULTS)/accuracy/pairs.jsonl --plots $(RESULTS)/accuracy
	$(VENV)/bin/bb-align eval $(BENCH_ACC_DIR) --workers 2 --pose-noise 2,2 --prior \
		--json $(RESULTS)/accuracy_prior/summary.json --records $(RESULTS)/accuracy_prior/pairs.jsonl

# Real-pair benchmark: every pair of real scans in ../shared/data (KITTI, Apollo-SouthBay, DAIR-V2X-C), without
# and with a seeded 2 m / 2 deg prior, scored against each pair's reference; then the multi-frame rows: the far
# street's 20 steps from a second of stream, without and with the GNSS-grade prior, and two cities apart (about two
# minutes more). Tables and plots into $(RESULTS)/real_pairs/.
SHARED_DATA ?= ../shared/data
bench-real: $(STAMP)
	$(VENV)/bin/bb-align real-pairs $(SHARED_DATA) --out $(RESULTS)/real_pairs
	$(PY) benchmarks/stream_acquire.py --data $(SHARED_DATA) --out $(RESULTS)/real_pairs/stream_real

# The real pairs' yardstick: point-to-plane ICP (small_gicp, the `bench` extra) on the full clouds from the same
# seeded prior, beside bb-align aligned in the same run; into docs/real_pairs/icp_from_prior.* (docs/real_pairs.md).
# A target of its own: it takes a few minutes on 2 cores, more than bench-real itself.
$(VENV)/.installed-bench: $(STAMP)
	$(PY) -m pip install -q -e '.[bench]'
	touch $@

bench-icp: $(VENV)/.installed-bench
	$(PY) benchmarks/icp_from_prior.py --data $(SHARED_DATA) $(RECORD_FLAG)

# Simulated far pairs beside the real KITTI 00 ones: the street family (a car following another 73-81 m ahead on a
# straight residential street), the turn family (the peer turned into a crossing street 40-70 m; HDL-64 on all
# away) and the accuracy benchmark's pairs >= 70 m (run bench-accuracy first); table, JSON and plot into
# $(RESULTS)/real_pairs/ (docs/real_pairs.md). The two families are rendered de-skewed, as KITTI odometry's scans are.
bench-sim-real: $(STAMP)
	rm -rf out/sim_street out/sim_turn
	$(VENV)/bin/bb-align sim out/sim_street --family street --scenarios 20 --seed 7 --fleet hdl64 \
		--min-distance 73 --max-distance 81 --no-distortion --workers 2
	$(VENV)/bin/bb-align sim out/sim_turn --family turn --scenarios 20 --seed 7 --fleet hdl64 --no-distortion \
		--workers 2
	$(PY) benchmarks/sim_vs_real.py --data $(SHARED_DATA) --sim "mixed, >= 70 m=$(BENCH_ACC_DIR)@70" \
		--sim "street family=out/sim_street" --sim "turn family=out/sim_turn" $(RECORD_FLAG)

# Simulated street places, each rendered as the real KITTI 00 run is (10 follower sweeps against 2 sweeps of the car
# 73-81 m ahead), and the real place's standing among them ($(RESULTS)/sim/places.*; about 10 minutes on 2 cores).
bench-sim-places: $(STAMP)
	$(PY) benchmarks/sim_places.py --data $(SHARED_DATA) --places 40 $(RECORD_FLAG)

# The engine's departures from the paper, measured (docs/engine.md; real rows need ../shared/data).
bench-engine: $(STAMP)
	$(PY) benchmarks/engine_ablation.py --data $(SHARED_DATA)

# Floods against a bb-align serve child process: several keyless sessions, then large queries (docs/security.md;
# results into $(RESULTS)/).
bench-flood: $(STAMP)
	mkdir -p $(RESULTS)
	$(PY) benchmarks/stream_flood.py --seconds 10 --blocks 3 --flooders 2 --sizes small,big --pin \
		--json $(RESULTS)/security_stream_flood_pinned.json --plot $(RESULTS)/security_stream_flood_pinned.png
	$(PY) benchmarks/stream_flood.py --seconds 10 --blocks 3 --flooders 2 --sizes small,big \
		--json $(RESULTS)/security_stream_flood_unpinned.json --plot $(RESULTS)/security_stream_flood_unpinned.png
	$(PY) benchmarks/query_flood.py --seconds 25 --senders 2 --mb 4 --kind envelope --pin \
		> $(RESULTS)/security_query_flood.json
