# Two entry points a fresh machine needs: `make demo` and `make test` (the fast tier).
# CI (.ci/run) also runs `make lint` and `make test-system` (real service, studies in small).
# Supply chain (needs PyPI, never part of `make test`): `make lock`, `make sbom`, `make audit`.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
# The locked dependency set: every package of the venv, pinned (`make lock` refreshes it).
LOCK := requirements.lock
# The supply-chain tools live in their own venv, so that they are not in the SBOM they write.
TOOLS := build/supply-chain
SBOM := build/slamtka-sbom.cdx.json
# Debian tools the tests use as independent clients and validators (DCMTK, dicom3tools).
SYSTEM_TOOLS := storescu echoscu dsrdump dciodvfy

.PHONY: demo test test-system lint typecheck bench clean lock sbom audit

# The solver's C kernels are built by the install (setup.py), so their source is a prerequisite.
$(STAMP): pyproject.toml setup.py solver/_kernels.c $(LOCK)
	@missing=""; for t in $(SYSTEM_TOOLS); do command -v $$t >/dev/null || missing=1; done; \
	if [ -n "$$missing" ]; then \
	  SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
	  $$SUDO apt-get update -qq && $$SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq dcmtk dicom3tools >/dev/null; \
	fi
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet --constraint $(LOCK) -e '.[test,lint]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/slamtka theatre

test: $(STAMP)
	$(BIN)/pytest -n 2 -q -m "not system and not slow"

test-system: $(STAMP)
	$(BIN)/pytest -n 2 -q -m "system and not slow"

# mypy cannot follow setuptools' package-dir mapping, so it reads the `slamtka` namespace
# through a tree of links to the repository's folders.
TYPECHECK := build/typecheck
typecheck: $(STAMP)
	@rm -rf $(TYPECHECK) && mkdir -p $(TYPECHECK)/slamtka
	@for p in service solver drivers; do ln -s ../../../$$p $(TYPECHECK)/slamtka/$$p; done
	@ln -s ../../../solver/sim $(TYPECHECK)/slamtka/sim && ln -s ../../../service/bench $(TYPECHECK)/slamtka/bench
	cd $(TYPECHECK) && $(abspath $(BIN))/mypy --config-file $(abspath pyproject.toml) -p slamtka \
	  --exclude 'slamtka/(service/bench|solver/sim)/'

lint: $(STAMP) typecheck
	$(BIN)/ruff check service solver drivers tests

bench: $(STAMP)
	$(BIN)/slamtka bench accuracy --runs 20 --levels 1 --out bench-out/accuracy

lock: $(STAMP)
	$(BIN)/pip freeze --exclude-editable > $(LOCK)

$(TOOLS)/.installed:
	$(PYTHON) -m venv $(TOOLS)
	$(TOOLS)/bin/pip install --quiet --upgrade pip cyclonedx-bom pip-audit
	touch $@

# CycloneDX (JSON) of the venv installed from the lock, with the project as root component.
sbom: $(STAMP) $(TOOLS)/.installed
	$(TOOLS)/bin/cyclonedx-py environment --pyproject pyproject.toml --output-reproducible \
	  --output-format JSON --output-file $(SBOM) $(BIN)/python
	@echo "wrote $(SBOM)"

# Known vulnerabilities of every pinned package of the lock (AUDIT_SERVICE: pypi or osv);
# strict: a package that could not be looked up fails the audit instead of passing unseen.
AUDIT_SERVICE ?= pypi
audit: $(TOOLS)/.installed
	$(TOOLS)/bin/pip-audit --requirement $(LOCK) --no-deps --disable-pip --strict \
	  --vulnerability-service $(AUDIT_SERVICE) --progress-spinner off

clean:
	rm -rf $(VENV) bench-out .pytest_cache $(TOOLS) $(SBOM) solver/_kernels.*.so
