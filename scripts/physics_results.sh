#!/usr/bin/env bash
# The physics results of docs/results.md (the expert, the priors, the tasks, text to physics) as
# one resumable queue, for a machine that may be handed back to you, or not, between sessions.
# Every training resumes exactly from its last checkpoint when its run folder holds one; a finished
# training or an evaluation whose output exists costs nothing; so run it again, as it is, to
# continue wherever it stopped.
#
#   scripts/physics_results.sh                 # every stage, in the order below
#   scripts/physics_results.sh priors tasks    # only these stages (names below)
#   SEEDS="0 1 2 3" scripts/physics_results.sh tasks   # one more seed for every task cell
#   kill -TERM PID                             # the training under way stops at its next checkpoint,
#                                              # and the queue stops after it
#   STOP_AT=19:40 scripts/physics_results.sh   # the same TERM, sent by the queue to itself at that time
#                                              # (anything `date -d` reads: "19:40", "+150 min";
#                                              #  a clock time already past means tomorrow's)
#   mkdir -p runs/dry && ln -s ../bandai2.h5 runs/dry/ && R=runs/dry EXPERT_IT=40 PRIOR_IT=20 TASK_IT=10 \
#     GEN_N=4 GEN_SECONDS=3 EVAL_N=8 BALLS_N=4 KIN_IT=20 T2M_RECIPE=recipes/eval/t2m_toy.yaml \
#     SEEDS=0 scripts/physics_results.sh         # every stage at toy size, one seed (~35 min on 2 cores
#                                              # measured before the seeded task stages, not since)
#   mkdir -p /tmp/frozen && git archive HEAD motok | tar -x -C /tmp/frozen && \
#     MOTOK="env PYTHONPATH=/tmp/frozen .venv/bin/python -P -m motok.cli.main" scripts/physics_results.sh
#                                              # the queue on a copy of the code, so that editing the
#                                              # checkout cannot reach it (-P: not the checkout first)
#
# Stages, most important first (each waits for what it reads):
#   data      runs/bandai2.h5, Bandai-Namco set 2 preprocessed
#   expert    the whole-dataset expert, to EXPERT_IT iterations, then its val/test evaluations
#   priors    hybrid, continuous, discrete+, discrete, hybrid-vq distilled from it, PRIOR_IT iterations each (Fig. 4, Table 1),
#             each evaluated at once: imitation on the train and test clips (Fig. 4), its Table 1 generations
#   prioreval Table 1 (motion matching of every prior's generations)
#   tasks     the task tables: in-betweening (Table 2), head tracking (Table 3) and navigation over the
#             continuous, discrete, discrete+ and hybrid priors, on every seed of SEEDS, TASK_IT iterations
#             each, into $R/tasks/TASK_PRIOR_seedN; each run evaluated when it finishes (Tables 2-3 on the
#             test clips; navigation's targets, then thrown balls every 0.3 s and every $BALL_PERIODS s)
#   codebooks Fig. 13: navigation over the hybrid's first 1, 2, 4 codebooks and discrete+'s first 4, every seed
#   t2p       text to physics: tokenizer, GPT and evaluator, then GPT kinematic, GPT tracked and real tracked rows
#   plots     the curves of every run that exists, one figure per comparison, in runs/plots/
#
# On a fresh machine, the shortest chains first: text to physics needs only the hybrid
# prior, the task tables the continuous, discrete and discrete+ ones too; then the rest
# (hybrid-vq, Table 1):
#   PRIORS=hybrid TABLE1=0 scripts/physics_results.sh data expert priors t2p
#   PRIORS="hybrid continuous discrete+ discrete" TABLE1=0 scripts/physics_results.sh priors tasks codebooks
#   scripts/physics_results.sh
#
# Settings (environment): PRIORS (some of: hybrid continuous discrete+ discrete hybrid-vq; unset: all)
# the priors the `priors` stage distils (and the task stages use), TABLE1=0 leaves their Table 1
# generations to `prioreval`; SEEDS="0 1 2" the training seeds of every task cell (--set seed=N; the
# evaluations draw the same episodes, seed 0, for every run), TASKS (some of: inbetween hmd navigation;
# unset: all), CONTINUOUS_SET=KEY=VALUE one --set for the continuous prior's runs (default none: the recipes give it
# its exploration std and learning rate);
# R=runs, MOTOK=.venv/bin/motok, NICE=5, EXPERT_IT=13000 (--until: the recipe's
# 40k-iteration LR schedule), PRIOR_IT=1500 and TASK_IT=3000 (--set iterations); the evaluation sizes
# GEN_N=1336 samples of GEN_SECONDS=30 s per Table 1 row (599 transitions each at 20 fps: the paper's 800,000;
# about 5 min of simulation per row, docs/eval.md), EVAL_N=256 task episodes, BALLS_N=64
# thrown-ball episodes; KIN_IT (unset: the recipes') iterations of the evaluator, tokenizer and GPT
# of t2p, and T2M_RECIPE=recipes/eval/t2m.yaml its protocol (small values make a dry run of the whole
# queue at toy size). PRIOR_IT is half the
# recipes' 3,000: a hybrid student matched its teacher after 400 iterations (docs/history.md). Both
# budgets can grow later: PRIOR_IT=3000 continues every prior to 3,000 (constant learning rates; the
# loss-weight ramps span the first 12.5 % of the budget, so only they differ from a 3,000 run).
# Time on 2 cores (measured, docs/results.md): expert 3.3 h, priors 33-45 min each and their
# evaluations ~0.6 h in all, text to physics 1 h; a task run 25-47 min, its evaluations a few
# minutes (a navigation run's thrown balls ~15 min more), so `tasks` at 3 seeds (36 runs) is about
# 25 h and `codebooks` (12 runs) about 9 h: about 42 h in all, in pieces. Every command's wall time goes to $R/logs/times.tsv;
# `scripts/physics_tables.py --status` shows where each run stands and the time of each stage so far.
# ARITH=avx2 (default) caps numpy, OpenBLAS and torch at their AVX2 kernels on an x86 machine with
# AVX-512, for every stage, so that a run resumed or redone on that CPU model repeats to the digit:
# AVX-512 kernels give other bits (even the preprocessed data differs, in 6e-5 of its feature values
# by up to 5e-10), and a training on other bits is another training. ARITH=native leaves them be.
set -euo pipefail
cd "$(dirname "$0")/.."
R=${R:-runs}
MOTOK=${MOTOK:-.venv/bin/motok}
read -ra M <<< "$MOTOK"  # a command of several words too, e.g. a frozen copy of the code
NICE=${NICE:-5}
EXPERT_IT=${EXPERT_IT:-13000}
PRIOR_IT=${PRIOR_IT:-1500}
TASK_IT=${TASK_IT:-3000}
GEN_N=${GEN_N:-1336}
GEN_SECONDS=${GEN_SECONDS:-30}
EVAL_N=${EVAL_N:-256}
BALLS_N=${BALLS_N:-64}
read -ra BALL_PERIODS <<< "${BALL_PERIODS-1 3 1000}"  # besides the paper's 0.3 s; 1000: no ball in 8 s
KIN=()
[ -n "${KIN_IT:-}" ] && KIN=(--set iterations="$KIN_IT")
T2M_RECIPE=${T2M_RECIPE:-recipes/eval/t2m.yaml}
ALL_PRIORS=(hybrid continuous discrete+ discrete hybrid-vq)
read -ra wanted <<< "${PRIORS:-${ALL_PRIORS[*]}}"
for k in "${wanted[@]}"; do
    case " ${ALL_PRIORS[*]} " in *" $k "*) ;; *) echo "PRIORS: unknown prior '$k' (expected some of: ${ALL_PRIORS[*]})" >&2; exit 2 ;; esac
