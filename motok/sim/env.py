"""N humanoids on one model: the batched physics environment, and nothing but physics.

``set_state(ids, qpos, qvel)`` puts environments in given states; ``step(targets)`` holds PD
targets ``(N, nu)`` (hinge angles, clipped to the joint ranges) for ``substeps`` physics steps and
returns ``(diverged, invalid)`` masks. After either, :attr:`bodies` holds the world body states
and :meth:`observation` the hybrid-latent paper's Eq. 7 proprioception of every environment.

What a policy is asked to do (goals, rewards, terminations, reference states) is the control
stage's business (``motok.control.mdp`` terms composed into ``motok.control.tasks``); this module
knows no reference motion and draws no random numbers.

``launch(targets)`` / ``finish()`` split a step in two: the physics runs on a worker thread
(MuJoCo releases the GIL while it steps) until ``finish`` collects it, so the caller can run a
policy on other environments meanwhile (``motok.control.rl.rollout`` steps groups of environments
in turn this way). ``step`` is ``launch`` then ``finish``, with no thread.

Bad input stays contained: targets with non-finite entries either raise before anything is
stepped (``nan_actions="raise"``) or hold that environment's current pose for the step and are
reported as ``invalid`` (``"terminate"``), the other environments stepping normally. A
simulation MuJoCo had to reset is reported as ``diverged``.

The model may hold more than the humanoid: free bodies appended after it (the thrown balls of
``motok.sim.balls``). :attr:`qpos`, :attr:`qvel`, :attr:`bodies`, the observation and the
actions then still describe the humanoid alone (its state is the prefix ``qpos[:, :hum.nq]``,
``qvel[:, :hum.nv]`` of the model's), and ``set_state`` takes the humanoid's state and leaves the
other bodies where they are; ``stepper.qpos`` and ``stepper.set_columns`` reach the rest.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from motok.arrays import copy, like, xp
from motok.errors import UserError
from motok.ranges import In
from motok.sim.humanoid import Humanoid, load_humanoid
from motok.sim.obs import Bodies, observation
from motok.sim.steppers import Stepper, make_stepper


@dataclass
class SimConfig:
    num_envs: In[int, ">= 1"] = 16  # humanoids simulated side by side, each its own episode
    control_hz: In[float | None, "> 0"] = None  # None: the humanoid's (30 Hz by default)
    nthread: In[int, ">= 0"] = 2  # CPU threads the C MuJoCo steppers use (0 and 1: one; ignored by warp)
    stepper: str = "auto"  # batch (MuJoCo >= 4.0), rollout, or auto: batch when available (backend mujoco)
    backend: str = "mujoco"  # or "warp": MuJoCo Warp (pip install motok[gpu]), the same MJCF batched on a device
    device: str = "cpu"  # the physics device; "cuda" (or "cuda:1") needs backend warp
    nan_actions: str = "raise"  # or "terminate": that env holds its pose and is reported invalid
    groups: In[int, ">= 1"] = 1  # environment groups a collector steps in turn, each while the policy runs on another
    # Keep the whole rollout (state, observations, goals, rewards, resets, policy, buffers) where the
    # physics state is: torch tensors on MuJoCo Warp's device, with no host copy per step (docs/sim.md
    # "On the device"). C MuJoCo's state is host memory, where the rollout runs anyway: no effect there.
    on_device: bool = False
    # PD targets low-passed from one control step to the next, y_t = b a_t + (1 - b) y_(t-1), the
    # filter some character controllers train with against high-frequency chatter (docs/sim.md);
    # after a reset it starts from the joints' angles. 1: each step's targets as given; None: the
    # world of the controller this one is trained from or over (same_world), 1 for an expert.
    target_filter: In[float | None, "(0, 1]"] = None

    @property
    def filter_b(self) -> float:
        return 1.0 if self.target_filter is None else float(self.target_filter)

    def same_world(self, parent: "SimConfig", who: str, humanoid_hz: float | None = None) -> "SimConfig":
        """Act in the world ``parent`` was trained in (a student in its teacher's, a task policy
        in its prior's): its PD-target filter and control rate unless this config sets them, and a
        different one refused, since the parent's actions mean other motion through another filter
        or held for another time. A parent at the humanoid's rate (``control_hz`` None) acts at
        ``humanoid_hz``, the shared humanoid's: a rate this config sets is compared with that one
        (and not compared when it is not given), and an unset one stays unset, as the parent's."""
        if self.control_hz is None:
            self.control_hz = parent.control_hz
        else:
            theirs = parent.control_hz if parent.control_hz is not None else humanoid_hz
            if theirs is not None and float(self.control_hz) != float(theirs):
                at = "env.control_hz=" if parent.control_hz is not None else "its humanoid's rate, "
                raise UserError(f"env.control_hz={self.control_hz:g} but {who} acts at {at}{float(theirs):g}: "
                                "leave it unset to act in the same world")
        if self.target_filter is None:
            self.target_filter = parent.filter_b
        elif self.filter_b != parent.filter_b:
            raise UserError(f"env.target_filter={self.filter_b:g} but {who} acts through env.target_filter="
                            f"{parent.filter_b:g}: leave it unset to act in the same world")
        return self

    def portable(self) -> "SimConfig":
        """C MuJoCo on the CPU, whatever backend and device the config says: how a loaded run's
        config starts (where a run was trained is no default for where it is used, e.g. a GPU run
        evaluated on a laptop; an evaluation's ``--device`` then chooses)."""
        self.backend, self.device, self.on_device = "mujoco", "cpu", False
        return self

    @property
    def rollout_on_device(self) -> bool:
        return self.on_device and self.backend == "warp"

    def on(self, device: str | None) -> "SimConfig":
        """The physics on ``device`` (an evaluation's ``--device``; None keeps the run's): a GPU means
        MuJoCo Warp, since C MuJoCo runs on the CPU only."""
        if device is not None:
            self.device = device
            self.backend = "warp" if device != "cpu" else self.backend
        return self


class HumanoidEnv:
    """Batched physics of one humanoid model; see the module docstring for the contract."""

    def __init__(self, humanoid: Humanoid | str, cfg: SimConfig | None = None, stepper: Stepper | None = None):
        self.hum = load_humanoid(humanoid) if not isinstance(humanoid, Humanoid) else humanoid
        self.cfg = c = cfg or SimConfig()
        m = self.hum.model
        if c.nan_actions not in ("raise", "terminate"):
            raise UserError(f"nan_actions must be 'raise' or 'terminate', not {c.nan_actions!r}")
        if not 0.0 < c.filter_b <= 1.0:
            raise UserError(f"env.target_filter must be in (0, 1] (1: no filter), not {c.target_filter!r}")
        self.control_hz = float(c.control_hz or self.hum.control_hz)
        self.dt = 1.0 / self.control_hz
        self.substeps = max(1, int(round(self.dt / m.opt.timestep)))
        self.num_envs = c.num_envs
        self.nq, self.nv = self.hum.nq, self.hum.nv  # the humanoid's part of the state (all of it, for a plain model)
        self.stepper = stepper or make_stepper(c.stepper, self.hum, c.num_envs, self.substeps, c.nthread,
                                               c.backend, c.device)
        self.hinge_adr = self.hum.hinge_qpos_adr
        self.ctrl_low, self.ctrl_high = m.actuator_ctrlrange[:, 0].copy(), m.actuator_ctrlrange[:, 1].copy()
        # MuJoCo's position actuator: tau = kp (ctrl - q) - kv qd, so ctrl = q* + (kv / kp) qd* gives
        # tau = kp (q* - q) + kv (qd* - qd), a PD servo on a target angle *and* velocity.
        self.velocity_lead = -m.actuator_biasprm[:, 2] / m.actuator_gainprm[:, 0]
        driven = m.actuator_trnid[:, 0]
        if not np.array_equal(m.jnt_qposadr[driven], self.hinge_adr):
            raise UserError(f"{self.hum.path}: actuators must drive the hinges in qpos order")
        self.hinge_dof = m.jnt_dofadr[driven]
        self.end_effectors = list(self.hum.skeleton.end_effectors)
        self.on_device = c.rollout_on_device
        if self.on_device:
            st = self.stepper
            self.torch_device = st.torch_device
            # The constants the action map and the checks read every step, moved once.
            self.hinge_adr, self.hinge_dof = like(st.qpos_t, self.hinge_adr), like(st.qpos_t, self.hinge_dof)
            self.velocity_lead = like(st.qpos_t, self.velocity_lead)
            self.ctrl_low, self.ctrl_high = like(st.qpos_t, self.ctrl_low), like(st.qpos_t, self.ctrl_high)
        self.bodies: Bodies = self._bodies()
        self._obs = observation(self.qpos, self.qvel, self.bodies, self.end_effectors)
        self._filtered = copy(self.qpos[:, self.hinge_adr]) if c.filter_b < 1.0 else None
        self._worker = None  # a one-thread executor, created by the first threaded launch
        self._pending = None

    def _bodies(self, ids=None) -> Bodies:
        return self.stepper.bodies_tensor(ids) if self.on_device else self.stepper.bodies(ids)

    @property
    def action_dim(self) -> int:
        return self.hum.model.nu

    @property
    def obs_dim(self) -> int:
        return self._obs.shape[1]

    @property
    def qpos(self):
        """The humanoid's generalized positions ``(N, hum.nq)``, a live view of the stepper's
        (host numpy, or the device tensor with ``on_device``)."""
        return (self.stepper.qpos_t if self.on_device else self.stepper.qpos)[:, :self.nq]

    @property
    def qvel(self):
        return (self.stepper.qvel_t if self.on_device else self.stepper.qvel)[:, :self.nv]

    def observation(self):
        """Eq. 7 of every environment at its current state, ``(N, obs_dim)`` (a copy)."""
        return copy(self._obs)

    def set_state(self, ids: np.ndarray, qpos: np.ndarray, qvel: np.ndarray) -> None:
        """Overwrite the states of ``ids`` and refresh their body states and observations: the
        humanoid's ``(len(ids), hum.nq)`` / ``(.., hum.nv)`` (other bodies of the model keep theirs)
        or the model's whole ``(.., nq)`` / ``(.., nv)``. Solver warm starts are forgotten either way.
        With ``on_device`` all three are device tensors and nothing is checked on the host."""
        if self.on_device:
            return self._set_state_tensor(ids, qpos, qvel)
        ids = np.atleast_1d(np.asarray(ids, dtype=np.int64))
        if ids.size and (ids.min() < 0 or ids.max() >= self.num_envs):
            raise IndexError(f"environment ids must be in 0..{self.num_envs - 1}, got {ids.tolist()}")
        m = self.hum.model
        qpos, qvel = np.asarray(qpos), np.asarray(qvel)
        if (qpos.shape[-1], qvel.shape[-1]) not in ((self.nq, self.nv), (m.nq, m.nv)):
            raise ValueError(f"states must have {self.nq} qpos and {self.nv} qvel columns (the humanoid's) or "
                             f"{m.nq} and {m.nv} (the model's), got {qpos.shape[-1]} and {qvel.shape[-1]}")
        if qpos.shape[-1] != m.nq:  # the humanoid's prefix only: complete the rows with the other bodies' states
            qpos = np.concatenate([np.broadcast_to(qpos, (len(ids), self.nq)), self.stepper.qpos[ids, self.nq:]], 1)
            qvel = np.concatenate([np.broadcast_to(qvel, (len(ids), self.nv)), self.stepper.qvel[ids, self.nv:]], 1)
        self.stepper.set_state(ids, qpos, qvel)
        self._restart_filter(ids)
        if len(ids) == self.num_envs:
            sim = self.bodies = self.stepper.bodies()
        else:
            sim = self.stepper.bodies(ids)
            self.bodies.put(ids, sim)
        self._obs[ids] = observation(self.qpos[ids], self.qvel[ids], sim, self.end_effectors)

    def _set_state_tensor(self, ids, qpos, qvel) -> None:
        import torch

        st, m = self.stepper, self.hum.model
        if qpos.shape[-1] != m.nq:  # the humanoid's prefix only: the other bodies keep theirs
            qpos = torch.cat([qpos.expand(len(ids), self.nq), st.qpos_t[ids, self.nq:]], 1)
            qvel = torch.cat([qvel.expand(len(ids), self.nv), st.qvel_t[ids, self.nv:]], 1)
        st.set_state_tensor(ids, qpos, qvel)
        self._restart_filter(ids)
        sim = st.bodies_tensor(ids)
        self.bodies.put(ids, sim)
        self._obs[ids] = observation(self.qpos[ids], self.qvel[ids], sim, self.end_effectors)

    def _checked(self, targets):
        """Targets as the stepper takes them (host float64, or the device tensor's dtype), non-finite
        rows refused or held at the current pose, clipped to the actuator ranges; ``(ctrl, invalid)``."""
        q = targets.to(self.stepper.qpos_t.dtype) if self.on_device else np.asarray(targets, dtype=np.float64)
        if tuple(q.shape) != (self.num_envs, self.action_dim):
            raise ValueError(f"actions must have shape ({self.num_envs}, {self.action_dim}), got {tuple(q.shape)}")
        x = xp(q)
        invalid = ~x.isfinite(q).all(1)
        # On the device, "raise" reads the mask on the host (one sync a step); GPU recipes use "terminate".
        if self.cfg.nan_actions == "raise" and bool(invalid.any()):
            bad = [i for i, b in enumerate(invalid.tolist()) if b]
            raise ValueError(f"non-finite actions for environments {bad}; nothing was stepped "
                             "(set nan_actions='terminate' to end those episodes instead)")
        q = x.where(invalid[:, None], self.qpos[:, self.hinge_adr], q)
        return x.clip(q, self.ctrl_low, self.ctrl_high), invalid

    def _restart_filter(self, ids) -> None:
        if self._filtered is not None:
            self._filtered[ids] = self.qpos[ids][:, self.hinge_adr]

    def launch(self, targets: np.ndarray, threaded: bool = True) -> None:
        """Start one control step with PD targets ``(N, nu)``; :meth:`finish` completes it."""
        if self._pending is not None:
            raise RuntimeError("finish() the step in flight before launching another")
        ctrl, invalid = self._checked(targets)
        if self._filtered is not None:
            b = self.cfg.filter_b
            ctrl = b * ctrl + (1.0 - b) * self._filtered
            self._filtered = copy(ctrl)
        if self.on_device:  # a device queues the work by itself: no thread
            self._pending = (self.stepper.step_tensor(ctrl), invalid)
        elif threaded:
            if self._worker is None:
                from concurrent.futures import ThreadPoolExecutor
                self._worker = ThreadPoolExecutor(1, thread_name_prefix="motok-physics")
            self._pending = (self._worker.submit(self.stepper.step, ctrl), invalid)
        else:
            self._pending = (self.stepper.step(ctrl), invalid)

    def finish(self) -> tuple[np.ndarray, np.ndarray]:
        """Wait for the step in flight; refresh body states and observations; ``(diverged, invalid)``."""
        if self._pending is None:
            raise RuntimeError("no step in flight: launch() first")
        result, invalid = self._pending
        self._pending = None
        diverged = result.result() if hasattr(result, "result") else result
        self.bodies = self._bodies()
        self._obs = observation(self.qpos, self.qvel, self.bodies, self.end_effectors)
        return diverged, invalid

    def step(self, targets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Hold PD targets ``(N, nu)`` for one control step; returns ``(diverged, invalid)``."""
        self.launch(targets, threaded=False)
        return self.finish()
