"""N humanoids on one model, tracking reference motions: the batched imitation environment.

``reset(ids)`` puts environments in a reference state (reference state initialisation: a random
clip and frame, or given ones); ``step(actions)`` sets PD targets ``q_hat = base + a``, residual
actions on either the current hinge positions (``action_base="current"``, as the hybrid-latent
paper's code does, and the only choice for policies without a reference) or the next reference
frame's (``"reference"``: a zero action is PD tracking of the reference's angles *and* velocities,
the usual residual form for imitation experts; exploration noise does not accumulate), clipped
to the joint ranges, holds them for ``substeps`` physics steps, and returns

    obs (N, D_s)         Eq. 7 observation, heading frame
    goal (N, D_g)        Eq. 9 differences to the next K reference frames
    reward (dict)        Eq. 10 terms ``pos``, ``rot``, ``vel``, ``ang_vel`` and ``total``, each (N,)
    terminated (N,)      bodies too far from their reference (``termination``: any body, or on
                         average as PHC counts a failure, beyond 0.5 m), a non-finite action
                         (with ``nan_actions="terminate"``) or a diverged simulation
    truncated (N,)       time limit or the end of the reference clip, never set with terminated
    info (dict)          ``clip``, ``frame``, ``max_body_error``, ``mean_body_error``, ``diverged``,
                         ``invalid_action``

There is no auto-reset: the caller reads the final observation (for bootstrapping truncated
episodes) and then calls ``reset(ids)`` for the finished environments.

Public state for learners built on top (AMP discriminators, evaluators): ``bodies`` (the world
body states after the last step or reset), ``qpos``/``qvel``, ``clip``/``frame`` and ``lib``.

Stepping lives behind :class:`Stepper` (set full states, step all environments with fixed
controls for a few substeps and report the ones that diverged, give body states).
:class:`BatchStepper` (the default) runs MuJoCo >= 4.0's ``mujoco.batch`` thread pool, which
also computes the body kinematics natively; :class:`RolloutStepper` runs ``mujoco.rollout``
(C++ threads, GIL released) with numpy forward kinematics. A GPU batch simulator (MuJoCo Warp)
is a third implementation of the same three methods (docs/sim.md).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from motok.sim.humanoid import Humanoid, load_humanoid
from motok.sim.obs import (Bodies, RewardConfig, TreeKinematics, body_errors, cross3, goal, observation,
                           reward_terms)
from motok.sim.reference import ReferenceLibrary

RESET_CLEARANCE = 0.002  # m: a reference pose whose geometry dips below the floor is lifted to this height


class Stepper(Protocol):
    """The only code that advances physics. Arrays are host numpy, ``(N, .)``."""

    qpos: np.ndarray
    qvel: np.ndarray

    def set_state(self, ids: np.ndarray, qpos: np.ndarray, qvel: np.ndarray) -> None:
        """Overwrite full states (and forget solver warm starts, so a reset env is a fresh env)."""

    def step(self, ctrl: np.ndarray) -> np.ndarray:
        """Advance every environment by ``substeps`` with ``ctrl (N, nu)`` held; returns a
        ``(N,)`` mask of environments whose simulation diverged (MuJoCo reset them)."""

    def bodies(self, ids: np.ndarray | None = None) -> Bodies:
        """World body states at the current state, skeleton order, of ``ids`` (default: all)."""


class RolloutStepper:
    """CPU stepping with ``mujoco.rollout`` (MuJoCo >= 3.2): its C++ thread pool steps chunks of
    environments without the GIL, one call covering all substeps; kinematics by numpy FK."""

    def __init__(self, hum: Humanoid, num_envs: int, substeps: int, nthread: int = 2):
        import mujoco
        from mujoco import rollout

        model = hum.model
        self.model, self.n, self.substeps = model, num_envs, substeps
        self.fk = TreeKinematics(hum)
        spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
        self.nstate = mujoco.mj_stateSize(model, spec)
        self.nthread = max(1, min(int(nthread), num_envs))
        self._pool = rollout.Rollout(nthread=self.nthread if self.nthread > 1 else 0)
        self._datas = [mujoco.MjData(model) for _ in range(self.nthread)]
        self._models = [model] * num_envs
        d = self._datas[0]
        self.state = np.zeros((num_envs, self.nstate))
        mujoco.mj_getState(model, d, self.state[0], spec)
        self.state[:] = self.state[0]
        # Locate time, qpos and qvel inside a state row by writing marked values through MjData.
        d.time, d.qpos[:], d.qvel[:] = -1.0, np.arange(model.nq) + 1e3, np.arange(model.nv) + 1e6
        probe = np.zeros(self.nstate)
        mujoco.mj_getState(model, d, probe, spec)
        self._t = int(np.flatnonzero(probe == -1.0)[0])
        self._q = int(np.flatnonzero(probe == 1e3)[0])
        self._v = int(np.flatnonzero(probe == 1e6)[0])
        self.state[:, self._t] = 1.0  # MuJoCo's reset of a diverged sim sets time 0: a visible marker
        self._ctrl = np.zeros((num_envs, substeps, model.nu))
        self._out = np.zeros((num_envs, substeps, self.nstate))
        self._chunk = max(1, num_envs // (4 * self.nthread))

    @property
    def qpos(self) -> np.ndarray:
        return self.state[:, self._q:self._q + self.model.nq]

    @property
    def qvel(self) -> np.ndarray:
        return self.state[:, self._v:self._v + self.model.nv]

    def set_state(self, ids, qpos, qvel) -> None:
        self.state[ids, self._q:self._q + self.model.nq] = qpos
        self.state[ids, self._v:self._v + self.model.nv] = qvel
        self.state[ids, self._t] = 1.0  # rollout itself starts every call from a zero warm start

    def step(self, ctrl: np.ndarray) -> np.ndarray:
        self._ctrl[:] = ctrl[:, None]
        t0 = self.state[:, self._t].copy()
        datas = self._datas if self.nthread > 1 else self._datas[:1]
        self._pool.rollout(self._models, datas, self.state, self._ctrl, skip_checks=True, nstep=self.substeps,
                           state=self._out, sensordata=None, chunk_size=self._chunk)
        self.state[:] = self._out[:, -1]
        expected = t0 + 0.5 * self.substeps * self.model.opt.timestep
        return (self.state[:, self._t] < expected) | ~np.isfinite(self.state).all(1)

    def bodies(self, ids=None) -> Bodies:
        return self.fk(self.qpos, self.qvel) if ids is None else self.fk(self.qpos[ids], self.qvel[ids])


class BatchStepper:
    """CPU stepping with ``mujoco.batch`` (MuJoCo >= 4.0): one persistent MjData per environment
    on a native thread pool; each control step ends with the position and velocity stages at the
    new state, so MuJoCo computes the body kinematics in the workers (and the next step reuses
    them) instead of a numpy pass on the caller's thread."""

    def __init__(self, hum: Humanoid, num_envs: int, substeps: int, nthread: int = 2):
        import mujoco
        from mujoco.batch import Batch

        self.model, self.n, self.substeps = hum.model, num_envs, substeps
        self._vel = int(mujoco.mjtStage.mjSTAGE_VEL)
        self.b = Batch(hum.model, num_envs, nthread=max(1, int(nthread)), persistent=True)
        self.qpos, self.qvel, self._ctrl = self.b.bind("qpos"), self.b.bind("qvel"), self.b.bind("ctrl")
        self._warm = self.b.bind("qacc_warmstart")
        self._xpos, self._xmat, self._xquat = self.b.bind("xpos"), self.b.bind("xmat"), self.b.bind("xquat")
        self._cvel, self._com = self.b.bind("cvel"), self.b.bind("subtree_com")
        ids = hum.body_ids
        # Skeletons listed depth-first (Bandai-Namco's is) map to consecutive bodies: slice, not gather.
        contiguous = np.array_equal(ids, np.arange(ids[0], ids[0] + len(ids)))
        self._ids = slice(int(ids[0]), int(ids[0]) + len(ids)) if contiguous else ids
        self._root = int(hum.model.body_rootid[ids[0]])  # one tree: every body's cvel refers to its com
        self.b.forward(stage=self._vel)

    def _warnings(self) -> np.ndarray:
        return self.b.warning[..., 1].sum(-1)

    def set_state(self, ids, qpos, qvel) -> None:
        self.qpos[ids], self.qvel[ids], self._warm[ids] = qpos, qvel, 0.0
        self.b.forward(np.asarray(ids), stage=self._vel)

    def step(self, ctrl: np.ndarray) -> np.ndarray:
        from mujoco.batch import SimulationError

        before = self._warnings()
        self._ctrl[:] = ctrl
        failed = np.zeros(self.n, dtype=bool)
        try:
            self.b.step(nstep=self.substeps, stage=self._vel)
        except SimulationError as e:  # those sims kept their previous state; the others completed
            failed[e.ids] = True
        return failed | (self._warnings() > before) | ~np.isfinite(self.qpos).all(1)

    def bodies(self, ids=None) -> Bodies:
        e = slice(None) if ids is None else np.asarray(ids)
        if ids is not None and not isinstance(self._ids, slice):
            e = e[:, None]
        pos, cvel = self._xpos[e, self._ids], self._cvel[e, self._ids]
        ang = cvel[..., :3]
        vel = cvel[..., 3:] + cross3(ang, pos - self._com[e, self._root].reshape(len(pos), 1, 3))
        # Copies: the bound arrays change at the next call, and a caller may keep these.
        return Bodies(pos.copy(), vel, ang.copy(), rot=self._xmat[e, self._ids].reshape(len(pos), -1, 3, 3).copy(),
                      quat=self._xquat[e, self._ids].copy())


