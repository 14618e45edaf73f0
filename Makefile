# Quick start: `make demo` and `make test` set up .venv on first use.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.perscli-installed

.PHONY: install test-slow demo demo-diagnose demo-field test bench bench-render bench-measure bench-correlate bench-diagnose man samples clean

$(STAMP): pyproject.toml setup.py src/perscli/_kernels.c $(wildcard man/*.1)
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test]'
	# bytecode up front, as a regular (non-editable) install does: with PYTHONDONTWRITEBYTECODE set
	# every command would otherwise recompile perscli's sources (~70 ms a process)
	$(BIN)/python -m compileall -q src/perscli
	# the man pages where man looks for them when .venv/bin is on PATH (an editable install skips
	# data files): man perscli-render
	mkdir -p $(VENV)/share/man/man1
	cp man/*.1 $(VENV)/share/man/man1/
	touch $@

# perscli in .venv, with its man pages
install: $(STAMP)
	@echo "installed: .venv/bin/perscli (source .venv/bin/activate, then perscli --help, man perscli-render)"

# The main job on the bundled sample data: persistence of three earlier
# exposures on the fourth, then the persistence alone.
demo: $(STAMP)
	mkdir -p demo_output
	$(BIN)/perscli -v apply-persistence sample_data/exp4.fits sample_data/exp1.fits \
	    sample_data/exp2.fits sample_data/exp3.fits -o demo_output/exp4_persist.fits --overwrite
	$(BIN)/perscli -v apply-persistence sample_data/exp4.fits sample_data/exp1.fits \
	    sample_data/exp2.fits sample_data/exp3.fits --mode predict -o demo_output/exp4_predicted.fits --overwrite
	@$(MAKE) --no-print-directory demo-diagnose
	@echo "demo outputs in demo_output/"

# diagnose on a small field: three exposures "measured" with a dark current of 0.3 e-/s (the hidden
# effect) and simulated with the Roman model (0.015 e-/s); diagnose names it, fits it and writes
# demo_output/diagnose/report.md with the model that closes the gap.
DIAG := demo_output/diagnose_inputs
POINT := --ra 10 --dec -44 --pa 30 --filter J129 --sca 7 --bounds 1001 1128 2001 2128
demo-diagnose: $(STAMP)
	mkdir -p $(DIAG)
	$(BIN)/perscli catalog --ra 9.5386 --dec -44.0435 --size 1 --star-density 10 --seed 1 -o $(DIAG)/truth.fits --overwrite
	$(BIN)/perscli render $(DIAG)/truth.fits $(POINT) --mjd 61541.97 --seed 11 -o $(DIAG)/sim0.fits --overwrite
	$(BIN)/perscli render $(DIAG)/truth.fits $(POINT) --mjd 61541.97196528 --seed 12 --previous $(DIAG)/sim0.fits \
	    -o $(DIAG)/sim1.fits --overwrite
	$(BIN)/perscli render $(DIAG)/truth.fits $(POINT) --mjd 61541.97393056 --seed 13 --previous $(DIAG)/sim0.fits \
	    --previous $(DIAG)/sim1.fits -o $(DIAG)/sim2.fits --overwrite
	$(BIN)/perscli render $(DIAG)/truth.fits $(POINT) --mjd 61541.97 --seed 21 --set dark.current=0.3 -o $(DIAG)/meas0.fits --overwrite
	$(BIN)/perscli render $(DIAG)/truth.fits $(POINT) --mjd 61541.97196528 --seed 22 --set dark.current=0.3 \
	    --persistence-source all --previous $(DIAG)/meas0.fits -o $(DIAG)/meas1.fits --overwrite
	$(BIN)/perscli render $(DIAG)/truth.fits $(POINT) --mjd 61541.97393056 --seed 23 --set dark.current=0.3 \
	    --persistence-source all --previous $(DIAG)/meas0.fits --previous $(DIAG)/meas1.fits -o $(DIAG)/meas2.fits \
	    --overwrite
	$(BIN)/perscli -v diagnose $(DIAG)/meas0.fits $(DIAG)/meas1.fits $(DIAG)/meas2.fits --simulated $(DIAG)/sim0.fits \
	    --simulated $(DIAG)/sim1.fits --simulated $(DIAG)/sim2.fits -o demo_output/diagnose --overwrite

# A small real field: Gaia DR2 stars plus simulated galaxies, observed by three
# consecutive J129 exposures of the public Roman WAS schedule (bundled: rows 4182-4184,
# 170 s apart) on the same 2048x2048 pixels of SCA 1; the third exposure is
# rendered with and without the persistence of the first two.
SHARED ?= ../shared/data
FIELD  := demo_output/field
demo-field: $(STAMP)
	@test -d $(SHARED)/gaia || { echo "demo-field needs the Gaia DR2 chunks in $(SHARED)/gaia"; exit 1; }
	mkdir -p $(FIELD)
	$(BIN)/perscli pointings select --ra 9.98 --dec -43.86 \
	    --radius 0.04 --filter J129 --limit 3 --sca 1 -o $(FIELD)/pointings.fits --overwrite
	$(BIN)/perscli catalog --ra 10.0477 --dec -43.7909 --size 20 --gaia $(SHARED)/gaia/145650.fits \
	    --seed 1 -o $(FIELD)/truth.fits --overwrite
	$(BIN)/perscli -v render $(FIELD)/truth.fits --pointings $(FIELD)/pointings.fits --row 0 --bounds 1 2048 1 2048 \
	    --seed 1 -o $(FIELD)/exp1.fits --overwrite
	$(BIN)/perscli -v render $(FIELD)/truth.fits --pointings $(FIELD)/pointings.fits --row 1 --bounds 1 2048 1 2048 \
	    --seed 2 --previous $(FIELD)/exp1.fits -o $(FIELD)/exp2.fits --overwrite
	$(BIN)/perscli -v render $(FIELD)/truth.fits --pointings $(FIELD)/pointings.fits --row 2 --bounds 1 2048 1 2048 \
	    --seed 3 --previous $(FIELD)/exp1.fits --previous $(FIELD)/exp2.fits -o $(FIELD)/exp3.fits --overwrite \
	    --plot $(FIELD)/exp3.png
	$(BIN)/perscli -v render $(FIELD)/truth.fits --pointings $(FIELD)/pointings.fits --row 2 --bounds 1 2048 1 2048 \
	    --seed 3 --set persistence=off -o $(FIELD)/exp3_nopersist.fits --overwrite
	@echo "field demo outputs in $(FIELD)/"

# the suite a developer runs often (at most 10 minutes on 2 cores); the slow tests (the whole small
# study, the README walkthrough, the calibration of diagnose) are `make test-slow`, which CI also runs
test: $(STAMP)
	$(BIN)/python -m pytest -q -m "not slow"

test-slow: $(STAMP)
	$(BIN)/python -m pytest -q -m slow

# All benchmarks (several minutes); each rewrites only its own section of benchmarks/RESULTS.md.
bench: $(STAMP)
	$(BIN)/python benchmarks/bench_apply_persistence.py
	$(BIN)/python benchmarks/bench_render.py
	$(BIN)/python benchmarks/bench_measure.py
	$(BIN)/python benchmarks/bench_correlate.py
	$(BIN)/python benchmarks/bench_diagnose.py

bench-render: $(STAMP)
	$(BIN)/python benchmarks/bench_render.py

bench-measure: $(STAMP)
	$(BIN)/python benchmarks/bench_measure.py

bench-correlate: $(STAMP)
	$(BIN)/python benchmarks/bench_correlate.py

bench-diagnose: $(STAMP)
	$(BIN)/python benchmarks/bench_diagnose.py

man: $(STAMP)
	$(BIN)/perscli man --all -o man --overwrite

samples: $(STAMP)
	$(BIN)/python sample_data/make_samples.py sample_data

clean:
	rm -rf demo_output build src/*.egg-info
