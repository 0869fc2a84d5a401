SHELL := /bin/bash
.PHONY: setup test test-full unit integration demo demo-pbr bench campaign clean
ENV := . scripts/env.sh &&

setup:
	@bash scripts/setup.sh

# The short suite (about 30 minutes on 2 cores): of each family of live cases, those drawn from AFT_SUITE_SEED
# (printed; tests/conftest.py, aft_ftm.suite). test-full runs every case (about 45 minutes).
test: setup
	$(ENV) python -m pytest -q -p no:cacheprovider -rs --durations=25 tests

test-full: setup
	$(ENV) AFT_SUITE=full python -m pytest -q -p no:cacheprovider -rs --durations=25 tests

unit: setup
	$(ENV) python -m pytest -q -p no:cacheprovider tests/unit

integration: setup
	$(ENV) python -m pytest -q -p no:cacheprovider -s tests/integration

demo: setup
	$(ENV) python scripts/demo_tjp

demo-pbr: setup
	$(ENV) python scripts/demo_pbr

bench: setup
	$(ENV) python scripts/bench_report $(if $(QUICK),--quick)

campaign: setup
	$(ENV) python scripts/campaign --adapt --faults $(or $(FAULTS),1000) $(if $(SEED),--seed $(SEED))

clean:
	rm -rf catkin_ws/build catkin_ws/devel
