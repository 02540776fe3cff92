"""The physics expert of the hybrid-latent paper (appendix B.2): PPO on the imitation environment
with ``r = w_im r_im + w_style r_style`` (0.5 each in the paper).

* ``r_im``, Eq. 10, a **product** ``r_root r_q r_alpha r_ee`` of ``exp(-k e)`` terms with the paper's
  exponents ``k = (10, 2, 0.5, 40)``. The environment's own ``reward["total"]`` is PHC's weighted
  *sum* of different terms (docs/sim.md), so the product is computed here from the simulated and
  reference states (:func:`imitation_errors`): ``e_root`` the squared root position error (m^2),
  ``e_q`` the sum over hinges of squared joint angle errors (rad^2, DeepMimic's pose term),
  ``e_alpha`` the mean over hinges of squared joint velocity errors ((rad/s)^2; a sum would make
  ``exp(-0.5 e)`` vanish for any walking policy), ``e_ee`` the sum over end effectors of squared
  root-relative position errors (m^2).
* ``r_style``, Eq. 11: the AMP discriminator of ``motok.control.amp``.

Training saves a bundle (kind ``control-expert``) every ``save_every`` iterations with the MJCF
(``RUN/humanoid.xml``) and its hash, the observation/action spec, the normaliser statistics, and
everything needed to resume exactly: optimisers, replay buffer, torch/numpy/env RNG states. At a
checkpoint every environment restarts from a fresh reference state, in an uninterrupted run as
in a resumed one, which is what makes resuming bit-exact without saving MuJoCo's solver state.
"""

from __future__ import annotations

import fnmatch
import hashlib
import json
import shutil
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from motok import progress as _progress
from motok.artifacts import Provenance, command_line, hash_inputs
from motok.checkpoint import (CheckpointError, MetricsLog, load_bundle, register_kind, rng_state, save_bundle,
                              set_rng_state)
from motok.config import from_dict, to_dict
from motok.control.amp import AMP, AMPConfig
from motok.control.networks import ActorCritic, EncoderDecoderPolicy, RunningNorm, ValueNet
from motok.control.ppo import PPO, PPOConfig, Rollout
from motok.sim.env import EnvConfig, HumanoidEnv
from motok.sim.humanoid import Humanoid, load_humanoid
from motok.sim.obs import Bodies, observation
from motok.sim.reference import ReferenceLibrary

KIND = "control-expert"
register_kind(KIND, (1,))


@dataclass
class ImitationConfig:
    k_root: float = 10.0
    k_q: float = 2.0
    k_alpha: float = 0.5
    k_ee: float = 40.0


@dataclass
class NetConfig:
    latent_dim: int = 64
    encoder: list[int] = field(default_factory=lambda: [512, 256])
    decoder: list[int] = field(default_factory=lambda: [512, 256])
    value: list[int] = field(default_factory=lambda: [512, 256])
    activation: str = "elu"
    log_std: float = -1.6
    learn_log_std: bool = False


@dataclass
class ExpertConfig:
    seed: int = 0
    iterations: int = 1000
    w_im: float = 0.5
    w_style: float = 0.5
    save_every: int = 50
    eval_every: int = 0  # iterations between `evaluate` passes logged as eval_* metrics (0: never)
    torch_threads: int = 1  # 2 fights MuJoCo's worker threads on a 2-core machine: 3x slower updates
    env: EnvConfig = field(default_factory=lambda: EnvConfig(num_envs=64))
    ppo: PPOConfig = field(default_factory=PPOConfig)
    net: NetConfig = field(default_factory=NetConfig)
    amp: AMPConfig = field(default_factory=AMPConfig)
    imitation: ImitationConfig = field(default_factory=ImitationConfig)


# ---------------------------------------------------------------------- Eq. 10, product form
def imitation_errors(pos, ref_pos, q, q_ref, qd, qd_ref, ee) -> dict[str, np.ndarray]:
    """Squared errors ``(N,)`` of body positions ``(N, J, 3)`` (root = body 0), hinge angles and
    velocities ``(N, H)`` and end effectors ``ee`` (body indices, root-relative)."""
    rel, rel_ref = pos[:, ee] - pos[:, :1], ref_pos[:, ee] - ref_pos[:, :1]
    return {"root": ((pos[:, 0] - ref_pos[:, 0]) ** 2).sum(-1), "q": ((q - q_ref) ** 2).sum(-1),
            "alpha": ((qd - qd_ref) ** 2).mean(-1), "ee": ((rel - rel_ref) ** 2).sum(-1).sum(-1)}


