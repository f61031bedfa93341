"""Torch threads and ``OMP_WAIT_POLICY``: time representative calls under each setting, quiet and under load.

    python -m data_tools.benchmarks.bench_threads        # 3 rounds, 0 and 1 competing busy process, about 5 min
    python -m data_tools.benchmarks.bench_threads --rounds 1 --busy 0 --repeats 3

Settings: torch intra-op threads 1 or 2 (``torch.set_num_threads``) times ``OMP_WAIT_POLICY`` unset (OpenMP's
default: idle threads spin for a while before they sleep) or ``PASSIVE`` (they sleep at once). OpenMP reads the
variable when it starts, so each setting runs in a fresh child process. Calls, float32 on the CPU:

- ``ENMILoss fwd+bwd``: ENMILoss of 8 pairs of 128 x 128, 32 bins, a per-pixel variance, and its gradient;
- ``enmi_surface`` and ``ecr_surface``: a 128 x 128 local image at the 101 x 101 placements of a 228 x 228 window;
- ``fit_mask step``: the per-pixel Gaussian NLL of 64 pairs of 128 x 128, backward and an Adam step (the training
  step of ``enmi-fit-mask``).

Each child times every call ``--repeats`` times after a warm-up and reports the medians. A round runs every setting
once (the order rotates from round to round) for each load: ``--busy N`` starts N processes that spin on the CPU
while the round runs (the machine's other work comes on top; the load average is printed). The table gives the
median over rounds of each call's time and of its per-round ratio to torch's default (2 threads on a 2-core
machine, ``OMP_WAIT_POLICY`` unset).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time

SETTINGS = (("2", ""), ("2", "PASSIVE"), ("1", ""), ("1", "PASSIVE"))  # (threads, OMP_WAIT_POLICY); first: baseline
CALLS = ("ENMILoss fwd+bwd", "enmi_surface", "ecr_surface", "fit_mask step")


def make_calls() -> dict:
    """The calls to time, each a function of no arguments, on fixed seeded inputs."""
    import torch

    from enmi_torch import ECR, ENMI, ENMILoss
    from enmi_torch.variance import LearnedVariance

    generator = torch.Generator().manual_seed(0)
    reference = torch.rand(8, 1, 128, 128, generator=generator) * 256
    captured = (reference + 20 * torch.randn(reference.shape, generator=generator)).requires_grad_(True)
    rows = torch.linspace(0, 1, 128).reshape(1, 1, 128, 1)
    variance = (50 + 1000 * rows**3).expand(1, 1, 128, 128).clone().requires_grad_(True)
    loss = ENMILoss(bins=32, value_range=(0.0, 256.0))

    def enmi_loss() -> None:
        loss(captured, reference, variance).backward()

    window = torch.rand(1, 1, 228, 228, generator=generator) * 256
    local = window[..., 50:178, 50:178] + 10 * torch.randn(1, 1, 128, 128, generator=generator)
    surface_variance = variance[0, 0].detach()

    prior = torch.rand(64, 1, 128, 128, generator=generator) * 256
    noisy = prior + 12 * torch.randn(prior.shape, generator=generator)
    valid = torch.ones(prior.shape, dtype=torch.bool)
    mask = LearnedVariance((128, 128), "pixel")
    mask.reset_parameters(144.0)
    optimizer = torch.optim.Adam(mask.parameters(), lr=0.05)

    def fit_step() -> None:
        optimizer.zero_grad()
        mask.nll(noisy, prior, valid).backward()
        optimizer.step()

    return {
        "ENMILoss fwd+bwd": enmi_loss,
        "enmi_surface": lambda: ENMI().surface(local, window, surface_variance),
        "ecr_surface": lambda: ECR().surface(local, window, surface_variance),
        "fit_mask step": fit_step,
    }


def child(repeats: int, threads: int) -> None:
    """Time each call in this process; print one JSON line of median seconds."""
    import torch

    torch.set_num_threads(threads)
    medians = {}
    for name, call in make_calls().items():
        call()  # warm-up
        times = []
        for _ in range(repeats):
            start = time.perf_counter()
            call()
            times.append(time.perf_counter() - start)
        medians[name] = statistics.median(times)
    print(json.dumps(medians))


def run_child(threads: str, policy: str, repeats: int) -> dict[str, float]:
    environment = {key: value for key, value in os.environ.items() if key != "OMP_WAIT_POLICY"}
    if policy:
        environment["OMP_WAIT_POLICY"] = policy
    command = [sys.executable, "-m", __spec__.name, "--child", "--threads", threads, "--repeats", str(repeats)]
    result = subprocess.run(command, env=environment, capture_output=True, text=True, check=True)
    return json.loads(result.stdout.strip().splitlines()[-1])


def label(setting: tuple[str, str]) -> str:
    threads, policy = setting
    return f"{threads} thread{'s' if threads != '1' else ''}, {policy or 'default'}"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=5, help="timed runs of each call per child (median)")
    parser.add_argument("--busy", type=int, nargs="+", default=[0, 1], help="competing busy processes, per load")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--threads", type=int, default=1, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        child(args.repeats, args.threads)
        return
    import torch

    print(
        f"threads benchmark: {os.cpu_count()} CPUs, torch {torch.__version__} (default {torch.get_num_threads()} "
        f"threads), {args.rounds} rounds, {args.repeats} repeats per child, busy processes {args.busy}",
        flush=True,
    )
    # seconds[busy][setting][call] and ratios[busy][setting][call]: one value per round.
    seconds = {busy: {setting: {call: [] for call in CALLS} for setting in SETTINGS} for busy in args.busy}
    ratios = {busy: {setting: {call: [] for call in CALLS} for setting in SETTINGS} for busy in args.busy}
    loads = {busy: [] for busy in args.busy}
    for round_index in range(args.rounds):
        order = SETTINGS[round_index % len(SETTINGS) :] + SETTINGS[: round_index % len(SETTINGS)]
        for busy in args.busy:
            spinners = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(busy)]
            try:
                results = {}
                for setting in order:
                    started = time.perf_counter()
                    results[setting] = run_child(*setting, args.repeats)
                    print(
                        f"round {round_index + 1}/{args.rounds}, {busy} busy: {label(setting)} "
                        f"({time.perf_counter() - started:.0f} s)",
                        flush=True,
                    )
                loads[busy].append(os.getloadavg()[0])
            finally:
                for spinner in spinners:
                    spinner.terminate()
                    spinner.wait()
            for setting in SETTINGS:
                for call in CALLS:
                    seconds[busy][setting][call].append(results[setting][call])
                    ratios[busy][setting][call].append(results[setting][call] / results[SETTINGS[0]][call])
    for busy in args.busy:
        print(
            f"\n{busy} competing busy process(es), 1-minute load average at the rounds' ends "
            f"{', '.join(f'{load:.1f}' for load in loads[busy])}; median ms [ratio to {label(SETTINGS[0])}, median "
            "of per-round ratios]:"
        )
        print("| call | " + " | ".join(label(setting) for setting in SETTINGS) + " |")
        print("| --- " * (len(SETTINGS) + 1) + "|")
        for call in CALLS:
            cells = [
                f"{1000 * statistics.median(seconds[busy][setting][call]):.1f} "
                f"[{statistics.median(ratios[busy][setting][call]):.2f}x]"
                for setting in SETTINGS
            ]
            print(f"| {call} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
