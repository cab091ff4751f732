"""mvreg: global multiview registration of 3D scans with certificates of optimality.

One-call API: ``mvreg.register(folder_or_clouds, **options) -> Registration``.
Staged API: ``mvreg.solver`` (PatchProblem, solve, certify), ``mvreg.pairwise``.
"""

__version__ = "0.1.0"
__all__ = ["Registration", "register", "__version__"]


def __getattr__(name):  # lazy: `import mvreg` stays light (no open3d until needed)
    if name in ("register", "Registration"):
        from mvreg import pipeline

        return getattr(pipeline, name)
    raise AttributeError(f"module 'mvreg' has no attribute {name!r}")
