"""The one Warp kernel motok adds to MuJoCo Warp's step (imported only by ``warp_stepper``, since
it needs ``warp`` at import time): C MuJoCo's divergence check and reset, which MuJoCo Warp does
not have.

C MuJoCo's ``mj_step`` resets a simulation (``mj_resetData``) whose ``qpos`` or ``qvel`` is
non-finite or above ``mjMAXVAL`` before the step, or whose ``qacc`` is after it, and counts a
warning; the MuJoCo steppers report such environments as diverged. Launched after every substep
(inside the CUDA graph on a GPU), this kernel does the same per world: the flagged world restarts
from ``qpos0`` at rest with no warm start and zero controls for the remaining substeps, and
``bad`` records it. C MuJoCo resets between its forward pass and the integration, so the reset
world integrates that substep from ``qpos0``; here the check follows the whole substep, so the reset
world has one substep less at rest (the physics of a world that blew up, not of a healthy one).
"""

from __future__ import annotations

import warp as wp


@wp.kernel
def check_and_reset(qpos0: wp.array(dtype=wp.float32), maxval: wp.float32, qpos: wp.array2d(dtype=wp.float32),
                    qvel: wp.array2d(dtype=wp.float32), qacc: wp.array2d(dtype=wp.float32),
                    warm: wp.array2d(dtype=wp.float32), ctrl: wp.array2d(dtype=wp.float32),
                    bad: wp.array(dtype=wp.int32)):
    w = wp.tid()
    nq, nv = qpos.shape[1], qvel.shape[1]
    broken = int(0)
    # One thread per world walks its ~100 numbers: cheap next to a physics step, and no race on the reset.
    for j in range(nq):
        x = qpos[w, j]
        if not wp.isfinite(x) or wp.abs(x) > maxval:
            broken = 1
    for j in range(nv):
        v, a = qvel[w, j], qacc[w, j]
        if not wp.isfinite(v) or wp.abs(v) > maxval or not wp.isfinite(a) or wp.abs(a) > maxval:
            broken = 1
    if broken == 1:
        bad[w] = 1
        for j in range(nq):
            qpos[w, j] = qpos0[j]
        for j in range(nv):
            qvel[w, j] = 0.0
            qacc[w, j] = 0.0
            warm[w, j] = 0.0
        for j in range(ctrl.shape[1]):  # mj_resetData zeroes the controls too: the substeps left run unactuated
            ctrl[w, j] = 0.0
