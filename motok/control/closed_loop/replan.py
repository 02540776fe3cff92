"""The re-plans of the closed loop: the simulated motion as tokens, the GPT's continuation of them,
and the new plan placed where the simulated character is (:mod:`motok.control.closed_loop.loop` runs it).

T2M-GPT is autoregressive over motion tokens (Zhang et al. 2023, Sec. 3.2), so a plan can be
continued from any tokens; the closed loop continues it from the character's own. At a re-plan:

1. **Encode** (:meth:`Planner.context`): the simulated body positions of the last ``context``
   tokens (a whole number of them, ending on the current control step, which is on a token
   boundary) go back to the data frame, are resampled from the control rate to the motion's frame
   rate and put through the feature pipeline (``extract_features``, as ``control track`` writes
   simulated motion and ``preprocess`` the data), and the tokenizer encodes them: ``context * rate
   + 1`` positions, ``context * rate`` feature frames, ``context`` tokens.
2. **Continue** (:meth:`Planner.continue_plan`): the GPT, on the prompt of this moment, continues
   those tokens (``generate(prefix=...)``) to the motion's length, with each row's own random
   stream going on from its earlier plans.
3. **Decode and anchor** (:func:`anchor`): the context and the new tokens are decoded together, so
   the decoder sees what leads into the new part and the seam is its own, and the frames after
   the context are the plan. Tokens are root-relative (the features integrate root velocities
   from the window's first frame), so the decoded root path is in a frame of its own: it is
   turned about the vertical and moved on the floor so that its first frame has the simulated
   character's root position and heading at this moment (heading: HumanML3D's forward from hips
   and shoulders, measured the same way on both). The plan then starts from the character, not
   from where the old plan had got to; heights stay the decoder's, and the plan is stood on the
   floor as every tracked motion is (``place_on_floor``).

The physics is not touched: the controller goes on from the state it reached, along the new
reference (:meth:`motok.control.tasks.imitation.ImitationTask.follow`).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
import torch

from motok.control.closed_loop.timeline import Clock
from motok.features.humanml3d import extract_features
from motok.features.kinematics import forward_direction
from motok.features.resample import resample_positions
from motok.sim.humanoid import from_mj
from motok.skeleton import Skeleton


@dataclass
class Planner:
    """A GPT ready to plan: the model, its tokenizer, the skeleton and offsets of its motion,
    the text embeddings of every prompt, and the sampling options of ``generate``."""

    model: object  # MotionGPT
    tokenizer: object  # VQVAE
    skeleton: Skeleton
    offsets: np.ndarray
    legacy: bool
    clock: Clock
    embeddings: dict[str, torch.Tensor]
    sampling: dict = field(default_factory=dict)  # temperature, top_k, top_p, argmax, guidance
    provenance: dict = field(default_factory=dict)  # the weights' hashes, for the artifacts' provenance
    seconds: float = 0.0  # wall time spent planning: encoding, generating, decoding

    def context(self, window_mj: np.ndarray) -> np.ndarray:
        """The tokens of a simulated window: body positions ``(S + 1, J, 3)`` in MuJoCo's frame at
        the control rate, ``S`` a whole number of tokens' worth of steps."""
        c, t0 = self.clock, time.perf_counter()
        pos = from_mj(np.asarray(window_mj, dtype=np.float64))
        if abs(c.control_hz - c.fps) > 1e-6:
            pos = resample_positions(pos, c.control_hz, c.fps)
        f = extract_features(pos, self.skeleton, target_offsets=self.offsets, fps=c.fps, legacy=self.legacy)
        with torch.no_grad():
            idx = self.tokenizer.encode_features(torch.from_numpy(f.features)[None], 1)
        self.seconds += time.perf_counter() - t0
        return idx[0, :, 0].numpy().astype(np.int64)

    def continue_plan(self, texts: list[str], prefix: np.ndarray | None, targets: list[int],
                      generators: list[torch.Generator]) -> list[np.ndarray]:
        """New tokens for each row: ``texts[b]``'s embedding, continuing ``prefix[b]`` (none for a
        first plan) up to ``targets[b]`` tokens in all, drawn from ``generators[b]``."""
        from motok.gpt.sample import generate

        t0 = time.perf_counter()
        emb = torch.stack([self.embeddings[t] for t in texts])
        pre = None if prefix is None else torch.as_tensor(prefix, dtype=torch.long)
        g = generate(self.model, emb, target_len=torch.as_tensor(targets), seeds=generators, prefix=pre,
                     **self.sampling)
        self.seconds += time.perf_counter() - t0
        return [c.numpy().astype(np.int64) for c in g.codes]

    def decode(self, codes: np.ndarray) -> np.ndarray:
        """Joint positions ``(len * rate, J, 3)`` of tokens, as ``gpt sample`` makes a clip of them."""
        from motok.tokenizer.tokens import features_to_clip

        t0 = time.perf_counter()
        with torch.no_grad():
            feats = self.tokenizer.decode_features(torch.as_tensor(codes, dtype=torch.long).view(1, -1, 1), 1)
        joints = features_to_clip("plan", feats[0].numpy(), self.skeleton, self.legacy).joints
        self.seconds += time.perf_counter() - t0
        return joints


