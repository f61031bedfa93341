"""Time and peak memory of ENMILoss against kornia's and MONAI's mutual-information losses, and its kernel floor.

    python -m data_tools.benchmarks.bench_enmi_loss [--batch 8] [--size 256] [--bins 32] [--repeats 7] [--threads 1]

Every method scores the same B x 1 x H x W captured/reference batch with the same number of bins; ENMILoss also
takes a per-pixel variance map (and gets its gradient). Each round times every method once, interleaved, after a
warm-up round; the table gives medians over ``--repeats`` rounds and the median of the per-round ratios, which a
shared machine disturbs less than the times. Peak memory is measured in a fresh subprocess per method (CPU: the
resident-set high-water mark above the inputs, reset through /proc/self/clear_refs; CUDA:
torch.cuda.max_memory_allocated). Ratios are against MONAI, and ENMILoss's also against its kernel floor: the
elementwise work no implementation of its forward and backward avoids, timed in the same rounds on the same
inputs: one ``erf`` over the ``(N, bins + 1)`` standardised bin edges, one ``index_add_`` of ``(N, bins)`` weights
into the ``(B * bins, bins)`` histogram rows and one ``exp`` over the ``(N, bins - 1)`` interior edges' ``-z^2 / 2``
(``N = B * H * W``), each one call on whole tensors. A second floor runs the same three calls in the chunks the
library uses (about 1M weights, cache-resident), a bound no allocation or memory traffic adds to.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time

import torch
from tqdm import tqdm

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


def floor_calls(captured: torch.Tensor, variance: torch.Tensor, bins: int, chunked: bool):
    """The kernel floor of ENMILoss's forward and backward on these inputs: a callable running its three calls."""
    from enmi_torch.histogram import _CHUNK_ELEMENTS

    batch = captured.shape[0]
    values = captured.detach().reshape(batch, -1, 1)
    inverse_scale = (2 * variance.detach()).rsqrt().reshape(1, -1, 1)
    edges = torch.linspace(0.0, 256.0, bins + 1, device=captured.device)
    standardized = ((edges - values) * inverse_scale).reshape(-1, bins + 1)
    exponent = standardized[:, 1:-1].square().mul(-1.0).clamp_min(-80.0).contiguous()
    rows = torch.randint(0, batch * bins, (standardized.shape[0],), generator=torch.Generator().manual_seed(1))
    rows = rows.to(captured.device)
    weights = torch.rand(standardized.shape[0], bins, device=captured.device)
    step = max(1, _CHUNK_ELEMENTS // bins) if chunked else standardized.shape[0]
    parts = [slice(start, start + step) for start in range(0, standardized.shape[0], step)]

    def run() -> None:
        histogram = weights.new_zeros(batch * bins + 1, bins)
        for part in parts:
            torch.erf(standardized[part])
            histogram.index_add_(0, rows[part], weights[part])
            torch.exp(exponent[part])

    return run


def time_methods(args) -> tuple[dict[str, dict[str, list[float]]], dict[str, list[float]]]:
    """Interleaved rounds: seconds of each method's forward and forward+backward, and of the two floors."""
    losses = {method: make_loss(method, args.bins) for method in METHODS}
    captured, reference, variance = make_inputs(args.batch, args.size, args.device, requires_grad=True)
    floors = {
        "whole tensors": floor_calls(captured, variance, args.bins, chunked=False),
        "in chunks": floor_calls(captured, variance, args.bins, chunked=True),
    }

    def synchronize():
        if args.device.startswith("cuda"):
            torch.cuda.synchronize()

    times = {method: {"forward": [], "forward_backward": []} for method in METHODS}
    floor_times = {name: [] for name in floors}
    for repeat in tqdm(range(args.repeats + 1), desc="rounds (the first is a warm-up)", unit="round"):
        for method, loss in losses.items():
            captured.grad = variance.grad = None
            synchronize()
            start = time.perf_counter()
            with torch.no_grad():
                loss(captured, reference, variance)
            synchronize()
            middle = time.perf_counter()
            loss(captured, reference, variance).backward()
            synchronize()
            end = time.perf_counter()
            if repeat:
                times[method]["forward"].append(middle - start)
                times[method]["forward_backward"].append(end - middle)
        for name, run in floors.items():
            synchronize()
            start = time.perf_counter()
            run()
            synchronize()
            if repeat:
                floor_times[name].append(time.perf_counter() - start)
    return times, floor_times


def median_ratio(numerators: list[float], denominators: list[float]) -> float:
    return statistics.median(a / b for a, b in zip(numerators, denominators, strict=True))


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
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--device", default="cpu")
    parser.add_argument(
        "--chunk_elements", type=int, default=None, help="elements per chunk of ENMILoss's histogram (CPU)"
    )
    parser.add_argument("--memory-of", choices=METHODS, help=argparse.SUPPRESS)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    if args.chunk_elements is not None:
        import enmi_torch.histogram

        enmi_torch.histogram._CHUNK_ELEMENTS = args.chunk_elements
    if args.memory_of:
        print(json.dumps({"peak_bytes": peak_memory_of(args.memory_of, args)}))
        return

    times, floor_times = time_methods(args)
    peak_mib = {}
    for method in tqdm(METHODS, desc="peak memory (a process each)", unit="method"):
        command = [sys.executable, "-m", __spec__.name, *sys.argv[1:], "--memory-of", method]
        output = subprocess.run(command, check=True, capture_output=True, text=True).stdout
        peak_mib[method] = json.loads(output.strip().splitlines()[-1])["peak_bytes"] / 2**20
    monai = "monai.GlobalMutualInformationLoss"
    print(
        f"B={args.batch}, {args.size}x{args.size}, {args.bins} bins, device={args.device}, "
        f"threads={torch.get_num_threads()}, torch {torch.__version__}; medians of {args.repeats} interleaved rounds"
    )
    if args.chunk_elements is not None:
        print(f"ENMILoss's histogram in chunks of {args.chunk_elements} elements")
    header = "| method | forward (ms) | forward+backward (ms) | peak memory (MiB) | fwd+bwd / MONAI | memory / MONAI |"
    print(header)
    print("|" + "---|" * 6)
    for method in METHODS:
        forward_backward = times[method]["forward_backward"]
        print(
            f"| {method} | {1e3 * statistics.median(times[method]['forward']):.1f} | "
            f"{1e3 * statistics.median(forward_backward):.1f} | {peak_mib[method]:.1f} | "
            f"{median_ratio(forward_backward, times[monai]['forward_backward']):.3f} | "
            f"{peak_mib[method] / peak_mib[monai]:.3f} |"
        )
    enmi_loss = times["enmi_torch.ENMILoss"]["forward_backward"]
    print("\n| ENMILoss fwd+bwd against its kernel floor | floor (ms) | ENMILoss / floor |")
    print("| --- | --- | --- |")
    for name, floor in floor_times.items():
        print(
            f"| erf + index_add_ + exp, {name} | {1e3 * statistics.median(floor):.1f} | "
            f"{median_ratio(enmi_loss, floor):.2f} |"
        )


if __name__ == "__main__":
    main()
