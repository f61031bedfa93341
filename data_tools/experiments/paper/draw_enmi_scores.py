"""README figure for NMI and ENMI: score against shift on a real image with noise that grows with distance.

    python -m data_tools.experiments.paper.draw_enmi_scores  # writes runs/enmi_vs_nmi.png
    python -m data_tools.experiments.paper.draw_enmi_scores --figure docs/images/enmi_vs_nmi.png  # the README figure

The reference is a 48 x 48 crop of scikit-image's bundled CC0 ``gravel()``; the captured image is the crop
shifted by s pixels plus Gaussian noise of variance N0 (1 + 99 d^3), d the row's distance from the bottom
(far rows noisier, as on the road). At each noise level, NMI (hard bins) and ENMI (mass weights, the true variance
map) score every shift in -6..6 for ``--draws`` noise draws; the figure shows a captured image, the variance map,
and the share of draws in which the true shift scores best.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import torch
from skimage import data
from tqdm import tqdm

from enmi_torch.scores.enmi import enmi
from enmi_torch.scores.nmi import nmi

SIZE = 48
SHIFTS = range(-6, 7)
NOISE_POWERS = [300.0, 1000.0, 3000.0, 10000.0, 30000.0, 100000.0, 300000.0]


def variance_map(size: int, noise_power: float) -> torch.Tensor:
    """``(1, 1, size, size)`` variance ``N0 (1 + 99 d^3)``, ``d`` the distance from the bottom row (0 to 1)."""
    distance = torch.linspace(1.0, 0.0, size, dtype=torch.float64).reshape(1, 1, size, 1)
    return (noise_power * (1 + 99 * distance**3)).expand(1, 1, size, size)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--figure", type=Path, default=Path("runs/enmi_vs_nmi.png"), help="PNG to write")
    parser.add_argument("--draws", type=int, default=100, help="noise draws per N0 (default 100)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    image = torch.from_numpy(data.gravel().astype("float64"))
    top, left = 200, 200
    reference = image[top : top + SIZE, left : left + SIZE].reshape(1, 1, SIZE, SIZE)
    shifted = torch.cat(
        [image[top : top + SIZE, left + shift : left + shift + SIZE].reshape(1, 1, SIZE, SIZE) for shift in SHIFTS]
    )
    generator = torch.Generator().manual_seed(args.seed)
    unit_noise = torch.randn(args.draws, 1, SIZE, SIZE, generator=generator, dtype=torch.float64)
    centre = list(SHIFTS).index(0)

    success = {"NMI (hard bins)": [], "ENMI (mass weights, true variance)": []}
    for noise_power in tqdm(NOISE_POWERS, desc="noise powers", unit="N0"):
        variance = variance_map(SIZE, noise_power)
        noise = unit_noise * variance.sqrt()
        # (shifts * draws) captured images: every shift sees the same noise draw.
        captured = (shifted.unsqueeze(1) + noise.unsqueeze(0)).reshape(-1, 1, SIZE, SIZE)
        references = reference.expand_as(captured)
        for label, score in (
            ("NMI (hard bins)", nmi(captured, references)),
            ("ENMI (mass weights, true variance)", enmi(captured, references, variance)),
        ):
            best = score.reshape(len(SHIFTS), args.draws).argmax(0)
            success[label].append((best == centre).double().mean().item())

    figure, axes = plt.subplots(1, 3, figsize=(13, 4))
    example_power = NOISE_POWERS[len(NOISE_POWERS) // 2]
    example = variance_map(SIZE, example_power)
    axes[0].imshow((reference + unit_noise[:1] * example.sqrt())[0, 0].clamp(0, 255), cmap="gray", vmin=0, vmax=255)
    axes[0].set_title(f"captured: gravel() crop + noise, N0 = {example_power:g}")
    shown = axes[1].imshow(example[0, 0], cmap="viridis", norm=matplotlib.colors.LogNorm())
    axes[1].set_title("noise variance sigma^2 (far rows on top)")
    figure.colorbar(shown, ax=axes[1], fraction=0.046)
    for axis in axes[:2]:
        axis.set_xticks([])
        axis.set_yticks([])
    for label, rates in success.items():
        axes[2].semilogx(NOISE_POWERS, rates, marker="o", label=label)
    axes[2].set_xlabel("noise power N0 (variance N0 near, 100 N0 far)")
    axes[2].set_ylabel(f"true shift wins among {len(SHIFTS)} shifts")
    axes[2].set_title(f"share of {args.draws} noise draws")
    axes[2].legend(fontsize=8)
    axes[2].grid(alpha=0.3)
    figure.tight_layout()
    args.figure.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(args.figure, dpi=80)
    print("N0 | " + " | ".join(success))
    for index, noise_power in enumerate(NOISE_POWERS):
        print(f"{noise_power:g} | " + " | ".join(f"{rates[index]:.2f}" for rates in success.values()))
    print(f"wrote {args.figure}")


if __name__ == "__main__":
    main()
