# One-command set-up: every target below creates the virtual environment on first use.
#   make demo    simulate the default street scene and write its clouds and bags
#   make test    run every test
#   make bench   print throughput and peak memory of the hot paths
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
OUT    ?= output/demo

.PHONY: venv demo test bench lock clean

venv: $(STAMP)

# Rebuilt only when the pins or the package metadata change, so the second run is quick.
$(STAMP): requirements.lock setup.py
	@$(PYTHON) -c 'import sys; assert sys.version_info[:2] == (3, 11), \
	  "ROS 2 Jazzy wheels need CPython 3.11, found " + sys.version.split()[0]'
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade "pip==25.3" "setuptools==80.9.0" "wheel==0.45.1"
	$(PY) -m pip install --quiet -r requirements.lock
	$(PY) -m pip install --quiet --no-deps --no-build-isolation -e .
	touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/uncertain-facade-map simulate --scene street --out $(OUT) --force

test: $(STAMP)
	$(PY) -m pytest

bench: $(STAMP)
	$(PY) -m uncertain_facade_map.bench

# Re-resolve requirements.in and rewrite requirements.lock (needs the registries).
lock:
	rm -rf .venv-lock && $(PYTHON) -m venv .venv-lock
	.venv-lock/bin/pip install --quiet -r requirements.in
	.venv-lock/bin/python tools/freeze_lock.py > requirements.lock
	rm -rf .venv-lock

clean:
	rm -rf $(VENV) output build install log