def make_stepper(kind: str, hum: Humanoid, num_envs: int, substeps: int, nthread: int) -> Stepper:
    if kind == "auto":
        try:
            import mujoco.batch  # noqa: F401  (MuJoCo >= 4.0)
            kind = "batch"
        except ImportError:
            kind = "rollout"
    if kind == "batch":
        return BatchStepper(hum, num_envs, substeps, nthread)
    if kind == "rollout":
        return RolloutStepper(hum, num_envs, substeps, nthread)
    raise ValueError(f"unknown stepper {kind!r}: use auto, batch or rollout")


@dataclass
class EnvConfig:
    num_envs: int = 16
    control_hz: float | None = None  # None: the humanoid's (30 Hz by default); the library must match
    max_episode_seconds: float = 10.0
    goal_frames: int = 1  # K reference frames ahead in the goal (Eq. 9)
    termination_distance: float = 0.5  # m, from the reference
    termination: str = "any"  # "any" body beyond the distance, or the "mean" over bodies (PHC's failure test)
    early_termination: bool = True
    nthread: int = 2
    stepper: str = "auto"  # batch (MuJoCo >= 4.0), rollout, or auto: batch when available
    action_scale: float = 1.0  # q_hat = base + action_scale * a
    action_base: str = "current"  # base = current hinge angles q, or "reference": the next reference frame's
    nan_actions: str = "raise"  # or "terminate": the env is terminated, the others step normally
    seed: int = 0
    reward: RewardConfig = field(default_factory=RewardConfig)


