"""Speed benchmarks: each times the library against a baseline, in interleaved rounds; none draws a figure."""