done
PRIORS=()  # in the queue's order, whatever the order asked
for k in "${ALL_PRIORS[@]}"; do case " ${wanted[*]} " in *" $k "*) PRIORS+=("$k") ;; esac; done
TABLE1=${TABLE1:-1}
read -ra SEEDS <<< "${SEEDS:-0 1 2}"  # every task cell on each (motok/eval/seeds.py decides from 3 or more)
for s in "${SEEDS[@]}"; do
    [[ "$s" =~ ^[0-9]+$ ]] || { echo "SEEDS: '$s' is not a seed (expected integers >= 0, e.g. SEEDS=\"0 1 2\")" >&2; exit 2; }
done
[ ${#SEEDS[@]} -gt 0 ] || { echo "SEEDS: empty (expected integers >= 0, e.g. SEEDS=\"0 1 2\")" >&2; exit 2; }
ALL_TASKS=(inbetween hmd navigation)
read -ra TASKS <<< "${TASKS:-${ALL_TASKS[*]}}"
for t in "${TASKS[@]}"; do
    case " ${ALL_TASKS[*]} " in *" $t "*) ;; *) echo "TASKS: unknown task '$t' (expected some of: ${ALL_TASKS[*]})" >&2; exit 2 ;; esac
done
TASK_PRIORS=()  # the task tables' four priors, among those PRIORS names
for k in continuous discrete discrete+ hybrid; do case " ${PRIORS[*]} " in *" $k "*) TASK_PRIORS+=("$k") ;; esac; done
# the continuous prior's Gaussian policy at Tables 6-8's lr: at the recipes' 3e-4 its updates leave
# PPO's trust region (docs/results.md); empty: the recipe's, like every other prior
CONTINUOUS_SET=${CONTINUOUS_SET-}
DATA=$R/bandai2.h5
EXPERT=$R/expert_set2
export MOTOK_NO_PROGRESS=${MOTOK_NO_PROGRESS:-1}
ARITH=${ARITH:-avx2}
case $ARITH in avx2|native) ;; *) echo "ARITH=$ARITH: expected avx2 or native" >&2; exit 2 ;; esac
if [ "$ARITH" = avx2 ] && grep -qw avx512f /proc/cpuinfo 2>/dev/null; then
    # numpy objects to disabling a target the machine lacks: only where AVX-512 is there
    export ATEN_CPU_CAPABILITY=avx2 MKL_CBWR=AVX2 DNNL_MAX_CPU_ISA=AVX2 OPENBLAS_CORETYPE=Haswell \
        NPY_DISABLE_CPU_FEATURES="X86_V4 AVX512_ICL"