class HumanoidEnv:
    """Batched imitation environment; see the module docstring for the step contract."""

    def __init__(self, humanoid: Humanoid | str, library: ReferenceLibrary, cfg: EnvConfig | None = None,
                 stepper: Stepper | None = None):
        self.hum = load_humanoid(humanoid) if not isinstance(humanoid, Humanoid) else humanoid
        self.lib, self.cfg = library, cfg or EnvConfig()
        c, m = self.cfg, self.hum.model
        hz = float(c.control_hz or self.hum.control_hz)
        if abs(library.fps - hz) > 1e-6:
            raise ValueError(f"the reference library is at {library.fps:g} Hz but the control rate is {hz:g} Hz")
        if c.action_base not in ("current", "reference"):
            raise ValueError(f"action_base must be 'current' or 'reference', not {c.action_base!r}")
        if c.termination not in ("any", "mean"):
            raise ValueError(f"termination must be 'any' or 'mean', not {c.termination!r}")
        if c.nan_actions not in ("raise", "terminate"):
            raise ValueError(f"nan_actions must be 'raise' or 'terminate', not {c.nan_actions!r}")
        self.dt = 1.0 / hz
        self.substeps = max(1, int(round(self.dt / m.opt.timestep)))
        self.num_envs = N = c.num_envs
        self.stepper = stepper or make_stepper(c.stepper, self.hum, N, self.substeps, c.nthread)
        self.hinge_adr = self.hum.hinge_qpos_adr
        self.ctrl_low, self.ctrl_high = m.actuator_ctrlrange[:, 0].copy(), m.actuator_ctrlrange[:, 1].copy()
        # MuJoCo's position actuator: tau = kp (ctrl - q) - kv qd, so ctrl = q* + (kv / kp) qd* gives
        # tau = kp (q* - q) + kv (qd* - qd), a PD servo on a target angle *and* velocity.
        self.velocity_lead = -m.actuator_biasprm[:, 2] / m.actuator_gainprm[:, 0]
        driven = m.actuator_trnid[:, 0]
        if not np.array_equal(m.jnt_qposadr[driven], self.hinge_adr):
            raise ValueError(f"{self.hum.path}: actuators must drive the hinges in qpos order")
        self.hinge_dof = m.jnt_dofadr[driven]
        self.end_effectors = list(self.hum.skeleton.end_effectors)
        self.max_steps = max(1, int(round(c.max_episode_seconds * hz)))
        self.rng = np.random.default_rng(c.seed)
        self.clip = np.zeros(N, dtype=np.int64)
        self.frame = np.zeros(N, dtype=np.int64)  # reference frame the simulation is at, within the clip
        self.steps = np.zeros(N, dtype=np.int64)
        self.limit = np.ones(N, dtype=np.int64)
        self.bodies: Bodies | None = None
        self._obs, self._goal = None, None

    # ------------------------------------------------------------------ sizes
    @property
    def action_dim(self) -> int:
        return self.hum.model.nu

    @property
    def obs_dim(self) -> int:
        return 1 + 6 + 3 + 3 + 2 * self.action_dim + 3 * len(self.end_effectors)

    @property
    def goal_dim(self) -> int:
        return self.cfg.goal_frames * len(self.hum.skeleton.joints) * 15

    @property
    def qpos(self) -> np.ndarray:
        return self.stepper.qpos

    @property
    def qvel(self) -> np.ndarray:
        return self.stepper.qvel

    # ------------------------------------------------------------------ reference access
    def _ref(self, clips: np.ndarray, frames: np.ndarray) -> Bodies:
        last = self.lib.starts[clips + 1] - 1
        g = np.minimum(self.lib.starts[clips] + frames, last)
        L = self.lib
        return Bodies(L.body_pos[g], L.body_vel[g], L.body_angvel[g], quat=L.body_quat[g])

    # ------------------------------------------------------------------ API
    def reset(self, ids=None, clips=None, frames=None) -> tuple[np.ndarray, np.ndarray]:
        """Reference state initialisation for ``ids`` (all by default): random clip and frame from
        the env's seeded generator unless ``clips``/``frames`` (names or indices) are given.
        Returns the full ``(obs, goal)`` arrays, the other environments' rows unchanged."""
        N = self.num_envs
        ids = np.arange(N) if ids is None else np.atleast_1d(np.asarray(ids, dtype=np.int64))
        if ids.size and (ids.min() < 0 or ids.max() >= N):
            raise IndexError(f"environment ids must be in 0..{N - 1}, got {ids.tolist()}")
        if self._obs is None and len(ids) != N:
            self.reset()  # every environment needs a state before a subset can be reset
        K = self.cfg.goal_frames
        if clips is None:
            c, f = self.lib.sample(len(ids), self.rng, horizon=K + 1)
        else:
            c = np.array([self.lib.index(x) for x in np.broadcast_to(np.asarray(clips, dtype=object), ids.shape)])
            f = np.broadcast_to(np.asarray(0 if frames is None else frames, dtype=np.int64), ids.shape).copy()
            bad = (f < 0) | (f + K + 2 > self.lib.lengths[c])
            if bad.any():
                raise ValueError(f"start frames {f[bad].tolist()} leave no step with {K} reference frames ahead "
                                 f"(clip lengths {self.lib.lengths[c[bad]].tolist()} at {self.lib.fps:g} Hz)")
        g = self.lib.starts[c] + f
        qpos, qvel = self.lib.qpos[g].copy(), self.lib.qvel[g].copy()
        qpos[:, 2] += np.maximum(RESET_CLEARANCE - self.lib.lowest[g], 0.0)
        self.stepper.set_state(ids, qpos, qvel)
        self.clip[ids], self.frame[ids], self.steps[ids] = c, f, 0
        # The last step's goal still needs K frames ahead: frame + K <= last frame of the clip.
        self.limit[ids] = np.minimum(self.max_steps, self.lib.lengths[c] - 1 - f - K)
        self._update(ids)
        return self._obs.copy(), self._goal.copy()

    def _update(self, ids: np.ndarray, refs: Bodies | None = None) -> None:
        """Refresh body states and the observation and goal rows of ``ids``; ``refs`` are the
        reference bodies at frames ``frame + 1 .. frame + K`` of ``ids`` when already gathered."""
        qpos, qvel = self.stepper.qpos, self.stepper.qvel
        full = len(ids) == self.num_envs
        sim = self.stepper.bodies(None if full else ids)
        if full or self.bodies is None:
            self.bodies = sim if full else self.stepper.bodies()
        else:
            self.bodies.put(ids, sim)
        if self._obs is None:
            self._obs = np.zeros((self.num_envs, self.obs_dim))
            self._goal = np.zeros((self.num_envs, self.goal_dim))
        if refs is None:
            refs = self._ref(self.clip[ids, None], self.frame[ids, None] + np.arange(1, self.cfg.goal_frames + 1))
        self._obs[ids] = observation(qpos[ids], qvel[ids], sim, self.end_effectors)
        self._goal[ids] = goal(sim, refs)

    def step(self, actions: np.ndarray):
        """Apply residual actions ``(N, nu)``; see the module docstring for what is returned."""
        if self._obs is None:
            raise RuntimeError("call reset() before step()")
        a = np.asarray(actions, dtype=np.float64)
        if a.shape != (self.num_envs, self.action_dim):
            raise ValueError(f"actions must have shape ({self.num_envs}, {self.action_dim}), got {a.shape}")
        invalid = ~np.isfinite(a).all(1)
        if invalid.any():
            if self.cfg.nan_actions == "raise":
                raise ValueError(f"non-finite actions for environments {np.flatnonzero(invalid).tolist()}; "
                                 "nothing was stepped (set nan_actions='terminate' to end those episodes instead)")
            a = np.where(invalid[:, None], 0.0, a)
        ctrl = np.clip(self.action_base() + self.cfg.action_scale * a, self.ctrl_low, self.ctrl_high)
        diverged = self.stepper.step(ctrl)
        self.frame += 1
        self.steps += 1
        refs = self._ref(self.clip[:, None], self.frame[:, None] + np.arange(self.cfg.goal_frames + 1))
        self._update(np.arange(self.num_envs), refs.take((slice(None), slice(1, None))))
        ref = refs.take((slice(None), 0))
        rewards = reward_terms(self.bodies, ref, self.cfg.reward)
        dist = body_errors(self.bodies, ref)
        err, mean_err = dist.max(-1), dist.mean(-1)
        off = mean_err if self.cfg.termination == "mean" else err
        fell = off > self.cfg.termination_distance if self.cfg.early_termination else np.zeros_like(diverged)
        terminated = fell | diverged | invalid
        truncated = (self.steps >= self.limit) & ~terminated
        for v in rewards.values():
            v[diverged | invalid] = 0.0
        info = {"clip": self.clip.copy(), "frame": self.frame.copy(), "max_body_error": err,
                "mean_body_error": mean_err,
                "diverged": diverged, "invalid_action": invalid, "episode_steps": self.steps.copy()}
        return self._obs.copy(), self._goal.copy(), rewards, terminated, truncated, info

    def action_base(self) -> np.ndarray:
        """``(N, nu)`` hinge angles the next actions are offsets from (``EnvConfig.action_base``)."""
        if self.cfg.action_base == "current":
            return self.stepper.qpos[:, self.hinge_adr]
        g = np.minimum(self.lib.starts[self.clip] + self.frame + 1, self.lib.starts[self.clip + 1] - 1)
        return self.lib.qpos[g][:, self.hinge_adr] + self.velocity_lead * self.lib.qvel[g][:, self.hinge_dof]

    def reference_qpos(self, ids=None) -> np.ndarray:
        """The reference qpos at each env's current frame (for PD tracking baselines)."""
        ids = np.arange(self.num_envs) if ids is None else np.asarray(ids)
        last = self.lib.starts[self.clip[ids] + 1] - 1
        return self.lib.qpos[np.minimum(self.lib.starts[self.clip[ids]] + self.frame[ids], last)]


