"""Benchmarks: ``warp-cloth bench NAME`` runs ``warp_cloth.bench.NAME.main(argv)``.

Timings on shared machines are noisy: every benchmark reports ratios measured in the same run
(e.g. a step against a trivial kernel over the same arrays) beside absolute figures, and takes
the median of repeats.
"""
