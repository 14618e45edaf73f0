# Quick start: `make demo` and `make test` set up .venv on first use.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.perscli-installed

.PHONY: demo test bench man samples clean

$(STAMP): pyproject.toml setup.py src/perscli/_kernels.c
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test]'
	touch $@

# The main job on the bundled sample data: persistence of three earlier
# exposures on the fourth, then the persistence alone.
demo: $(STAMP)
	mkdir -p demo_output
	$(BIN)/perscli -v apply-persistence sample_data/exp4.fits sample_data/exp1.fits \
	    sample_data/exp2.fits sample_data/exp3.fits -o demo_output/exp4_persist.fits --overwrite
	$(BIN)/perscli -v apply-persistence sample_data/exp4.fits sample_data/exp1.fits \
	    sample_data/exp2.fits sample_data/exp3.fits --mode predict -o demo_output/exp4_predicted.fits --overwrite
	@echo "demo outputs in demo_output/"

test: $(STAMP)
	$(BIN)/python -m pytest -q

bench: $(STAMP)
	$(BIN)/python benchmarks/bench_apply_persistence.py

man: $(STAMP)
	$(BIN)/python -m perscli.cli.manpages man

samples: $(STAMP)
	$(BIN)/python sample_data/make_samples.py sample_data

clean:
	rm -rf demo_output build src/*.egg-info
