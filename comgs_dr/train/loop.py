"""The training loop shared by step 1 and step 2."""
from __future__ import annotations

from pathlib import Path


def plot_psnr(log: list, path: Path) -> None:
    """PNG of test (and train) PSNR against training wall-clock time."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    ev = [r for r in log if "psnr_test" in r]
    fig, ax = plt.subplots(figsize=(5, 3.2), dpi=120)
    tr_ = [r for r in log if "psnr_train" in r]
    if tr_:
        ax.plot([r["time_s"] for r in tr_], [r["psnr_train"] for r in tr_], ".", ms=2, alpha=0.4, label="train view")
    if ev:
        ax.plot([r["time_s"] for r in ev], [r["psnr_test"] for r in ev], "o-", label="test views")
    ax.set_xlabel("training time [s]")
    ax.set_ylabel("PSNR [dB]")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
