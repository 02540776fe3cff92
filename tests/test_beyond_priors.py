"""The priors of the paper's future work (hybrid-fsq, hybrid-grvq, hybrid-parts): their capability
rows drive the high-level action spaces, the FSQ margin on hand values, where each term of Eq. 6
sends its gradient, the body parts read from the skeleton and the part-wise posterior's inputs,
and on real data: distillation, a bundle that loads back with identical outputs, unconditional
generation, the imitation evaluation and task training over each kind."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from typer.testing import CliRunner

from motok.cli.main import app
from motok.config import load_config
from motok.control.highlevel.heads import PartCategoricalPolicy
from motok.control.highlevel.policy import HighLevelNetConfig, action_space, build_high_level, load_task_run
from motok.control.mdp.resets import reference_state
from motok.control.priors import distill
from motok.control.priors.distill import distill_loss
from motok.control.priors.generate import generate, rollout
from motok.control.priors.kinds import KINDS
from motok.control.priors.model import DistillConfig, LatentPrior, load_prior
from motok.control.priors.parts import PART_NAMES, action_parts, body_parts, goal_parts
from motok.control.rl.policies import MultiCategoricalPolicy
from motok.errors import UserError
from motok.sim.reference import load_library
from tiny_runs import small_prior_config, tiny_prior_bundle

pytestmark = pytest.mark.usefixtures("one_thread")
RECIPES = Path(__file__).resolve().parent.parent / "recipes" / "control"
NEW = ("hybrid-fsq", "hybrid-grvq", "hybrid-parts")
W = {"action": 10.0, "reg": 0.05, "commit": 1.0, "mm": 1.0, "kl": 0.0, "part": 1.0}
TINY_TASK = ("iterations=2", "save_every=1000", "env.num_envs=4", "env.nthread=1", "ppo.horizon=8",
             "ppo.minibatch_size=16", "ppo.epochs=1", "net.policy=[16]", "net.value=[16]")


def recipe_model(kind: str) -> LatentPrior:
    """The recipe's sizes, on the set-2 humanoid's dimensions (102 observation, 315 goal, 37 actions)."""
    torch.manual_seed(0)
    return LatentPrior(load_config(DistillConfig, RECIPES / f"prior_{kind}.yaml").prior, 102, 315, 37)


def small_model(kind: str, **kw) -> tuple[LatentPrior, torch.Tensor]:
    torch.manual_seed(0)
    cfg = replace(small_prior_config(kind), **kw)
    return LatentPrior(cfg, obs_dim=10, goal_dim=6, action_dim=4), torch.randn(64, 16)


# ---------------------------------------------------------------------- capability rows and action spaces

def test_the_rows_say_which_terms_of_eq6_each_new_kind_has():
    assert KINDS["hybrid-fsq"].losses == ("mm_loss",)  # FSQ: no commitment loss
    assert KINDS["hybrid-grvq"].losses == ("commit_loss", "mm_loss")
    assert KINDS["hybrid-parts"].losses == ("commit_loss", "mm_loss", "part_loss")
    assert all(KINDS[k].margin and KINDS[k].residual and KINDS[k].schedule == "mm" for k in NEW)
    assert [k for k, c in KINDS.items() if c.parts] == ["hybrid-parts"]


def test_the_recipes_sizes_give_the_hand_derived_action_spaces():
    net = HighLevelNetConfig(policy=[16], value=[16])
    # hybrid-fsq: 8 groups x 3 channels of 5 levels; M groups -> 3 M categoricals of 5 classes
    fsq = recipe_model("hybrid-fsq")
    assert action_space(fsq, None) | {} == {"kind": "code indices, one categorical per index column",
                                            "codebooks": 8, "heads": 24, "codes": 5}
    pol = build_high_level(net, fsq, 102, 2, 2).policy
    assert isinstance(pol, MultiCategoricalPolicy) and (pol.heads, pol.classes) == (6, 5)
    assert pol.net[-1].out_features == 6 * 5
    # hybrid-grvq: 2 groups x 4 codebooks of 128; M -> 2 M categoricals of 128
    grvq = recipe_model("hybrid-grvq")
    pol = build_high_level(net, grvq, 102, 2, 3).policy
    assert (pol.heads, pol.classes) == (6, 128) and action_space(grvq, None)["heads"] == 8
    with pytest.raises(UserError, match="1..4"):
        action_space(grvq, 5)
    # hybrid-parts: one network per part, M categoricals of 128 each; columns level-major (lower, upper, ...)
    parts = recipe_model("hybrid-parts")
    assert action_space(parts, 3)["parts"] == {"lower": 3, "upper": 3}
    pol = build_high_level(net, parts, 102, 2, 3).policy
    assert isinstance(pol, PartCategoricalPolicy) and pol.action_shape == (6,)
    assert pol.columns(0).tolist() == [0, 2, 4] and pol.columns(1).tolist() == [1, 3, 5]
    assert all(pol.parts[n].net[-1].out_features == 3 * 128 for n in PART_NAMES)
    # the paper's hybrid is unchanged: 8 codebooks of 128
    assert action_space(recipe_model("hybrid"), None)["heads"] == 8


def test_the_part_policy_puts_each_parts_choice_in_its_columns():
    torch.manual_seed(0)
    pol = PartCategoricalPolicy(5, torch.tensor([0, 1, 0, 1]), 7, PART_NAMES, (8,))
    x = torch.randn(3, 5)
    a, logp = pol.act(x, deterministic=True)
    lower = pol.parts["lower"].log_probs(x).argmax(-1)
    upper = pol.parts["upper"].log_probs(x).argmax(-1)
    assert torch.equal(a[:, [0, 2]], lower) and torch.equal(a[:, [1, 3]], upper)
    lp, ent = pol.evaluate(x, a)
    want = pol.parts["lower"].evaluate(x, lower)[0] + pol.parts["upper"].evaluate(x, upper)[0]
    assert torch.allclose(lp, want) and torch.allclose(logp, want) and ent.shape == (3,)


# ---------------------------------------------------------------------- the FSQ margin

def test_the_fsq_margin_on_hand_values_and_its_round_trip():
    # latent 6 = 2 groups x 3 channels: no projections, so the margin's channels are y itself
    model, _ = small_model("hybrid-fsq", latent_dim=6, num_codebooks=2, fsq_channels=3, fsq_levels=5)
    model.eval()
    q = model.quantizer
    y = torch.tensor([[0.1, 0.3, -2.0, 0.6, -0.2, 5.0]])
    # 5 levels: half-width 2, bound 2 tanh(y) = [0.199, 0.583, -1.928, 1.074, -0.395, 2.0] -> round
    out = q(y)
    assert out.indices.tolist() == [[2, 3, 0, 3, 2, 4]]  # levels 0..4
    assert torch.allclose(out.z_q, torch.tensor([[0.0, 0.5, -1.0, 0.5, 0.0, 1.0]]))
    assert out.losses["commit"] == 0 and out.losses["codebook"] == 0
    assert torch.equal(q.decode(out.indices), out.z_q) and torch.equal(q.encode(y), out.indices)
    assert q(y, 1).indices.tolist() == [[2, 3, 0, -1, -1, -1]]  # M = 1 group: the second at level zero
    assert torch.equal(q(y, 1).z_q[0, 3:], torch.zeros(3))
    # through the model: z_bar - z_p is the quantized bound of z - z_p, within half a step (1/4)
    x = torch.randn(256, 16)
    o = model(x)
    y = o.z - o.z_p
    step = 1 / 2
    assert (o.z_bar - o.z_p - torch.tanh(y)).abs().max() <= step / 2 + 1e-6
    assert torch.allclose(model.codes_to_latent(x[:, :10], o.indices), o.z_bar, atol=1e-6)


def test_the_fsq_straight_through_gradient_is_the_unrounded_paths():
    """d z_bar / d z = W_out diag(1 - tanh(h)^2) W_in with h = W_in y + b_in: the rounding passes the
    gradient unchanged, the bound and the projections do not (FSQ, not VQ's identity)."""
    model, x = small_model("hybrid-fsq")  # latent 8 -> 4 groups x 3 channels -> 8
    model.eval()
    q = model.quantizer
    out = model(x)
    out.z.retain_grad()
    w = torch.randn_like(out.z_bar)
    (out.z_bar * w).sum().backward()
    h = q.project_in(out.z - out.z_p).detach()
    want = ((w @ q.project_out.weight) * (1 - torch.tanh(h) ** 2)) @ q.project_in.weight
    assert torch.allclose(out.z.grad, want, atol=1e-6) and not torch.allclose(out.z.grad, w)


# ---------------------------------------------------------------------- where Eq. 6 sends the gradient

def term_grads(model: LatentPrior, x: torch.Tensor, term: str) -> dict[str, bool]:
    """Which modules ``term`` of Eq. 6 reaches (any nonzero gradient)."""
    model.zero_grad(set_to_none=True)
    model.train()
    _, terms = distill_loss(model(x), torch.randn(64, 4), 8, torch.zeros(8, 8, dtype=torch.bool), W)
    if terms[term].requires_grad:
        terms[term].backward()
    return {name: any(p.grad is not None and bool(p.grad.abs().sum() > 0) for p in mod.parameters())
            for name, mod in (("posterior", model.posterior), ("prior", model.prior), ("decoder", model.decoder),
                              ("quantizer", model.quantizer))}


def test_eq6_gradients_of_hybrid_fsq():
    model, x = small_model("hybrid-fsq")
    # FSQ's codebook is its projections, learned by what reaches the margin; the prior never by the action
    assert term_grads(model, x, "action_loss") == {"posterior": True, "prior": False, "decoder": True,
                                                   "quantizer": True}
    assert term_grads(model, x, "mm_loss") == {"posterior": True, "prior": True, "decoder": False, "quantizer": True}
    assert term_grads(model, x, "reg_loss") == {"posterior": True, "prior": True, "decoder": False, "quantizer": True}
    assert term_grads(model, x, "commit_loss") == dict.fromkeys(("posterior", "prior", "decoder", "quantizer"), False)


@pytest.mark.parametrize("kind", ["hybrid-grvq", "hybrid-parts"])
@pytest.mark.parametrize("quantizer", ["ema_reset", "vq"])
def test_eq6_gradients_of_the_group_rvq_kinds(kind, quantizer):
    model, x = small_model(kind, quantizer=quantizer)
    learned = quantizer == "vq"  # a gradient-learned codebook: its own loss only, never the others
    assert term_grads(model, x, "action_loss") == {"posterior": True, "prior": False, "decoder": True,
                                                   "quantizer": False}
    assert term_grads(model, x, "commit_loss") == {"posterior": True, "prior": False, "decoder": False,
                                                   "quantizer": False}
    assert term_grads(model, x, "mm_loss") == {"posterior": True, "prior": True, "decoder": False, "quantizer": False}
    assert term_grads(model, x, "reg_loss") == {"posterior": True, "prior": True, "decoder": False, "quantizer": False}
    model.zero_grad(set_to_none=True)
    out = model(x, model.num_codebooks)  # every codebook of every group in use
    if learned:
        out.losses["codebook"].backward()
        assert all(p.grad is not None for p in model.quantizer.parameters())
        assert model.posterior[0].weight.grad is None


def parts_model(**kw) -> tuple[LatentPrior, torch.Tensor]:
    """A part-wise prior on 10 observation and 6 goal entries (goal 0-2 lower, 3-5 upper), 4 actuators
    (0, 1 lower; 2, 3 upper); latent 8: dimensions 0-3 the lower group, 4-7 the upper."""
    torch.manual_seed(0)
    layout = (np.array([0, 0, 0, 1, 1, 1]), np.array([0, 0, 1, 1]))
    return LatentPrior(replace(small_prior_config("hybrid-parts"), **kw), 10, 6, 4, layout), torch.randn(64, 16)


def test_l_part_on_a_linear_decoder_by_hand():
    """With a linear decoder ``a = A [s, z_bar]``, redrawing group g's margin changes the actions by
    ``A_g (y_g' - y_g)``: ``L_part`` is the change on the other part's actuators only, so it is zero
    when the lower group drives only the legs and the upper group only the arms."""
    model, x = parts_model()
    model.decoder = torch.nn.Linear(18, 4, bias=False)
    with torch.no_grad():
        A = torch.zeros(4, 18)
        A[:2, 10:14] = torch.randn(2, 4)  # lower actuators <- lower group
        A[2:, 14:18] = torch.randn(2, 4)  # upper actuators <- upper group
        model.decoder.weight.copy_(A)
    model.train()
    assert float(model(x, 4).losses["part"].detach()) == 0.0
    with torch.no_grad():
        model.decoder.weight[3, 11] = 0.7  # an upper actuator now reads a lower-group dimension
    out = model(x, 4)
    y = out.z_bar - out.z_p
    want = (0.7 * (y.roll(1, 0)[:, 1] - y[:, 1])) ** 2  # only group 0's redraw, only actuator 3
    assert torch.allclose(out.losses["part"], want.mean(), rtol=1e-5)
    model.eval()
    assert float(model(x).losses["part"]) == 0.0  # a training term only


def test_l_part_reaches_the_decoder_and_posterior_not_the_prior():
    model, x = parts_model()
    assert term_grads(model, x, "part_loss") == {"posterior": True, "prior": False, "decoder": True,
                                                 "quantizer": False}


def test_group_rvq_decodes_the_sum_of_one_code_per_column_for_every_depth():
    model, x = small_model("hybrid-grvq")  # 2 groups x 4 codebooks of 16 codes, latent 8
    model.eval()
    s = x[:, :10]
    books = model.codebooks()
    assert books.shape == (8, 16, 8)
    for m in range(1, 5):
        out = model(x, m)
        idx = out.indices
        assert idx.shape == (64, 8) and (idx[:, :2 * m] >= 0).all() and (idx[:, 2 * m:] == -1).all()
        by_hand = model.prior(s) + sum(books[j][idx[:, j]] for j in range(2 * m))
        assert torch.allclose(model.codes_to_latent(s, idx[:, :2 * m]), by_hand, atol=1e-5)
        assert torch.allclose(model.codes_to_latent(s, idx, m), out.z_bar, atol=1e-5)
    # the first group's codes live in the first half of the dimensions only
    assert torch.all(books[0::2, :, 4:] == 0) and torch.all(books[1::2, :, :4] == 0)
    # quantizer dropout: one depth M per batch for both groups, every M drawn
    model.train()
    seen = set()
    for _ in range(60):
        used = (model(x).indices[0] >= 0).view(4, 2)
        assert torch.equal(used[:, 0], used[:, 1])
        seen.add(int(used[:, 0].sum()))
    assert seen == {1, 2, 3, 4}


# ---------------------------------------------------------------------- body parts

def test_the_body_parts_come_from_the_skeleton_tree(hum):
    sk = hum.skeleton
    part = body_parts(sk)
    lower = {sk.joints[j] for j in np.flatnonzero(part == 0)}
    assert lower == {"Hips", "UpperLeg_L", "LowerLeg_L", "Foot_L", "Toes_L", "UpperLeg_R", "LowerLeg_R", "Foot_R",
                     "Toes_R"}
    # actuators: per leg a ball hip (3), a knee hinge (1), a ball ankle (3); the other 23 hinges are above
    act = action_parts(hum)
    assert len(act) == 37 and (act == 0).sum() == 14
    assert all(n.split("_")[0] in ("UpperLeg", "LowerLeg", "Foot")
               for n, p in zip(hum.layout.hinge_names, act) if p == 0)
    g = goal_parts(sk, 2 * 21 * 15)  # two goal frames: (2, 21, 15)
    assert g.shape == (630,) and (g[:15] == 0).all() and (g[15:30] == 1).all()  # Hips, then Spine
    assert np.array_equal(g[:315], g[315:])
    with pytest.raises(UserError, match="15 per body"):
        goal_parts(sk, 100)


def test_each_half_of_the_part_posterior_reads_only_its_parts_goal(hum):
    obs_dim, goal_dim = 10, 21 * 15
    torch.manual_seed(0)
    model = LatentPrior(small_prior_config("hybrid-parts"), obs_dim, goal_dim, 4,
                        (goal_parts(hum.skeleton, goal_dim), np.array([0, 0, 1, 1])))
    x = torch.randn(32, obs_dim + goal_dim, requires_grad=True)
    z = model.posterior_latent(x)
    lower_goal = torch.as_tensor(goal_parts(hum.skeleton, goal_dim) == 0)
    for g, half in enumerate(z.split(4, -1)):
        (grad,) = torch.autograd.grad(half.sum(), x, retain_graph=True)
        goal = grad[:, obs_dim:].abs().sum(0)
        mine = lower_goal if g == 0 else ~lower_goal
        assert (goal[~mine] == 0).all() and (goal[mine] > 0).all()
        assert (grad[:, :obs_dim].abs().sum(0) > 0).all()  # both read the whole state s


# ---------------------------------------------------------------------- real data: distil, save, load, use

@pytest.fixture(scope="module")
def walk_lib(hum, small_dataset, tmp_path_factory):
    return load_library(hum, small_dataset, clips=[0, 1, 2], cache_dir=tmp_path_factory.mktemp("beyond-ref"))


@pytest.fixture(scope="module")
def expert_root(hum, walk_lib, small_dataset, tmp_path_factory):
    """A folder with a 1-iteration expert (and a 2-iteration hybrid prior beside it)."""
    root = tmp_path_factory.mktemp("beyond-runs")
    tiny_prior_bundle(root, hum, walk_lib, small_dataset)
    return root


@pytest.mark.parametrize("kind", NEW)
def test_a_new_kind_distils_loads_identically_generates_evaluates_and_trains_a_task(
        kind, hum, walk_lib, small_dataset, expert_root, tmp_path, monkeypatch):
    kept = []

    class Kept(distill.DistillTrainer):
        def __init__(self, *a, **k):
            super().__init__(*a, **k)
            kept.append(self)

    monkeypatch.setattr(distill, "DistillTrainer", Kept)
    cfg = DistillConfig(seed=0, iterations=3, save_every=1000, horizon=8, epochs=1, minibatch_size=32)
    cfg.env.num_envs, cfg.env.nthread = 4, 1
    cfg.task.termination = "mean"
    cfg.prior = small_prior_config(kind)
    run = tmp_path / "prior"
    distill.train(cfg, run, expert_root / "expert", walk_lib, data=small_dataset)
    trained = kept[0].model.eval()
    obs, goal = kept[0].mdp.reset()  # real states and goals
    x = torch.as_tensor(np.concatenate([obs, goal], 1), dtype=torch.float32)
    _, _, loaded, meta = load_prior(run)
    assert meta["extra"]["prior"]["index_columns"] == trained.columns()
    a, b = trained(trained.norm(x)), loaded(loaded.norm(x))
    assert torch.equal(a.action, b.action) and torch.equal(a.z_bar, b.z_bar) and torch.equal(a.indices, b.indices)
    if kind == "hybrid-parts":  # the part masks came back from the bundle, not from a default
        assert torch.equal(loaded.part_inputs, trained.part_inputs) and not bool(loaded.part_inputs.all())
    # unconditional generation from real start states: uniform codes in the first M = 1 only
    qpos, qvel = reference_state(walk_lib, np.array([0, 1, 2]), np.array([0, 5, 10]))
    res = rollout(loaded, hum, cfg.env, cfg.action, qpos, qvel, 6, 1, torch.Generator().manual_seed(0))
    idx = res["indices"]
    assert idx.shape == (6, 3, loaded.columns(1)) and (idx >= 0).all() and (idx < loaded.quantizer.codebook_size).all()
    assert res["alive"][:, 0].all() and res["pos"].shape[:2] == (3, 7)
    summary = generate(run, tmp_path / "gen.h5", codebooks=1, seconds=0.5, num_samples=2, fall_height=-1.0)
    assert summary["written"] == 2 and summary["codebooks"] == 1
    # the commands: the imitation evaluation with the first codebook only, two PPO iterations of
    # navigation over the frozen prior with M = 1
    r = CliRunner().invoke(app, ["control", "eval", "--task", "imitation", "--prior", str(run), "--codebooks", "1",
                                 "--json"])
    assert r.exit_code == 0, r.output
    ev = json.loads((run / "eval_m1.json").read_text())
    assert len(ev["clips"]) == 3 and ev["checkpoint"]["codebooks"] == 1
    r = CliRunner().invoke(app, ["control", "train", "--task", "navigation", "--prior", str(run), "--codebooks", "1",
                                 "-o", str(tmp_path / "nav"), "--json", *(f"--set={x}" for x in TINY_TASK)])
    assert r.exit_code == 0, r.output
    _, _, ac, model, _, tmeta = load_task_run(tmp_path / "nav")
    space = tmeta["extra"]["high_level_action"]
    assert space["heads"] == model.columns(1) == ac.policy.action_shape[0]
    assert ({"hybrid-fsq": 3, "hybrid-grvq": 2, "hybrid-parts": 2}[kind], space["codes"]) == \
        (space["heads"], loaded.quantizer.codebook_size)
    assert isinstance(ac.policy, PartCategoricalPolicy) == (kind == "hybrid-parts")
