"""The phrasing-held-out split of the Bandai-Namco set-2 captions, version 1: fixed.

Bandai captions are written from labels (10 contents x 7 styles) with a few wordings each, and
the test split's captions reuse the training wordings, so the test R-precision cannot show
whether a model follows a sentence it has never seen. This module fixes two held-out sets:

- **Held-out wordings** (:data:`HELDOUT_WORDINGS`): one wording per content (for example "makes a
  left turn", "jogs straight ahead") and one per style ("wearily", "like a teenager"). Every
  caption that uses one of them is removed from GPT training (``holdout: v1`` in the GPT recipe;
  :func:`is_heldout`); the clips stay, with their other captions. The test split's captions that
  use them are the ``heldout_wordings`` prompts.
- **Hand-written paraphrases** (:data:`CONTENT_PARAPHRASES`, :data:`STYLE_PARAPHRASES`,
  :data:`SUBJECTS`): for every content three phrasings and for every style two, in words the
  captions never use (tested), combined into the ``paraphrases`` prompts.

The ``train`` prompts are the test split's captions that use training wordings only. Nothing here
is ever tuned on: the lists are versioned (:data:`VERSION`) and changing them makes a new version.
docs/gpt.md documents the split; ``motok eval labels`` measures generation on it.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path

from motok.errors import MotokError

VERSION = 1

# Regular expressions on the lower-cased caption. Content wordings (one of the 3-4 per content):
HELDOUT_CONTENT = {
    "walk": r"takes several steps forward",
    "walk-turn-left": r"makes a left turn",
    "walk-turn-right": r"makes a right turn",
    "run": r"jogs straight ahead",
    "raise-up-left-hand": r"puts the left hand up in the air",
    "raise-up-right-hand": r"puts the right hand up in the air",
    "raise-up-both-hands": r"puts both hands up in the air",
    "wave-left-hand": r"waves with the left arm",
    "wave-right-hand": r"waves with the right arm",
    "wave-both-hands": r"waves with both arms",
}
# ... and style wordings (one of the 2-3 adverbial phrases per style):
HELDOUT_STYLE = {
    "active": r"\benergetically\b",
    "exhausted": r"\bwearily\b",
    "feminine": r"in a dainty way",
    "masculine": r"in a manly way",
    "normal": r"in a neutral way",
    "youthful": r"like a teenager",
    "elderly": r"with a stooped, elderly gait",
}
HELDOUT_WORDINGS = {**{f"content:{k}": v for k, v in HELDOUT_CONTENT.items()},
                    **{f"style:{k}": v for k, v in HELDOUT_STYLE.items()}}
_HELDOUT = re.compile("|".join(f"(?:{p})" for p in HELDOUT_WORDINGS.values()))

# Hand-written, none of their content words occurs in any set-2 caption (tests/test_labels.py).
CONTENT_PARAPHRASES = {
    "walk": ["strolls at a steady pace", "paces along a direct path", "goes on foot toward the front"],
    "walk-turn-left": ["strolls and then veers to the left", "paces along and curves toward the left side",
                       "goes on foot and swings around to the left"],
    "walk-turn-right": ["strolls and then veers to the right", "paces along and curves toward the right side",
                        "goes on foot and swings around to the right"],
    "run": ["sprints toward the front", "dashes toward the front at speed", "races along a direct path"],
    "raise-up-left-hand": ["hoists the left hand high", "reaches toward the sky with the left hand",
                           "holds the left arm high above the head"],
    "raise-up-right-hand": ["hoists the right hand high", "reaches toward the sky with the right hand",
                            "holds the right arm high above the head"],
    "raise-up-both-hands": ["hoists both hands high", "reaches toward the sky with both hands",
                            "holds both arms high above the head"],
    "wave-left-hand": ["greets a friend by flapping the left hand", "says goodbye with the left hand",
                       "shakes the left hand from side to side to say hello"],
    "wave-right-hand": ["greets a friend by flapping the right hand", "says goodbye with the right hand",
                        "shakes the right hand from side to side to say hello"],
    "wave-both-hands": ["greets a friend by flapping both hands", "says goodbye with both hands",
                        "shakes both hands from side to side to say hello"],
}
STYLE_PARAPHRASES = {
    "active": ["full of pep", "with plenty of vigor"],
    "exhausted": ["as though worn out", "like somebody drained after a long day"],
    "feminine": ["with ladylike poise", "in a delicate, girlish fashion"],
    "masculine": ["with a burly, tough swagger", "like a brawny tough guy"],
    "normal": ["in an ordinary, plain fashion", "in a regular everyday fashion"],
    "youthful": ["like a carefree kid", "with the bounce of a child"],
    "elderly": ["like a frail grandpa", "with an aged, hunched body"],
}
SUBJECTS = ["A human", "Somebody", "A figure", "The actor", "An individual"]


class PhrasingError(MotokError, ValueError):
    pass


@dataclass(frozen=True)
class Prompt:
    text: str
    content: str
    style: str | None  # None when the sentence names no style


def is_heldout(caption: str) -> bool:
    """True when the caption uses a held-out wording (and so never trains the GPT)."""
    return _HELDOUT.search(caption.lower()) is not None


def paraphrase_prompts() -> list[Prompt]:
    """Every content paraphrase without a style and with each style paraphrase: 10 x 3 x 15 = 450."""
    out, k = [], 0
    for content, phrases in CONTENT_PARAPHRASES.items():
        for ph in phrases:
            for style, sp in [(None, "")] + [(s, p) for s, ps in STYLE_PARAPHRASES.items() for p in ps]:
                subject = SUBJECTS[k % len(SUBJECTS)]
                k += 1
                out.append(Prompt(f"{subject} {ph}{' ' + sp if sp else ''}.", content, style))
    return out


def caption_prompts(data: str | Path, split: str = "test", heldout: bool = False) -> list[Prompt]:
    """The distinct captions of ``split`` whose wording is held out (``heldout``) or not, with the
    content and style of their clips (every Bandai caption names a style)."""
    from motok.artifacts import read_strings
    from motok.data.dataset import MotionFile

    with MotionFile(data, "motion-dataset") as mf:
        keep = set(mf.split_indices(split))
        labels = read_strings(mf.h5["clips/labels"])
        g = mf.h5["captions"]
        rows = list(zip(g["clip"][()].tolist(), read_strings(g["text"])))
    seen, out = set(), []
    for clip, text in rows:
        lab = json.loads(labels[clip] or "{}") if clip in keep else {}
        if "content" not in lab or is_heldout(text) != heldout:
            continue
        p = Prompt(text, lab["content"], lab.get("style"))
        if p not in seen:
            seen.add(p)
            out.append(p)
    return out


PROMPT_SETS = ("train", "heldout_wordings", "paraphrases")


def prompt_set(name: str, data: str | Path, split: str = "test") -> list[Prompt]:
    """``train``: test captions in training wordings; ``heldout_wordings``: test captions in held-out
    wordings; ``paraphrases``: the hand-written sentences."""
    if name == "train":
        return caption_prompts(data, split, heldout=False)
    if name == "heldout_wordings":
        return caption_prompts(data, split, heldout=True)
    if name == "paraphrases":
        return paraphrase_prompts()
    raise PhrasingError(f"unknown prompt set {name!r}; choose from {', '.join(PROMPT_SETS)}")
