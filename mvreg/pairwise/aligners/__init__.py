"""Pairwise aligners by name: the interface and registry (:mod:`.base`) and the methods.

Importing this package registers every method below in :data:`ALIGNERS`; a new method
is one new module here plus one import line in the registry block (see :mod:`.base`).
"""

from mvreg.pairwise.aligners.base import (
    ALIGNERS,
    AlignerFactory,
    PairwiseAligner,
    make_aligner,
    register_aligner,
)

# The registry: one line per method.
from mvreg.pairwise.aligners.feature_ransac import FeatureRansacAligner, align_pair
from mvreg.pairwise.aligners.icp_guess import IcpGuessAligner
from mvreg.pairwise.aligners.rotation_search import RotationSearchAligner, search_pair

__all__ = [
    "ALIGNERS",
    "AlignerFactory",
    "FeatureRansacAligner",
    "IcpGuessAligner",
    "PairwiseAligner",
    "RotationSearchAligner",
    "align_pair",
    "make_aligner",
    "register_aligner",
    "search_pair",
]
