"""The lab beside the library: experiments, speed benchmarks and checks; not part of the wheel.

Run a script from the repository root as a module, e.g. ``python -m data_tools.benchmarks.bench_scores``.
"""