def heading(joints: np.ndarray, skeleton: Skeleton) -> float:
    """Yaw (radians, about +Y, 0 facing +Z) of one pose ``(J, 3)``: HumanML3D's forward from the
    hips and shoulders, unsmoothed, so the simulated pose and the plan are measured alike."""
    f = forward_direction(np.asarray(joints, dtype=np.float64)[None], skeleton, smooth=False)[0]
    return math.atan2(f[0], f[2])


def anchor(plan: np.ndarray, root: np.ndarray, yaw: float, skeleton: Skeleton) -> np.ndarray:
    """``plan`` ``(T, J, 3)`` turned about the vertical and moved on the floor so that its first
    frame has root ``root`` (x, z; y is left alone) and heading ``yaw``."""
    p = np.asarray(plan, dtype=np.float64)
    a = yaw - heading(p[0], skeleton)
    c, s = math.cos(a), math.sin(a)
    x, z = p[..., 0], p[..., 2]
    out = p.copy()
    out[..., 0], out[..., 2] = c * x + s * z, -s * x + c * z
    out[..., [0, 2]] += np.asarray(root, dtype=np.float64)[[0, 2]] - out[0, 0, [0, 2]]
    return out


def plan_change(old: np.ndarray, new: np.ndarray) -> dict:
    """How far a re-plan moved the reference, over the frames both plans hold ``(T, J, 3)``:
    ``change_mm`` (every joint, in the world: drift taken back included), ``pose_change_mm``
    (root-relative) and ``root_shift_mm`` (the root, on the floor, at the re-plan)."""
    from motok.eval.metrics import mpjpe

    n = min(len(old), len(new))
    o, w = old[:n], new[:n]
    return {"change_mm": round(float(mpjpe(w, o, root_relative=False).mean()), 2),
            "pose_change_mm": round(float(mpjpe(w, o).mean()), 2),
            "root_shift_mm": round(float(np.linalg.norm(w[0, 0, [0, 2]] - o[0, 0, [0, 2]]) * 1000.0), 2)}


@dataclass
class Plan:
    """One plan of one motion: made at token ``start`` (its first frame) for the prompt ``text``,
    reaching token ``end``; ``context`` the simulated motion's tokens the GPT continued (none for
    the first plan), ``codes`` the tokens it added, ``joints`` the placed plan ``(T, J, 3)`` (the
    data's frame, in the world, at the motion's rate), ``info`` where it was anchored and how much
    it changed the reference."""

    start: int
    end: int
    text: str
    reason: str  # start, every (--replan-every), prompt (a --then switch) or horizon (the plan ran out)
    context: list[int]
    codes: list[int]
    joints: np.ndarray
    info: dict = field(default_factory=dict)


