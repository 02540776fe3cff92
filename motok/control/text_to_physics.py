"""Text -> kinematic motion -> physically simulated motion, in one step (``motok gpt sample --prior``).

The GPT's motion is what ``motok gpt sample`` writes; it becomes the reference of
``motok control track`` (:func:`motok.control.track.track`): each clip is placed on the floor and
tracked from its first frame by a distilled prior's posterior and decoder (``--prior PRIOR``,
optionally ``--codebooks M``) or by the expert (``--expert RUN``) until it ends or the
controller's failure test stops it.

**Output layout.** ``OUT.h5`` is the simulated motion, the ``motion`` artifact ``control track``
writes; the kinematic motion the GPT generated is kept beside it as ``OUT.kinematic.h5``
(:func:`kinematic_path`), a plain ``gpt sample`` output. Two files rather than two clip names in
one: every reader of a motion artifact (``motok eval``, ``render``, ``export bvh``, ``eval
motion-matching``) then takes the simulated or the kinematic motion whole, with the same clip
names in both, and never mixes them in one evaluation. A clip that fails keeps the part played;
one that fails before two frames is reported and left out of ``OUT.h5`` (not of the kinematic
file). ``--render`` is track's video of the first clip, the kinematic motion drawn as a ghost;
``--bvh`` exports the simulated clips.
"""

from __future__ import annotations

import time
from pathlib import Path

from motok.atomic import check_writable
from motok.checkpoint import read_meta
from motok.control.priors.load import Controller, load_controller
from motok.errors import UserError

H5 = (".h5", ".hdf5")
VIDEO = (".mp4", ".gif")  # what track's MuJoCo render (motok.sim.render) writes
KINDS = {"--prior": ("control-prior", "a distilled prior, from `motok control distill`"),
         "--expert": ("control-expert", "an expert run, from `motok control expert train`")}


def kinematic_path(out) -> Path:
    """Where the kinematic motion of ``OUT.h5`` goes: ``OUT.kinematic.h5`` beside it."""
    out = Path(out)
    return out.with_name(f"{out.stem}.kinematic{out.suffix}")


def load_physics_controller(prior=None, expert=None, codebooks: int | None = None) -> Controller:
    """:func:`motok.control.priors.load.load_controller` behind checks that name the option at
    fault: exactly one controller, of the bundle kind its option expects, and ``codebooks`` within
    the prior's (a wrong bundle costs a line, not a sampling run and a traceback)."""
    if prior is None and expert is None:
        raise UserError("--codebooks goes with --prior PRIOR (a control-prior bundle)" if codebooks is not None
                        else "simulate with one controller: --prior PRIOR or --expert RUN")
    if prior is not None and expert is not None:
        raise UserError("simulate with one controller: --prior PRIOR or --expert RUN, not both")
    if expert is not None and codebooks is not None:
        raise UserError("--codebooks selects a prior's codebooks: it goes with --prior PRIOR, not --expert")
    option, path = ("--prior", prior) if prior is not None else ("--expert", expert)
    want, what = KINDS[option]
    found = read_meta(path).get("kind")
    if found != want:
        other = next((o for o, (k, _) in KINDS.items() if k == found), None)
        hint = f"; pass it with {other}" if other else ""
        raise UserError(f"{option} {path}: expected a {want} bundle ({what}), found kind {found!r}{hint}")
    return load_controller(expert, prior, codebooks)


def text_to_physics(gpt, texts: list[str], out, *, prior=None, expert=None, codebooks: int | None = None,
                    render=None, bvh=None, **sampling) -> dict:
    """Sample ``texts`` with the GPT run ``gpt`` (``sampling``: the options of
    :func:`motok.gpt.sample.sample`: ``num_samples``, ``seed``, ``seconds``, ``top_k``, ...) into
    ``OUT.kinematic.h5``, track every clip with the controller (``prior`` or ``expert``) into
    ``out``, optionally render the first clip over its kinematic ghost (``render``) and export the
    simulated clips to BVH (``bvh``, numbered when several). Returns the summary with ``per_clip``:
    text, tokens, tracked to the end, time of failure, MPJPE and G-MPJPE to the placed
    kinematic motion."""
    from motok.control.track import track
    from motok.data.dataset import MotionFile
    from motok.gpt.sample import sample

    out = check_writable(out, suffixes=H5)
    kin = check_writable(kinematic_path(out), what="the kinematic motion")
    if render is not None:
        check_writable(render, suffixes=VIDEO, what="--render (with --prior or --expert)")
    if bvh is not None:
        check_writable(bvh, suffixes=(".bvh",), what="--bvh")
    controller = load_physics_controller(prior, expert, codebooks)

    kinematic = sample(gpt, texts, kin, **sampling)
    hum = controller.humanoid
    with MotionFile(kin) as mf:
        joints = list(mf.skeleton.joints)
    if joints != list(hum.skeleton.joints):
        raise UserError(f"{gpt} generates the {len(joints)}-joint skeleton of its tokenizer, which is not the "
                        f"controller's humanoid ({hum.skeleton.num_joints} joints, {hum.skeleton.name!r}): "
                        f"use a controller trained on the GPT's data")
    t0 = time.perf_counter()
    tracked = track(controller, kin, out, render=render)
    t_track = time.perf_counter() - t0
    per_tracked = tracked.pop("per_clip")

    texts_of = [t for t in texts for _ in range(sampling.get("num_samples", 1))]
    per = {}
    for name, text, tokens, secs in zip(kinematic["names"], texts_of, kinematic["tokens"], kinematic["seconds"]):
        r = per_tracked[name]
        failed = None if r["tracked_to_end"] or "seconds" not in r else r["seconds"]
        per[name] = {"text": text, "tokens": tokens, "kinematic_seconds": secs, **r, "failed_at_s": failed}
    bvhs = export_bvhs(out, bvh) if bvh is not None else []
    meta = controller.meta
    summary = {"output": str(out), "kinematic": str(kin), "controller": str(prior if prior is not None else expert),
               "controller_kind": meta.get("kind"),
               **({"codebooks": codebooks} if codebooks is not None else {}),
               **{k: v for k, v in tracked.items() if k != "output"}, "bvh": bvhs,
               "time_sample_s": kinematic["time_total_s"], "time_track_s": round(t_track, 2)}
    if kinematic["truncated"]:
        summary["truncated"] = kinematic["truncated"]
    return {**summary, "per_clip": per}


def export_bvhs(motion, bvh) -> list[str]:
    """Every clip of ``motion`` to ``bvh`` (``NAME_CLIP.bvh`` when there are several, as ``gpt
    sample --bvh`` numbers them)."""
    from motok.data.dataset import MotionFile
    from motok.data.export import export_bvh

    bvh, written = Path(bvh), []
    with MotionFile(motion) as mf:
        names = list(mf.names)
        for name in names:
            path = bvh if len(names) == 1 else bvh.with_name(f"{bvh.stem}_{name}{bvh.suffix}")
            written.append(str(export_bvh(path, mf.clip(name).joints, mf.skeleton, mf.offsets, mf.fps)))
    return written
