"""The stepper on MuJoCo Warp (``mujoco_warp``, optional: ``pip install motok[gpu]``): N worlds of
the same MJCF batched on a Warp device, ``cuda`` for the paper's thousands of environments or
``cpu`` (slow, one thread) to test it without a GPU.

It keeps :class:`motok.sim.steppers.Stepper`'s contract: host numpy in and out (``qpos``/``qvel``
float64 mirrors refreshed after every call, ``bodies()`` as float64 numpy), so the environment,
tasks and policies run unchanged. The state itself lives on the device as torch tensors that
alias Warp's arrays (``wp.to_torch``, no copies): ``qpos_t``, ``qvel_t``, ``ctrl_t`` and
:meth:`bodies_tensor`, which the on-device rollout (``env.on_device``: policy, goals, rewards,
resets and Eq. 7 in torch on the same device) uses without the host mirrors, with
:meth:`step_tensor` and :meth:`set_state_tensor`; docs/sim.md "On the device".

Where it differs from the MuJoCo steppers, and why:

* float32 (MuJoCo Warp's precision), and a different box-box collider: trajectories agree with
  float64 MuJoCo to micrometres until a contact the two decide differently, then drift apart as
  chaotically as between two timesteps (tests/test_warp.py states the tolerances).
* MuJoCo Warp has no divergence check: C MuJoCo resets a world whose qpos, qvel or qacc is
  non-finite or above ``mjMAXVAL`` (1e10) and counts a warning. :mod:`motok.sim.warp_kernels`
  does the same after every substep (the world restarts from ``qpos0`` at rest) and the step
  reports it as diverged. As ``mujoco.batch``'s forward pass does, a non-finite or huge state
  given to ``set_state`` is reset to ``qpos0`` there, without a report.
* Contact and constraint buffers are preallocated (``nconmax`` per world on average, pooled over
  the worlds; ``njmax`` rows per world, hard): worlds that overflowed them are counted in
  :attr:`overflows` (their contacts were dropped) so a run can tell.
"""

from __future__ import annotations

from contextlib import contextmanager

import numpy as np

from motok.errors import UserError
from motok.sim.humanoid import Humanoid
from motok.sim.obs import Bodies

MAXVAL = 1e10  # C MuJoCo's mjMAXVAL: mj_checkPos/Vel/Acc reset a simulation beyond it

# Per-world buffer sizes. PD tracking with falls on the CPU (docs/sim.md) averages 4.7 contacts and
# 19 constraint rows per world, at most 13 and 52; a humanoid lying on the floor has more. nconmax
# is an average (the contact pool is shared by all worlds), njmax a per-world limit.
NCONMAX, NJMAX = 48, 192


def _import():
    try:
        import warp as wp
        # Before mujoco_warp initialises Warp: its banner and one line per compiled module would flood a log.
        wp.config.log_level = wp.LOG_WARNING
        import mujoco_warp as mjw
    except ImportError as e:  # the CPU install does not carry them
        raise UserError(f"env.backend 'warp' needs MuJoCo Warp: pip install 'motok[gpu]' ({e})") from None
    return wp, mjw


