# Two entry points (README "Quick start"): `make demo` and `make test`.
# Each creates the virtual environment on first use; nothing is installed by hand.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
OUT    ?= demo-output
PYTEST_ARGS ?=
# The independent Bonn BTF readers (btf-extractor, pysmtb) need numpy < 2, the project numpy >= 2: they
# live in their own venv, built once by `make test`; tests/tasks/test_bonn_independent.py runs them there
# (docs/bonn-formats.md, "Independent readers").
VENV_READERS ?= .venv-readers
READERS_LOG  := $(VENV_READERS).log

.PHONY: demo test bench bench-summary venv clean readers

venv: $(STAMP)

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --disable-pip-version-check -e '.[test]'
	touch $(STAMP)

# A failed build does not fail `make test`: the log keeps pip's output and the cross-check tests skip,
# quoting its last error line. The log marks the attempt as made; `make readers` tries again.
$(READERS_LOG):
	@echo "building $(VENV_READERS) (btf-extractor, pysmtb; under a minute; log: $(READERS_LOG))"
	@rm -rf $(VENV_READERS); start=$$(date +%s); \
	if { $(PYTHON) -m venv $(VENV_READERS) \
	  && $(VENV_READERS)/bin/pip install --disable-pip-version-check \
	       "numpy<2" "nptyping<2" "cython<0.30" poetry-core setuptools simplejpeg \
	  && $(VENV_READERS)/bin/pip install --disable-pip-version-check --no-build-isolation \
	       btf-extractor==1.7.0 pysmtb==0.4.0 \
	  && touch $(VENV_READERS)/.installed; } > $@ 2>&1; then \
	  echo "built $(VENV_READERS) in $$(( $$(date +%s) - start )) s" | tee -a $@; \
	else \
	  echo "FAILED to build $(VENV_READERS) after $$(( $$(date +%s) - start )) s" >> $@; \
	  echo "could not build $(VENV_READERS) (see $(READERS_LOG)); the independent-reader tests will be skipped"; \
	fi

readers:
	@rm -f $(READERS_LOG)
	@$(MAKE) --no-print-directory $(READERS_LOG)

demo: $(STAMP)
	$(BIN)/btf demo --out $(OUT)

# pytest exits 5 when it collected no test (e.g. a -k filter that matches
# nothing); say so plainly instead of failing with a bare status.
test: $(STAMP) $(READERS_LOG)
	@BTF_READERS_PYTHON="$${BTF_READERS_PYTHON:-$(abspath $(VENV_READERS))/bin/python}" \
	  $(BIN)/python -m pytest $(PYTEST_ARGS); rc=$$?; \
	if [ $$rc -eq 5 ]; then echo "pytest collected no tests (exit 5); nothing was checked"; exit 0; fi; \
	exit $$rc

# Speed is measured here, never in tests; results go to docs/benchmarks.md ("Running them").
# Each benchmark's JSON goes to $(BENCH_OUT)/NAME.json, its progress to NAME.log; a failing one is
# recorded as failed and the next one runs; the table of every bar ends the run. QUICK=1 runs only the
# benchmarks with a --quick mode (a smoke run whose figures are not results), into bench-results-quick.
# BENCHES="benchmarks/bench_als.py ..." runs only those (the table still shows the folder's other results).
QUICK     ?=
BENCH_OUT ?= bench-results$(if $(QUICK),-quick)
BENCHES   ?= $(sort $(wildcard benchmarks/bench_*.py))

bench: $(STAMP)
	@mkdir -p $(BENCH_OUT); \
	for f in $(BENCHES); do \
	  name=$$(basename $$f .py); name=$${name#bench_}; \
	  rm -f $(BENCH_OUT)/$$name.json $(BENCH_OUT)/$$name.log; \
	  if [ -n "$(QUICK)" ] && ! grep -q -e '"--quick"' $$f; then \
	    echo '{"benchmark": "'$$name'", "skipped": "no quick mode", "bars": []}' > $(BENCH_OUT)/$$name.json; \
	    continue; \
	  fi; \
	  echo "== $$f$(if $(QUICK), --quick) (progress: $(BENCH_OUT)/$$name.log)"; start=$$(date +%s); \
	  $(BIN)/python $$f $(if $(QUICK),--quick) > $(BENCH_OUT)/$$name.json 2> $(BENCH_OUT)/$$name.log; \
	  echo "exit status $$? after $$(( $$(date +%s) - start )) s" >> $(BENCH_OUT)/$$name.log; \
	done; \
	$(BIN)/python benchmarks/summary.py $(BENCH_OUT)

# The table again, from the results of the last `make bench` (QUICK=1: of the last quick run).
bench-summary: $(STAMP)
	@$(BIN)/python benchmarks/summary.py $(BENCH_OUT)

clean:
	rm -rf $(VENV) $(OUT) .pytest_cache $(VENV_READERS) $(READERS_LOG)