fi
mkdir -p "$R/logs"

stopped=0
trap 'stopped=1; [ -n "${child:-}" ] && kill -TERM "$child" 2>/dev/null' TERM

log() { printf '[%s] %s\n' "$(date -u +%H:%M:%S)" "$*"; }

# log_time LOG STATUS SECONDS ARGS...: one line per command in $R/logs/times.tsv (end time UTC, stage,
# log, seconds, its output or run folder, ok / stopped / exit N): a run trained in pieces has one
# line per piece, so its time is their sum; `physics_tables.py --status` adds them up per stage.
log_time() {
    local name=$1 status=$2 secs=$3 out="" prev=""; shift 3
    for a in "$@"; do case $prev in -o|--policy) out=$a ;; esac; prev=$a; done
    printf '%s\t%s\t%s\t%s\t%s\t%s\n' "$(date -u +%FT%TZ)" "${STAGE:-}" "$name" "$secs" "$out" "$status" \
        >> "$R/logs/times.tsv"
}

# run LOG CMD...: one command at low priority, its output in $R/logs/LOG.log; the queue stops when
# it fails or was asked to stop.
run() {
    local name=$1; shift
    if [ "$stopped" = 1 ]; then log "stopped on request before $name"; exit 0; fi  # a TERM between two commands
    log "$name: $*"
    local t0=$SECONDS
    nice -n "$NICE" "$@" >> "$R/logs/$name.log" 2>&1 &
    child=$!
    local rc=0
    wait "$child" || rc=$?
    wait "$child" 2>/dev/null || true  # a TERM interrupts the first wait, not the child
    child=
    local status=ok
    [ "$rc" != 0 ] && status="exit $rc"
    [ "$stopped" = 1 ] && status=stopped
    log_time "$name" "$status" $((SECONDS - t0)) "$@"
    if [ "$stopped" = 1 ]; then log "stopped on request after $name"; exit 0; fi
    if [ "$rc" != 0 ]; then log "$name failed (exit $rc): see $R/logs/$name.log"; exit "$rc"; fi
}

