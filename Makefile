# The two commands of README.md. Both build .venv first when it is missing or stale.
PY := .venv/bin/python
# OpenBLAS threads spinning on a 2-core machine slow small matrix work and the raycaster.
export OPENBLAS_NUM_THREADS ?= 1
RUN ?= runs/reproduce

.PHONY: reproduce test clean-venv

.venv/.installed: environment/requirements.txt pyproject.toml environment/setup_env.sh
	environment/setup_env.sh

reproduce: .venv/.installed
	$(PY) -m freereg_lib.reproduce --out $(RUN)

test: .venv/.installed
	$(PY) -m pytest -q --nbmake tests notebooks

clean-venv:
	rm -rf .venv
