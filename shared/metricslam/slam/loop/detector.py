"""``LoopDetector``: per keyframe, ORB bag-of-words retrieval then geometric verification.

Candidates are keyframes older than the ``skip_recent_keyframes`` most recent indexed ones (every
``keyframe_stride``-th keyframe is indexed) whose cosine
score reaches ``min_score_ratio`` times the score of the query against its immediate predecessor
(DBoW2's normalization: what "similar" means depends on the scene), best first, at most
``n_candidates``; each is verified with :func:`metricslam.slam.loop.verification.verify`.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from metricslam.camera import PinholeCamera
from metricslam.depth.model import to_gray_u8
from metricslam.slam.graph.config import LoopConfig
from metricslam.slam.loop.verification import LandmarkFeatures, landmark_features, verify
from metricslam.slam.loop.vocabulary import BinaryVocabulary, BowDatabase


@dataclass(frozen=True)
class LoopCandidate:
    """A verified loop: ``S_old_new`` (4, 4) maps the new keyframe's frame/units into the old's."""

    kf_old: int
    kf_new: int
    S_old_new: np.ndarray
    n_inliers: int
    score: float


class LoopDetector:
    """Place recognition over keyframes (see module docstring). Not thread-safe."""

    def __init__(self, config: LoopConfig | None = None, seed: int = 0) -> None:
        self.config = config or LoopConfig()
        self._calls = 0
        self._orb = cv2.ORB_create(nfeatures=self.config.n_orb_features, nlevels=4, fastThreshold=12)
        self._orb_landmarks = cv2.ORB_create(nlevels=1)
        self._fast = cv2.FastFeatureDetector_create(threshold=20, nonmaxSuppression=True)
        self._vocab: BinaryVocabulary | None = None
        self._db: BowDatabase | None = None
        self._pending: list[tuple[int, np.ndarray]] = []  # (kf_id, ORB descriptors) before training
        self._features: dict[int, LandmarkFeatures] = {}
        self._order: list[int] = []
        self._last_loop_at = -10**9
        self._rng = np.random.default_rng(seed)
        self.n_queries = 0
        self.n_verified = 0

    def add_and_query(self, kf_id: int, image: np.ndarray, camera: PinholeCamera,
                      landmarks_uv_px: np.ndarray, landmarks_inv_depth: np.ndarray) -> list[LoopCandidate]:
        """Add keyframe ``kf_id`` and return verified loops to older keyframes (maybe empty).

        Only every ``keyframe_stride``-th call does any work (consecutive keyframes see nearly
        the same place; a revisit spans many keyframes).
        """
        self._calls += 1
        if (self._calls - 1) % self.config.keyframe_stride:
            return []
        gray = to_gray_u8(image)
        f = self.config.image_scale
        # retrieval: ORB detection costs per pixel, so it runs on a downscaled image; landmark
        # descriptors (verification) stay at full resolution with a single-level ORB (cheap)
        small = gray if f == 1.0 else cv2.resize(
            gray, (round(gray.shape[1] * f), round(gray.shape[0] * f)), interpolation=cv2.INTER_AREA)
        _, desc = self._orb.detectAndCompute(small, None)
        desc = desc if desc is not None else np.zeros((0, 32), np.uint8)
        extra = None
        if self.config.fast_corners > 0:
            kps = self._fast.detect(gray, None)
            kps = sorted(kps, key=lambda k: -k.response)[: self.config.fast_corners]
            extra = np.array([k.pt for k in kps], dtype=float).reshape(-1, 2)
        self._features[kf_id] = landmark_features(self._orb_landmarks, gray, camera, landmarks_uv_px,
                                                  landmarks_inv_depth, extra_uv_px=extra)
        self._order.append(kf_id)
        if self._vocab is None:
            self._pending.append((kf_id, desc))
            if len(self._pending) >= self.config.vocabulary_train_keyframes:
                self._vocab = BinaryVocabulary.train([d for _, d in self._pending],
                                                     self.config.vocabulary_words)
                self._db = BowDatabase(self._vocab.size)
                for k, d in self._pending:
                    self._db.add(k, self._vocab.bow(d))
                self._pending = []
            return []
        v = self._vocab.bow(desc)
        self._db.add(kf_id, v)
        n = len(self._db)
        self.n_queries += 1
        cfg = self.config
        if n - 1 <= cfg.skip_recent_keyframes or n - 1 - self._last_loop_at < cfg.min_keyframes_between_loops:
            return []
        ref = float(self._db.row(n - 2) @ v)
        if ref <= 0:
            return []
        ids, scores = self._db.scores(v, upto=n - 1 - cfg.skip_recent_keyframes)
        order = np.argsort(-scores)[: cfg.n_candidates]
        out: list[LoopCandidate] = []
        for i in order:
            if scores[i] < cfg.min_score_ratio * ref:
                break
            old = int(ids[i])
            res = verify(self._features[kf_id], self._features[old], camera, cfg, self._rng)
            if res is not None:
                out.append(LoopCandidate(old, kf_id, res.S_old_new, res.n_inliers, float(scores[i])))
                self._last_loop_at = n - 1
                self.n_verified += 1
                break
        return out
