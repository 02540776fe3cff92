# make demo: install into .venv and run the main job end to end on the default data
#            (preprocess, tokenizer, GPT, text -> motion; about ten minutes on 2 CPU cores).
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
	$(BIN)/motok info $(DEMO)/bandai2.h5 --captions 2
	$(BIN)/motok render -d $(DEMO)/bandai2.h5 --clip dataset-2_walk_normal_001 -o $(DEMO)/walk_normal_001.gif
	$(BIN)/motok render -d $(DEMO)/bandai2.h5 --clip dataset-2_raise-up-both-hands_exhausted_001 -o $(DEMO)/raise_up_exhausted_001.mp4
	$(BIN)/motok export bvh -d $(DEMO)/bandai2.h5 --clip dataset-2_walk_normal_001 -o $(DEMO)/walk_normal_001.bvh
	$(BIN)/motok tokenize train --data $(DEMO)/bandai2.h5 --recipe recipes/tokenizer/demo.yaml -o $(DEMO)/tokenizer
	$(BIN)/motok tokenize encode --tokenizer $(DEMO)/tokenizer --data $(DEMO)/bandai2.h5 -o $(DEMO)/tokens.h5
	$(BIN)/motok gpt train -d $(DEMO)/tokens.h5 --recipe recipes/gpt/demo.yaml -o $(DEMO)/gpt
	OMP_NUM_THREADS=1 $(BIN)/motok gpt sample --gpt $(DEMO)/gpt --text "a person walks forward" --seed 0 \
		-o $(DEMO)/walk_generated.h5 --render $(DEMO)/walk_generated.gif --bvh $(DEMO)/walk_generated.bvh
	$(BIN)/motok plot $(DEMO)/tokenizer
	$(BIN)/motok plot $(DEMO)/gpt
	@echo
	@echo "demo outputs in $(DEMO)/: the dataset (bandai2.h5), two rendered clips, a BVH export,"
	@echo "a tokenizer and a GPT (with curves.png), and 'a person walks forward' generated as"
	@echo "walk_generated.gif / .bvh / .h5:"
	@ls -l $(DEMO)

bench: install
	$(BIN)/python benchmarks/preprocess.py

clean:
	rm -rf $(VENV) runs .pytest_cache
