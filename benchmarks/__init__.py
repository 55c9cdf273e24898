"""tdfd benchmarks: each script prints its figures and writes its section of docs/BENCHMARKS.md."""
