"""Figure: DeepProMP vs ProMP on the bimodal sine set, conditioned on 3 zero-crossing via-points
(which cannot tell the modes apart), on 3 via-points that can, and on many via-points.

Usage: python bench/plot_bimodal.py [--out docs/figures/bimodal_sine.png]
Prints the fractions of samples on each mode and between the modes (at x = 0.25).
"""
import argparse
import pathlib
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from deepprompt_ros.data.synthetic import bimodal_sine  # noqa: E402
from deepprompt_ros.primitive.deep_promp import DeepProMP  # noqa: E402
from deepprompt_ros.baselines.promp import ProMP  # noqa: E402


def fractions(s):
    q = s[:, 25, 0]
    return (q > 0.6).mean(), (q < -0.6).mean(), (np.abs(q) < 0.4).mean()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default=str(ROOT / "docs" / "figures" / "bimodal_sine.png"))
    ap.add_argument("--model", default=str(ROOT / "models" / "bimodal_sine.safetensors"))
    args = ap.parse_args(argv)
    x = np.linspace(0, 1, 101)
    deep = DeepProMP.from_checkpoint(args.model)
    ds = bimodal_sine(200, seed=0)
    Y = np.stack([d.resampled(101) for d in ds.demos])
    promp = ProMP(1, n_basis=15).fit(Y, x)
    held = bimodal_sine(3, seed=99).demos[0].resampled(101)
    cases = [("3 zero crossings", [0, 50, 100], np.zeros((3, 1))),
             ("3 via-points", [10, 25, 60], held[[10, 25, 60]]),
             ("12 via-points", list(range(0, 101, 9)), held[list(range(0, 101, 9))])]
    fig, axes = plt.subplots(2, 3, figsize=(12, 6), sharex=True, sharey=True)
    for col, (title, idx, yv) in enumerate(cases):
        xv = x[idx]
        s_deep = deep.sample(deep.condition(xv, yv), x, 200, rng=0)
        s_pro = promp.condition(xv, yv, noise_var=1e-4).sample(x, 200, np.random.default_rng(0))
        for row, (name, s) in enumerate((("DeepProMP", s_deep), ("ProMP", s_pro))):
            ax = axes[row, col]
            ax.plot(x, Y[:40, :, 0].T, color="0.85", lw=0.6)
            ax.plot(x, s[:60, :, 0].T, color="C0" if row == 0 else "C1", lw=0.6, alpha=0.6)
            ax.plot(xv, yv[:, 0], "kx", ms=8, mew=2)
            pos, neg, gap = fractions(s)
            ax.set_title(f"{name}: {title}\n+ {pos:.0%}  − {neg:.0%}  between {gap:.0%}", fontsize=9)
            print(f"{name:10s} {title:18s} on+ {pos:.3f} on- {neg:.3f} between {gap:.3f}")
    for ax in axes[-1]:
        ax.set_xlabel("phase x")
    fig.tight_layout()
    pathlib.Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=90)
    print(f"figure written to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
