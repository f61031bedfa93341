"""Mutation check: do the tests notice a swapped axis, a flipped sign or a wrong bound in the numerical core?

Each mutant changes one line of a module of the numerical core or the localization geometry (an arithmetic
operator, a comparison, a reduction axis, a constant, a boolean); the module's own tests (:data:`MODULES`) then run
on a copy of the repository. A mutant is killed when they fail
(or run past ``--timeout``); the survivors are printed with their line, to be read: either a test is missing or the
mutant is equivalent. Mutants are drawn at random (``--seed``) from all candidates, at most ``--per-module`` per
module; comment and docstring lines are skipped.

    python -m data_tools.checks.mutation_check                          # 8 mutants per module, a few minutes on 2 cores
    python -m data_tools.checks.mutation_check --per-module 30 --jobs 2
    python -m data_tools.checks.mutation_check --root ../other_checkout  # the same check on another version
"""

from __future__ import annotations

import argparse
import random
import re
import shutil
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

SURFACE_TESTS = ["tests/placement/test_surfaces.py", "tests/scores/test_score_objects.py"]
LOCALIZATION_TESTS = [
    "tests/localization/test_search.py",
    "tests/localization/test_peak.py",
    "tests/localization/test_candidates.py",
    "tests/localization/test_strategy.py",
]
# The option tables (which options apply under which others) and their users.
OPTION_TESTS = [
    "tests/utils/test_options.py",
    "tests/scores/test_ecr_options.py",
    "tests/localization/test_strategy.py",
    "tests/tracking/test_settings.py",
]
TRACKING_TESTS = [
    "tests/tracking/test_belief.py",
    "tests/tracking/test_calibration.py",
    "tests/tracking/test_health.py",
    "tests/tracking/test_settings.py",
    "tests/tracking/test_step.py",
    "tests/tracking/test_tracker.py",
]
ECR_TESTS = [
    "tests/scores/test_ecr.py",
    "tests/scores/test_ecr_model_variance.py",
    "tests/scores/test_ecr_correlated_misfit.py",
    "tests/scores/test_ecr_shrunk_response.py",
    "tests/scores/test_ecr_regional_misfit.py",
    "tests/scores/test_score_seams.py",
    *SURFACE_TESTS,
    "tests/test_losses.py",
    *LOCALIZATION_TESTS,
]
# Each module's tests: those of the code it holds (the functional losses live with their scores, ECR's two-stage
# pieces with ECR, NMI's choice between its two exact paths with NMI).
MODULES = {
    "binning": ["tests/test_binning.py"],
    "histogram": ["tests/test_histogram.py", "tests/test_histogram_candidates.py", "tests/utils/test_budget.py"],
    "information": ["tests/test_information.py"],
    "placement/inputs": SURFACE_TESTS,
    "placement/fft": SURFACE_TESTS,
    "placement/planes": SURFACE_TESTS,
    "placement/information": SURFACE_TESTS,
    "scores/base": ["tests/scores/test_score_objects.py", "tests/scores/test_score_seams.py"],
    "scores/ecr": ECR_TESTS,
    "scores/ecr_statistics": ECR_TESTS,
    "scores/ecr_model_variance": ECR_TESTS,
    "scores/ecr_placements": [*ECR_TESTS, "tests/scores/test_mixture.py"],
    "scores/ecr_regional_misfit": ["tests/scores/test_ecr_regional_misfit.py"],
    "scores/shrunk_response": ["tests/scores/test_ecr_shrunk_response.py", "tests/scores/test_ecr.py"],
    "scores/enmi": ["tests/test_information.py", *SURFACE_TESTS, "tests/test_losses.py", "tests/utils/test_budget.py"],
    "scores/nmi": [
        "tests/test_information.py",
        *SURFACE_TESTS,
        "tests/test_losses.py",
        "tests/utils/test_budget.py",
        "tests/test_histogram_candidates.py",
    ],
    "scores/ncc": [
        *SURFACE_TESTS,
        "tests/scores/test_ncc.py",
        "tests/scores/test_score_seams.py",
        "tests/registration/test_register.py",
    ],
    "localization/search": LOCALIZATION_TESTS,
    "localization/strategy": [*LOCALIZATION_TESTS, "tests/utils/test_checks.py"],
    "localization/candidates": LOCALIZATION_TESTS,
    "localization/peak": LOCALIZATION_TESTS,
    "variance/empirical": ["tests/variance/test_empirical.py"],
    "variance/perspective": ["tests/variance/test_perspective.py"],
    "registration/refine": ["tests/registration/test_register.py", "tests/registration/test_stage.py"],
    "registration/response_fit": ["tests/registration/test_register.py"],
    "registration/stage": ["tests/registration/test_stage.py", "tests/registration/test_register.py"],
    "registration/warp": ["tests/registration/test_register.py", "tests/registration/test_stage.py"],
    "registration/interpolation": ["tests/registration/test_interpolation.py", "tests/registration/test_register.py"],
    "tracking/calibration": TRACKING_TESTS,
    "tracking/tracker": TRACKING_TESTS,
    "tracking/step": TRACKING_TESTS,
    "tracking/search": TRACKING_TESTS,
    "tracking/settings": TRACKING_TESTS,
    "tracking/belief": TRACKING_TESTS,
    "utils/checks": ["tests/utils/test_checks.py", "tests/registration/test_register.py", "tests/utils/test_budget.py"],
    "utils/options": OPTION_TESTS,
    "scores/ecr_options": ["tests/scores/test_ecr_options.py", "tests/scores/test_ecr.py"],
    "training/fit_checks": ["tests/training/test_fit_checks.py"],
    "training/preemption": ["tests/training/test_preemption.py"],
}

