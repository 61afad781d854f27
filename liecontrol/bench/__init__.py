"""Benchmarks against anchor libraries; every figure is a ratio measured in the same run."""
