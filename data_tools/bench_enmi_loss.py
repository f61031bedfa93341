"""Time and peak memory of ENMILoss against kornia's and MONAI's mutual-information losses, side by side.

    python data_tools/bench_enmi_loss.py [--batch 8] [--size 256] [--bins 32] [--repeats 7] [--device cpu]

Every method scores the same B x 1 x H x W captured/reference batch with the same number of bins; ENMILoss also
takes a per-pixel variance map (and gets its gradient). Times are medians over ``--repeats`` runs after a warm-up;
peak memory is measured in a fresh subprocess per method (CPU: the resident-set high-water mark above the inputs,
reset through /proc/self/clear_refs; CUDA: torch.cuda.max_memory_allocated). Ratios are against MONAI.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time

import torch

METHODS = ("enmi_torch.ENMILoss", "kornia.normalized_mutual_information_loss_2d", "monai.GlobalMutualInformationLoss")


def make_inputs(batch: int, size: int, device: str, requires_grad: bool):
    generator = torch.Generator().manual_seed(0)
    reference = torch.rand(batch, 1, size, size, generator=generator) * 256
    captured = reference + 20 * torch.randn(batch, 1, size, size, generator=generator)
    rows = torch.linspace(0, 1, size).reshape(1, 1, size, 1)
    variance = (50 + 1000 * rows**3).expand(1, 1, size, size).clone()
    tensors = [tensor.to(device) for tensor in (captured, reference, variance)]
    for tensor in (tensors[0], tensors[2]):
        tensor.requires_grad_(requires_grad)
    return tensors


def make_loss(method: str, bins: int):
    """A callable ``(captured, reference, variance) -> scalar loss`` for one method."""
    if method == "enmi_torch.ENMILoss":
        from enmi_torch import ENMILoss

        module = ENMILoss(bins=bins, value_range=(0.0, 256.0))
        return lambda captured, reference, variance: module(captured, reference, variance=variance)
    if method == "kornia.normalized_mutual_information_loss_2d":
        from kornia.losses import normalized_mutual_information_loss_2d

        return lambda captured, reference, variance: normalized_mutual_information_loss_2d(
            captured[:, 0], reference[:, 0], num_bins=bins
        ).mean()
    from monai.losses import GlobalMutualInformationLoss

    module = GlobalMutualInformationLoss(num_bins=bins)
    # MONAI expects intensities in [0, 1].
    return lambda captured, reference, variance: module(captured / 256, reference / 256)


def time_method(method: str, args) -> dict[str, float]:
    loss = make_loss(method, args.bins)
    captured, reference, variance = make_inputs(args.batch, args.size, args.device, requires_grad=True)

    def synchronize():
        if args.device.startswith("cuda"):
            torch.cuda.synchronize()

    forward, forward_backward = [], []
    for repeat in range(args.repeats + 1):
        synchronize()
        start = time.perf_counter()
        with torch.no_grad():
            loss(captured, reference, variance)
        synchronize()
        middle = time.perf_counter()
        loss(captured, reference, variance).backward()
        synchronize()
        end = time.perf_counter()
        if repeat:  # the first run is a warm-up
            forward.append(middle - start)
            forward_backward.append(end - middle)
    return {"forward_s": statistics.median(forward), "forward_backward_s": statistics.median(forward_backward)}


def _resident_bytes(field: str) -> int:
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith(field):
                return int(line.split()[1]) * 1024
    raise RuntimeError(f"{field} not in /proc/self/status")


def peak_memory_of(method: str, args) -> int:
    """Run in a fresh process: bytes of peak memory one forward+backward adds above its inputs."""
    loss = make_loss(method, args.bins)
    small = make_inputs(1, 32, args.device, requires_grad=True)
    loss(*small).backward()  # load code paths and caches before the measurement
    captured, reference, variance = make_inputs(args.batch, args.size, args.device, requires_grad=True)
    if args.device.startswith("cuda"):
        torch.cuda.synchronize()
        torch.cuda.reset_peak_memory_stats()
        baseline = torch.cuda.memory_allocated()
        loss(captured, reference, variance).backward()
        torch.cuda.synchronize()
        return torch.cuda.max_memory_allocated() - baseline
    with open("/proc/self/clear_refs", "w") as clear_refs:
        clear_refs.write("5")  # resets the resident-set high-water mark (VmHWM)
    baseline = _resident_bytes("VmRSS:")
    loss(captured, reference, variance).backward()
    return _resident_bytes("VmHWM:") - baseline


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--bins", type=int, default=32)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--memory-of", choices=METHODS, help=argparse.SUPPRESS)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    if args.memory_of:
        print(json.dumps({"peak_bytes": peak_memory_of(args.memory_of, args)}))
        return

    results = {}
    for method in METHODS:
        results[method] = time_method(method, args)
        command = [sys.executable, __file__, *sys.argv[1:], "--memory-of", method]
        output = subprocess.run(command, check=True, capture_output=True, text=True).stdout
        results[method]["peak_mib"] = json.loads(output.strip().splitlines()[-1])["peak_bytes"] / 2**20
    reference = results["monai.GlobalMutualInformationLoss"]
    print(
        f"B={args.batch}, {args.size}x{args.size}, {args.bins} bins, device={args.device}, "
        f"threads={torch.get_num_threads()}, medians of {args.repeats}"
    )
    header = "| method | forward (ms) | forward+backward (ms) | peak memory (MiB) | fwd+bwd / MONAI | memory / MONAI |"
    print(header)
    print("|" + "---|" * 6)
    for method, result in results.items():
        print(
            f"| {method} | {1e3 * result['forward_s']:.1f} | {1e3 * result['forward_backward_s']:.1f} | "
            f"{result['peak_mib']:.1f} | {result['forward_backward_s'] / reference['forward_backward_s']:.3f} | "
            f"{result['peak_mib'] / reference['peak_mib']:.3f} |"
        )


if __name__ == "__main__":
    main()
