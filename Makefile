# rig: make install | make demo | make test | make bench
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: install demo test bench clean

install: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[test]'
	touch $(STAMP)

demo: install
	$(BIN)/rig demo --out demo_out

test: install
	MPLBACKEND=Agg $(BIN)/python -m pytest -q tests

bench: install
	$(BIN)/rig bench sim --seconds 100 --rate 5000
	$(BIN)/rig bench loop --rate 5000 --seconds 10
	$(BIN)/rig bench loop --feedforward --rate 5000 --seconds 5 --rounds 4

clean:
	rm -rf $(VENV) demo_out build *.egg-info
