"""One formula for numpy and torch: the array module of the arrays a function was given.

The physics terms (Eq. 7's observation, Eq. 9's goal, Eq. 10's reward, the terminations, the
reference look-ups) are written once against the functions numpy and torch share by name and
positional signature (``stack``, ``concatenate``, ``exp``, ``sqrt``, ``where``, ``hypot``,
``clip``, ``amax``, ``minimum``, ``matmul``, ``zeros_like``). Given host numpy arrays they run on
the host (C MuJoCo's steppers); given torch tensors they run wherever the tensors live, so a
MuJoCo Warp rollout on a GPU keeps its state on the device (docs/sim.md "On the device").
Array methods both share (``sum(-1)``, ``mean(-1)``, ``reshape``, indexing) need nothing.
"""

from __future__ import annotations

import numpy as np


def xp(*arrays):
    """``torch`` if any of ``arrays`` is a torch tensor, else ``numpy``. Mixing the two is an error
    the caller should see, not a silent host copy, so torch wins only where torch was given."""
    for a in arrays:
        if type(a).__module__.startswith("torch"):
            import torch

            return torch
    return np


def is_tensor(a) -> bool:
    return type(a).__module__.startswith("torch")


def copy(a):
    """A copy that owns its memory (``ndarray.copy`` / ``Tensor.clone``)."""
    return a.clone() if is_tensor(a) else a.copy()


def like(a, values, dtype=None):
    """``values`` (host numbers or arrays) as an array of ``a``'s module, and device for a tensor;
    ``dtype`` defaults to ``a``'s for floating values. Constants such as the actuators' velocity
    lead are moved once, when an environment is built, not per step."""
    if is_tensor(a):
        import torch

        v = np.asarray(values)
        if dtype is None and v.dtype.kind == "f":
            dtype = a.dtype
        return torch.as_tensor(v, dtype=dtype, device=a.device)
    return np.asarray(values, dtype=dtype)


def take_along(a, idx, axis: int):
    """``np.take_along_axis`` / ``torch.gather``: the entries of ``a`` at ``idx`` along ``axis``."""
    return a.gather(axis, idx) if is_tensor(a) else np.take_along_axis(a, idx, axis)
