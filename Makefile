# Two entry points for a newcomer: `make demo` and `make test`.
# Both create .venv from nothing, install the package and its dependencies,
# then run. Re-running is cheap: the install step is skipped when
# pyproject.toml has not changed since the last install.
PY ?= python3
VENV ?= .venv
VPY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: install test demo bench clean sysdeps

$(VPY):
	$(PY) -m venv $(VENV)
	$(VPY) -m pip install -q --upgrade pip

# open3d needs Debian's libusb-1.0-0 at import time.
sysdeps:
	@if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then \
	  if [ "$$(id -u)" = "0" ] && command -v apt-get >/dev/null; then \
	    echo "installing libusb-1.0-0 (needed by open3d)"; \
	    (apt-get install -y -q libusb-1.0-0 >/dev/null 2>&1 || \
	     (apt-get update -q >/dev/null && apt-get install -y -q libusb-1.0-0 >/dev/null)) || \
	     { echo "ERROR: could not install libusb-1.0-0; open3d will not import"; exit 1; }; \
	  else \
	    echo "ERROR: open3d needs the system library libusb-1.0-0; install it (e.g. 'sudo apt-get install libusb-1.0-0')"; exit 1; \
	  fi; \
	fi

# torch: install the CPU build first when no torch is present, so pip does not
# pull several GB of CUDA packages on a machine without a GPU.
$(STAMP): pyproject.toml | $(VPY)
	@$(MAKE) --no-print-directory sysdeps
	@$(VPY) -c 'import torch' 2>/dev/null || $(VPY) -m pip install -q torch==2.13.0
	$(VPY) -m pip install -q -e '.[dev]'
	@touch $(STAMP)

install: $(STAMP)

# two workers (Warp's CPU backend runs a launch on one core); a file's tests stay on one worker, so its
# module fixtures are made once; files are handed out in collection order, the long ones first (tests/conftest.py)
test: install
	$(VPY) -m pytest -q -x -n 2 --dist loadfile --no-loadscope-reorder --durations=15 tests

demo: install
	$(VPY) -m empm_gym.demo --out demo_out

bench: install
	$(VPY) benchmarks/bench_mpm.py

clean:
	rm -rf $(VENV) demo_out .pytest_cache
