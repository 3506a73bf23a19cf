# Quick start: `make demo` (set up + run the main job on the built-in synthetic scene)
# and `make test` (set up + run the whole test suite). Both work on a fresh machine.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
DEMO_OUT ?= out/demo

.PHONY: setup demo test test-fast lint bench soak fuzz clean

setup: $(STAMP)

# open3d's Linux wheels link against libusb-1.0; install it where it is missing.
$(STAMP): pyproject.toml
	@if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then \
		echo "installing libusb-1.0 (needed by open3d)"; \
		if [ "$$(id -u)" = 0 ]; then SUDO=""; else SUDO="sudo"; fi; \
		$$SUDO apt-get update -qq && $$SUDO apt-get install -y -qq libusb-1.0-0 >/dev/null; \
	fi
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[dev]'
	@touch $(STAMP)

demo: $(STAMP)
	$(BIN)/planeslam demo --out $(DEMO_OUT)

# Both test targets spread the test modules over the machine's cores (pytest-xdist; each
# module runs whole in one worker, so its fixtures are made once) and keep compiled
# bytecode and pytest's rewritten test modules even where PYTHONDONTWRITEBYTECODE is set
# (recompiling them cost about 5 s of every run).
PYTEST := PYTHONDONTWRITEBYTECODE= $(BIN)/python -m pytest -q -n auto --dist loadfile

test: $(STAMP)
	$(PYTEST)

# The unit tests (each test module sets its tier with `pytestmark`; a test of a unit module
# that crosses stages is marked integration itself), without the slow ones and those on the
# real data (< 20 s); `make test` runs everything.
test-fast: $(STAMP)
	$(PYTEST) -m "unit and not integration and not slow and not data"

lint: $(STAMP)
	$(BIN)/ruff check planeslam factors eval tests examples
	$(BIN)/ruff format --check planeslam factors eval tests examples
	$(BIN)/mypy planeslam factors eval examples

bench: $(STAMP)
	$(BIN)/planeslam bench frontend

# Many short runs with random faults (in-process and through the CLI), then a check that
# child processes, open files and memory are back where they started (a few minutes).
soak: $(STAMP)
	$(BIN)/python -m tests.soak

# The property-based fault corpus (tests/test_faults_fuzz.py) with many more examples
# than the suite's: about 10 minutes on one core (FUZZ_EXAMPLES per reader).
FUZZ_EXAMPLES ?= 12000
fuzz: $(STAMP)
	PLANESLAM_FUZZ=1 PLANESLAM_FUZZ_EXAMPLES=$(FUZZ_EXAMPLES) $(BIN)/python -m pytest -q -p no:cacheprovider tests/test_faults_fuzz.py

clean:
	rm -rf $(VENV) out build *.egg-info
