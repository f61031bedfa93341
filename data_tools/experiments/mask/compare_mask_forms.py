"""With few pairs, the mask's prior matters: per-pixel, smooth, and parametric (radial, perspective) fits compared.

    python -m data_tools.experiments.mask.compare_mask_forms

Runs ``enmi-fit-mask`` on 32 synthetic pairs of 128 x 128 (lidar-like and camera-like) with each form and prints
the relative RMS error of the learned mask against the true variance, next to the paper's empirical mask's.
"""

from __future__ import annotations

import tempfile

from enmi_torch.training.fit_mask import fit_mask

PAIRS = 32
FORMS = {
    "lidar": [
        ("pixel", []),
        ("pixel, smoothness 100", ["--model.smoothness", "100"]),
        ("radial", ["--model.form", "radial"]),
    ],
    "camera": [
        ("pixel", []),
        ("pixel, smoothness 100", ["--model.smoothness", "100"]),
        ("perspective", ["--model.form", "perspective"]),
    ],
}


def main() -> None:
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        for flavour, forms in FORMS.items():
            for name, options in forms:
                summary = fit_mask(
                    [
                        *("--trainer.logger.init_args.save_dir", folder, "--trainer.enable_progress_bar", "false"),
                        *("--data.flavour", flavour, "--data.train_pairs", str(PAIRS), "--data.batch_size", "8"),
                        *("--trainer.max_epochs", "60", "--trainer.check_val_every_n_epoch", "60"),
                        *("--model.lr", "0.1", "--data.val_pairs", "16", *options),
                    ]
                )
                errors = summary["errors"]
                rows.append((flavour, name, errors["rel_rms_vs_truth"], errors["empirical_rel_rms_vs_truth"]))
    print(f"\n{PAIRS} pairs of 128x128, relative RMS error against the true variance")
    print("| data | form | learned mask | paper's empirical mask |")
    print("| --- | --- | --- | --- |")
    for flavour, name, learned, empirical in rows:
        print(f"| {flavour}-like | {name} | {100 * learned:.1f} % | {100 * empirical:.1f} % |")


if __name__ == "__main__":
    main()
