"""peers_*.png: accuracy and time per method (bunny, synthetic sets, patch problems)."""

from __future__ import annotations

import numpy as np

from bench.peers.settings import REFERENCE, ROT_OK_DEG, ordered_methods


def plots(a, bunny, synth, patches) -> list[str]:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return []
    out = []
    if bunny:
        ok = [r for r in bunny if "rot_max" in r and r["method"] != REFERENCE]
        ms = [r["method"] for r in ok]
        fig, ax = plt.subplots(1, 3, figsize=(13, 4.2))
        y = np.arange(len(ms))
        ax[0].barh(y, [max(r["rot_max"], 1e-4) for r in ok])
        ax[0].set_xscale("log")
        ax[0].set_xlabel("max rotation error (deg)")
        ax[1].barh(y, [max(r["tr_max"], 1e-4) for r in ok])
        ax[1].set_xscale("log")
        ax[1].set_xlabel("max translation error (mm)")
        ax[2].barh(y - 0.2, [r["pairwise_s"] for r in ok], 0.4, label="pairwise")
        ax[2].barh(y + 0.2, [r["global_s"] for r in ok], 0.4, label="global")
        ax[2].set_xlabel("wall time (s)")
        ax[2].legend()
        for x in ax:
            x.set_yticks(y)
            x.set_yticklabels(ms if x is ax[0] else [])
            x.invert_yaxis()
            x.grid(True, axis="x", alpha=0.3)
        fig.suptitle("Ten real Stanford Bunny scans vs bun.conf")
        fig.tight_layout()
        fig.savefig(a.out / "peers_bunny.png", dpi=110)
        plt.close(fig)
        out.append("peers_bunny.png")
    if synth:
        fig, ax = plt.subplots(figsize=(8, 5.5))
        style = {
            "mvreg": ("o", "C0"), "mvreg/spectral": ("o", "C9"), "mvreg/gpm": ("o", "C8"),
            "mvreg/balm": ("o", "C7"), "mvreg/c-admm": ("o", "C6"), "mvreg/no-refine": ("s", "C0"),
            "open3d": ("^", "C3"), "open3d/all-uncertain": ("v", "C5"),
            "open3d/mvreg-pairs": ("^", "C1"), "gtsam": ("D", "C2"),
            "chain/mvreg-pairs": ("x", "C4"), "chain/open3d-pairs": ("+", "C3"),
        }  # fmt: skip
        for m in ordered_methods(synth):
            g = [r for r in synth if r["method"] == m and "rot_max" in r]
            if not g or m == REFERENCE:
                continue
            mk, col = style.get(m, ("*", "k"))
            for full in (True, False):
                gg = [r for r in g if (r["registered"] == r["scans"]) == full]
                if not gg:
                    continue
                filled = full and mk not in ("x", "+")
                ax.scatter(
                    [r["pairwise_s"] + r["global_s"] for r in gg],
                    [max(r["rot_max"], 1e-4) for r in gg],
                    label=m if full or not any(r["registered"] == r["scans"] for r in g) else None,
                    s=22,
                    marker=mk,
                    facecolors=col if filled or mk in ("x", "+") else "none",
                    edgecolors=col,
                )
        ax.axhline(ROT_OK_DEG, color="grey", ls="--", lw=0.8)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("pairwise + global wall time (s)")
        ax.set_ylabel("max rotation error over the scans (deg)")
        ax.set_title(
            "data_synth scans of the shared meshes (one point per run;\n"
            "hollow: not every scan registered, error over the registered ones)",
            fontsize=10,
        )
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7, ncol=2)
        fig.tight_layout()
        fig.savefig(a.out / "peers_synthetic.png", dpi=110)
        plt.close(fig)
        out.append("peers_synthetic.png")
    if bunny or synth:
        fig, ax = plt.subplots(1, 2, figsize=(11, 4.2))
        for r in bunny:
            if (
                r["method"] in ("mvreg", "open3d", "chain/mvreg-pairs", "chain/open3d-pairs")
                and "rot_per_scan" in r
            ):
                e = list(r["rot_per_scan"].values())
                ax[0].semilogy(range(len(e)), np.maximum(e, 1e-3), "o-", label=r["method"], ms=3)
        ax[0].set_title("bunny, scans in file order")
        clean = [r for r in synth if r.get("condition") == "clean" and "rot_per_scan" in r]
        for i, mesh in enumerate(dict.fromkeys(r["mesh"] for r in clean)):
            for r in clean:
                if r["mesh"] == mesh and r["method"] in ("chain/mvreg-pairs", "mvreg"):
                    e = list(r["rot_per_scan"].values())
                    ax[1].semilogy(
                        range(len(e)), np.maximum(e, 1e-3),
                        "-" if r["method"] == "mvreg" else "--", color=f"C{i}", ms=3,
                        marker="o", label=f"{mesh} {r['method']}",
                    )  # fmt: skip
        ax[1].set_title("synthetic, clean (solid: mvreg, dashed: chain)")
        for x in ax:
            x.set_xlabel("scan index (chain order)")
            x.set_ylabel("rotation error (deg), gauge-aligned")
            x.grid(True, which="both", alpha=0.3)
            x.legend(fontsize=6)
        fig.tight_layout()
        fig.savefig(a.out / "peers_drift.png", dpi=110)
        plt.close(fig)
        out.append("peers_drift.png")
    if patches:
        fig, ax = plt.subplots(1, 2, figsize=(10, 4))
        for m in ("mvreg", "gtsam"):
            g = [r for r in patches if r["method"] == m and "rot_max" in r]
            if g:
                ax[0].loglog(
                    [r["M"] for r in g], [r["pairwise_s"] + r["global_s"] for r in g], "o-", label=m
                )
                ax[1].semilogx([r["M"] for r in g], [r["rot_max"] for r in g], "o-", label=m)
                if m == "gtsam":
                    ax[1].semilogx(
                        [r["M"] for r in g],
                        [r["rot_max_rotation_stage"] for r in g],
                        "o--",
                        color="C1",
                        alpha=0.6,
                        label="gtsam, Shonan rotations only",
                    )
        ax[0].set_ylabel("wall time (s)")
        ax[1].set_ylabel("max rotation error (deg)")
        for x in ax:
            x.set_xlabel("patches M")
            x.grid(True, which="both", alpha=0.3)
            x.legend()
        fig.suptitle("Patch problems: mvreg matrix-free REG-ADMM vs GTSAM Shonan + pose graph")
        fig.tight_layout()
        fig.savefig(a.out / "peers_patches.png", dpi=110)
        plt.close(fig)
        out.append("peers_patches.png")
    return out