# train DIR LOG CMD...: CMD -o DIR, with --resume when DIR holds a checkpoint.
train() {
    local dir=$1 name=$2; shift 2
    local resume=()
    [ -f "$dir/bundle.json" ] && resume=(--resume)
    run "$name" "$@" -o "$dir" "${resume[@]}"
}

# once OUT LOG CMD...: CMD unless OUT exists.
once() {
    local out=$1; shift
    [ -e "$out" ] && return 0
    run "$@"
}

stage_data() {
    once "$DATA" preprocess "${M[@]}" preprocess --recipe recipes/preprocess/bandai2.yaml -o "$DATA"
}

stage_expert() {
    train "$EXPERT" expert_set2 "${M[@]}" control expert train -d "$DATA" --split train \
        --recipe recipes/control/expert_set2.yaml --until "$EXPERT_IT"
    for split in val test; do
        once "$EXPERT/eval_$split.json" expert_eval "${M[@]}" control expert eval --expert "$EXPERT" -d "$DATA" --split "$split"
    done
}

stage_priors() {
    for k in "${PRIORS[@]}"; do
        train "$R/prior_$k" "prior_$k" "${M[@]}" control distill --expert "$EXPERT" --kind "$k" \
            --recipe "recipes/control/prior_$k.yaml" --set iterations="$PRIOR_IT"
        prior_evals "$k" "$TABLE1"  # at once: a session that ends mid-stage keeps every finished prior's numbers
    done
}

# table1_rows KIND: the Table 1 rows of one prior, as "codebooks tag" (codebooks "all": the whole prior).
table1_rows() {
    case $1 in
        discrete+) for m in 1 2 3; do echo "$m $1-m$m"; done ;;
        hybrid) for m in 1 2 3 4 5 6 7 8; do echo "$m $1-m$m"; done ;;
        *) echo "all $1" ;;
    esac
}

# prior_evals KIND [GENERATE]: imitation on the train and test clips (Fig. 4) and, unless GENERATE
# is 0, the Table 1 generations of one prior.
prior_evals() {
    local k=$1 p=$R/prior_$1 m tag
    once "$p/eval.json" prior_eval "${M[@]}" control eval --task imitation --prior "$p"
    once "$p/eval_test.json" prior_eval "${M[@]}" control eval --task imitation --prior "$p" -d "$DATA" --split test
    [ "${2:-1}" = 0 ] && return 0
    while read -r m tag; do
        local cb=()
        [ "$m" != all ] && cb=(--codebooks "$m")
        once "$R/table1/$tag.h5" generate "${M[@]}" control generate --prior "$p" "${cb[@]}" \
            --seconds "$GEN_SECONDS" -n "$GEN_N" --seed 0 -o "$R/table1/$tag.h5" < /dev/null
    done < <(table1_rows "$k")
}

