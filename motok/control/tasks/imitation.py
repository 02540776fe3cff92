"""The imitation task: track reference clips (hybrid-latent paper section 4.3 / appendix B.2).

* reset: reference state initialisation (``mdp.resets``) at a random clip and frame (clips drawn
  in proportion to their usable length) or at given ones;
* goal: Eq. 9 differences to the next K reference frames (``mdp.observations.imitation_goal``);
* reward: Eq. 10, the product form (``mdp.rewards.imitation_reward``), 0 after a diverged
  simulation or an invalid action;
* terminated: early termination when the bodies are too far from the reference
  (``mdp.terminations.tracking_failure``), a diverged simulation or an invalid action;
  truncated: the time limit or the end of the clip (one step before the goal runs out of frames).

Evaluation (:func:`evaluate`): every clip played from its first frame with the most likely action
(``motok control expert eval``, ``motok control eval --task imitation --prior``, the ``eval_*``
metrics logged while training, the difficulty evaluations of ``motok.control.rl.sampling``, and
tracking's :func:`play`).
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, field, replace
from functools import partial

import numpy as np

from motok.arrays import copy, is_tensor, like, xp
from motok.control.mdp.actions import ActionConfig, pd_targets
from motok.control.mdp.observations import imitation_goal
from motok.control.mdp.resets import (ClipProbabilities, check_rate, check_start_frames, given_starts, host_lengths,
                                      reference_bodies, reference_state, sample_starts)
from motok.control.mdp.rewards import ImitationConfig, feet_error, imitation_errors, imitation_reward
from motok.control.mdp.task_env import Task, TaskEnv
from motok.control.mdp.terminations import MODES, body_distances, end_of_step, tracking_failure
from motok.control.rl.networks import ActorCritic
from motok.control.rl.rollout import as_tensor
from motok.errors import UserError
from motok.eval.metrics import acceleration_error, mpjpe, velocity_error
from motok.eval.physical import PhysicalSums, clip_sums
from motok.ranges import In
from motok.sim.env import HumanoidEnv, SimConfig
from motok.sim.humanoid import Humanoid
from motok.sim.obs import Bodies
from motok.sim.reference import ReferenceLibrary
from motok.sim.soles import SlipSums, Soles, reference_corners, slip_sums, soles


@dataclass
class ImitationTaskConfig:
    max_episode_seconds: In[float, "> 0"] = 10.0  # time limit of an episode (a clip's end comes first when sooner)
    goal_frames: In[int, ">= 1"] = 1  # K reference frames ahead in the goal (Eq. 9)
    termination: str = "any"  # "any" body beyond the distance, or the "mean" over bodies (PHC's failure test)
    termination_distance: In[float, "> 0"] = 0.5  # m, from the reference
    early_termination: bool = True  # a body beyond termination_distance ends the episode (false: plays on)
    reward: ImitationConfig = field(default_factory=ImitationConfig)  # Eq. 10's exponents

    def __post_init__(self):
        if self.termination not in MODES:
            raise UserError(f"termination must be 'any' or 'mean', not {self.termination!r}")


class ImitationTask(Task):
    """Episode state: ``clip``, ``frame`` (the reference frame the simulation is at), ``steps``, ``limit``.

    With a library moved to a device (``ReferenceLibrary.to``), an ``on_device`` environment and a
    ``torch.Generator`` on that device as ``rng``, the episode state and every term are device
    tensors (the same code, :mod:`motok.arrays`)."""

    reward_key = "r_im"
    clip_p = ClipProbabilities()  # start-clip probabilities (None: by usable length)

    def __init__(self, cfg: ImitationTaskConfig, env: HumanoidEnv, lib: ReferenceLibrary, rng):
        check_rate(lib, env.control_hz)
        if is_tensor(lib.starts) != env.on_device:
            raise UserError("the reference library and the environment must both be on the device or both on the host")
        self.cfg, self.env, self.lib, self.rng = cfg, env, lib, rng
        N, K, S = env.num_envs, cfg.goal_frames, lib.starts
        self.max_steps = max(1, int(round(cfg.max_episode_seconds * env.control_hz)))
        self.goal_dim = K * len(env.hum.skeleton.joints) * 15
        self.clip, self.frame = like(S, np.zeros(N, dtype=np.int64)), like(S, np.zeros(N, dtype=np.int64))
        self.steps, self.limit = like(S, np.zeros(N, dtype=np.int64)), like(S, np.ones(N, dtype=np.int64))
        self._goal = like(lib.qpos, np.zeros((N, self.goal_dim)))
        self._window = like(S, np.arange(K + 1))  # the reference frame reached and the K the goal looks ahead to
        self._host_lengths = host_lengths(lib)  # to check given starts on the host
        sk = env.hum.skeleton
        self._feet = [*sk.feet_left, *sk.feet_right]  # ankles and toes: the foot-velocity term's bodies

    def reference(self, clips, frames) -> Bodies:
        """Reference body states at ``frames`` of ``clips`` (clamped to each clip's last frame)."""
        return reference_bodies(self.lib, clips, frames)

    def _ahead(self, ids):
        return self.frame[ids, None] + self._window[1:]

    def reset(self, ids, clips=None, frames=None) -> None:
        """Random clips (by ``clip_p``) and frames from the task's generator, unless
        ``clips``/``frames`` (names or indices) are given."""
        K, L = self.cfg.goal_frames, self.lib
        if clips is None:
            c, f = sample_starts(L, len(ids), self.rng, K + 1, self.clip_p)
        else:
            c, f = given_starts(L, clips, frames, len(ids))
            check_start_frames(L, c, f, K, self._host_lengths)
            c, f = like(L.starts, c), like(L.starts, f)
        self.env.set_state(ids, *reference_state(L, c, f))
        self.clip[ids], self.frame[ids], self.steps[ids] = c, f, 0
        # The last step's goal still needs K frames ahead: frame + K <= last frame of the clip.
        self.limit[ids] = xp(f).clip(L.lengths[c] - 1 - f - K, None, self.max_steps)
        self._goal[ids] = imitation_goal(self.env.bodies.take(ids), self.reference(self.clip[ids, None], self._ahead(ids)))

    def follow(self, lib: ReferenceLibrary, ids) -> None:
        """Go on in environments ``ids`` along clip ``i`` of ``lib`` for environment ``i``, from its
        frame 0, without touching the physics: the state the simulation reached is the start (a
        closed loop hands the controller each new plan this way). Every environment must be on
        clip ``i`` of the library it follows; the others keep their clip and frame."""
        check_rate(lib, self.env.control_hz)
        self.lib, self._host_lengths = lib, host_lengths(lib)
        self.clip[ids], self.frame[ids], self.steps[ids] = ids, 0, 0
        self.limit[ids] = xp(lib.lengths).clip(lib.lengths[ids] - 1 - self.cfg.goal_frames, None, self.max_steps)
        self._goal[ids] = imitation_goal(self.env.bodies.take(ids), self.reference(self.clip[ids, None], self._ahead(ids)))

    def goal(self):
        return copy(self._goal)

    def step_limit(self):
        return self.limit

    def next_reference(self):
        """``(qpos, qvel)`` of the reference frame the coming step should reach (the action base)."""
        g = self.lib.frame_index(self.clip, self.frame + 1)
        return self.lib.qpos[g], self.lib.qvel[g]

    def current_reference_qpos(self):
        return self.lib.qpos[self.lib.frame_index(self.clip, self.frame)]

    def update(self, diverged, invalid):
        env, L, c = self.env, self.lib, self.cfg
        self.frame += 1
        self.steps += 1
        refs = self.reference(self.clip[:, None], self.frame[:, None] + self._window)
        sim = env.bodies
        self._goal = imitation_goal(sim, refs.take((slice(None), slice(1, None))))
        ref = refs.take((slice(None), 0))
        g = L.frame_index(self.clip, self.frame)
        err = imitation_errors(sim.pos, ref.pos, env.qpos[:, 7:], L.qpos[g, 7:], env.qvel[:, 6:], L.qvel[g, 6:],
                               env.end_effectors)
        if c.reward.k_feet > 0:
            err["feet"] = feet_error(sim.vel, ref.vel, self._feet)
        dist = body_distances(sim, ref)
        fell = tracking_failure(dist, c.termination, c.termination_distance) if c.early_termination \
            else xp(dist).zeros_like(diverged)
        rewards, terminated, truncated = end_of_step(imitation_reward(err, c.reward), fell, diverged, invalid,
                                                     self.steps, self.limit)
        info = {"clip": copy(self.clip), "frame": copy(self.frame), "max_body_error": xp(dist).amax(dist, -1),
                "mean_body_error": dist.mean(-1), "diverged": diverged, "invalid_action": invalid,
                "episode_steps": copy(self.steps)}
        return rewards, terminated, truncated, info


# ---------------------------------------------------------------------- evaluation

ERRORS = ("mpjpe_mm", "g_mpjpe_mm", "root_vel_err_mm", "root_acc_err_mm")


def eval_metrics(res: dict, prefix: str = "eval_") -> dict:
    """The overall numbers of :func:`evaluate` as training metrics (with ``feet``, :data:`FEET` of
    the simulated motion and, prefixed ``ref_``, of its reference)."""
    o = res["overall"]
    out = {f"{prefix}success": o["success_rate"], f"{prefix}success_any_body": o["success_rate_any_body"],
           f"{prefix}seconds": o["seconds_played"] / max(o["clips"], 1), f"{prefix}mpjpe_mm": o["mpjpe_mm"],
           f"{prefix}g_mpjpe_mm": o["g_mpjpe_mm"]}
    if "feet" in res:  # the simulated feet, and the clips' own over the same frames (``ref_``)
        for who, tag in (("simulated", ""), ("reference", "ref_")):
            out.update({f"{prefix}{tag}{k}": res["feet"][who][k] for k in FEET})
    return out


def policy_device(policy):
    """Where a policy's weights are (a trainer may keep them on the physics device); CPU for a
    policy that is not a module (a student wrapper) or has no weights."""
    import torch

    params = getattr(policy, "parameters", None)
    first = next(params(), None) if callable(params) else None
    return first.device if first is not None else torch.device("cpu")


def play(hum, ac, lib, ids: np.ndarray, sim: SimConfig, task: ImitationTaskConfig, action: ActionConfig,
         keep_qpos: bool = False, sole: Soles | None = None, replan=None) -> dict:
    """One batch of clips ``ids`` from frame 0 until each ends or fails: simulated and reference body
    positions ``(N, T + 1, J, 3)`` with the ``alive`` mask of the frames each clip played, the
    first environment's qpos (and its reference's, ``ref_qpos``) when ``keep_qpos``, and with
    ``sole`` the simulated and reference sole corners ``(N, T + 1, K, 3)`` (``sole_sim``,
    ``sole_ref``; ``motok.sim.soles``).

    ``replan(steps, env, pos, active)``, called after every step with the environment, the body
    positions so far (a list of ``(N, J, 3)``, the start state first) and the environments still
    playing, may return
    ``(library, envs)``: those environments then follow the new library from where they are
    (:meth:`ImitationTask.follow`; ``ids`` must be ``0 .. N - 1``). Without it, nothing changes."""
    N = len(ids)
    # Host arrays whatever the training used (an evaluation is not the hot path); the policy stays where it is.
    env = HumanoidEnv(hum, replace(sim, num_envs=N, on_device=False))
    device = policy_device(ac)
    # The generator is never drawn from: every start is given.
    it = ImitationTask(task, env, lib, np.random.default_rng(0))
    mdp = TaskEnv(env, it, partial(pd_targets, action))
    obs, goal = mdp.reset(clips=ids, frames=0)
    pos, ref, qpos = [env.bodies.pos.copy()], [lib.body_pos[lib.starts[ids]]], [env.qpos[0].copy()]
    ref_qpos = [lib.qpos[lib.starts[ids[0]]]]
    corners = []

    def keep_corners(frames):
        if sole is not None:
            corners.append((sole.world(env.bodies.pos, env.bodies.rot).astype(np.float32),
                            reference_corners(sole, lib.body_pos[frames], lib.body_quat[frames]).astype(np.float32)))

    keep_corners(lib.starts[ids])
    alive, played = [np.ones(N, bool)], np.zeros(N, dtype=np.int64)
    active, success = np.ones(N, bool), np.zeros(N, bool)
    worst = np.zeros(N)  # largest single-body error over the frames played
    while active.any():
        _, a, _, _ = ac.act(as_tensor(np.concatenate([obs, goal], 1)).to(device), deterministic=True)
        obs, goal, _, term, trunc, info = mdp.step(a.cpu().numpy())
        worst = np.where(active, np.maximum(worst, info["max_body_error"]), worst)
        frames = lib.frame_index(it.clip, it.frame)
        pos.append(env.bodies.pos.copy()), ref.append(lib.body_pos[frames])
        keep_corners(frames)
        # A diverged simulation was put back to a default pose: that frame was never played.
        alive.append(active & ~np.asarray(info["diverged"], bool))
        if keep_qpos:
            qpos.append(env.qpos[0].copy())
            ref_qpos.append(lib.qpos[frames[0]])
        played += active
        success |= active & trunc
        active &= ~(term | trunc)
        new = replan(len(pos) - 1, env, pos, active.copy()) if replan is not None and active.any() else None
        if new is not None:
            lib, envs = new
            it.follow(lib, envs)
            goal = it.goal()
    out = {"pos": np.stack(pos, 1), "ref": np.stack(ref, 1), "alive": np.stack(alive, 1), "played": played,
           "success": success, "worst": worst, "qpos": np.stack(qpos), "dt": env.dt}
    if keep_qpos:
        out["ref_qpos"] = np.stack(ref_qpos)
    if sole is not None:
        out["sole_sim"], out["sole_ref"] = (np.stack([c[k] for c in corners], 1) for k in (0, 1))
    return out


def clip_slip(out: dict, k: int) -> tuple[SlipSums, SlipSums]:
    """Sole slip sums (simulated, reference) of environment ``k`` of a :func:`play` with ``sole``,
    over the states it played."""
    alive = out["alive"][k]
    return tuple(slip_sums(out[key][k], out["dt"], alive) for key in ("sole_sim", "sole_ref"))


def slip_report(sim: SlipSums, ref: SlipSums) -> dict:
    """Overall sole slip of the simulated bodies and of their reference over the same states."""
    return {"simulated": sim.result(), "reference": ref.result()}


FEET = ("skate_cm_s", "sole_slip_cm_s", "sole_penetration_mm", "jitter_m_s3")


def clip_feet(out: dict, k: int, feet) -> tuple[PhysicalSums, PhysicalSums]:
    """Joint skating and jitter (``motok.eval.physical``, Y up as the data) of the simulated bodies
    and of their reference over the states environment ``k`` of a :func:`play` played."""
    a = out["alive"][k]
    hz = 1.0 / out["dt"]
    return tuple(clip_sums(out[key][k, a][..., [1, 2, 0]], hz, feet) for key in ("pos", "ref"))


def feet_report(joints: tuple[PhysicalSums, PhysicalSums], sole: tuple[SlipSums, SlipSums]) -> dict:
    """``{"simulated": {...}, "reference": {...}}``: :data:`FEET` and the sole contact fraction of each,
    over the same states at the control rate, so the two rows compare like with like."""
    return {who: {**j.result(), **s.result()} for who, j, s in zip(("simulated", "reference"), joints, sole)}


def evaluate(hum: Humanoid, ac: ActorCritic, lib: ReferenceLibrary, sim: SimConfig, task: ImitationTaskConfig,
             action: ActionConfig, render=None, batch: int = 256, clips=None, feet: bool = False) -> dict:
    """Every clip from its first frame with the most likely action, until the clip's end (success)
    or early termination (the task's criterion; ``success_rate_any_body`` also requires every
    single body to have stayed within the distance, the stricter test). Errors over the frames
    played: MPJPE (root-relative) and G-MPJPE (global) in mm, root velocity (mm/frame) and
    acceleration (mm/frame^2) errors from finite differences (``motok.eval.metrics``).

    Clips are played ``batch`` at a time, sorted by length, so a batch ends with its longest clip
    and a long clip does not keep thousands of finished environments stepping. ``clips``: indices
    of the library's clips to play (default: all).

    With ``feet`` the result also has ``feet`` (:func:`feet_report`: joint skating, sole slip, sole
    penetration and jitter of the simulated motion beside the reference's over the frames played)
    and each clip its simulated ``skate_cm_s`` and ``sole_slip_cm_s``."""
    tcfg = replace(task, max_episode_seconds=1e9)
    chosen = np.arange(len(lib)) if clips is None else np.asarray(clips, dtype=np.int64)
    order = chosen[np.argsort(-lib.lengths[chosen], kind="stable")]
    chunks = [order[i:i + batch] for i in range(0, len(order), batch)]
    per, video_qpos = {}, None
    success, worst = np.zeros(len(lib), bool), np.zeros(len(lib))
    if render is not None and 0 not in chosen:
        raise ValueError("render draws the library's first clip: include clip 0")
    sole = soles(hum) if feet else None
    skel = hum.skeleton
    foot_joints = (tuple(skel.feet_left), tuple(skel.feet_right))
    joint_sums, sole_sums = (PhysicalSums(), PhysicalSums()), (SlipSums(), SlipSums())
    for ids in chunks:
        first = render is not None and 0 in ids
        if first:  # the rendered clip leads its batch, so its qpos are row 0
            ids = np.concatenate([[0], ids[ids != 0]])
        out = play(hum, ac, lib, ids, sim, tcfg, action, keep_qpos=first, sole=sole)
        if first:
            video_qpos = (out["qpos"], int(out["played"][0]))
        for k, i in enumerate(ids):
            a = out["alive"][k]
            p, r = out["pos"][k, a], out["ref"][k, a]
            success[i], worst[i] = out["success"][k], out["worst"][k]
            per[lib.names[i]] = {
                "success": bool(out["success"][k]), "max_body_error_m": float(out["worst"][k]),
                "seconds": float(out["played"][k] * out["dt"]),
                "clip_seconds": float((lib.lengths[i] - 1 - tcfg.goal_frames) * out["dt"]),
                "mpjpe_mm": float(mpjpe(p, r).mean()), "g_mpjpe_mm": float(mpjpe(p, r, root_relative=False).mean()),
                "root_vel_err_mm": float(velocity_error(p[:, :1], r[:, :1]).mean()) if len(p) > 1 else float("nan"),
                "root_acc_err_mm": float(acceleration_error(p[:, :1], r[:, :1]).mean()) if len(p) > 2
                else float("nan")}
            if feet:
                j_sim, j_ref = clip_feet(out, k, foot_joints)
                s_sim, s_ref = clip_slip(out, k)
                for total, one in zip((*joint_sums, *sole_sums), (j_sim, j_ref, s_sim, s_ref)):
                    total.add(one)
                per[lib.names[i]].update(skate_cm_s=j_sim.result()["skate_cm_s"],
                                         sole_slip_cm_s=s_sim.result()["sole_slip_cm_s"])
    per = {lib.names[i]: per[lib.names[i]] for i in chosen}
    strict = (success & (worst <= tcfg.termination_distance))[chosen]
    out = {"overall": {"clips": len(chosen), "termination": f"{tcfg.termination} body error > {tcfg.termination_distance:g} m",
                       "success_rate_any_body": float(strict.mean()), **summarise(per)}, "clips": per}
    if feet:
        out["feet"] = feet_report(joint_sums, sole_sums)
    if render is not None:
        from motok.sim.render import render_trajectory
        qpos, played = video_qpos
        n = played + 1
        ghost = lib.qpos[lib.starts[0]:lib.starts[0] + n]
        path, backend = render_trajectory(hum, qpos[:n], render, lib.fps, ghost=ghost, title=f"expert {lib.names[0]}")
        out["video"] = f"{path} ({backend})"
    return out


def summarise(per: dict) -> dict:
    """Success over clips and errors weighted by the time each clip was played."""
    w = np.array([v["seconds"] for v in per.values()])
    res = {"success_rate": float(np.mean([v["success"] for v in per.values()])), "seconds_played": float(w.sum())}
    for k in ERRORS:
        vals = np.array([v[k] for v in per.values()])
        ok = np.isfinite(vals)
        res[k] = float(np.average(vals[ok], weights=np.maximum(w[ok], 1e-9))) if ok.any() else float("nan")
    return res


def name_parts(name: str) -> tuple[str, str]:
    """``(content, style)`` of a Bandai-Namco-style clip name ``dataset-N_content_style_NNN``;
    other names form one group."""
    parts = name.split("_")
    return (parts[1], parts[2]) if len(parts) >= 4 else ("all", "all")


def by_group(per: dict) -> dict[str, dict[str, dict]]:
    """:func:`summarise` per content and per style: ``{"content": {...}, "style": {...}}``."""
    groups: dict[str, dict[str, dict]] = {"content": defaultdict(dict), "style": defaultdict(dict)}
    for name, r in per.items():
        content, style = name_parts(name)
        groups["content"][content][name] = r
        groups["style"][style][name] = r
    return {kind: {g: {"clips": len(m), **summarise(m)} for g, m in sorted(d.items())} for kind, d in groups.items()}


def subset(names: list[str], per_group: int) -> list[str]:
    """A fixed evaluation subset: the first ``per_group`` clips (in name order) of every
    content x style group, so the training curve sees every kind of motion."""
    seen: dict[tuple[str, str], int] = defaultdict(int)
    out = []
    for n in sorted(names):
        g = name_parts(n)
        if seen[g] < per_group:
            out.append(n)
            seen[g] += 1
    return out