def imitation_reward(err: dict[str, np.ndarray], cfg: ImitationConfig) -> dict[str, np.ndarray]:
    """Eq. 10: ``r_im = exp(-10 e_root) exp(-2 e_q) exp(-0.5 e_alpha) exp(-40 e_ee)`` and its factors."""
    r = {f"r_{k}": np.exp(-getattr(cfg, f"k_{k}") * err[k]) for k in ("root", "q", "alpha", "ee")}
    r["r_im"] = r["r_root"] * r["r_q"] * r["r_alpha"] * r["r_ee"]
    return r


def env_imitation_reward(env: HumanoidEnv, cfg: ImitationConfig) -> dict[str, np.ndarray]:
    """Eq. 10 for every environment at its current state against its current reference frame."""
    L = env.lib
    g = np.minimum(L.starts[env.clip] + env.frame, L.starts[env.clip + 1] - 1)
    err = imitation_errors(env.bodies.pos, L.body_pos[g], env.qpos[:, 7:], L.qpos[g, 7:], env.qvel[:, 6:],
                           L.qvel[g, 6:], env.end_effectors)
    return imitation_reward(err, cfg)


def reference_observations(lib: ReferenceLibrary, end_effectors) -> np.ndarray:
    """Eq. 7 observation of every library frame: what the discriminator's reference samples are."""
    bodies = Bodies(lib.body_pos, lib.body_vel, lib.body_angvel, quat=lib.body_quat)
    return observation(lib.qpos, lib.qvel, bodies, end_effectors)


def build_actor_critic(cfg: ExpertConfig, obs_dim: int, goal_dim: int, action_dim: int) -> ActorCritic:
    n = cfg.net
    pol = EncoderDecoderPolicy(obs_dim, goal_dim, action_dim, n.latent_dim, tuple(n.encoder), tuple(n.decoder),
                               n.activation, n.log_std, n.learn_log_std)
    return ActorCritic(RunningNorm(obs_dim + goal_dim), pol, ValueNet(obs_dim + goal_dim, tuple(n.value), n.activation))


def select_clips(data, pattern: str | None) -> list[str]:
    from motok.data.dataset import MotionFile
    with MotionFile(data, "motion-dataset") as mf:
        names = list(mf.names)
    if not pattern:
        return names
    chosen = [n for n in names if fnmatch.fnmatchcase(n, pattern)]
    if not chosen:
        raise ValueError(f"no clip of {data} matches {pattern!r} (e.g. {names[:3]})")
    return chosen


def _t(a) -> torch.Tensor:
    return torch.as_tensor(np.nan_to_num(np.asarray(a, dtype=np.float32)))  # a diverged env may hold non-finite rows


def _split(state: dict, prefix: str) -> dict:
    return {k[len(prefix):]: v for k, v in state.items() if k.startswith(prefix)}


def mjcf_hash(hum: Humanoid) -> str:
    return hashlib.sha256(Path(hum.path).read_bytes()).hexdigest()


