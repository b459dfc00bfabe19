"""Binary visual vocabulary and TF-IDF keyframe database over ORB descriptors.

Why not a DBoW port: the PyPI ports of DBoW2/DBoW3 (``pydbow`` 2022, ``pydbow3`` 2019,
``dbow3py`` 2020) are unmaintained and ship no wheels for Python 3.11 / numpy 2. ``faiss-cpu``
is well kept, but at a few hundred words its binary index only does the exact Hamming search
that OpenCV's ``BFMatcher(NORM_HAMMING)`` already does in C++. So: OpenCV for ORB and word
assignment, a flat vocabulary built by k-majority (k-means in Hamming space, the binary-word
clustering DBoW uses per tree level) trained online on the first keyframes of the run (no
vocabulary file to ship, adapts to the domain), fixed IDF weights from those keyframes, and a
dense L2-normalized TF-IDF matrix whose product with the query is the cosine score (10,000
keyframes x 400 words is 16 MB and ~1 ms per query).
"""

from __future__ import annotations

import cv2
import numpy as np

from metricslam.errors import GraphError


def _hamming_assign(desc: np.ndarray, words: np.ndarray) -> np.ndarray:
    """Nearest word index (N,) for binary descriptors (N, 32) uint8."""
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=False)
    matches = matcher.match(desc, words)
    out = np.empty(len(desc), dtype=np.int64)
    for m in matches:
        out[m.queryIdx] = m.trainIdx
    return out


class BinaryVocabulary:
    """Flat vocabulary of ``k`` binary words (k, 32) uint8 trained by k-majority."""

    def __init__(self, words: np.ndarray, idf: np.ndarray) -> None:
        self.words = np.ascontiguousarray(words, dtype=np.uint8)
        self.idf = np.asarray(idf, dtype=np.float32)

    @property
    def size(self) -> int:
        return int(self.words.shape[0])

    @classmethod
    def train(cls, descriptor_sets: list[np.ndarray], k: int, iterations: int = 8,
              seed: int = 0) -> BinaryVocabulary:
        """k-majority clustering of all descriptors; IDF from the per-image document counts."""
        sets = [d for d in descriptor_sets if d is not None and len(d)]
        if not sets:
            raise GraphError("cannot train a visual vocabulary without ORB descriptors; the images "
                             "may be blank or too small")
        X = np.concatenate(sets).astype(np.uint8)
        k = int(min(k, len(X)))
        rng = np.random.default_rng(seed)
        words = X[rng.choice(len(X), size=k, replace=False)].copy()
        bits = np.unpackbits(X, axis=1).astype(np.float32)  # (N, 256)
        for _ in range(iterations):
            assign = _hamming_assign(X, words)
            counts = np.bincount(assign, minlength=k)
            order = np.argsort(assign, kind="stable")
            alive = counts > 0
            starts = np.concatenate([[0], np.cumsum(counts)[:-1]])[alive]
            sums = np.add.reduceat(bits[order], starts, axis=0)  # per-cluster bit counts
            words[alive] = np.packbits(sums / counts[alive, None] >= 0.5, axis=1)
            dead = np.flatnonzero(~alive)  # re-seed empty clusters
            if dead.size:
                words[dead] = X[rng.choice(len(X), size=dead.size, replace=False)]
        df = np.zeros(k, dtype=np.float32)
        for d in sets:
            df[np.unique(_hamming_assign(d, words))] += 1
        idf = np.log((len(sets) + 1.0) / (df + 1.0)) + 1e-3
        return cls(words, idf)

    def bow(self, desc: np.ndarray) -> np.ndarray:
        """L2-normalized TF-IDF vector (k,) float32 of one image's descriptors."""
        v = np.zeros(self.size, dtype=np.float32)
        if desc is None or len(desc) == 0:
            return v
        w = _hamming_assign(desc, self.words)
        v += np.bincount(w, minlength=self.size).astype(np.float32) / len(w)
        v *= self.idf
        n = float(np.linalg.norm(v))
        return v / n if n > 0 else v


class BowDatabase:
    """Rows of TF-IDF vectors, one per keyframe, in insertion order; cosine-score queries."""

    def __init__(self, n_words: int) -> None:
        self._M = np.zeros((64, n_words), dtype=np.float32)
        self._ids: list[int] = []

    def __len__(self) -> int:
        return len(self._ids)

    def add(self, kf_id: int, v: np.ndarray) -> None:
        if len(self._ids) == self._M.shape[0]:
            self._M = np.vstack([self._M, np.zeros_like(self._M)])
        self._M[len(self._ids)] = v
        self._ids.append(int(kf_id))

    def scores(self, v: np.ndarray, upto: int) -> tuple[np.ndarray, np.ndarray]:
        """Cosine scores of ``v`` against the first ``upto`` rows -> (kf_ids, scores)."""
        upto = max(0, min(upto, len(self._ids)))
        return np.asarray(self._ids[:upto]), self._M[:upto] @ v

    def row(self, i: int) -> np.ndarray:
        return self._M[i]

    def rows(self) -> tuple[np.ndarray, np.ndarray]:
        """Copies of all ``(kf_ids (M,) int64, rows (M, k) float32)``, in insertion order."""
        n = len(self._ids)
        return np.asarray(self._ids, dtype=np.int64), self._M[:n].copy()

    def forget_oldest(self) -> int:
        """Drop the oldest row (positions of the others shift down by one); its keyframe id."""
        kf_id = self._ids.pop(0)
        n = len(self._ids)
        self._M[:n] = self._M[1:n + 1]
        self._M[n] = 0.0
        return kf_id
