# Two commands on a fresh clone:
#   make demo   - set up .venv and run the main job on the bundled default
#   make test   - set up .venv (if needed) and run the test suite
VENV ?= .venv
STAMP := $(VENV)/.installed
OUT ?= outputs/demo

.PHONY: demo test setup bench clean

$(STAMP): pyproject.toml scripts/setup_env.sh
	VENV=$(VENV) bash scripts/setup_env.sh
	touch $(STAMP)

setup: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/tactile-slam demo --out $(OUT)

test: $(STAMP)
	$(VENV)/bin/python -m pytest -q --timeout=600

clean:
	rm -rf $(VENV) outputs
