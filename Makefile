# Two commands on a fresh machine with only python3: `make demo` and `make test`.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: demo test digests bench bench-anchors bench-borders bench-ratecontrol bench-memory fuzz reproduce clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e ".[test,compare,ros,ros2,dask,zarr,slam,fast,remote]"
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/dftpcc demo

test: $(STAMP)
	$(BIN)/python -m pytest -q
	$(MAKE) test-web

# The JavaScript decoder (web/, Node >= 20 and npm): npm ci when node_modules is missing or older than
# the lockfile, a build (tsc checks, esbuild bundles), then node:test against the Python decoder on
# files written from ../shared/data into a temporary folder by the venv's python (a few minutes the
# first time, reused while the codec and web/test/fixtures.py are unchanged).
WEB_STAMP := web/node_modules/.package-lock.json

$(WEB_STAMP): web/package.json web/package-lock.json
	@command -v npm >/dev/null || { echo "make test-web needs Node >= 20 and npm"; exit 1; }
	cd web && npm ci --no-audit --no-fund
	touch $(WEB_STAMP)

.PHONY: test-web
test-web: $(STAMP) $(WEB_STAMP)
	cd web && npm run build
	cd web && PYTHON=$(abspath $(BIN))/python node test/prepare.mjs
	cd web && PYTHON=$(abspath $(BIN))/python node --test --test-concurrency=1 test/*.test.mjs

# JS decode speed (M cells/s) in Node and in headless chromium against the Python decoder and the lerc npm
# decoder (at equal maximum error), same run, one core each, on the shared DEMs and a 4 M-cell mosaic, after
# W warm-up decodes, and where Chromium's time goes stage by stage (~3 min; ARGS="--repeats N --warmup W
# --side S --no-mosaic --no-browser"); then the viewer's time to first rendered frame of the mosaic in
# headless chromium (~1 min). web/bench/ab.mjs compares two builds interleaved in one page.
.PHONY: bench-web
bench-web: $(STAMP) $(WEB_STAMP)
	cd web && npm run build
	cd web && PYTHON=$(abspath $(BIN))/python node bench/bench.mjs $(ARGS)
	cd web && PYTHON=$(abspath $(BIN))/python node bench/first_frame.mjs

# The viewer page of `dftpcc view` (web/viewer/) into src/dftpcc/viewer_assets/, which is committed so that
# pip users need no Node; web/test/viewer.test.mjs fails while the committed copy differs from a fresh build.
.PHONY: viewer test-viewer
viewer: $(WEB_STAMP)
	cd web && node viewer/build.mjs

# Only the viewer's browser tests (make test-web runs them with the rest; needs /usr/bin/chromium).
test-viewer: $(STAMP) $(WEB_STAMP)
	cd web && PYTHON=$(abspath $(BIN))/python node --test test/viewer.test.mjs

# Bits, error and speed per profile and cutoff (ARGS=--quick for fewer cutoffs and repeats).
bench: $(STAMP)
	$(BIN)/python -m benchmarks.bench_codec $(ARGS)

# Rate-distortion against Draco, JPEG2000, HTJ2K, JPEG XL, LERC, SZ3 and LAZ, and a table at equal maximum error (~7 min on the shared 2-core box; ARGS=--quick ~2 min).
bench-anchors: $(STAMP)
	$(BIN)/python -m benchmarks.bench_anchors $(ARGS)

# Rate control per target, smooth against consistent fill (~2 min): rewrites its section of docs/benchmarks.md.
bench-ratecontrol: $(STAMP)
	$(BIN)/python -m benchmarks.bench_ratecontrol $(ARGS)

# A target's CPU time against one fixed encode, per map, untiled and tiled, 3 runs, the achieved error against the bound (issue 43; ~10 min on the shared 2-core box; ARGS=--quick one run, ARGS=--with-search also the search's sizes, slow).
.PHONY: bench-targets
bench-targets: $(STAMP)
	$$(command -v taskset >/dev/null && echo taskset -c 0) $(BIN)/python -m benchmarks.bench_ratecontrol --speed $(ARGS)

# A map's decode against one inverse DCT of its grid, on a 1.6 M-cell mosaic of two shared DEMs, fixed and with a residual layer, then each shared DEM with a predicted residual layer at 1 m, each backend (issue 43 item 3; ~4 min).
.PHONY: bench-decode
bench-decode: $(STAMP)
	$$(command -v taskset >/dev/null && echo taskset -c 0) $(BIN)/python -m benchmarks.bench_decode $(ARGS)

# What each of a tiled target's runs (first, covering base layer, base layer alone) costs and how often it gives the smallest file (issue 43; ~10 min).
.PHONY: bench-tiled-runs
bench-tiled-runs: $(STAMP)
	$$(command -v taskset >/dev/null && echo taskset -c 0) $(BIN)/python -m benchmarks.bench_tiled_runs $(ARGS)

# Peak memory of a large cloud read whole and in chunks (~1 min, temporary LAZ files of up to 22.7 M points).
bench-memory: $(STAMP)
	$(BIN)/python -m benchmarks.bench_memory $(ARGS)

# dftpcc as a Zarr chunk codec against zarr's default (zstd), LERC and SZ3 at equal maximum error (6-9 min on the shared 2-core box; ARGS=--quick ~15 s).
.PHONY: bench-zarr
bench-zarr: $(STAMP)
	$(BIN)/python -m benchmarks.bench_zarr $(ARGS)

# Per-stage speed on one core against DracoPy, LERC and HTJ2K, then one core against two apart (~1 min; needs both cores, so no taskset;
# ARGS=--quick for 3 repeats): rewrites its section of docs/benchmarks.md.
.PHONY: bench-speed
bench-speed: $(STAMP)
	$(BIN)/python -m benchmarks.bench_speed $(ARGS)

# A map growing scan by scan: per-scan latency of add + encode (16/64-beam, 0.1/0.5 m, maps of 1e5-1e7 cells) and bytes sent per minute of driving, deltas against the whole map and Draco-coded scans (~6 min; ARGS=--quick ~1 min).
.PHONY: bench-slam
bench-slam: $(STAMP)
	$(BIN)/python -m benchmarks.bench_slam $(ARGS)

# The rover-ground link (issue 44): rover latency per scan on maps of 1e5-1e7 cells, downlink bytes, scan-to-ground
# time at 2 and 20 kB/s, recovery after 10 % loss and a 60 s outage, final files compared (~25 min; ARGS=--quick ~6 min).
.PHONY: bench-link
bench-link: $(STAMP)
	$(BIN)/python -m benchmarks.bench_link $(ARGS)

# Tiled maps (issue 12): rate cost per tile size, seams on every map, one tile read from disk, speed; rewrites its section of docs/benchmarks.md and docs/figures/tiles_error_map.png (~15-20 min on the shared 2-core box; ARGS=--quick a few minutes).
.PHONY: bench-tiles
bench-tiles: $(STAMP)
	$(BIN)/python -m benchmarks.bench_tiles $(ARGS)

# Maps larger than memory: peak memory and throughput of a 1.6 G-cell GeoTIFF and a 102 M-point LAZ at a quarter, half and the whole, serial and on 2 dask workers (~75 min on the shared 2-core box, up to ~8 GB of temporary files under /tmp, removed after; ARGS=--quick ~7 min).
.PHONY: bench-big
bench-big: $(STAMP)
	$(BIN)/python -m benchmarks.bench_big $(ARGS)

# Regenerates docs/reproduction.md and docs/figures/repro_* from ../shared/data.
reproduce: $(STAMP)
	$(BIN)/python scripts/reproduce.py

# Border handling, fill and coder at equal error (~4 min): rewrites docs/borders.md.
bench-borders: $(STAMP)
	$(BIN)/python -m benchmarks.bench_borders > docs/borders.md

# The files the codec writes on ../shared/data, against tests/digests.json (~5 min; exact, so on the recording machine).
digests: $(STAMP)
	$(BIN)/python scripts/digests.py

# The decoder and link-frame fuzz campaigns (100,000 inputs, ~2 min each), the deltas' (100,000; 34 min
# at a load of 20 on the shared 2-core box) and the growing map's state file (100,000 states, the peak
# memory of every 10th measured; ~25 min on the shared box); the test suite runs short ones.
fuzz: $(STAMP)
	$(BIN)/python tests/fuzz/fuzz_decoder.py --iterations 100000 --seed 11
	$(BIN)/python tests/fuzz/fuzz_link.py --iterations 100000 --seed 11
	$(BIN)/python tests/fuzz/fuzz_delta.py --iterations 100000 --seed 11
	$(BIN)/python tests/fuzz/fuzz_state.py --iterations 100000 --seed 11 --trace-every 10

# Can the rover still localize? Simulated lidar scans registered (GICP) against maps rebuilt at each cutoff
# and target on Mars Gale, Moon Kepler, Davos and the IGN field: rewrites docs/relocalization.md and
# docs/figures/reloc_*.png (12-16 min on the shared 2-core box; ARGS=--quick, a few minutes, writes no docs).
.PHONY: relocalize
relocalize: $(STAMP)
	$(BIN)/python scripts/relocalize.py $(ARGS)

clean:
	rm -rf $(VENV) build *.egg-info src/*.egg-info .pytest_cache .hypothesis web/node_modules web/dist
