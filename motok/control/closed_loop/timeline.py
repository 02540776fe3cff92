"""Prompts over time and the re-plan schedule of the closed loop (:mod:`motok.control.closed_loop.loop`).

Everything here is counted in motion tokens. The tokenizer turns ``rate`` frames at the motion's
``fps`` into one token (0.2 s for Bandai-Namco: 4 frames at 20 fps) and the GPT continues a
sequence of whole tokens, so a plan can only be continued from a token boundary: re-plans, prompt
switches and lengths fall on them, and the physics re-plans on the control step that falls on one
(6 steps of 30 Hz per token). A time that is not on a boundary is refused rather than rounded, so
what the report says happened is what was asked.

A motion (:class:`Row`) has its prompts as ``(start token, text)``, the first at 0. Its plans are
re-made at the earliest of: the next multiple of ``every`` tokens (``--replan-every``), the next
prompt switch, and one token before the current plan runs out (a motion longer than the GPT's
positions is planned piece by piece: :func:`plan_window`).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field

from motok.errors import UserError

TOL = 1e-6  # seconds: a time within this of a token boundary is on it


@dataclass(frozen=True)
class Clock:
    """The token grid: ``rate`` frames per token at ``fps``, ``control_hz`` physics steps per
    second, and the GPT's ``max_codes`` positions."""

    fps: float
    rate: int
    control_hz: float
    max_codes: int

    @property
    def token_seconds(self) -> float:
        return self.rate / self.fps

    @property
    def steps_per_token(self) -> int:
        steps = self.token_seconds * self.control_hz
        if abs(steps - round(steps)) > 1e-6:
            raise UserError(f"the control rate {self.control_hz:g} Hz does not step on token boundaries "
                            f"({self.rate} frames at {self.fps:g} fps = {self.token_seconds:g} s per token): "
                            f"the closed loop needs a whole number of control steps per token")
        return int(round(steps))

    def tokens(self, seconds: float, option: str) -> int:
        """``seconds`` as a whole number of tokens, or a one-line error naming ``option``."""
        n = seconds / self.token_seconds
        if not math.isfinite(seconds) or seconds <= 0 or abs(n - round(n)) * self.token_seconds > TOL:
            raise UserError(f"{option} {seconds:g}: expected a positive multiple of the token duration "
                            f"{self.token_seconds:g} s ({self.rate} frames at {self.fps:g} fps), where plans "
                            f"can be continued")
        return int(round(n))

    def length(self, seconds: float | None) -> int:
        """Tokens of a motion of ``seconds`` (rounded as ``gpt sample --seconds`` rounds); the GPT's
        longest (``max_codes``) when None."""
        if seconds is None:
            return self.max_codes
        if not (math.isfinite(seconds) and seconds > 0):
            raise UserError(f"--seconds {seconds:g}: expected a length > 0")
        return max(1, round(seconds * self.fps / self.rate))


@dataclass
class Row:
    """One motion of the closed loop: its clip name, prompts ``(start token, text)`` (the first at
    0), length in tokens, the seed of its draws, and the labels and captions its clips carry."""

    name: str
    prompts: list[tuple[int, str]]
    tokens: int
    seed: int
    labels: dict = field(default_factory=dict)
    captions: list = field(default_factory=list)
    split: str = "none"

    def text_at(self, token: int) -> str:
        return [t for start, t in self.prompts if start <= token][-1]

    @property
    def switches(self) -> list[int]:
        return [start for start, _ in self.prompts[1:]]


THEN = re.compile(r"^\s*([0-9]*\.?[0-9]+)\s*s?(?:\s+(.*?))?\s*$", re.S)


def parse_then(then: list[str]) -> list[tuple[float, str]]:
    """``--then "TIME TEXT"`` values (``"4s a person waves"``, ``"4 a person waves"``) as
    ``(seconds, text)``, checked: times increasing from above 0, texts not empty."""
    out = []
    for value in then:
        m = THEN.match(str(value))
        if not m:
            raise UserError(f"--then {value!r}: expected a time in seconds, then the text, in one argument: "
                            f"--then \"4s a person waves\"")
        t, text = float(m.group(1)), (m.group(2) or "").strip()
        if not text:
            raise UserError(f"--then {value!r}: the text is empty; give the sentence the motion turns to")
        if t <= 0 or (out and t <= out[-1][0]):
            after = f"after the previous --then ({out[-1][0]:g} s)" if out else "after 0 s (the first --text)"
            raise UserError(f"--then {value!r}: expected times that increase, this one {after}")
        out.append((t, text))
    return out


def timeline_prompts(text: str, then: list[tuple[float, str]], clock: Clock, tokens: int) -> list[tuple[int, str]]:
    """The prompts of one timeline in tokens, checked against the token grid and the length."""
    prompts = [(0, text)]
    for t, txt in then:
        n = clock.tokens(t, "--then")
        if n >= tokens:
            raise UserError(f"--then {t:g}s: expected a time before the end of the motion "
                            f"({tokens * clock.token_seconds:g} s; --seconds sets it)")
        prompts.append((n, txt))
    return prompts


def timeline_rows(texts: list[str], then: list[tuple[float, str]], clock: Clock, seconds: float | None,
                  num_samples: int, seed: int) -> list[Row]:
    """The motions ``gpt sample --closed-loop`` makes: ``num_samples`` per text (named and seeded
    as ``gpt sample`` names and seeds them), or per timeline when ``then`` continues one text."""
    from motok.gpt.sample import sample_name

    if then and len(texts) != 1:
        raise UserError(f"--then continues one --text; {len(texts)} texts were given")
    tokens = clock.length(seconds)
    rows = []
    for i, text in enumerate(texts):
        prompts = timeline_prompts(text, then, clock, tokens) if then else [(0, text)]
        ends = [s for s, _ in prompts[1:]] + [tokens]
        caps = [(txt, "", 0.0, 0.0) for _, txt in prompts] if len(prompts) == 1 else \
            [(txt, "", s * clock.token_seconds, e * clock.token_seconds) for (s, txt), e in zip(prompts, ends)]
        for j in range(num_samples):
            labels = {"text": text, "sample": j, "seed": seed + j}
            if len(prompts) > 1:
                labels["prompts"] = [[round(s * clock.token_seconds, 6), txt] for s, txt in prompts]
            rows.append(Row(sample_name(i, text, j), prompts, tokens, seed + j, labels, caps))
    return rows


def plan_window(token: int, total: int, max_codes: int) -> tuple[int, int]:
    """``(context, horizon)`` in tokens of a plan made at ``token`` of a motion of ``total``: the
    GPT continues ``context`` tokens of the simulated motion with ``horizon`` new ones. While the
    whole motion fits the GPT's positions the context is everything simulated so far and the plan
    reaches the end (the positions mean what they meant in training: time since the start);
    beyond, the last half of the positions hold the context and the plan reaches as far as the
    rest allow."""
    remaining = total - token
    if token + remaining <= max_codes:
        return token, remaining
    context = min(token, max_codes // 2)
    return context, min(remaining, max_codes - context)


def next_replan(start: int, end: int, row: Row, every: int | None) -> int | None:
    """The token at which the plan made at ``start`` (reaching ``end``) of ``row`` is re-made: the
    next multiple of ``every``, the next prompt switch, or one token before the plan runs out;
    None when the plan is tracked to the end of the motion."""
    candidates = [w for w in row.switches if w > start]
    if every:
        candidates.append((start // every + 1) * every)
    if end < row.tokens:
        candidates.append(max(end - 1, start + 1))
    n = min(candidates, default=None)
    return n if n is not None and n < min(end, row.tokens) else None
