"""What a frozen sentence encoder separates: left from right, one hand from both,
walking from running, across wordings. ``motok eval text-separation --encoder NAME``.

For a contrast with meanings A and B, each said in several wordings ``w`` so that ``A_w`` and
``B_w`` differ only in the contrasted words ("... turns left" / "... turns right"):

- ``same_wording`` = mean cos(A_w, B_w): the other meaning, same words;
- ``same_meaning`` = mean cos(A_w, A_v), w != v (and for B): the same meaning, other words;
- ``margin`` = same_meaning - same_wording: > 0 when meaning outweighs wording;
- ``closer_rate``: share of (w, v) with cos(A_w, A_v) > cos(A_w, B_w) (and for B), i.e. another
  wording of the same request is nearer than the same wording of the other request. A GPT
  conditioned on the embedding can only follow a new wording as well as the embedding puts it
  near the right request.

Wordings are the set-2 caption wordings and the hand-written paraphrases of
:mod:`motok.text.phrasings`; the cosine is of unit-norm embeddings.
"""

from __future__ import annotations

import itertools

import numpy as np

from motok.text.phrasings import CONTENT_PARAPHRASES

# Caption wordings as the set-2 captions phrase each content ({s}: left / right).
_CAPTION = {
    "walk-turn": ["walks forward and turns {s}", "turns to the {s} while walking", "walks and makes a {s} turn"],
    "raise-one": ["raises the {s} hand", "lifts the {s} arm up", "puts the {s} hand up in the air"],
    "raise-both": ["raises both hands up", "lifts both arms overhead", "puts both hands up in the air"],
    "wave-one": ["waves the {s} hand", "lifts the {s} hand and waves", "waves with the {s} arm"],
    "wave-both": ["waves both hands", "waves both hands in the air", "waves with both arms"],
    "walk": ["walks forward", "walks straight ahead", "walks in a straight line"],
    "run": ["runs forward", "jogs straight ahead", "runs in a straight line"],
}


def _sentences(wordings: list[str], side: str | None = None) -> list[str]:
    return [f"A person {w.format(s=side) if side else w}." for w in wordings]


def contrasts() -> dict[str, tuple[list[str], list[str]]]:
    """name -> (A sentences, B sentences), aligned wording by wording."""
    P = CONTENT_PARAPHRASES

    def para(content: str) -> list[str]:
        return [f"A person {p}." for p in P[content]]

    turn = _sentences(_CAPTION["walk-turn"], "left"), _sentences(_CAPTION["walk-turn"], "right")
    out = {
        "turn left / right": (turn[0] + para("walk-turn-left"), turn[1] + para("walk-turn-right")),
        "raise left / right hand": (_sentences(_CAPTION["raise-one"], "left") + para("raise-up-left-hand"),
                                    _sentences(_CAPTION["raise-one"], "right") + para("raise-up-right-hand")),
        "wave left / right hand": (_sentences(_CAPTION["wave-one"], "left") + para("wave-left-hand"),
                                   _sentences(_CAPTION["wave-one"], "right") + para("wave-right-hand")),
        "raise one hand / both": (_sentences(_CAPTION["raise-one"], "left") + para("raise-up-left-hand"),
                                  _sentences(_CAPTION["raise-both"]) + para("raise-up-both-hands")),
        "wave one hand / both": (_sentences(_CAPTION["wave-one"], "left") + para("wave-left-hand"),
                                 _sentences(_CAPTION["wave-both"]) + para("wave-both-hands")),
        "walk / run": (_sentences(_CAPTION["walk"]) + para("walk"), _sentences(_CAPTION["run"]) + para("run")),
    }
    return out


def _unit(x: np.ndarray) -> np.ndarray:
    return x / np.maximum(np.linalg.norm(x, axis=1, keepdims=True), 1e-12)


def measure(embed, pairs: dict[str, tuple[list[str], list[str]]] | None = None) -> dict:
    """The statistics of the module docstring per contrast; ``embed(list[str]) -> (n, d)``."""
    pairs = pairs or contrasts()
    out = {}
    for name, (A, B) in pairs.items():
        if len(A) != len(B) or len(A) < 2:
            raise ValueError(f"contrast {name!r}: needs two aligned lists of at least two wordings")
        e = _unit(np.asarray(embed(list(A) + list(B)), np.float64))
        a, b = e[:len(A)], e[len(A):]
        cross = (a * b).sum(1)  # same wording, other meaning
        same, closer = [], []
        for x in (a, b):
            for w, v in itertools.permutations(range(len(A)), 2):
                c = float(x[w] @ x[v])
                same.append(c)
                closer.append(c > cross[w])
        out[name] = {"same_wording": round(float(cross.mean()), 4), "same_meaning": round(float(np.mean(same)), 4),
                     "margin": round(float(np.mean(same) - cross.mean()), 4),
                     "closer_rate": round(float(np.mean(closer)), 4), "wordings": len(A)}
    return out


def nearest_caption_accuracy(embed, prompts, captions: dict[str, dict]) -> dict:
    """For each prompt, the label of the nearest caption (cosine) among ``captions`` (text ->
    labels): the share that has the prompt's content (and style where the prompt names one)."""
    texts = sorted(captions)
    ref = _unit(np.asarray(embed(texts), np.float64))
    q = _unit(np.asarray(embed([p.text for p in prompts]), np.float64))
    best = (q @ ref.T).argmax(1)
    hit_c = [captions[texts[k]].get("content") == p.content for k, p in zip(best, prompts)]
    hit_s = [captions[texts[k]].get("style") == p.style for k, p in zip(best, prompts) if p.style]
    return {"content": round(float(np.mean(hit_c)), 4), "style": round(float(np.mean(hit_s)), 4) if hit_s else None,
            "prompts": len(prompts)}