class WarpStepper:
    """MuJoCo Warp stepping of ``num_envs`` worlds on ``device`` (``cpu`` or ``cuda[:i]``)."""

    def __init__(self, hum: Humanoid, num_envs: int, substeps: int, device: str = "cpu",
                 nconmax: int = NCONMAX, njmax: int = NJMAX):
        import torch

        wp, mjw = self.wp, self.mjw = _import()
        wp.init()
        if device.startswith("cuda") and not wp.is_cuda_available():
            raise UserError(f"device {device!r}: Warp finds no CUDA driver here (use --device cpu)")
        self.device = wp.get_device(device)
        self.torch_device = torch.device("cpu" if self.device.is_cpu else f"cuda:{self.device.ordinal}")
        self.model, self.n, self.substeps = hum.model, num_envs, substeps
        # On a GPU, Warp kernels and this class's torch ops share one torch-created stream, so they are
        # ordered on the aliased arrays; not the legacy default stream, which CUDA cannot capture into a
        # graph. torch's streams do not sync with the caller's by themselves: _scope orders them.
        self._torch_stream = None if self.device.is_cpu else torch.cuda.Stream(self.torch_device)
        self._stream = None if self.device.is_cpu else wp.stream_from_torch(self._torch_stream)
        with self._scope():
            self.m = mjw.put_model(hum.model)
            self.d = mjw.make_data(hum.model, nworld=num_envs, nconmax=nconmax, njmax=njmax)
            # Overflows are counted below; MuJoCo Warp's own printf per step (the capped Newton
            # reaching its 10 iterations is normal here) would flood the log.
            self.m.opt.warn_overflow = 0
            self._bad, self._unreported = wp.zeros(num_envs, dtype=wp.int32), wp.zeros(num_envs, dtype=wp.int32)
            self._qpos0_wp = wp.array(hum.model.qpos0.astype(np.float32))
        t = wp.to_torch
        d = self.d
        self.qpos_t, self.qvel_t, self.ctrl_t = t(d.qpos), t(d.qvel), t(d.ctrl)
        self._warm, self._overflow = t(d.qacc_warmstart), t(d.overflow)
        self._xpos, self._xquat, self._xmat = t(d.xpos), t(d.xquat), t(d.xmat)
        self._cvel, self._com = t(d.cvel), t(d.subtree_com)
        self._ids = torch.as_tensor(hum.body_ids, device=self.torch_device)
        self._root = int(hum.model.body_rootid[hum.body_ids[0]])  # one tree: every body's cvel refers to its com
        # Capacity overflows only; the solver's iteration-limit bits are normal with a capped Newton.
        O = mjw.OverflowType
        self._capacity = int(O.NEFC | O.NJMAX_NNZ | O.BROADPHASE | O.NARROWPHASE | O.CCD)
        self._overflows = torch.zeros((), dtype=torch.int64, device=self.torch_device)  # counted on the device
        self._graph = None  # the substeps as one CUDA graph, captured on the second step (kernels loaded by then)
        self._stepped = False
        self.qpos = np.zeros((num_envs, hum.model.nq))
        self.qvel = np.zeros((num_envs, hum.model.nv))
        self.qpos[:] = hum.model.qpos0
        self.set_state(np.arange(num_envs), self.qpos, self.qvel)

    @property
    def overflows(self) -> int:
        """World-steps whose contacts or constraint rows did not fit the buffers (their excess was dropped)."""
        return int(self._overflows)

    @contextmanager
    def _scope(self):
        """Warp's device (and on a GPU this stepper's stream, after the caller's work and before the
        caller's next: the caller may have just written ``ctrl`` and will read the state next)."""
        with self.wp.ScopedDevice(self.device):
            if self._stream is None:
                yield
                return
            import torch

            caller = torch.cuda.current_stream(self.torch_device)
            self._torch_stream.wait_stream(caller)
            with self.wp.ScopedStream(self._stream), torch.cuda.stream(self._torch_stream):
                yield
            caller.wait_stream(self._torch_stream)

    def _as(self, a):
        import torch

        if isinstance(a, torch.Tensor):
            return a.to(device=self.torch_device, dtype=self.qpos_t.dtype)
        return torch.as_tensor(np.asarray(a), dtype=self.qpos_t.dtype, device=self.torch_device)

    def _check(self, bad) -> None:
        from motok.sim.warp_kernels import check_and_reset

        d = self.d
        self.wp.launch(check_and_reset, dim=self.n, inputs=[self._qpos0_wp, MAXVAL, d.qpos, d.qvel, d.qacc,
                                                             d.qacc_warmstart, d.ctrl, bad])

    def _kinematics(self) -> None:
        """Position and velocity stages at the current state: body frames, com and cvel, which
        MuJoCo Warp's step leaves at the state before its last integration (as C MuJoCo does)."""
        self.mjw.kinematics(self.m, self.d)
        self.mjw.com_pos(self.m, self.d)
        self.mjw.com_vel(self.m, self.d)

    def _sync(self, ids=None) -> None:
        """Refresh the host mirrors (all rows, or ``ids``); with ``bodies()``, the device-to-host copies of a step."""
        if ids is None:
            self.qpos[:], self.qvel[:] = self.qpos_t.cpu().numpy(), self.qvel_t.cpu().numpy()
        else:
            i = self._rows(ids)
            self.qpos[ids], self.qvel[ids] = self.qpos_t[i].cpu().numpy(), self.qvel_t[i].cpu().numpy()

    def _rows(self, ids):
        import torch

        return torch.as_tensor(np.asarray(ids, dtype=np.int64), device=self.torch_device)

    def set_state(self, ids, qpos, qvel) -> None:
        self.set_state_tensor(self._rows(np.atleast_1d(ids)), qpos, qvel)
        self._sync(np.atleast_1d(ids))

    def set_state_tensor(self, ids, qpos, qvel) -> None:
        """:meth:`set_state` with device tensors (``ids`` int64), leaving the host mirrors alone."""
        with self._scope():
            self.qpos_t[ids], self.qvel_t[ids], self._warm[ids] = self._as(qpos), self._as(qvel), 0.0
            self._check(self._unreported)
            self._kinematics()

    def set_columns(self, ids, qcols, qpos, vcols, qvel) -> None:
        rows = self._rows(ids)[:, None]
        with self._scope():
            self.qpos_t[rows, self._rows(qcols)] = self._as(qpos)
            self.qvel_t[rows, self._rows(vcols)] = self._as(qvel)
            self._check(self._unreported)
            self._kinematics()
        self._sync(np.unique(ids))

    def _substeps(self) -> None:
        self._bad.zero_()
        for _ in range(self.substeps):
            self.mjw.step(self.m, self.d)
            self._check(self._bad)

    def step_tensor(self, ctrl):
        """One control step with ``ctrl`` a tensor or array ``(N, nu)``; returns the diverged mask
        as a device tensor and leaves the host mirrors alone (the on-device path)."""
        import torch

        with self._scope():
            self.ctrl_t[:] = ctrl if isinstance(ctrl, torch.Tensor) else self._as(ctrl)
            if self._graph is not None:
                self.wp.capture_launch(self._graph)
            elif self._stepped and not self.device.is_cpu:
                with self.wp.ScopedCapture() as cap:
                    self._substeps()
                self._graph = cap.graph
                self.wp.capture_launch(self._graph)
            else:
                self._substeps()
            self._stepped = True
            bad = self.wp.to_torch(self._bad) != 0
            self._overflows += ((self._overflow & self._capacity) != 0).sum()  # no host sync per step
            self._overflow.zero_()
            self._kinematics()
        return bad

    def step(self, ctrl: np.ndarray) -> np.ndarray:
        bad = self.step_tensor(ctrl)
        self._sync()
        return bad.cpu().numpy()

    def bodies_tensor(self, ids=None) -> Bodies:
        """World body states as device tensors ``(N, J, .)`` of the Warp arrays' dtype (float32)."""
        import torch

        e = slice(None) if ids is None else self._rows(ids)
        # Gathers by body index copy, so a caller may keep these across steps (as with the other steppers).
        pos, cvel = self._xpos[e][:, self._ids], self._cvel[e][:, self._ids]
        ang = cvel[..., :3]
        vel = cvel[..., 3:] + torch.linalg.cross(ang, pos - self._com[e][:, self._root, None], dim=-1)
        return Bodies(pos, vel, ang, rot=self._xmat[e][:, self._ids], quat=self._xquat[e][:, self._ids])

    def bodies(self, ids=None) -> Bodies:
        b = self.bodies_tensor(ids)
        f = lambda t: t.cpu().numpy().astype(np.float64)  # noqa: E731  (the protocol's host float64)
        return Bodies(f(b.pos), f(b.vel), f(b.angvel), rot=f(b.rot), quat=f(b.quat))