class Loop:
    """The plans of a batch of motions (:class:`~motok.control.closed_loop.timeline.Row`), made as
    :func:`~motok.control.tasks.imitation.play` asks: the first ones by :meth:`start`, the next
    ones by the ``replan`` callback (this object called) whenever a motion's next re-plan falls on
    the control step just played. ``push(steps, env)``, when given, runs after every control step
    before anything else: a disturbance for tests and robustness studies. ``pos`` holds the
    simulated body positions of every step so far (MuJoCo's frame)."""

    def __init__(self, planner: Planner, hum, rows: list, every: int | None, push=None):
        self.planner, self.hum, self.rows, self.every, self.push = planner, hum, rows, every, push
        self.clock = planner.clock
        self.spt = self.clock.steps_per_token
        # One random stream per motion, seeded as `gpt sample` seeds it and going on plan after plan,
        # so a first plan is the open loop's sample and a re-plan never repeats an earlier draw.
        self.generators = [torch.Generator().manual_seed(int(r.seed)) for r in rows]
        self.plans: list[list[Plan]] = [[] for _ in rows]
        self.libs: list = [None] * len(rows)
        self.due: list[int | None] = [None] * len(rows)
        self.pos: list[np.ndarray] = []

    def start(self, batch: int = 64):
        """The first plans (the GPT from the text alone, as ``gpt sample``), as one library."""
        from motok.sim.reference import concat_libraries

        mc = self.clock.max_codes
        for a in range(0, len(self.rows), batch):
            ids = list(range(a, min(a + batch, len(self.rows))))
            codes = self.planner.continue_plan([self.rows[i].text_at(0) for i in ids], None,
                                               [min(self.rows[i].tokens, mc) for i in ids],
                                               [self.generators[i] for i in ids])
            for i, c in zip(ids, codes):
                self._adopt(i, 0, [], c, self.planner.decode(c), "start", {})
        return concat_libraries(self.libs)

    def __call__(self, steps: int, env, pos: list, active: np.ndarray):
        from motok.control.closed_loop.timeline import plan_window
        from motok.sim.reference import concat_libraries

        self.pos = pos
        if self.push is not None:
            self.push(steps, env)
        if steps % self.spt:
            return None
        n, rate, sk = steps // self.spt, self.clock.rate, self.planner.skeleton
        due = [int(i) for i in np.flatnonzero(active) if self.due[i] == n]
        if not due:
            return None
        groups: dict[int, list[tuple[int, int]]] = {}
        for i in due:  # rows with the same context length continue in one batch
            c, h = plan_window(n, self.rows[i].tokens, self.clock.max_codes)
            groups.setdefault(c, []).append((i, h))
        for c, members in groups.items():
            window = np.stack(pos[steps - c * self.spt:steps + 1])  # (c * spt + 1, N, J, 3)
            ctx = np.stack([self.planner.context(window[:, i]) for i, _ in members])
            texts = [self.rows[i].text_at(n) for i, _ in members]
            new = self.planner.continue_plan(texts, ctx, [c + h for _, h in members],
                                             [self.generators[i] for i, _ in members])
            for (i, _), cx, codes in zip(members, ctx, new):
                joints = self.planner.decode(np.concatenate([cx, codes]))[c * rate:]
                now = from_mj(np.asarray(window[-1, i], dtype=np.float64))
                yaw = heading(now, sk)
                placed = anchor(joints, now[0], yaw, sk)
                row = self.rows[i]
                reason = "prompt" if n in row.switches else "every" if self.every and n % self.every == 0 else "horizon"
                info = {"sim_root_m": [round(float(now[0, 0]), 4), round(float(now[0, 2]), 4)],
                        "sim_heading_deg": round(math.degrees(yaw), 2),
                        "plan_heading_deg": round(math.degrees(heading(placed[0], sk)), 2)}
                self._adopt(i, n, cx.tolist(), codes, placed, reason, info)
        return concat_libraries(self.libs), np.asarray(due, dtype=np.int64)

    def _adopt(self, i: int, token: int, context: list[int], codes: np.ndarray, joints: np.ndarray, reason: str,
               info: dict) -> None:
        """Plan ``joints`` (from ``token``) becomes motion ``i``'s reference: stood on the floor, its
        library built, its next re-plan set, and how it changed the reference measured."""
        from motok.control.closed_loop.timeline import next_replan
        from motok.control.track import place_on_floor
        from motok.sim.reference import library_from_joints

        c, row = self.clock, self.rows[i]
        lib, shift = place_on_floor(library_from_joints(self.hum, [row.name], [joints], c.fps, c.control_hz))
        placed = np.asarray(joints, dtype=np.float64).copy()
        placed[..., 1] += shift[0]
        end = token + len(codes)
        self.due[i] = next_replan(token, end, row, self.every)
        if self.plans[i]:
            old = self.plans[i][-1]
            span = ((self.due[i] or end) - token) * c.rate  # the part the new plan is tracked for
            k = (token - old.start) * c.rate
            info.update(plan_change(old.joints[k:k + span], placed[:span]))
            both = min(old.end, end) - token
            was = np.asarray(old.codes[token - old.start:token - old.start + both])
            info["codes_changed"] = round(float(np.mean(was != np.asarray(codes[:both]))), 4) if both > 0 else None
        self.plans[i].append(Plan(token, end, row.text_at(token), reason, list(context),
                                  [int(x) for x in codes], placed, info))
        self.libs[i] = lib
