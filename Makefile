# The two README commands: `make demo` and `make test`. Both create .venv/ when missing.
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.irtrack-installed

.PHONY: demo test bench venv clean

$(STAMP): pyproject.toml scripts/install.sh
	bash scripts/install.sh $(VENV) dev
	@touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(PY) -m groundsim demo

# pytest exit 5 means "no tests were collected": say so plainly, neither a failure nor a pass.
test: $(STAMP)
	@$(PY) -m pytest; rc=$$?; \
	if [ $$rc -eq 5 ]; then echo "make test: NO TESTS RAN (pytest exit 5)"; exit 0; fi; \
	exit $$rc

bench: $(STAMP)
	$(PY) -m bench

clean:
	rm -rf out .pytest_cache
