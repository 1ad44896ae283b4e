# The two commands of README.md. Both build .venv first when it is missing or stale.
PY := .venv/bin/python
# OpenBLAS threads spinning on a 2-core machine slow small matrix work and the raycaster.
export OPENBLAS_NUM_THREADS ?= 1
RUN ?= runs/reproduce

.PHONY: reproduce book test clean-venv

.venv/.installed: environment/requirements.txt pyproject.toml environment/setup_env.sh
	environment/setup_env.sh

# Runs the notebooks into $(RUN), then writes the site ($(RUN)/site) and the README's gallery.
reproduce: .venv/.installed
	$(PY) -m freereg_lib reproduce --out $(RUN)

# The executed notebooks of $(RUN), the pages of docs/ and the API reference of the method as one static
# site, $(RUN)/site/index.html: Sphinx + myst-nb + sphinx-book-theme (book/conf.py), offline, nitpicky,
# warnings as errors (freereg_lib/commands/book.py lays out the sources).
book: .venv/.installed
	$(PY) -m freereg_lib.commands.book $(RUN)

# Two pytest workers (pytest-xdist), a test file or notebook each at a time: many tests wait on
# kernels and subprocesses, so two keep both cores busy. nbmake's 300 s cell limit is for one
# notebook alone; with another test beside it notebook 04's benchmark cell needs more.
# The notebooks and test_notebooks.py (the longest files) are named first so that they start first and
# the short tests fill the other worker, instead of one long notebook running alone at the end.
# setup_env.sh --browser installs Chromium for tests/test_site.py where it runs as root.
test: .venv/.installed
	environment/setup_env.sh --browser
	$(PY) -m pytest -q -n 2 --dist loadfile --nbmake --nbmake-timeout=900 --durations=15 notebooks tests/test_notebooks.py tests

clean-venv:
	rm -rf .venv
