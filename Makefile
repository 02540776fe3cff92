# make demo: install into .venv and run the main job end to end on the default data.
# make test: install the same way and run the test suite.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.motok-installed
DEMO   := runs/demo
# torch first and pinned: this machine carries a CPU build of 2.13.0; a looser spec would pull a multi-GB CUDA build.
TORCH  := torch==2.13.0

.PHONY: install demo test bench clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q $(TORCH)
	$(BIN)/python -m pip install -q -e '.[dev]'
	touch $(STAMP)

install: $(STAMP)

test: install
	$(BIN)/python -m pytest -q -ra

demo: install
	$(BIN)/motok preprocess --recipe recipes/preprocess/bandai2.yaml -o $(DEMO)/bandai2.h5
	$(BIN)/motok info $(DEMO)/bandai2.h5
	$(BIN)/motok render $(DEMO)/bandai2.h5 --clip dataset-2_walk_normal_001 -o $(DEMO)/walk_normal_001.gif
	$(BIN)/motok render $(DEMO)/bandai2.h5 --clip dataset-2_raise-up-both-hands_exhausted_001 -o $(DEMO)/raise_up_exhausted_001.mp4
	$(BIN)/motok export bvh $(DEMO)/bandai2.h5 --clip dataset-2_walk_normal_001 -o $(DEMO)/walk_normal_001.bvh
	@echo
	@echo "demo outputs in $(DEMO)/:"
	@ls -l $(DEMO)

bench: install
	$(BIN)/python benchmarks/preprocess.py

clean:
	rm -rf $(VENV) runs .pytest_cache
