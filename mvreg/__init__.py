"""mvreg: global multiview registration of 3D scans with certificates of optimality.

One-call API: ``mvreg.register(folder_or_clouds, **options) -> Registration``.
Staged API: ``mvreg.solver`` (PatchProblem, solve, certify), ``mvreg.pairwise``.
"""

__version__ = "0.1.0"
