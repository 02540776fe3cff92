"""Sole slip of one controller under changes to its world, zero-shot (docs/history.md, "Feet").

Each variant edits the loaded MuJoCo model in memory (the run's MJCF stays as it is) and tracks the
same clips with ``motok.control.track``; a row per variant: tracked to the end, MPJPE, and the sole
slip of the simulated and reference feet (``motok.sim.soles``). Variants: ``base``, ``noslipN``
(N noslip iterations), ``fricF`` (sliding friction F on every geom), ``timeconstT`` (contact solref
time constant T s), ``elliptic`` (elliptic friction cones, impratio 10), ``kvX`` (every PD damping
times X), ``kpX`` (stiffness and damping times X), ``ramp`` (each control step's PD targets ramped
from the previous step's over its substeps instead of held, on the rollout stepper), ``emaB`` (the
PD targets low-passed from step to step, ``env.target_filter`` B) and ``rollout`` (the rollout
stepper holding the targets: the control for ``ramp``).

    python scripts/sole_slip_variants.py --expert runs/expert_set2 -d runs/bandai2.h5 --split test \\
        --clips 'dataset-2_walk*' base noslip10 fric2 timeconst0.01 elliptic
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np

from motok.control.priors.load import load_controller
from motok.control.track import track
from motok.sim import steppers

ROLLOUT = steppers.RolloutStepper


class RampStepper(steppers.RolloutStepper):
    """PD targets ramped linearly over the substeps from the previous control step's (from the
    joints' own angles after a reset) to the new ones: no step in the targets every 33 ms."""

    def __init__(self, hum, num_envs, substeps, nthread=2):
        super().__init__(hum, num_envs, substeps, nthread)
        self._driven = self.model.jnt_qposadr[self.model.actuator_trnid[:, 0]]
        self._prev = np.zeros((num_envs, self.model.nu))
        self._frac = (np.arange(1, substeps + 1) / substeps)[None, :, None]

    def set_state(self, ids, qpos, qvel) -> None:
        super().set_state(ids, qpos, qvel)
        self._prev[ids] = self.qpos[ids][:, self._driven]

    def _substep_ctrl(self, ctrl: np.ndarray) -> None:
        target = np.asarray(ctrl, np.float64)
        self._ctrl[:] = self._prev[:, None] + self._frac * (target - self._prev)[:, None]
        self._prev = target.copy()


def apply(ctl, variant: str) -> None:
    cfg, model = ctl.cfg, ctl.humanoid.model
    if variant == "base":
        return
    if variant in ("ramp", "rollout"):
        cfg.env.stepper = "rollout"
        steppers.RolloutStepper = RampStepper if variant == "ramp" else ROLLOUT
        return
    if variant.startswith("ema"):  # the environment's own filter (env.target_filter), zero-shot
        cfg.env.target_filter = float(variant[3:])
        return
    if variant.startswith("kv"):
        model.actuator_biasprm[:, 2] *= float(variant[2:])
        return
    if variant.startswith("kp"):
        x = float(variant[2:])
        model.actuator_gainprm[:, 0] *= x
        model.actuator_biasprm[:, 1:3] *= x
        return
    if variant.startswith("noslip"):
        model.opt.noslip_iterations = int(variant[len("noslip"):])
    elif variant.startswith("fric"):
        model.geom_friction[:, 0] = float(variant[len("fric"):])
    elif variant.startswith("timeconst"):
        model.geom_solref[:, 0] = float(variant[len("timeconst"):])
    elif variant == "elliptic":
        model.opt.cone, model.opt.impratio = 1, 10.0
    else:
        raise SystemExit(f"unknown variant {variant!r} (base, noslipN, fricF, timeconstT, elliptic, kvX, kpX, "
                         f"ramp, emaB, rollout)")


def clip_parser(doc: str) -> argparse.ArgumentParser:
    """The controller (``--expert`` or ``--prior``) and the clips it plays, as ``control track`` takes them."""
    ap = argparse.ArgumentParser(description=doc.split("\n")[0])
    ap.add_argument("--expert")
    ap.add_argument("--prior")
    ap.add_argument("-d", "--data", required=True)
    ap.add_argument("--split")
    ap.add_argument("--clips")
    return ap


def main() -> None:
    ap = clip_parser(__doc__)
    ap.add_argument("variants", nargs="+")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        for v in a.variants:
            ctl = load_controller(expert=a.expert, prior=a.prior)
            steppers.RolloutStepper = ROLLOUT
            apply(ctl, v)
            r = track(ctl, a.data, Path(tmp) / f"{v}.h5", clips=a.clips, split=a.split)
            s, ref = r["sole_slip"]["simulated"], r["sole_slip"]["reference"]
            print(json.dumps({"variant": v, "tracked_to_end": round(r["tracked_to_end"], 3),
                              "mpjpe_mm": round(r["mpjpe_mm"], 1), "slip_cm_s": round(s["sole_slip_cm_s"], 1),
                              "slip_ratio": round(s["sole_slip_ratio"], 3), "contact": round(s["sole_contact_fraction"], 3),
                              "reference_slip_cm_s": round(ref["sole_slip_cm_s"], 1)}), flush=True)


if __name__ == "__main__":
    main()
