"""Loop closure, place recognition half: ORB features, a vocabulary tree over binary descriptors,
an inverted-index keyframe database and the paper's loop query with a geometric check.

Modules: :mod:`.features` (ORB per image), :mod:`.vocabulary` (tree, TF-IDF, L1 score, file format,
training), :mod:`.database` (inverted index), :mod:`.detector` (the query rule and the geometric check).
The shipped vocabulary lives in ``data/`` and is rebuilt by ``neb-slam vocab train``.
"""

from .database import KeyframeDatabase, QueryResult
from .detector import (
    GeometricCheck,
    KeyframeFeatures,
    LoopCandidate,
    LoopDetection,
    LoopDetector,
    LoopQuery,
    match_descriptors,
)
from .features import OrbExtractor, OrbFeatures, OrbParams
from .vocabulary import (
    BowVector,
    Vocabulary,
    hamming_distance,
    l1_score,
    load_vocabulary,
    majority_centre,
    shipped_vocabulary_path,
    train_vocabulary,
)

__all__ = [
    "BowVector",
    "GeometricCheck",
    "KeyframeDatabase",
    "KeyframeFeatures",
    "LoopCandidate",
    "LoopDetection",
    "LoopDetector",
    "LoopQuery",
    "OrbExtractor",
    "OrbFeatures",
    "OrbParams",
    "QueryResult",
    "Vocabulary",
    "hamming_distance",
    "l1_score",
    "load_vocabulary",
    "majority_centre",
    "match_descriptors",
    "shipped_vocabulary_path",
    "train_vocabulary",
]
