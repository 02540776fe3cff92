"""What an unloadable ``train_state.pt`` is, said plainly.

motok writes training states with ``torch.save`` (a zip holding tensors and plain containers)
and reads them with ``torch.load(weights_only=True)``, which refuses anything else. A refusal
has three different causes that call for different actions, so the message names the one it is:

- a plain pickle (not torch's zip format), e.g. ``pickle.dump`` of a state: refused without being
  opened, because unpickling runs whatever code the file names;
- torch's format holding Python objects beyond tensors (a pickled class or function): refused
  for the same reason;
- a damaged file (cut short by a full disk or a copy): the only case to call "truncated".
"""

from __future__ import annotations

import os

ZIP_MAGIC = b"PK\x03\x04"
PICKLE_PROTO = 0x80  # the first opcode of every pickle of protocol 2 and later
NEVER = "motok never loads a pickle, because loading one can run any code it holds"


def state_refusal(path: str | os.PathLike, error: BaseException | None = None) -> str | None:
    """Before loading (``error`` None): why ``path`` must not be handed to ``torch.load`` at all,
    or None. After ``torch.load`` failed with ``error``: what the file is."""
    try:
        with open(path, "rb") as f:
            head = f.read(4)
    except OSError as e:
        return f"{path}: cannot read the training state ({e.strerror or e})"
    if error is None:
        if head.startswith(ZIP_MAGIC):
            return None
        if head[:1] == bytes([PICKLE_PROTO]) and len(head) > 1 and 2 <= head[1] <= 5:
            return (f"{path} is a plain Python pickle, not the tensors-only format motok writes; {NEVER}. "
                    f"Resume from a state motok saved, or start the run again")
        if not head:
            return f"{path} is empty: the training state was cut short (a full disk or an interrupted copy)"
        return (f"{path} is not a torch training state (it does not start like one); if it was made "
                f"outside motok, it may be a pickle, which {NEVER}")
    text = str(error)
    if "Weights only load failed" in text or type(error).__name__ == "UnpicklingError":
        return (f"{path} holds Python objects besides tensors (pickled classes or functions); {NEVER}. "
                f"Resume from a state motok saved, or start the run again")
    return (f"{path}: unreadable training state, the file is truncated or corrupted "
            f"({type(error).__name__}: {text.splitlines()[0] if text else ''})")


def write_state(obj, tmp: str | os.PathLike, final: str | os.PathLike) -> None:
    """``torch.save(obj, tmp)`` through memory: torch's own file writer reports a full disk as
    "iostream error" with no errno, while Python's raises ``OSError(ENOSPC)``, which the command
    line turns into one line naming ``final`` (the file the temporary one was to become)."""
    import io

    import torch

    buf = io.BytesIO()
    torch.save(obj, buf)
    try:
        with open(tmp, "wb") as f:
            f.write(buf.getbuffer())
    except OSError as e:
        raise OSError(e.errno, e.strerror, str(final)) from None
