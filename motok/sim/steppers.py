"""The code that advances physics: set full states, step every environment with fixed controls
for a few substeps and report the ones that diverged, give body states.

:class:`BatchStepper` (the default) runs MuJoCo >= 4.0's ``mujoco.batch`` thread pool, which also
computes the body kinematics natively; :class:`RolloutStepper` runs ``mujoco.rollout`` (C++
threads, GIL released) with numpy forward kinematics. The third implementation,
:class:`motok.sim.warp_stepper.WarpStepper`, runs MuJoCo Warp on a GPU (or slowly on the CPU), chosen
by ``backend="warp"`` (``env.backend: warp`` in a recipe; docs/sim.md).
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from motok.errors import UserError
from motok.sim.humanoid import Humanoid
from motok.sim.obs import Bodies, TreeKinematics, cross3


class Stepper(Protocol):
    """The only code that advances physics. Arrays are host numpy, ``(N, .)``."""

    qpos: np.ndarray
    qvel: np.ndarray

    def set_state(self, ids: np.ndarray, qpos: np.ndarray, qvel: np.ndarray) -> None:
        """Overwrite full states (and forget solver warm starts, so a reset env is a fresh env)."""

    def set_columns(self, ids: np.ndarray, qcols: np.ndarray, qpos: np.ndarray, vcols: np.ndarray,
                    qvel: np.ndarray) -> None:
        """Overwrite some coordinates of ``ids``: ``qpos[ids, qcols]``, ``qvel[ids, vcols]`` (columns
        ``(w,)`` for every row or ``(len(ids), w)`` per row), keeping the rest of their state, warm
        starts included (a thrown ball of ``motok.sim.balls`` leaves the humanoid's solve alone)."""

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

    def set_columns(self, ids, qcols, qpos, vcols, qvel) -> None:
        rows = np.asarray(ids)[:, None]
        self.state[rows, self._q + np.asarray(qcols)] = qpos
        self.state[rows, self._v + np.asarray(vcols)] = qvel

    def _substep_ctrl(self, ctrl: np.ndarray) -> None:
        """The controls of every substep, ``self._ctrl (N, substeps, nu)``: held (a diagnostic of
        scripts/sole_slip_variants.py ramps them)."""
        self._ctrl[:] = ctrl[:, None]

    def step(self, ctrl: np.ndarray) -> np.ndarray:
        self._substep_ctrl(ctrl)
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

    def set_columns(self, ids, qcols, qpos, vcols, qvel) -> None:
        rows = np.asarray(ids)[:, None]
        self.qpos[rows, qcols], self.qvel[rows, vcols] = qpos, qvel
        self.b.forward(np.unique(ids), stage=self._vel)  # derived fields current, as after set_state (rows may repeat)

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


def make_stepper(kind: str, hum: Humanoid, num_envs: int, substeps: int, nthread: int, backend: str = "mujoco",
                 device: str = "cpu") -> Stepper:
    """``backend`` ``mujoco`` (C MuJoCo on the CPU; ``kind`` picks batch or rollout) or ``warp``
    (MuJoCo Warp on ``device``; ``kind`` and ``nthread`` do not apply)."""
    if backend == "warp":
        from motok.sim.warp_stepper import WarpStepper  # optional dependency: imported only when asked for
        return WarpStepper(hum, num_envs, substeps, device=device)
    if backend != "mujoco":
        raise UserError(f"unknown backend {backend!r}: use mujoco or warp")
    if device != "cpu":
        raise UserError(f"device {device!r} needs backend 'warp' (--set env.backend=warp): C MuJoCo runs on the CPU")
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
    raise UserError(f"unknown stepper {kind!r}: use auto, batch or rollout")
