"""Inverted-index keyframe database: the same scores as a brute-force dense computation."""

from __future__ import annotations

import numpy as np
import pytest

from neb_slam_core.loop.database import KeyframeDatabase
from neb_slam_core.loop.vocabulary import BowVector, l1_score

N_WORDS = 300


def random_bow(rng: np.random.Generator, n: int) -> BowVector:
    ids = np.sort(rng.choice(N_WORDS, size=n, replace=False)).astype(np.int32)
    w = rng.uniform(0.1, 1.0, n)
    return BowVector(ids, w / w.sum())


def brute_force(query: BowVector, vectors: list[BowVector]) -> np.ndarray:
    """DBoW's L1 score by its definition, on dense vectors: 1 - |q - v|_1 / 2."""
    q = query.dense(N_WORDS)
    return np.array([1.0 - 0.5 * np.abs(q - v.dense(N_WORDS)).sum() for v in vectors])


def test_inverted_index_scores_equal_the_dense_computation():
    rng = np.random.default_rng(0)
    vectors = [random_bow(rng, int(rng.integers(5, 40))) for _ in range(60)]
    db = KeyframeDatabase(N_WORDS)
    ids = [100 + 3 * i for i in range(len(vectors))]  # caller ids need not be dense
    for i, v in zip(ids, vectors):
        db.add(i, v)
    for _ in range(10):
        q = random_bow(rng, 30)
        expected = brute_force(q, vectors)
        result = db.query(q)
        got = dict(zip(result.keyframe_ids.tolist(), result.scores.tolist()))
        # every keyframe with a word in common, and only those, with the dense score
        sharing = [i for i, v in zip(ids, vectors) if np.intersect1d(v.word_ids, q.word_ids).size]
        assert sorted(got) == sorted(sharing)
        for i, s in zip(ids, expected):
            # the postings keep float32 weights: a sum of at most 40 of them is within 1e-6 of float64's
            assert got.get(i, 0.0) == pytest.approx(s, abs=1e-6)
        assert np.all(np.diff(result.scores) <= 0)  # best first


def test_a_keyframe_queried_with_its_own_vector_scores_one():
    rng = np.random.default_rng(1)
    db = KeyframeDatabase(N_WORDS)
    vectors = [random_bow(rng, 20) for _ in range(5)]
    for i, v in enumerate(vectors):
        db.add(i, v)
    result = db.query(vectors[3])
    assert result.keyframe_ids[0] == 3 and result.scores[0] == pytest.approx(1.0)
    assert db.score(3, 3) == pytest.approx(1.0)
    assert db.score(1, 2) == pytest.approx(l1_score(vectors[1], vectors[2]))


def test_hand_worked_scores_top_k_and_exclusion():
    db = KeyframeDatabase(10)
    db.add(0, BowVector(np.array([1, 2]), np.array([0.5, 0.5])))
    db.add(1, BowVector(np.array([2, 3]), np.array([0.25, 0.75])))
    db.add(2, BowVector(np.array([4]), np.array([1.0])))
    db.add(3, BowVector(np.array([1, 3]), np.array([0.5, 0.5])))
    q = BowVector(np.array([1, 2]), np.array([0.5, 0.5]))
    r = db.query(q)
    # kf 0: min(.5,.5)+min(.5,.5) = 1; kf 3: min(.5,.5) = .5 on word 1; kf 1: min(.5,.25) = .25; kf 2: nothing
    assert r.keyframe_ids.tolist() == [0, 3, 1] and r.scores.tolist() == pytest.approx([1.0, 0.5, 0.25])
    r = db.query(q, max_results=2)
    assert r.keyframe_ids.tolist() == [0, 3]
    r = db.query(q, max_results=2, exclude_ids=[0, 99])
    assert r.keyframe_ids.tolist() == [3, 1]
    assert len(db.query(BowVector.empty())) == 0
    assert len(db.query(BowVector(np.array([9]), np.array([1.0])))) == 0
    assert len(db) == 4 and 2 in db and 7 not in db


def test_adding_a_keyframe_twice_or_foreign_words_is_refused():
    db = KeyframeDatabase(10)
    db.add(0, BowVector(np.array([1]), np.array([1.0])))
    with pytest.raises(ValueError, match="already"):
        db.add(0, BowVector(np.array([2]), np.array([1.0])))
    with pytest.raises(ValueError, match="word ids"):
        db.add(1, BowVector(np.array([10]), np.array([1.0])))


def test_posting_lists_grow_past_their_capacity():
    db = KeyframeDatabase(3)
    for i in range(100):  # word 0 in every keyframe: its list is reallocated several times
        db.add(i, BowVector(np.array([0, 1 + i % 2]), np.array([0.5, 0.5])))
    r = db.query(BowVector(np.array([0]), np.array([1.0])))
    assert len(r) == 100 and r.scores.tolist() == pytest.approx([0.5] * 100)
    assert r.keyframe_ids.tolist() == list(range(100))  # ties: insertion order
