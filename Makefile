# neurncd_ros: one command for the demo, one for the tests.
# Everything installs into .venv from pinned requirements; nothing by hand.

PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
PYTEST_ARGS ?=

.PHONY: venv test test-all demo bench params clean

venv: $(STAMP)

$(STAMP): requirements.txt requirements-dev.txt setup.py
	@$(PYTHON) -c 'import sys; assert sys.version_info[:2] == (3, 11), "Python 3.11 is required (ROS 2 Jazzy wheels), found " + sys.version' 
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -r requirements.txt -r requirements-dev.txt
	$(PY) -m pip install --quiet --no-deps --no-build-isolation -e .
	touch $(STAMP)

test: venv
	$(PY) -m pytest -q test $(PYTEST_ARGS)

test-all: venv
	$(PY) -m pytest -q --slow test $(PYTEST_ARGS)

demo: venv
	$(PY) -m neurncd_ros.cli demo

bench: venv
	$(PY) -m neurncd_ros.cli bench

params: venv
	$(PY) -m neurncd_ros.cli params --format markdown

clean:
	rm -rf build install log out .pytest_cache
