"""Controllers with nothing learned, the references a learned policy must beat."""

from __future__ import annotations

import numpy as np

from motok.control.mdp.task_env import TaskEnv
from motok.control.tasks.imitation import ImitationTask, ImitationTaskConfig
from motok.sim.env import HumanoidEnv, SimConfig
from motok.sim.humanoid import Humanoid
from motok.sim.reference import ReferenceLibrary


def next_reference_angles(a, env: HumanoidEnv, task: ImitationTask) -> np.ndarray:
    """The action map of plain PD tracking: the next reference frame's hinge angles (``a`` unused)."""
    return task.next_reference()[0][:, env.hinge_adr]


def pd_track(hum: Humanoid, lib: ReferenceLibrary, clips, seconds: float | None = None, nthread: int = 2) -> dict:
    """Plain PD tracking from frame 0 of each clip (targets = next reference frame, no policy):
    the baseline a learned expert must beat. Survival is the time until a body is 0.5 m off;
    ``mean_reward`` the Eq. 10 imitation reward per step survived."""
    ids = [lib.index(c) for c in clips]
    steps = int(min(lib.lengths[ids].min() - 2, (seconds or 1e9) * lib.fps))
    env = HumanoidEnv(hum, SimConfig(num_envs=len(ids), nthread=nthread))
    task = ImitationTask(ImitationTaskConfig(early_termination=False, max_episode_seconds=1e9), env, lib,
                         np.random.default_rng(0))
    mdp = TaskEnv(env, task, next_reference_angles)
    mdp.reset(clips=ids, frames=0)
    qpos, ref_qpos = [env.qpos.copy()], [task.current_reference_qpos()]
    survival = np.full(len(ids), steps / lib.fps)
    fallen = np.zeros(len(ids), dtype=bool)
    rewards = []
    no_action = np.zeros((len(ids), 0))
    for t in range(steps):
        _, _, r, _, _, info = mdp.step(no_action)
        new = ~fallen & ((info["max_body_error"] > task.cfg.termination_distance) | info["diverged"])
        survival[new] = (t + 1) / lib.fps
        fallen |= new
        rewards.append(np.where(fallen, 0.0, r["r_im"]))
        qpos.append(env.qpos.copy())
        ref_qpos.append(task.current_reference_qpos())
    return {"clips": [lib.names[i] for i in ids], "survival_s": survival, "seconds": steps / lib.fps,
            "mean_reward": np.sum(rewards, 0) / np.maximum(np.round(survival * lib.fps), 1) if rewards
            else np.zeros(len(ids)),
            "qpos": np.stack(qpos, 1), "ref_qpos": np.stack(ref_qpos, 1)}


def pd_track_run(hum: Humanoid, lib: ReferenceLibrary, seconds: float | None = None, video=None,
                 stick: bool = False) -> dict:
    """``motok sim pd-track``: :func:`pd_track` of every clip of ``lib`` as a summary, and a video
    of the first clip with its reference as a ghost when ``video`` is a path."""
    res = pd_track(hum, lib, range(len(lib)), seconds)
    written = None
    if video is not None:
        from motok.sim.render import render_trajectory
        written = render_trajectory(hum, res["qpos"][0], video, lib.fps, ghost=res["ref_qpos"][0],
                                    title=f"PD tracking {lib.names[0]}", backend="stick" if stick else "auto")
    s = res["survival_s"]
    return {"clips": len(s), "tracked_s": round(res["seconds"], 2), "survival_mean_s": round(float(s.mean()), 3),
            "survival_median_s": round(float(np.median(s)), 3), "survival_max_s": round(float(s.max()), 3),
            "per_clip": dict(zip(res["clips"], [round(float(x), 3) for x in s])),
            **({"video": f"{written[0]} ({written[1]})"} if written else {})}
