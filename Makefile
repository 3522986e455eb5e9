# The two commands a newcomer types: `make demo` and `make test`. Both bootstrap .venv first
# (idempotent; see scripts/bootstrap.sh).
PY := .venv/bin/python
export AMENT_PREFIX_PATH := $(CURDIR)/.venv

.PHONY: bootstrap demo test bench fuzz colcon clean
bootstrap:
	@scripts/bootstrap.sh

demo: bootstrap
	@.venv/bin/mlv-ros demo

test: bootstrap
	@$(PY) -m pytest

bench: bootstrap
	@.venv/bin/mlv-ros bench all

# Not part of `make test`: atheris (requirements/fuzz.txt) on the DICOM reader and the message
# decoders for FUZZ_SECONDS per target; prints a JSON summary, fails if a crash was found.
FUZZ_SECONDS ?= 60
fuzz: bootstrap
	@$(PY) -m pip install --disable-pip-version-check -q -r requirements/fuzz.txt
	@$(PY) fuzz/run.py --seconds $(FUZZ_SECONDS)

clean:
	rm -rf build install log .venv mlv_ros/core/meshless/_fused_c.so mlv_ros/core/_median_c.so