# Table 1 over every prior's generations (the evaluations above, for priors distilled before they ran in `priors`).
stage_prioreval() {
    local gens=() k m tag
    for k in "${ALL_PRIORS[@]}"; do
        [ -f "$R/prior_$k/bundle.json" ] || continue
        prior_evals "$k"
        while read -r m tag; do gens+=(--motions "$R/table1/$tag.h5"); done < <(table1_rows "$k")
    done
    [ ${#gens[@]} -gt 0 ] && once "$R/table1/table1.json" motion_matching "${M[@]}" eval motion-matching \
        -d "$DATA" --split train --heldout test "${gens[@]}" -o "$R/table1/table1.json" -o "$R/table1/table1.md"
    return 0
}

# The task tables (Tables 2-3, navigation) and Fig. 13, each cell on every seed of SEEDS at one
# budget (TASK_IT iterations), so that docs/results.md can decide each ordering by the rule of
# motok/eval/seeds.py. Seeds outermost: after the first pass every cell has one seed.
task_dir() { echo "$R/tasks/$1_$2_seed$3"; }  # TASK PRIOR[_mM] SEED

# seeded TASK PRIOR SEED DIR [ARGS...]: one task policy over a frozen prior, trained (resumed
# where its folder holds a checkpoint, skipped when finished) and then evaluated.
seeded() {
    local t=$1 k=$2 s=$3 dir=$4; shift 4
    [ -f "$R/prior_$k/bundle.json" ] || { log "skip $dir: no prior_$k"; return 0; }
    local extra=()
    [ "$k" = continuous ] && [ -n "$CONTINUOUS_SET" ] && extra=(--set "$CONTINUOUS_SET")
    if [ ! -f "$dir/bundle.json" ] || [ -n "$(unfinished "$dir")" ]; then
        train "$dir" "$(basename "$dir")" "${M[@]}" control train --task "$t" --prior "$R/prior_$k" \
            --recipe "recipes/control/task_$t.yaml" --set iterations="$TASK_IT" --set seed="$s" "${extra[@]}" "$@"
    fi
    task_evals "$t" "$s" "$dir"
}

# unfinished DIR: "I of N" when DIR's checkpoint stands before the iterations its config asks for
# (a run a session's end stopped); nothing for a finished run or a bundle that does not say.
unfinished() {
    python3 -c 'import json, sys
b = json.load(open(sys.argv[1]))
it, goal = b.get("extra", {}).get("iteration"), b.get("config", {}).get("iterations")
if it is not None and goal and it < goal: print(f"{it} of {goal}")' "$1/bundle.json"
}

# task_evals TASK SEED DIR: the evaluations of one finished task run; videos of seed 0 only.
task_evals() {
    local t=$1 s=$2 dir=$3 part p
    [ -f "$dir/bundle.json" ] || { log "skip $dir: no checkpoint to evaluate"; return 0; }
    # an evaluation file is never made again: one of a half-trained policy would stand for the run
    part=$(unfinished "$dir")
    if [ -n "$part" ]; then log "skip $dir: not evaluated at iteration $part (its training resumes first)"; return 0; fi
    local video=()
    [ "$s" = "${SEEDS[0]}" ] && video=(--render "$dir/$t.mp4")
    if [ "$t" = navigation ]; then  # no reference motion: the targets are drawn
        once "$dir/eval_$t.json" task_eval "${M[@]}" control eval --task "$t" --policy "$dir" -n "$EVAL_N" "${video[@]}"
        once "$dir/perturb.json" perturb "${M[@]}" control perturb --policy "$dir" -n "$BALLS_N"
        for p in "${BALL_PERIODS[@]}"; do  # the same starts (seed 0) under fewer balls: what the barrage takes
            once "$dir/perturb_period$p.json" perturb "${M[@]}" control perturb --policy "$dir" -n "$BALLS_N" --period "$p"
        done
    else  # Tables 2-3: windows and head trajectories of the test clips, never trained on
        once "$dir/eval_${t}_test.json" task_eval "${M[@]}" control eval --task "$t" --policy "$dir" -n "$EVAL_N" \
            -d "$DATA" --split test "${video[@]}"
    fi
}

stage_tasks() {
    local s t k
    for s in "${SEEDS[@]}"; do
        for t in "${TASKS[@]}"; do
            for k in "${TASK_PRIORS[@]}"; do seeded "$t" "$k" "$s" "$(task_dir "$t" "$k" "$s")"; done
        done
    done
}

# Fig. 13: the navigation policy over the first M codebooks of the hybrid prior against all 8, and
# discrete+ over the first 4 against the hybrid's 4 (the two at equal M). M = 1 is `tasks`'
# navigation run: the task's protocol default (docs/control/tasks.md).
stage_codebooks() {
    local s m
    for s in "${SEEDS[@]}"; do
        for m in 2 4 8; do
            seeded navigation hybrid "$s" "$(task_dir navigation "hybrid_m$m" "$s")" --codebooks "$m"
        done
        seeded navigation discrete+ "$s" "$(task_dir navigation "discrete+_m4" "$s")" --codebooks 4
    done
}

stage_t2p() {
    local K=$R/kinematic P=$R/prior_hybrid
    mkdir -p "$K"
    once "$K/bow-v2/bundle.json" evaluator "${M[@]}" eval train-evaluator -d "$DATA" --recipe recipes/eval/evaluator.yaml \
        "${KIN[@]}" -o "$K/bow-v2"
    train "$K/tokenizer" tokenizer "${M[@]}" tokenize train -d "$DATA" --recipe recipes/tokenizer/ema_reset.yaml "${KIN[@]}"
    once "$K/tokens.h5" tokens "${M[@]}" tokenize encode -t "$K/tokenizer" -d "$DATA" -o "$K/tokens.h5"
    train "$K/gpt" gpt "${M[@]}" gpt train -d "$K/tokens.h5" --recipe recipes/gpt/default.yaml "${KIN[@]}"
    # each keyed on what is written last: a stop between the motion and its report redoes both;
    # the physics table scores each motion beside its tracked copy on the clips both hold
    # (--common-clips), the GPT's whole kinematic row being t2m-kinematic's
    once "$K/t2m-kinematic.json" t2m "${M[@]}" eval t2m -e "$K/bow-v2" -d "$DATA" -t "$K/tokenizer" --gpt "$K/gpt" \
        --recipe "$T2M_RECIPE" --save-generated "$K/generated.h5" -o "$K/t2m-kinematic.json" -o "$K/t2m-kinematic.md"
    once "$K/generated_sim.track.json" track "${M[@]}" control track -d "$K/generated.h5" --prior "$P" -o "$K/generated_sim.h5" --json
    once "$K/real_test_sim.track.json" track "${M[@]}" control track -d "$DATA" --split test --prior "$P" -o "$K/real_test_sim.h5" --json
    once "$K/t2m-physics.json" t2m "${M[@]}" eval t2m -e "$K/bow-v2" -d "$DATA" --motions "$K/generated.h5" \
        --motions "$K/generated_sim.h5" --motions "$K/real_test_sim.h5" --recipe "$T2M_RECIPE" --common-clips \
        -o "$K/t2m-physics.json" -o "$K/t2m-physics.md"
}

# plot NAME KEYS RUN...: the runs that exist on one figure over samples ($R/plots/NAME.png) and one
# over training wall time (NAME_wall.png), drawn anew each time.
plot() {
    local name=$1 keys=$2; shift 2
    local runs=()
    for d in "$@"; do [ -f "$d/metrics.jsonl" ] && runs+=("$d"); done
    [ ${#runs[@]} -gt 0 ] || return 0
    mkdir -p "$R/plots"
    # --missing-ok: a run stopped early (or a dry run) may not have logged an evaluation yet
    run plots "${M[@]}" plot "${runs[@]}" --keys "$keys" --x samples --smooth 0.95 --missing-ok -o "$R/plots/$name.png"
    run plots "${M[@]}" plot "${runs[@]}" --keys "$keys" --x wall_s --smooth 0.95 --missing-ok \
        -o "$R/plots/${name}_wall.png"
}

stage_plots() {
    plot expert success,episode_seconds,r_im,samples_per_s,eval_success,eval_mpjpe_mm "$EXPERT"
    plot priors eval_success,eval_mpjpe_mm,rollout_action_err,code_usage,samples_per_s "${ALL_PRIORS[@]/#/$R/prior_}"
    # r_task: the task reward per step, in [0, 1]: the return normalised by its maximum. The first
    # seed's run of each prior (the other seeds' curves are alike in shape; their spread is the tables')
    local s=${SEEDS[0]} task keys k runs
    for task in "${ALL_TASKS[@]}"; do
        case $task in
            navigation) keys=r_task,episode_seconds,eval_reached_share,eval_approach_share,eval_falls_per_episode ;;
            inbetween) keys=r_task,episode_seconds,eval_success_rate,eval_mpjpe_mm_mean ;;
            hmd) keys=r_task,episode_seconds,eval_success_rate,eval_head_error_mm_mean ;;
        esac
        runs=()
        for k in continuous discrete discrete+ hybrid; do runs+=("$(task_dir "$task" "$k" "$s")"); done
        plot "$task" "$keys" "${runs[@]}"
    done
    plot codebooks r_task,episode_seconds,eval_approach_share,eval_falls_per_episode \
        "$(task_dir navigation hybrid "$s")" "$(task_dir navigation hybrid_m2 "$s")" \
        "$(task_dir navigation hybrid_m4 "$s")" "$(task_dir navigation hybrid_m8 "$s")" "$(task_dir navigation discrete+_m4 "$s")"
}

ALL=(data expert priors prioreval tasks codebooks t2p plots)

# STOP_AT: the queue sends itself the TERM of `kill -TERM` at that time (a session's end): the
# training under way stops at its next checkpoint and the queue after it. The timer goes with the
# queue (and its sleep with the timer), so an early finish leaves nothing behind.
arm_stop() {
    [ -n "${STOP_AT:-}" ] || return 0
    local at now
    at=$(date -d "$STOP_AT" +%s 2>/dev/null) ||
        { echo "STOP_AT=$STOP_AT: not a time date -d reads (e.g. 19:40 or '+150 min')" >&2; exit 2; }
    now=$(date +%s)
    # a clock time already past today is meant for tomorrow (a session that crosses midnight)
    if [ "$at" -le "$now" ] && [[ "$STOP_AT" =~ ^[0-9]{1,2}:[0-9]{2}$ ]]; then
        at=$(date -d "tomorrow $STOP_AT" +%s)
    fi
    [ "$at" -gt "$now" ] || { echo "STOP_AT=$STOP_AT ($(date -u -d "@$at" +%H:%M:%S) UTC) is not in the future" >&2; exit 2; }
    log "stopping itself at $(date -u -d "@$at" '+%F %H:%M:%S') UTC (STOP_AT=$STOP_AT)"
    # shellcheck disable=SC2016  # $s is the timer's own variable
    ( trap 'kill "$s" 2>/dev/null; wait "$s"; exit 0' TERM; sleep $((at - now)) & s=$!; wait "$s"; kill -TERM $$ ) &
    timer=$!
    trap 'rc=$?; kill "$timer" 2>/dev/null || true; exit "$rc"' EXIT  # the queue's own status (set -e: a gone timer's kill fails)
}

main() {
    local stages=("$@") s
    [ ${#stages[@]} -gt 0 ] || stages=("${ALL[@]}")
    for s in "${stages[@]}"; do
        case " ${ALL[*]} " in *" $s "*) ;; *) echo "unknown stage '$s' (expected one of: ${ALL[*]})" >&2; exit 2 ;; esac
    done
    arm_stop
    for s in "${stages[@]}"; do
        log "stage $s"
        STAGE=$s
        "stage_$s"
    done
    log "done: results under $R/ (logs in $R/logs/)"
}

# bash reads a script as it runs it: with the whole body parsed as one function first, editing or
# checking out this file while a queue runs for hours cannot change what that queue does next
main "$@"; exit
