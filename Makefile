# backpack-slam: `make demo` and `make test` set everything up from a fresh clone.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
OUT    ?= out/demo

.PHONY: demo test setup syslibs lint typecheck unit clean

setup: syslibs $(STAMP)

# open3d needs libusb-1.0 (and on slim systems libgomp1/libgl1/libegl1)
syslibs:
	@missing=""; \
	for lib in libusb-1.0.so.0 libgomp.so.1; do \
	  ldconfig -p 2>/dev/null | grep -q "$$lib" || missing="$$missing $$lib"; \
	done; \
	if [ -n "$$missing" ]; then \
	  if [ "$$(id -u)" = "0" ] && command -v apt-get >/dev/null; then \
	    echo "installing system libraries for open3d:$$missing"; \
	    (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0 libgomp1 >/dev/null) \
	      || { echo "error: apt-get install libusb-1.0-0 libgomp1 failed"; exit 1; }; \
	  else \
	    echo "error: missing system libraries:$$missing; run: sudo apt-get install libusb-1.0-0 libgomp1"; exit 1; \
	  fi; \
	fi

$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[dev]'
	@touch $(STAMP)

demo: setup
	$(VENV)/bin/backpack-slam demo --out $(OUT)

lint: setup
	$(VENV)/bin/ruff check .
	$(VENV)/bin/mypy

unit: setup
	$(PY) -m pytest -q -n 2 --dist loadfile

test: lint unit

clean:
	rm -rf $(VENV) out .mypy_cache .ruff_cache .pytest_cache
