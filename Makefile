# iCrowdNav pipeline. Every stage target takes PROFILE=smoke|default|paper, DATA_DIR=<dir>, ARGS="..." (extra CLI
# options for every stage it runs, e.g. ARGS=--overwrite to replace outputs made by an older config or code) and
# <STAGE>_ARGS="..." for one stage only (RECORD_ARGS, EXPORT_ARGS, PRETRAIN_ARGS, TRAIN_ARGS, EVAL_ARGS, ROLLOUT_ARGS).
#   make all      install (if needed), then run the pipeline end to end on the default profile
#   make test     install (if needed), then run the test suite
SHELL := /bin/bash
PROFILE ?= default
DATA_DIR ?= data
VENV ?= .venv
ARGS ?=
RECORD_ARGS ?=
EXPORT_ARGS ?=
ROLLOUT_ARGS ?=
EVAL_ARGS ?=
PRETRAIN_ARGS ?=
TRAIN_ARGS ?=
TRAIN_VARIANTS ?= teacher full no_i2 no_bev drl_vo sarl_om vint
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
export HF_HUB_OFFLINE := 1
export PYTHONHASHSEED := 0

.PHONY: install all record pretrain train eval rollout smoke test bench lint timings help

help:
	@echo "targets: install all record pretrain train eval rollout smoke test bench lint timings   (PROFILE=$(PROFILE) DATA_DIR=$(DATA_DIR))"

# The venv is rebuilt only when the lock file or pyproject.toml change (the stamp is newer otherwise).
# uv installs the exact pins of requirements.lock; its cache (~/.cache/uv) makes a re-install fast.
install: $(STAMP)
$(STAMP): requirements.lock pyproject.toml
	@test -x $(PY) || python3 -m venv $(VENV)
	@$(PY) -m pip --version >/dev/null 2>&1 || $(PY) -m ensurepip >/dev/null
	@$(VENV)/bin/python -m pip install -q --disable-pip-version-check "uv==0.13.9"
	$(VENV)/bin/uv pip sync -q --python $(PY) requirements.lock
	$(VENV)/bin/uv pip install -q --python $(PY) --no-deps -e . --config-settings editable_mode=compat
	@touch $(STAMP)

# record: expert episodes -> DATA_DIR/raw/<run>/*.mcap, then export -> DATA_DIR/datasets/<repo_id>/ (LeRobot v3.0)
record: install
	$(PY) -m pipeline record --profile $(PROFILE) --data-dir $(DATA_DIR) $(ARGS) $(RECORD_ARGS)
	$(PY) -m pipeline export --profile $(PROFILE) --data-dir $(DATA_DIR) $(ARGS) $(EXPORT_ARGS)

# pretrain: the intention model (-> DATA_DIR/checkpoints/intention/, minutes) and the spatio-temporal BEV encoder
# (-> DATA_DIR/checkpoints/bev/) on DATA_DIR/datasets/<repo_id> (a killed run continues with PRETRAIN_ARGS=--resume)
pretrain: install
	$(PY) -m pipeline pretrain-intention --profile $(PROFILE) --data-dir $(DATA_DIR) $(ARGS) $(INTENTION_ARGS)
	$(PY) -m pipeline pretrain --profile $(PROFILE) --data-dir $(DATA_DIR) $(ARGS) $(PRETRAIN_ARGS)

# train: the privileged teacher, then each visual student variant (DAgger from the teacher through the recorder,
# optional PPO fine-tuning), then the learned baselines (DRL-VO, SARL*-OM, ViNT-style)
# -> DATA_DIR/checkpoints/policy/<variant>/ (TRAIN_VARIANTS; a killed run: TRAIN_ARGS=--resume)
train: install
	@set -e; for v in $(TRAIN_VARIANTS); do \
	  $(PY) -m pipeline train --profile $(PROFILE) --data-dir $(DATA_DIR) --variant $$v $(ARGS) $(TRAIN_ARGS); done

# eval: the benchmark (every method on the same seeded episodes + long-horizon runs on a GVG map)
# -> DATA_DIR/eval/<run_name>/ (report.md, results.json/csv, paired tests, figures, videos, MCAP logs)
eval: install
	$(PY) -m pipeline eval --profile $(PROFILE) --data-dir $(DATA_DIR) $(ARGS) $(EVAL_ARGS)

# the expert's acceptance run on the test scenes: metrics, figures, videos -> DATA_DIR/rollouts/<run>/
rollout: install
	$(PY) -m pipeline rollout --profile $(PROFILE) --data-dir $(DATA_DIR) $(ARGS) $(ROLLOUT_ARGS)

all: install record pretrain train eval

# Every stage on tiny sizes through real files, into its own data dir (replaced on each run).
smoke: install
	$(MAKE) --no-print-directory record pretrain train eval PROFILE=smoke DATA_DIR=$(DATA_DIR)/smoke ARGS=--overwrite

test: install
	$(PY) -m pytest -q -p no:cacheprovider

bench: install
	$(PY) -m pipeline bench --profile $(PROFILE) --data-dir $(DATA_DIR)

# every finished stage's wall time in DATA_DIR (from the manifests): how long `make all` took, stage by stage
timings: install
	$(PY) -m pipeline timings $(DATA_DIR)

lint: install
	$(VENV)/bin/ruff check pipeline sim recorder pretrain rl evaluation tests docs/notes/scripts
