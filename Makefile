# rig: make install | make demo | make test | make bench | make bench-console
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: install demo test bench bench-console browser clean

install: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[test]'
	touch $(STAMP)

demo: install
	$(BIN)/rig demo --out demo_out --overwrite

# Debian's chromium for the console's browser tests; installing needs root (CI has it). Without it the
# browser tests skip with one line saying why.
browser:
	@if command -v chromium >/dev/null 2>&1; then :; \
	elif [ "$$(id -u)" = 0 ]; then \
	  echo "make: installing chromium (apt-get) for the console's browser tests"; \
	  (DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null 2>&1 || \
	   (apt-get update -qq >/dev/null 2>&1 && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null)) \
	  || echo "make: chromium could not be installed: the console's browser tests will be skipped"; \
	else echo "make: chromium is missing and this is not root: the console's browser tests will be skipped"; fi

test: install browser
	MPLBACKEND=Agg $(BIN)/python -m pytest -q tests

bench: install
	$(BIN)/rig bench sim --seconds 100 --rate 5000
	$(BIN)/rig bench loop --rate 5000 --seconds 10
	$(BIN)/rig bench loop --feedforward --rate 5000 --seconds 5 --rounds 4

bench-console: install browser
	$(BIN)/rig bench loop --console --rate 5000

clean:
	rm -rf $(VENV) demo_out build *.egg-info