# Where a module's code lived in older checkouts, newest first, for --root: before the scores package (337d306 and
# earlier) and before the localization package (4f0c41e and earlier). Modules that share a file draw each mutant once.
LEGACY_FILES = {
    "placement/inputs": ["localization/surface", "score_surface"],
    "placement/fft": ["localization/surface", "score_surface"],
    "placement/planes": ["localization/surface", "score_surface"],
    "placement/information": ["localization/surface", "score_surface"],
    "scores/ecr": ["correlation_ratio"],
    "scores/ecr_statistics": ["scores/ecr", "correlation_ratio"],
    "scores/ecr_model_variance": ["scores/ecr", "correlation_ratio"],
    "scores/ecr_placements": ["scores/ecr", "correlation_ratio"],
    "scores/enmi": ["information"],
    "scores/nmi": ["information"],
    "scores/ncc": ["localization/surface", "score_surface"],
    "localization/search": ["localize"],
    "localization/strategy": ["localization/search", "localize"],
    "localization/candidates": ["localization/search", "localize"],
    "localization/peak": ["localize"],
    "registration/response_fit": ["registration/refine"],
    "registration/stage": ["registration/refine"],
    "registration/warp": ["registration/refine"],
    "tracking/step": ["tracking/tracker"],
    "tracking/search": ["tracking/tracker"],
}


def module_file(root: Path, module: str) -> Path:
    """The module's source file in the checkout ``root`` (its legacy name where the new one is absent)."""
    path = root / "enmi_torch" / f"{module}.py"
    for legacy in LEGACY_FILES.get(module, []):
        if path.is_file():
            break
        path = root / "enmi_torch" / f"{legacy}.py"
    return path


def module_tests(root: Path, module: str) -> list[str]:
    """The module's test files that the checkout ``root`` has."""
    return [test for test in MODULES[module] if (root / test).is_file()]


# (pattern, replacement): each match on a line gives one mutant.
OPERATORS = [
    (r" \+ ", " - "),
    (r" - ", " + "),
    (r" \* ", " / "),
    (r" / ", " * "),
    (r" <= ", " < "),
    (r" >= ", " > "),
    (r" < ", " <= "),
    (r" > ", " >= "),
    (r"dim=-1\b", "dim=-2"),
    (r"dim=-2\b", "dim=-1"),
    (r"\(-2, -1\)", "(-1, -2)"),
    (r"\(-1, -2\)", "(-2, -1)"),
    (r"\.transpose\(-1, -2\)", ""),
    (r"\b0\.5\b", "0.25"),
    (r"\+ 1\b", "+ 2"),
    (r"- 1\b", "- 2"),
    (r"\bTrue\b", "False"),
    (r"\bFalse\b", "True"),
    (r"\.amax\(", ".amin("),
    (r"\.clamp_min\(", ".clamp_max("),
]


def code_lines(text: str) -> list[int]:
    """Indices of the lines that are code: not blank, not comments, not inside docstrings."""
    lines, inside, quote = [], False, None
    for index, line in enumerate(text.splitlines()):
        stripped = line.strip()
        if inside:
            if quote in stripped:
                inside = False
            continue
        if stripped.startswith(('"""', "'''")):
            quote = stripped[:3]
            if not (stripped.count(quote) >= 2 and len(stripped) > 3):
                inside = True
            continue
        if stripped and not stripped.startswith("#"):
            lines.append(index)
    return lines


def candidates(root: Path, module: str) -> list[tuple[str, int, str, str]]:
    """Every ``(module, line index, original line, mutated line)`` of a module."""
    text = module_file(root, module).read_text()
    lines = text.splitlines()
    found = []
    for index in code_lines(text):
        line = lines[index]
        code = line.split("  #")[0]
        for pattern, replacement in OPERATORS:
            for match in re.finditer(pattern, code):
                mutated = line[: match.start()] + re.sub(pattern, replacement, match.group(0)) + line[match.end() :]
                if mutated != line:
                    found.append((module, index, line, mutated))
    return found


