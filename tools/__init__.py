"""Tools composing the three programs: demo, benchmarks, experiments."""
