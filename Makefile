# The two commands: `make run` (the whole pipeline on the embedded tiny profile) and
# `make test`. Both create .venv when it is missing or when the pinned set changed.
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
TORCH := torch==2.13.0
UV := uv==0.13.8
WAYMO := waymo-open-dataset-tf-2-12-0==1.6.7

export PREFECT_HOME := $(CURDIR)/.prefect
export PREFECT_SERVER_ANALYTICS_ENABLED := false
export PREFECT_LOGGING_LEVEL ?= WARNING
export DO_NOT_TRACK := 1
# MLflow reads DO_NOT_TRACK only as "true"; without this it fetches a config and posts usage at exit
export MLFLOW_DISABLE_TELEMETRY := true
export DVC_NO_ANALYTICS := 1
export MLFLOW_TRACKING_URI ?= sqlite:///$(CURDIR)/mlruns.db
export PATH := $(CURDIR)/$(BIN):$(PATH)

.PHONY: run test bench gpu-data serve setup clean

setup: $(STAMP)

# The stamp depends on the lock files: a changed pin reinstalls, an unchanged one does not.
$(STAMP): requirements.txt requirements.lock pyproject.toml
	@if ! ldconfig -p 2>/dev/null | grep -q libusb-1.0.so.0; then \
	  if [ "$$(id -u)" = 0 ]; then \
	    echo "open3d needs libusb-1.0-0: installing it with apt"; \
	    apt-get update -qq && apt-get install -y -qq libusb-1.0-0 >/dev/null; \
	  else echo "warning: libusb-1.0-0 is missing and we are not root; open3d may fail to import"; fi; \
	fi
	@# optional: only the real-browser check of the MLflow UI (tests/unit/flows/test_mlflow_ui.py) needs it
	@if ! command -v chromium >/dev/null 2>&1; then \
	  if [ "$$(id -u)" = 0 ]; then \
	    echo "the MLflow UI browser test needs chromium: installing it with apt"; \
	    (apt-get update -qq && apt-get install -y -qq chromium >/dev/null) || \
	      echo "warning: could not install chromium; tests/unit/flows/test_mlflow_ui.py will be skipped"; \
	  else echo "note: chromium is missing and we are not root; tests/unit/flows/test_mlflow_ui.py will be skipped"; fi; \
	fi
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	# torch first, alone, with pip (which takes the CPU wheel on this machine's disk; uv does not
	# look there), so that nothing later can pull a CUDA build: the rest names the same torch,
	# which the installed one satisfies. uv installs the pinned set in 64 s where pip took 248 s
	# (same 258 packages, same versions). Both byte-compile what they install: with
	# PYTHONDONTWRITEBYTECODE set (as on CI images), skipping it made every stage compile its
	# imports again from source (the gap between stages went from 16 to 30 s)
	$(BIN)/python -m pip install -q $(TORCH) $(UV)
	$(BIN)/uv pip install --python $(BIN)/python --compile-bytecode -q $(TORCH) -r requirements.txt -c requirements.lock
	$(BIN)/python -m pip install -q --no-deps $(WAYMO)
	$(BIN)/python -m pip install -q --no-deps --no-build-isolation -e .
	$(BIN)/python -c "import torch, open3d, prefect, mlflow, dvc; assert torch.__version__.startswith('2.13.0'), torch.__version__"
	touch $(STAMP)

# one Prefect server for every stage dvc starts (not one per stage), stopped when dvc ends;
# a PREFECT_API_URL in the environment (a server of yours, Prefect Cloud) is used instead
run: $(STAMP)
	$(BIN)/typ with-server $(BIN)/dvc repro
	$(BIN)/typ report

# two pytest-xdist workers of one thread each, a file per worker at a time (module fixtures run
# once): most long tests wait on servers and subprocesses, so two halve the wall time. The 25
# slowest tests are listed at the end, where the suite's time goes.
TEST_WORKERS ?= 2
test: $(STAMP)
	$(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist loadfile --no-loadscope-reorder --durations=25

# sampling needs the trained models of `make run` (artifacts/), pipeline its metrics (the
# default data's skipping; its dvc runs are in a throwaway copy); voxelize, pcd_lzf and attention
# need nothing.
# report.py gathers every reports/bench_*.md into reports/bench.md, with the pages of
# reports/gpu/ (bench/gpu.py on a GPU machine; not rerun here).
bench: $(STAMP)
	$(BIN)/python bench/voxelize.py --out reports
	$(BIN)/python bench/pcd_lzf.py --out reports
	$(BIN)/python bench/attention.py --out reports
	test -f artifacts/stage1/model.pt || $(BIN)/typ with-server $(BIN)/dvc repro
	$(BIN)/python bench/sampling.py --out reports
	$(BIN)/python bench/pipeline.py --out reports
	$(BIN)/python bench/ddp.py --out reports
	$(BIN)/python bench/report.py --out reports

# bench/gpu.py's data (.gpu/, carried to the GPU machine) and its CPU side (reports/gpu/cpu/):
# simulated, voxelized and re-simulated here at bench/gpu.yaml's size, with this project's tiny
# figures on the same pairs (after `make run`)
gpu-data: $(STAMP)
	$(BIN)/python bench/gpu_data.py --out .gpu --tiny .
	$(BIN)/python bench/gpu.py --device cpu --quick --phases timings --bundle .gpu --out reports/gpu/cpu

# the scheduled Prefect deployments on a local server (http://127.0.0.1:4200), or on the
# server / Prefect Cloud that PREFECT_API_URL names; Ctrl-C stops both
serve: $(STAMP)
	$(BIN)/typ serve

clean:
	rm -rf $(VENV) .prefect
