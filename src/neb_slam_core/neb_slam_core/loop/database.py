"""An inverted-index database of keyframes' bag-of-words vectors.

For every word the index keeps the keyframes whose vector contains it and their weights there (a
posting list). The L1 score of a query ``q`` against keyframe ``v`` is ``sum_w min(q_w, v_w)`` over the
words they share (:func:`~.vocabulary.l1_score`), so a query visits only the posting lists of its own
words and scores only the keyframes found there: time proportional to the (word, keyframe) pairs it
has in common with the database, not to the number of keyframes.

Posting lists are numpy arrays that grow by doubling (amortised O(1) per appended entry); a query
concatenates the lists of its words and accumulates ``min(q_w, v_w)`` per keyframe with one
``np.bincount``. Keyframes are numbered densely in insertion order inside the database; callers use
their own integer ids.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .vocabulary import BowVector, l1_score

_INITIAL_CAPACITY = 4


@dataclass(frozen=True)
class QueryResult:
    """Keyframes that share words with a query, best first.

    Attributes:
        keyframe_ids: ``(n,)`` int64 caller ids.
        scores: ``(n,)`` float64 L1 scores in (0, 1], decreasing (ties: earlier keyframe first).
    """

    keyframe_ids: np.ndarray
    scores: np.ndarray

    def __len__(self) -> int:
        return len(self.keyframe_ids)


class KeyframeDatabase:
    """Inverted index over the words of a vocabulary of ``n_words`` words."""

    def __init__(self, n_words: int):
        self.n_words = int(n_words)
        self._post_kf: list[np.ndarray | None] = [None] * self.n_words  # dense keyframe index per entry
        self._post_w: list[np.ndarray | None] = [None] * self.n_words  # float32 weight per entry
        self._post_n = np.zeros(self.n_words, dtype=np.int64)  # entries in use per word
        self._ids: list[int] = []  # dense index -> caller id
        self._index: dict[int, int] = {}  # caller id -> dense index
        self._vectors: list[BowVector] = []

    def __len__(self) -> int:
        return len(self._ids)

    def __contains__(self, keyframe_id: int) -> bool:
        return int(keyframe_id) in self._index

    @property
    def keyframe_ids(self) -> np.ndarray:
        """``(n,)`` int64 caller ids in insertion order."""
        return np.asarray(self._ids, dtype=np.int64)

    def vector(self, keyframe_id: int) -> BowVector:
        """The stored vector of ``keyframe_id`` (KeyError when absent)."""
        return self._vectors[self._index[int(keyframe_id)]]

    def add(self, keyframe_id: int, bow: BowVector) -> None:
        """Insert a keyframe's vector; ``keyframe_id`` must be new."""
        keyframe_id = int(keyframe_id)
        if keyframe_id in self._index:
            raise ValueError(f"KeyframeDatabase.add: keyframe {keyframe_id} is already in the database")
        if len(bow) and (bow.word_ids.min() < 0 or bow.word_ids.max() >= self.n_words):
            raise ValueError(f"KeyframeDatabase.add: word ids outside 0..{self.n_words - 1}")
        dense = len(self._ids)
        self._ids.append(keyframe_id)
        self._index[keyframe_id] = dense
        self._vectors.append(bow)
        # One Python step per word of the new keyframe: insertion is O(words in the keyframe).
        for w, weight in zip(bow.word_ids.tolist(), bow.weights.tolist()):
            n = self._post_n[w]
            kf = self._post_kf[w]
            if kf is None or n == len(kf):
                cap = _INITIAL_CAPACITY if kf is None else 2 * len(kf)
                new_kf = np.empty(cap, dtype=np.int32)
                new_w = np.empty(cap, dtype=np.float32)
                if kf is not None:
                    new_kf[:n] = kf[:n]
                    new_w[:n] = self._post_w[w][:n]
                self._post_kf[w], self._post_w[w] = new_kf, new_w
            self._post_kf[w][n] = dense
            self._post_w[w][n] = weight
            self._post_n[w] = n + 1

    def query(
        self, bow: BowVector, max_results: int | None = None, exclude_ids: np.ndarray | list[int] | None = None
    ) -> QueryResult:
        """Keyframes sharing at least one word with ``bow``, by decreasing L1 score.

        Args:
            max_results: keep only this many best (None: all).
            exclude_ids: caller ids left out of the result (e.g. the query's temporal neighbours).
        """
        empty = QueryResult(np.zeros(0, np.int64), np.zeros(0, np.float64))
        if len(bow) == 0 or not self._ids:
            return empty
        lengths = self._post_n[bow.word_ids]
        hit = np.flatnonzero(lengths)
        if hit.size == 0:
            return empty
        words = bow.word_ids[hit].tolist()
        kf = np.concatenate([self._post_kf[w][:n] for w, n in zip(words, lengths[hit].tolist())])
        w = np.concatenate([self._post_w[w][:n] for w, n in zip(words, lengths[hit].tolist())])
        q = np.repeat(bow.weights[hit], lengths[hit])
        # The dense accumulator of len(self) floats is one zero-fill (a memset): the work per query is
        # the concatenated postings; a sort-based np.unique compaction costs more at every size we use.
        scores = np.bincount(kf, weights=np.minimum(q, w), minlength=len(self._ids))
        found = np.flatnonzero(scores > 0)
        if exclude_ids is not None and len(exclude_ids):
            drop = [self._index[i] for i in np.asarray(exclude_ids, dtype=np.int64).tolist() if i in self._index]
            found = np.setdiff1d(found, np.asarray(drop, dtype=np.int64), assume_unique=True)
        s = scores[found]
        if max_results is not None and len(found) > max_results:
            top = np.argpartition(-s, max_results - 1)[:max_results]
            found, s = found[top], s[top]
        order = np.lexsort((found, -s))  # score descending, then insertion order
        return QueryResult(np.array([self._ids[i] for i in found[order].tolist()], dtype=np.int64), s[order])

    def score(self, keyframe_a: int, keyframe_b: int) -> float:
        """L1 score between two stored keyframes."""
        return l1_score(self.vector(keyframe_a), self.vector(keyframe_b))