def run_mutant(root: Path, mutant: tuple[str, int, str, str], timeout: float) -> bool:
    """Whether the module's tests fail on a copy of ``root`` with the mutant applied (killed).

    ``index`` -1 applies nothing: the baseline, whose tests must pass.
    """
    module, index, _, mutated = mutant
    with tempfile.TemporaryDirectory(prefix="mutant_") as folder:
        copy = Path(folder) / "repo"
        shutil.copytree(root / "enmi_torch", copy / "enmi_torch")
        shutil.copytree(root / "tests", copy / "tests")
        shutil.copy(root / "pyproject.toml", copy / "pyproject.toml")
        # tests/data_tools imports the data_tools package; the fit's tests run train/fit_mask.py
        for folder_name in ("configs", "data_tools", "train"):
            if (root / folder_name).is_dir():
                shutil.copytree(root / folder_name, copy / folder_name)
        path = module_file(copy, module)
        if index >= 0:
            lines = path.read_text().splitlines()
            lines[index] = mutated
            path.write_text("\n".join(lines) + "\n")
        command = [sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider", "-m", "not slow"]
        command += module_tests(root, module)
        environment = {"PYTHONPATH": str(copy), "HOME": folder, "MPLBACKEND": "Agg", "OMP_NUM_THREADS": "1"}
        try:
            result = subprocess.run(command, cwd=copy, env=environment, capture_output=True, timeout=timeout)
        except subprocess.TimeoutExpired:
            return True
        return result.returncode != 0


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0],
        epilog=__doc__.split("\n\n", 1)[1],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--root", type=Path, default=Path(__file__).resolve().parents[2], help="the checkout to test")
    parser.add_argument("--per-module", type=int, default=8, help="mutants drawn per module (default 8)")
    parser.add_argument("--modules", nargs="+", choices=sorted(MODULES), default=sorted(MODULES))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--jobs", type=int, default=1, help="mutants tested at once")
    parser.add_argument("--timeout", type=float, default=300.0, help="seconds before a mutant's tests count as killed")
    args = parser.parse_args(argv)
    if args.per_module < 1 or args.jobs < 1:
        parser.error(f"--per-module and --jobs must be >= 1, got {args.per_module} and {args.jobs}")
    if not (args.root / "enmi_torch").is_dir():
        parser.error(f"--root: {args.root} holds no enmi_torch package")
    generator = random.Random(args.seed)
    chosen, drawn = [], set()
    for module in args.modules:
        if not module_file(args.root, module).is_file():
            print(f"{module}: not in this checkout, skipped", file=sys.stderr)
            continue
        if run_mutant(args.root, (module, -1, "", ""), args.timeout):
            print(f"{module}: its tests fail without any mutant, skipped", file=sys.stderr)
            continue
        # On a legacy checkout two modules may share one file: a mutant is drawn once.
        found = [mutant for mutant in candidates(args.root, module) if mutant[1:] not in drawn]
        picked = generator.sample(found, min(args.per_module, len(found)))
        drawn.update(mutant[1:] for mutant in picked)
        chosen += picked
    start = time.perf_counter()
    results = {}
    with ThreadPoolExecutor(args.jobs) as pool:
        futures = {pool.submit(run_mutant, args.root, mutant, args.timeout): mutant for mutant in chosen}
        for done, (future, mutant) in enumerate(futures.items(), 1):
            results[mutant] = future.result()
            print(f"[{done}/{len(chosen)}] {time.perf_counter() - start:.0f} s", end="\r", file=sys.stderr, flush=True)
    print(file=sys.stderr)
    print("| module | mutants | killed | kill rate |")
    print("| --- | --- | --- | --- |")
    for module in args.modules:
        outcomes = [killed for mutant, killed in results.items() if mutant[0] == module]
        if outcomes:
            print(f"| {module} | {len(outcomes)} | {sum(outcomes)} | {sum(outcomes) / len(outcomes):.0%} |")
    total = list(results.values())
    print(f"| all | {len(total)} | {sum(total)} | {sum(total) / max(len(total), 1):.0%} |")
    survivors = [mutant for mutant, killed in results.items() if not killed]
    if survivors:
        print("\nSurvivors (a missing test, or an equivalent mutant):")
        for module, index, line, mutated in survivors:
            path = module_file(args.root, module).relative_to(args.root)
            print(f"  {path}:{index + 1}: {line.strip()}  ->  {mutated.strip()}")
    print(f"\n{len(total)} mutants in {time.perf_counter() - start:.0f} s (seed {args.seed})")


if __name__ == "__main__":
    main()
