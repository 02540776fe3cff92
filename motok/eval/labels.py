"""Label accuracy of motion (``motok eval labels``): does generated motion show the
content and the style its sentence asked for?

A small classifier of the dataset's labels (content and style, the Bandai-Namco set-2 labels or any
``content`` / ``style`` clip labels) is fitted on the real motion of the train split and reports its
own accuracy on the test split; it is then applied to generated motion, and the label accuracy is
the share of clips whose predicted content (style, where the sentence names one) is the requested one.

**Descriptor.** The clip's HumanML3D features (docs/features.md), normalised by the dataset's mean
and std, summarised over time by their mean and standard deviation over the whole clip and their
means over ``segments`` equal parts of it (the order of events: a turn, a raised then lowered arm).
Length-independent, so generated motion of any length is read like real motion. The root's yaw
velocity (channel 0) keeps its sign, which is what separates left from right turns; the arm joints'
root-relative positions separate the hands.

**Classifier.** Multinomial logistic regression per label (content, style) on the standardised
descriptors, L2-penalised, fitted full-batch with L-BFGS (a convex problem: the fit is
deterministic). Training clips are seen whole and as ``crops`` random crops of 60-100 % of their
length, so a shorter or longer generated motion is not out of distribution. Linear on purpose: a
probe that reads what the motion shows, with no capacity to memorise clips, and quick (seconds),
so every report fits it afresh and states its test accuracy beside the numbers it produces.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from motok.data.dataset import MotionFile
from motok.errors import MotokError
from motok.ranges import In

LABELS = ("content", "style")


class LabelsError(MotokError, ValueError):
    pass


@dataclass
class LabelsConfig:
    split: str = "train"  # real motion the classifier is fitted on
    test_split: str = "test"  # real motion it reports its own accuracy on
    segments: In[int, ">= 1"] = 3  # temporal parts whose means join the whole-clip mean and std
    crops: In[int, ">= 0"] = 4  # extra random crops (60-100 % of the clip) per training clip
    weight_decay: In[float, ">= 0"] = 1e-2  # L2 penalty on the weights (mean over samples + wd/2 |W|^2)
    max_iter: In[int, ">= 1"] = 200  # L-BFGS iterations
    seed: In[int, ">= 0"] = 0  # the training crops drawn
    threads: In[int, ">= 0"] = 1  # torch threads (0: torch's default)


def check_config(cfg: LabelsConfig) -> None:
    if cfg.segments < 1:
        raise LabelsError(f"segments {cfg.segments} must be >= 1")
    if cfg.crops < 0:
        raise LabelsError(f"crops {cfg.crops} must be >= 0")
    if cfg.weight_decay < 0:
        raise LabelsError(f"weight_decay {cfg.weight_decay} must be >= 0")


def descriptor(feats: np.ndarray, mean: np.ndarray, std: np.ndarray, segments: int = 3) -> np.ndarray:
    """``(T, D)`` raw features -> ``((2 + segments) * D,)``: mean, std, and per-part means of the
    normalised features."""
    x = (np.asarray(feats, np.float64) - mean) / std
    if len(x) == 0:
        raise LabelsError("a clip has no frames")
    parts = np.array_split(x, segments) if len(x) >= segments else [x] * segments
    return np.concatenate([x.mean(0), x.std(0)] + [p.mean(0) for p in parts]).astype(np.float32)


def _labels_of(raw: str) -> dict:
    d = json.loads(raw) if raw not in ("", "{}") else {}
    return {k: d[k] for k in LABELS if isinstance(d.get(k), str)}


def _read(mf: MotionFile, which: list[int]) -> tuple[list[np.ndarray], list[dict]]:
    from motok.artifacts import read_strings

    labels = read_strings(mf.h5["clips/labels"])
    return [mf.frames("features", i) for i in which], [_labels_of(labels[i]) for i in which]


@dataclass
class LabelClassifier:
    mean: np.ndarray  # feature statistics of the dataset
    std: np.ndarray
    segments: int
    mu: np.ndarray  # descriptor standardisation
    sigma: np.ndarray
    classes: dict  # label -> list of class names
    weights: dict  # label -> (W (C, F), b (C,))
    test_accuracy: dict  # label -> accuracy on the real test split
    test_clips: int

    def predict(self, clips: list[np.ndarray]) -> dict[str, list[str]]:
        X = (np.stack([descriptor(c, self.mean, self.std, self.segments) for c in clips]) - self.mu) / self.sigma
        out = {}
        for lab, (W, b) in self.weights.items():
            out[lab] = [self.classes[lab][k] for k in (X @ W.T + b).argmax(1)]
        return out


def _fit_logreg(X: np.ndarray, y: np.ndarray, n_classes: int, cfg: LabelsConfig) -> tuple[np.ndarray, np.ndarray]:
    import torch

    torch.manual_seed(cfg.seed)
    Xt, yt = torch.from_numpy(X).double(), torch.from_numpy(y).long()
    W = torch.zeros(n_classes, X.shape[1], dtype=torch.float64, requires_grad=True)
    b = torch.zeros(n_classes, dtype=torch.float64, requires_grad=True)
    opt = torch.optim.LBFGS([W, b], lr=1.0, max_iter=cfg.max_iter, line_search_fn="strong_wolfe",
                            tolerance_grad=1e-9, tolerance_change=1e-12)

    def closure():
        opt.zero_grad()
        loss = torch.nn.functional.cross_entropy(Xt @ W.T + b, yt) + 0.5 * cfg.weight_decay * (W * W).sum()
        loss.backward()
        return loss

    opt.step(closure)
    return W.detach().numpy().astype(np.float32), b.detach().numpy().astype(np.float32)


def fit_classifier(data: str | Path, cfg: LabelsConfig | None = None) -> LabelClassifier:
    """Fit on the real motion of ``cfg.split`` and measure on ``cfg.test_split`` (module docstring)."""
    import torch

    cfg = cfg or LabelsConfig()
    check_config(cfg)
    if cfg.threads > 0:
        torch.set_num_threads(cfg.threads)
    with MotionFile(data, "motion-dataset") as mf:
        mean, std = mf.stats()
        train_idx, test_idx = mf.split_indices(cfg.split), mf.split_indices(cfg.test_split)
        if not train_idx or not test_idx:
            raise LabelsError(f"{data}: split {cfg.split!r} or {cfg.test_split!r} is empty "
                              f"(splits: {sorted(set(mf.splits))})")
        tr_clips, tr_labels = _read(mf, train_idx)
        te_clips, te_labels = _read(mf, test_idx)
    mean, std = np.asarray(mean, np.float64), np.maximum(np.asarray(std, np.float64), 1e-8)
    rng = np.random.default_rng([cfg.seed, 18])
    X, rows = [], []
    for k, c in enumerate(tr_clips):
        views = [c]
        for _ in range(cfg.crops):
            n = max(1, int(round(len(c) * rng.uniform(0.6, 1.0))))
            a = int(rng.integers(0, len(c) - n + 1))
            views.append(c[a:a + n])
        X += [descriptor(v, mean, std, cfg.segments) for v in views]
        rows += [k] * len(views)
    X = np.stack(X)
    mu, sigma = X.mean(0), X.std(0) + 1e-6
    Xs = (X - mu) / sigma
    clf = LabelClassifier(mean, std, cfg.segments, mu, sigma, {}, {}, {}, len(te_clips))
    for lab in LABELS:
        have = [r for r in range(len(rows)) if lab in tr_labels[rows[r]]]
        if not have:
            continue
        names = sorted({tr_labels[rows[r]][lab] for r in have})
        y = np.array([names.index(tr_labels[rows[r]][lab]) for r in have])
        clf.classes[lab] = names
        clf.weights[lab] = _fit_logreg(Xs[have], y, len(names), cfg)
    if not clf.weights:
        raise LabelsError(f"{data}: no clip of split {cfg.split!r} has a content or style label")
    pred = clf.predict(te_clips)
    for lab in clf.weights:
        pairs = [(p, t[lab]) for p, t in zip(pred[lab], te_labels) if lab in t]
        clf.test_accuracy[lab] = float(np.mean([p == t for p, t in pairs])) if pairs else float("nan")
    return clf


def expected_labels(mf: MotionFile, which: list[int], lookup: dict[str, dict] | None = None) -> list[dict]:
    """What each clip asked for: its own ``content`` / ``style`` labels, else what ``lookup`` says of
    its first caption (a caption text -> labels map, e.g. the dataset's own and the phrasings')."""
    _, labs = _read(mf, which)
    out = []
    for i, lab in zip(which, labs):
        if not lab and lookup:
            caps = mf.captions(i)
            lab = dict(lookup.get(caps[0][0], {})) if caps else {}
        out.append(lab)
    return out


def caption_lookup(data: str | Path) -> dict[str, dict]:
    """Caption text -> labels for the dataset's captions (only texts with one label set) and the
    hand-written paraphrases of :mod:`motok.text.phrasings`."""
    from motok.artifacts import read_strings
    from motok.text.phrasings import paraphrase_prompts

    with MotionFile(data, "motion-dataset") as mf:
        labels = read_strings(mf.h5["clips/labels"])
        g = mf.h5["captions"]
        rows = list(zip(g["clip"][()].tolist(), read_strings(g["text"])))
    seen: dict[str, set] = {}
    for clip, text in rows:
        seen.setdefault(text, set()).add(json.dumps(_labels_of(labels[clip]), sort_keys=True))
    table = {t: json.loads(next(iter(v))) for t, v in seen.items() if len(v) == 1}
    for p in paraphrase_prompts():
        table[p.text] = {"content": p.content, **({"style": p.style} if p.style else {})}
    return table


def score(pred: dict[str, list[str]], expected: list[dict]) -> dict:
    """Label accuracy: per label, the share of clips that name it whose prediction matches, with
    counts and the accuracy per requested class (where left/right or one/both hands go wrong)."""
    out = {}
    for lab, ps in pred.items():
        pairs = [(p, e[lab]) for p, e in zip(ps, expected) if lab in e]
        per: dict[str, list[bool]] = {}
        for p, t in pairs:
            per.setdefault(t, []).append(p == t)
        out[lab] = {"accuracy": float(np.mean([p == t for p, t in pairs])) if pairs else None,
                    "clips": len(pairs),
                    "per_class": {k: round(float(np.mean(v)), 4) for k, v in sorted(per.items())}}
    out["clips"] = len(expected)
    out["unlabelled"] = sum(1 for e in expected if not e)
    return out


def evaluate_motions(clf: LabelClassifier, path: str | Path, lookup: dict[str, dict] | None = None) -> dict:
    """Label accuracy of every clip of a motion artifact, grouped by the clips' ``prompt_set``
    label when they carry one (``motok eval labels --gpt`` writes it), plus all clips together."""
    with MotionFile(path) as mf:
        which = list(range(len(mf)))
        clips, raw = _read(mf, which)
        expected = expected_labels(mf, which, lookup)
        from motok.artifacts import read_strings
        sets = [json.loads(x or "{}").get("prompt_set", "") for x in read_strings(mf.h5["clips/labels"])]
    if not clips:
        raise LabelsError(f"{path}: no clips")
    if all(not e for e in expected):
        raise LabelsError(f"{path}: no clip says what it should show (no content/style labels and no caption "
                          f"known to the dataset or the phrasings)")
    pred = clf.predict(clips)
    rows = {"all": score(pred, expected)}
    for name in sorted({s for s in sets if s}):
        keep = [k for k, s in enumerate(sets) if s == name]
        rows[name] = score({lab: [v[k] for k in keep] for lab, v in pred.items()}, [expected[k] for k in keep])
    return rows


def save_classifier(clf: LabelClassifier, path: str | Path, key: str) -> Path:
    """Arrays in a ``.npz`` (read back without pickle), names and accuracies as JSON inside it."""
    from motok.atomic import atomic_path

    meta = {"key": key, "segments": clf.segments, "classes": clf.classes, "test_accuracy": clf.test_accuracy,
            "test_clips": clf.test_clips}
    arrays = {"mean": clf.mean, "std": clf.std, "mu": clf.mu, "sigma": clf.sigma,
              "meta": np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)}
    for lab, (W, b) in clf.weights.items():
        arrays[f"W_{lab}"], arrays[f"b_{lab}"] = W, b
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)
    return Path(path)


def load_classifier(path: str | Path, key: str) -> LabelClassifier | None:
    """The classifier saved at ``path`` if it was fitted with the same ``key`` (data hash and config)."""
    path = Path(path)
    if not path.exists():
        return None
    with np.load(path, allow_pickle=False) as z:
        meta = json.loads(z["meta"].tobytes().decode())
        if meta.get("key") != key:
            return None
        weights = {lab: (z[f"W_{lab}"], z[f"b_{lab}"]) for lab in meta["classes"]}
        return LabelClassifier(z["mean"], z["std"], int(meta["segments"]), z["mu"], z["sigma"], meta["classes"],
                               weights, meta["test_accuracy"], int(meta["test_clips"]))


def classifier_for(data: str | Path, cfg: LabelsConfig, cache: str | Path | None = None) -> LabelClassifier:
    """:func:`fit_classifier`, reusing ``cache`` when it holds the fit of this dataset and config."""
    if cache is None:
        return fit_classifier(data, cfg)
    from motok.artifacts import hash_inputs

    key = json.dumps({"data": hash_inputs([Path(data)])[str(Path(data))], "config": cfg.__dict__}, sort_keys=True)
    clf = load_classifier(cache, key)
    if clf is None:
        clf = fit_classifier(data, cfg)
        save_classifier(clf, cache, key)
    return clf
