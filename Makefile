# Developer shortcuts; CI runs `.ci/run` (install, then `make lint` and `make test`).
.PHONY: install lint format typecheck test test-slow bench

install:  ## CPU torch first, so a CPU-only machine pulls no CUDA wheels
	python -m pip install "torch==2.13.0" || python -m pip install torch --index-url https://download.pytorch.org/whl/cpu
	python -m pip install -e ".[test,sumo,smarts]"

lint: typecheck
	ruff check sb3_gccp envs tests benchmarks
	black --check -q sb3_gccp envs tests benchmarks

format:
	black -q sb3_gccp envs tests benchmarks
	ruff check --fix sb3_gccp envs tests benchmarks

# mypy cannot follow setuptools' editable finder, so it reads envs/ through a link named gccp_envs.
typecheck:
	@tmp=$$(mktemp -d) && ln -s "$(CURDIR)/envs" "$$tmp/gccp_envs" && MYPYPATH="$$tmp" mypy -p gccp_envs -p sb3_gccp; \
	status=$$?; rm -rf "$$tmp"; exit $$status

test:
	python -m pytest -q -n 2

test-slow:
	python -m pytest -q -n 2 -m slow

bench:
	python benchmarks/env_speed.py
	python benchmarks/traffic_quality.py