class ExpertTrainer:
    """PPO + AMP on a :class:`HumanoidEnv`; ``run`` drives iterations, checkpoints and logs."""

    def __init__(self, cfg: ExpertConfig, hum: Humanoid, lib: ReferenceLibrary):
        self.cfg = cfg
        torch.manual_seed(cfg.seed)
        self.rng = np.random.default_rng(cfg.seed + 1)  # AMP sampling; the env has its own
        self.env = HumanoidEnv(hum, lib, replace(cfg.env, seed=cfg.seed))
        e = self.env
        self.ac = build_actor_critic(cfg, e.obs_dim, e.goal_dim, e.action_dim)
        self.ppo = PPO(self.ac, cfg.ppo, cfg.iterations)
        use_amp = cfg.amp.enabled and cfg.w_style != 0
        self.amp = AMP(cfg.amp, reference_observations(lib, e.end_effectors), lib.starts) if use_amp else None
        self.iteration, self.samples, self.wall = 0, 0, 0.0

    # ------------------------------------------------------------------ state
    def model_state(self) -> dict[str, torch.Tensor]:
        st = {f"ac.{k}": v for k, v in self.ac.state_dict().items()}
        if self.amp is not None:
            st.update({f"disc.{k}": v for k, v in self.amp.disc.state_dict().items()})
        return st

    def train_state(self) -> dict:
        ts = {"iteration": self.iteration, "samples": self.samples, "wall": self.wall, "rng": rng_state(),
              "ppo_opt": self.ppo.opt.state_dict(), "env_rng": json.dumps(self.env.rng.bit_generator.state),
              "amp_rng": json.dumps(self.rng.bit_generator.state)}
        if self.amp is not None:
            ts.update(amp_opt=self.amp.opt.state_dict(), replay=self.amp.replay.state())
        return ts

    def load(self, state: dict, ts: dict | None) -> None:
        self.ac.load_state_dict(_split(state, "ac."))
        if self.amp is not None:
            self.amp.disc.load_state_dict(_split(state, "disc."))
        if ts is None:
            return
        self.iteration, self.samples, self.wall = int(ts["iteration"]), int(ts["samples"]), float(ts["wall"])
        self.ppo.opt.load_state_dict(ts["ppo_opt"])
        set_rng_state(ts["rng"])
        self.env.rng.bit_generator.state = json.loads(ts["env_rng"])
        self.rng.bit_generator.state = json.loads(ts["amp_rng"])
        if self.amp is not None:
            self.amp.opt.load_state_dict(ts["amp_opt"])
            self.amp.replay.load(ts["replay"])

    def start_segment(self) -> None:
        """Fresh reference states for every environment: done at the start and after each checkpoint."""
        self.obs, self.goal = self.env.reset()
        N = self.env.num_envs
        self.ep_ret, self.ep_rim, self.ep_len = np.zeros(N), np.zeros(N), np.zeros(N, dtype=np.int64)

    # ------------------------------------------------------------------ one iteration
    def collect(self) -> tuple[Rollout, torch.Tensor, dict]:
        c, env, ac = self.cfg, self.env, self.ac
        T, N = c.ppo.horizon, env.num_envs
        ro = Rollout(T, N, env.obs_dim + env.goal_dim, env.action_dim)
        s, s2 = torch.zeros(T, N, env.obs_dim), torch.zeros(T, N, env.obs_dim)
        r_im = torch.zeros(T, N)
        for t in range(T):
            x = _t(np.concatenate([self.obs, self.goal], 1))
            ac.norm.update(x)
            xn, a, logp, v = ac.act(x)
            obs, goal, _, term, trunc, info = env.step(a.numpy())
            bad = info["diverged"] | info["invalid_action"]
            r_im[t] = torch.from_numpy(np.where(bad, 0.0, env_imitation_reward(env, c.imitation)["r_im"]))
            ro.x[t], ro.actions[t], ro.logp[t], ro.values[t] = xn, a, logp, v
            ro.terminated[t], ro.truncated[t] = torch.from_numpy(term), torch.from_numpy(trunc)
            s[t], s2[t] = _t(self.obs), _t(obs)
            if trunc.any():  # bootstrapping needs the value of the final observation, before the reset
                with torch.no_grad():
                    xf = ac.norm(_t(np.concatenate([obs[trunc], goal[trunc]], 1)))
                    ro.final_values[t, torch.from_numpy(trunc)] = ac.value(xf)
            done = term | trunc
            if done.any():
                obs, goal = env.reset(np.flatnonzero(done))
            self.obs, self.goal = obs, goal
        with torch.no_grad():
            last_value = ac.value(ac.norm(_t(np.concatenate([self.obs, self.goal], 1))))
        r_style = self.amp.reward(s.flatten(0, 1), s2.flatten(0, 1)).view(T, N) if self.amp else torch.zeros(T, N)
        ro.rewards = c.w_im * r_im + (c.w_style * r_style if self.amp else 0.0)
        stats = self._episodes(ro, r_im)
        stats.update(r_im=float(r_im.mean()), r_style=float(r_style.mean()), reward=float(ro.rewards.mean()))
        if self.amp is not None:
            stats.update(self.amp.update(s.flatten(0, 1), s2.flatten(0, 1), self.rng))
        return ro, last_value, stats

    def _episodes(self, ro: Rollout, r_im: torch.Tensor) -> dict:
        rets, rims, lens, succ = [], [], [], []
        for t in range(len(ro.rewards)):
            self.ep_ret += ro.rewards[t].numpy()
            self.ep_rim += r_im[t].numpy()
            self.ep_len += 1
            done = (ro.terminated[t] | ro.truncated[t]).numpy()
            if done.any():
                rets += self.ep_ret[done].tolist()
                rims += (self.ep_rim[done] / self.ep_len[done]).tolist()
                lens += self.ep_len[done].tolist()
                succ += ro.truncated[t].numpy()[done].tolist()  # ended without falling: clip end or time limit
                self.ep_ret[done], self.ep_rim[done], self.ep_len[done] = 0.0, 0.0, 0
        if not rets:
            return {}
        return {"episode_return": float(np.mean(rets)), "episode_r_im": float(np.mean(rims)),
                "episode_seconds": float(np.mean(lens)) * self.env.dt, "success": float(np.mean(succ)),
                "episodes": len(rets)}

    def step(self) -> dict:
        t0 = time.perf_counter()
        ro, last_value, stats = self.collect()
        t1 = time.perf_counter()
        stats.update(self.ppo.update(ro, last_value, self.iteration))
        n = ro.rewards.numel()
        self.iteration += 1
        self.samples += n
        dt = time.perf_counter() - t0
        self.wall += dt
        stats.update(iteration=self.iteration, samples=self.samples, wall_s=round(self.wall, 2),
                     samples_per_s=n / dt, rollout_s=t1 - t0, update_s=dt - (t1 - t0))
        return stats