def pd_track(hum: Humanoid, lib: ReferenceLibrary, clips, seconds: float | None = None, nthread: int = 2) -> dict:
    """Plain PD tracking from frame 0 of each clip (targets = next reference frame, no policy):
    the baseline a learned expert must beat. Survival is the time until a body is 0.5 m off."""
    ids = [lib.index(c) for c in clips]
    steps = int(min(lib.lengths[ids].min() - 2, (seconds or 1e9) * lib.fps))
    cfg = EnvConfig(num_envs=len(ids), early_termination=False, nthread=nthread, max_episode_seconds=1e9)
    env = HumanoidEnv(hum, lib, cfg)
    env.reset(clips=ids, frames=0)
    qpos, ref_qpos = [env.qpos.copy()], [env.reference_qpos()]
    survival = np.full(len(ids), steps / lib.fps)
    fallen = np.zeros(len(ids), dtype=bool)
    rewards = []
    for t in range(steps):
        g = np.minimum(lib.starts[env.clip] + env.frame + 1, lib.starts[env.clip + 1] - 1)
        _, _, r, _, _, info = env.step(lib.qpos[g][:, env.hinge_adr] - env.qpos[:, env.hinge_adr])
        new = ~fallen & ((info["max_body_error"] > env.cfg.termination_distance) | info["diverged"])
        survival[new] = (t + 1) / lib.fps
        fallen |= new
        rewards.append(np.where(fallen, 0.0, r["total"]))
        qpos.append(env.qpos.copy())
        ref_qpos.append(env.reference_qpos())
    return {"clips": [lib.names[i] for i in ids], "survival_s": survival, "seconds": steps / lib.fps,
            "mean_reward": np.sum(rewards, 0) / np.maximum(np.round(survival * lib.fps), 1) if rewards
            else np.zeros(len(ids)),
            "qpos": np.stack(qpos, 1), "ref_qpos": np.stack(ref_qpos, 1)}
