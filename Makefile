# The two commands a newcomer types: `make demo` and `make test`. Both bootstrap .venv first
# (idempotent; see scripts/bootstrap.sh).
PY := .venv/bin/python
export AMENT_PREFIX_PATH := $(CURDIR)/.venv

.PHONY: bootstrap demo test bench colcon clean
bootstrap:
	@scripts/bootstrap.sh

demo: bootstrap
	@.venv/bin/mlv-ros demo

test: bootstrap
	@$(PY) -m pytest

bench: bootstrap
	@.venv/bin/mlv-ros bench all

clean:
	rm -rf build install log .venv