def _spec(trainer: ExpertTrainer, hum: Humanoid) -> dict:
    e, m = trainer.env, hum.model
    return {"mjcf_sha256": mjcf_hash(hum), "obs_dim": e.obs_dim, "goal_dim": e.goal_dim, "action_dim": e.action_dim,
            "action": {"kind": "residual PD target offsets (rad): q_hat = base + action_scale * a",
                       "base": e.cfg.action_base, "action_scale": e.cfg.action_scale, "actuators": list(hum.layout.hinge_names),
                       "ctrl_range": m.actuator_ctrlrange.tolist()},
            "observation": "Eq. 7 s (heading frame) then Eq. 9 goal, normalised by ac.norm.{mean,var,count}",
            "normaliser": ["ac.norm.mean", "ac.norm.var", "ac.norm.count"], "control_hz": 1.0 / e.dt}


def train(cfg: ExpertConfig, run, hum: Humanoid, lib: ReferenceLibrary, *, resume: bool = False,
          until: int | None = None, data=None, command: str | None = None) -> dict:
    """Train (or resume) an expert into ``run``; stops after ``until`` iterations if given."""
    threads = torch.get_num_threads()
    torch.set_num_threads(max(1, cfg.torch_threads))
    try:
        return _train(cfg, Path(run), hum, lib, resume, until, data, command)
    finally:
        torch.set_num_threads(threads)


def _train(cfg, run: Path, hum, lib, resume, until, data, command) -> dict:
    run.mkdir(parents=True, exist_ok=True)
    saved = load_bundle(run, KIND, with_train_state=True) if resume else None
    if saved and saved[0]["extra"].get("mjcf_sha256") != mjcf_hash(hum):
        raise CheckpointError(f"{run}: the checkpoint was trained on another humanoid (MJCF hash differs)")
    if Path(hum.path).resolve() != (run / "humanoid.xml").resolve():
        shutil.copyfile(hum.path, run / "humanoid.xml")
    tr = ExpertTrainer(cfg, hum, lib)
    if saved:
        tr.load(saved[1], saved[2])
    inputs = hash_inputs([data]) if data else {}
    prov = Provenance(command=command or command_line(), config=to_dict(cfg), inputs=inputs)
    extra = {**_spec(tr, hum), "data": str(data) if data else None, "clips": list(lib.names)}
    log = MetricsLog(run / "metrics.jsonl", resume_from=tr.iteration if saved else None)
    stop = min(cfg.iterations, until if until is not None else cfg.iterations)
    per_it = cfg.ppo.horizon * tr.env.num_envs

    def save():
        save_bundle(run, KIND, tr.model_state(), to_dict(cfg), prov, train_state=tr.train_state(),
                    extra={**extra, "iteration": tr.iteration, "samples": tr.samples, "last_metrics": last})

    last: dict = {}
    tr.start_segment()
    bar = _progress.make_progress("samples", "ret {task.fields[ret]} len {task.fields[len]}s succ {task.fields[succ]}")
    with bar:
        task = bar.add_task("expert", total=stop * per_it, completed=tr.iteration * per_it, ret="-", len="-", succ="-")
        while tr.iteration < stop:
            stats = tr.step()
            if cfg.eval_every and tr.iteration % cfg.eval_every == 0:
                from motok.control.evaluate import eval_metrics, evaluate
                stats.update(eval_metrics(evaluate(cfg, hum, tr.ac, lib)))
            last = {**last, **stats}
            log.log(stats)
            bar.update(task, advance=per_it, ret=f"{last.get('episode_return', 0):.1f}",
                       len=f"{last.get('episode_seconds', 0):.2f}", succ=f"{last.get('success', 0):.2f}")
            if tr.iteration % cfg.save_every == 0 or tr.iteration == stop:
                save()
                tr.start_segment()
    if not (run / "bundle.json").exists():
        save()
    return {"run": str(run), "iterations": tr.iteration, "samples": tr.samples, "wall_s": round(tr.wall, 1),
            **{k: round(v, 4) for k, v in last.items() if k in ("episode_return", "episode_seconds", "success",
                                                                 "r_im", "samples_per_s")}}


def load_expert(run) -> tuple[ExpertConfig, Humanoid, ActorCritic, dict]:
    run = Path(run)
    meta, state, _ = load_bundle(run, KIND)
    cfg = from_dict(ExpertConfig, meta["config"])
    hum = load_humanoid(run / "humanoid.xml")
    if mjcf_hash(hum) != meta["extra"]["mjcf_sha256"]:
        raise CheckpointError(f"{run}/humanoid.xml does not match the checkpoint's MJCF hash")
    ex = meta["extra"]
    ac = build_actor_critic(cfg, ex["obs_dim"], ex["goal_dim"], ex["action_dim"])
    ac.load_state_dict(_split(state, "ac."))
    return cfg, hum, ac, meta
